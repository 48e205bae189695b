"""Wrapping-key backends: how the key store's data key is protected at rest.

The store encrypts each key with one random 256-bit data key (AES-256-GCM); a backend
wraps that data key. ``scrypt``: a key derived from a passphrase. ``pkcs11``: an AES key
that never leaves a PKCS#11 token (SoftHSM2 in the tests), used with RFC 3394 key wrap.
A backend that cannot unwrap (wrong passphrase, wrong token key) raises
:class:`WrongCredentialError` (exit 3) and nothing is written.
"""

from __future__ import annotations

import base64
import os
from typing import Any, Protocol

from ..errors import InputError

# scrypt cost recorded in the store; bounds refuse a hostile store that asks for gigabytes.
# The public API (docs/api.md): the passphrase backend; the token and TPM backends are
# reached through the CLI's --pkcs11-module and --tpm (they need hardware to show an example).
__all__ = ["PassphraseWrapper"]

SCRYPT_N, SCRYPT_R, SCRYPT_P = 2**15, 8, 1
SCRYPT_N_RANGE = (2**14, 2**20)


class WrongCredentialError(InputError):
    """The passphrase or token key does not open this key store."""

    code = "key-store-credential"


class KeyStoreFormatError(InputError):
    """The key store file is not a key store this version can read."""

    code = "key-store"


class Wrapper(Protocol):
    method: str

    def wrap(self, dek: bytes, aad: bytes) -> dict[str, Any]: ...

    def unwrap(self, params: dict[str, Any], aad: bytes, *, source: str) -> bytes: ...


def b64(data: bytes) -> str:
    return base64.b64encode(data).decode("ascii")


def unb64(value: Any, *, what: str, source: str) -> bytes:
    if not isinstance(value, str):
        raise KeyStoreFormatError(f"{what} is not a base64 string", file=source, actual=type(value).__name__)
    try:
        return base64.b64decode(value.encode("ascii"), validate=True)
    except (ValueError, UnicodeEncodeError):
        raise KeyStoreFormatError(f"{what} is not valid base64", file=source) from None


def _int_in(params: dict[str, Any], key: str, lo: int, hi: int, *, source: str) -> int:
    value = params.get(key)
    if type(value) is not int or not lo <= value <= hi:
        raise KeyStoreFormatError(
            f"wrapping parameter {key} is out of range", file=source, expected=f"{lo}..{hi}", actual=repr(value)[:40]
        )
    return value


class PassphraseWrapper:
    """The data key wrapped with AES-256-GCM under ``scrypt(passphrase)``: the passphrase
    backend of a :class:`~hcdf_trust.macsec.store.KeyStore` (``--passphrase-file``).

    Example:
        >>> from hcdf_trust.macsec.backends import PassphraseWrapper
        >>> from hcdf_trust.macsec.store import KeyStore
        >>> store = KeyStore.create("keys", PassphraseWrapper(b"correct horse battery staple"))
        >>> store.changed, store.path.name
        (True, 'macsec-keys.json')
    """

    method = "scrypt"

    def __init__(self, passphrase: bytes) -> None:
        if not passphrase:
            raise InputError("the key store passphrase is empty")
        self._passphrase = passphrase
        # (salt, n, r, p) -> key: a store opened twice in one run (before and under the lock) costs one scrypt
        self._derived: dict[tuple[bytes, int, int, int], bytes] = {}

    def _derive(self, salt: bytes, n: int, r: int, p: int) -> bytes:
        from cryptography.hazmat.primitives.kdf.scrypt import Scrypt

        key = self._derived.get((salt, n, r, p))
        if key is None:
            key = Scrypt(salt=salt, length=32, n=n, r=r, p=p).derive(self._passphrase)
            self._derived[salt, n, r, p] = key
        return key

    def wrap(self, dek: bytes, aad: bytes) -> dict[str, Any]:
        from cryptography.hazmat.primitives.ciphers.aead import AESGCM

        salt, nonce = os.urandom(16), os.urandom(12)
        kek = self._derive(salt, SCRYPT_N, SCRYPT_R, SCRYPT_P)
        wrapped = AESGCM(kek).encrypt(nonce, dek, aad)
        return {
            "method": self.method,
            "salt": b64(salt),
            "n": SCRYPT_N,
            "r": SCRYPT_R,
            "p": SCRYPT_P,
            "nonce": b64(nonce),
            "wrapped_key": b64(wrapped),
        }

    def unwrap(self, params: dict[str, Any], aad: bytes, *, source: str) -> bytes:
        from cryptography.exceptions import InvalidTag
        from cryptography.hazmat.primitives.ciphers.aead import AESGCM

        n = _int_in(params, "n", *SCRYPT_N_RANGE, source=source)
        if n & (n - 1):
            raise KeyStoreFormatError("scrypt n is not a power of two", file=source, actual=str(n))
        r = _int_in(params, "r", 1, 32, source=source)
        p = _int_in(params, "p", 1, 4, source=source)
        salt = unb64(params.get("salt"), what="scrypt salt", source=source)
        nonce = unb64(params.get("nonce"), what="wrapping nonce", source=source)
        wrapped = unb64(params.get("wrapped_key"), what="wrapped key", source=source)
        if len(nonce) != 12 or len(wrapped) != 48:
            raise KeyStoreFormatError("the wrapped data key has the wrong length", file=source)
        kek = self._derive(salt, n, r, p)
        try:
            return AESGCM(kek).decrypt(nonce, wrapped, aad)
        except InvalidTag:
            raise WrongCredentialError(
                "wrong passphrase: it does not open this key store (nothing was changed)", file=source
            ) from None


def passphrase_from(file: str | None) -> bytes:
    """The store passphrase: :func:`hcdf_trust.passphrase.read_passphrase` (the one rule:
    ``--passphrase-file`` or ``$HCDF_TRUST_PASSPHRASE``)."""
    from ..passphrase import read_passphrase

    data = read_passphrase(file)
    assert data is not None
    return data


PKCS11_KEY_LABEL = "hcdf-trust-macsec-store"


class Pkcs11Wrapper:
    """The data key wrapped (RFC 3394 AES key wrap) by a non-extractable AES-256 key inside a PKCS#11 token.

    The token key is made on first use (``--pkcs11-module``, ``--token-label``, ``--pin-file``)
    with SENSITIVE set and EXTRACTABLE cleared: it never leaves the token. The data key is
    unwrapped into this process only, to decrypt the store's entries.
    """

    method = "pkcs11"

    def __init__(self, module: str, token_label: str, pin: bytes, *, key_label: str = PKCS11_KEY_LABEL) -> None:
        try:
            import pkcs11
        except ImportError:  # pragma: no cover - depends on the install
            raise InputError("the PKCS#11 backend needs python-pkcs11: pip install 'hcdf-trust[hsm]'") from None
        self._pkcs11 = pkcs11
        self.module = module
        self.token_label = token_label
        self.key_label = key_label
        self._pin = pin.decode("utf-8", "replace")

    def _session(self) -> Any:
        p = self._pkcs11
        from pkcs11 import exceptions as pe

        try:
            lib = p.lib(self.module)
        except (RuntimeError, OSError, pe.PKCS11Error) as exc:
            raise InputError(f"cannot load PKCS#11 module {self.module}: {exc}", file=self.module) from None
        try:
            token = lib.get_token(token_label=self.token_label)
        except (pe.NoSuchToken, pe.MultipleTokensReturned):
            raise InputError(
                f"no single PKCS#11 token labelled {self.token_label!r} in {self.module}", file=self.module
            ) from None
        try:
            return token.open(user_pin=self._pin, rw=True)
        except (pe.PinIncorrect, pe.PinInvalid, pe.PinLenRange):
            raise WrongCredentialError(
                f"wrong PIN for PKCS#11 token {self.token_label!r} (nothing was changed)", file=self.module
            ) from None
        except pe.PKCS11Error as exc:
            raise InputError(f"cannot open PKCS#11 token {self.token_label!r}: {exc!r}", file=self.module) from None

    def _kek(self, session: Any, *, create: bool) -> Any:
        from pkcs11 import Attribute, KeyType, ObjectClass
        from pkcs11 import exceptions as pe

        try:
            return session.get_key(label=self.key_label, key_type=KeyType.AES, object_class=ObjectClass.SECRET_KEY)
        except pe.NoSuchKey:
            if not create:
                raise WrongCredentialError(
                    f"PKCS#11 token {self.token_label!r} has no key labelled {self.key_label!r}: "
                    f"it is not the token this store was made with",
                    file=self.module,
                ) from None
        except pe.MultipleObjectsReturned:
            raise InputError(
                f"PKCS#11 token {self.token_label!r} has several keys labelled {self.key_label!r}", file=self.module
            ) from None
        template = {
            Attribute.SENSITIVE: True,
            Attribute.EXTRACTABLE: False,
            Attribute.WRAP: True,
            Attribute.UNWRAP: True,
        }
        return session.generate_key(KeyType.AES, 256, label=self.key_label, store=True, template=template)

    def wrap(self, dek: bytes, aad: bytes) -> dict[str, Any]:
        from pkcs11 import Attribute, KeyType, Mechanism, ObjectClass

        with self._session() as session:
            kek = self._kek(session, create=True)
            obj = session.create_object(
                {
                    Attribute.CLASS: ObjectClass.SECRET_KEY,
                    Attribute.KEY_TYPE: KeyType.AES,
                    Attribute.VALUE: dek,
                    Attribute.TOKEN: False,
                    Attribute.SENSITIVE: False,
                    Attribute.EXTRACTABLE: True,
                }
            )
            blob = kek.wrap_key(obj, mechanism=Mechanism.AES_KEY_WRAP)
            obj.destroy()
        return {
            "method": self.method,
            "token_label": self.token_label,
            "key_label": self.key_label,
            "mechanism": "AES_KEY_WRAP",
            "wrapped_key": b64(bytes(blob)),
        }

    def unwrap(self, params: dict[str, Any], aad: bytes, *, source: str) -> bytes:
        from pkcs11 import Attribute, KeyType, Mechanism, ObjectClass
        from pkcs11 import exceptions as pe

        blob = unb64(params.get("wrapped_key"), what="wrapped key", source=source)
        if len(blob) != 40:
            raise KeyStoreFormatError("the wrapped data key has the wrong length", file=source)
        label = params.get("key_label")
        if isinstance(label, str) and label:
            self.key_label = label
        with self._session() as session:
            kek = self._kek(session, create=False)
            try:
                obj = kek.unwrap_key(
                    ObjectClass.SECRET_KEY,
                    KeyType.AES,
                    blob,
                    mechanism=Mechanism.AES_KEY_WRAP,
                    template={Attribute.TOKEN: False, Attribute.SENSITIVE: False, Attribute.EXTRACTABLE: True},
                )
            except pe.PKCS11Error:
                raise WrongCredentialError(
                    f"the key {self.key_label!r} of PKCS#11 token {self.token_label!r} does not open this key store "
                    f"(nothing was changed)",
                    file=source,
                ) from None
            dek = bytes(obj[Attribute.VALUE])
            obj.destroy()
        return dek


def pin_from(file: str | None) -> bytes:
    """A token PIN: :func:`hcdf_trust.passphrase.read_pin` (``--pin-file`` or ``$HCDF_TRUST_PKCS11_PIN``)."""
    from ..passphrase import read_pin

    return read_pin(file)


class TpmWrapper:
    """The data key sealed to a TPM 2.0 (tpm2-pytss): only this TPM can unseal it.

    ``tcti`` is a TSS2 TCTI string: ``device:/dev/tpmrm0``, ``swtpm:host=127.0.0.1,port=2321``.
    The sealed object (keyed hash, ``fixedTPM``/``fixedParent``) lives under the owner
    hierarchy's ECC P-256 storage primary, re-created from the TPM's seed on every run.
    The sealed object has an empty authorization value: anyone who can use this TPM can
    unseal it, and could seal a substitute data key of their own, so the store folder must
    be writable by its owner only (as the 0700/0600 modes make it).
    """

    method = "tpm"
    PRIMARY = "ecc256"

    def __init__(self, tcti: str) -> None:
        os.environ.setdefault("TSS2_LOG", "all+NONE")  # errors are reported once, by us, not by the TSS's logger
        try:
            import tpm2_pytss  # noqa: F401
        except ImportError:  # pragma: no cover - depends on the install
            raise InputError("the TPM backend needs tpm2-pytss: pip install 'hcdf-trust[tpm]'") from None
        self.tcti = tcti

    def _esapi(self) -> Any:
        from tpm2_pytss import ESAPI, TSS2_Exception

        try:
            return ESAPI(self.tcti)
        except (TSS2_Exception, RuntimeError, OSError) as exc:
            raise InputError(f"cannot reach the TPM at {self.tcti!r}: {exc}", file=self.tcti) from None

    def wrap(self, dek: bytes, aad: bytes) -> dict[str, Any]:
        from tpm2_pytss import TPM2B_PUBLIC, TPM2B_SENSITIVE_CREATE, TPM2B_SENSITIVE_DATA, TPMS_SENSITIVE_CREATE
        from tpm2_pytss.constants import TPMA_OBJECT

        ectx = self._esapi()
        try:
            primary, *_ = ectx.create_primary(TPM2B_SENSITIVE_CREATE(), self.PRIMARY)
            sensitive = TPM2B_SENSITIVE_CREATE(TPMS_SENSITIVE_CREATE(data=TPM2B_SENSITIVE_DATA(dek)))
            attrs = TPMA_OBJECT.USERWITHAUTH | TPMA_OBJECT.FIXEDTPM | TPMA_OBJECT.FIXEDPARENT
            template = TPM2B_PUBLIC.parse("keyedhash", objectAttributes=attrs)
            private, public, *_ = ectx.create(primary, sensitive, template)
            ectx.flush_context(primary)
        finally:
            ectx.close()
        return {
            "method": self.method,
            "primary": self.PRIMARY,
            "private": b64(bytes(private.marshal())),
            "public": b64(bytes(public.marshal())),
        }

    def unwrap(self, params: dict[str, Any], aad: bytes, *, source: str) -> bytes:
        from tpm2_pytss import TPM2B_PRIVATE, TPM2B_PUBLIC, TPM2B_SENSITIVE_CREATE, TSS2_Exception

        if params.get("primary") != self.PRIMARY:
            raise KeyStoreFormatError("unknown TPM primary template", file=source, expected=self.PRIMARY)
        private_blob = unb64(params.get("private"), what="TPM private blob", source=source)
        public_blob = unb64(params.get("public"), what="TPM public blob", source=source)
        try:
            private, _ = TPM2B_PRIVATE.unmarshal(private_blob)
            public, _ = TPM2B_PUBLIC.unmarshal(public_blob)
        except (TSS2_Exception, ValueError, TypeError):
            raise KeyStoreFormatError("the TPM blobs are malformed", file=source) from None
        ectx = self._esapi()
        try:
            primary, *_ = ectx.create_primary(TPM2B_SENSITIVE_CREATE(), self.PRIMARY)
            try:
                sealed = ectx.load(primary, private, public)
                dek = bytes(ectx.unseal(sealed))
                ectx.flush_context(sealed)
            except TSS2_Exception:
                raise WrongCredentialError(
                    f"the TPM at {self.tcti!r} cannot unseal this key store: it was sealed to another TPM "
                    f"(nothing was changed)",
                    file=source,
                ) from None
            finally:
                ectx.flush_context(primary)
        finally:
            ectx.close()
        if len(dek) != 32:
            raise KeyStoreFormatError("the unsealed data key has the wrong length", file=source)
        return dek
