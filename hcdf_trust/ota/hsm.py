"""Signing keys in a PKCS#11 token (RFC 7512 URIs): the private key never leaves it.

``--key pkcs11:token=release;object=fw-signing[?module-path=/usr/lib/softhsm/libsofthsm2.so]``.
The PIN comes from ``--pin-file``, the URI's ``pin-source=file:…`` or
``HCDF_TRUST_PKCS11_PIN``; a ``pin-value`` on the command line is refused. The module is
the URI's ``module-path``, else ``HCDF_TRUST_PKCS11_MODULE``, else SoftHSM2's usual path.

Images are signed through imgtool's external-signature path: a first ``create()`` with
``vector_to_sign="digest"`` gives the image digest, the token signs it (``CKM_ECDSA`` on
the digest, or ``CKM_EDDSA`` on the digest as imgtool does for non-pure Ed25519), and a
second ``create()`` takes the signature as ``fixed_sig``. A PKCS#11 ECDSA signature is raw
``r‖s``: MCUboot's ECDSA TLV wants DER, COSE wants it raw. The manifest's COSE_Sign1 is
made by cwt, through a cwt key object (:class:`_TokenCoseKey`) whose ``sign`` asks the token.
"""

from __future__ import annotations

import copy
import hashlib
import os
import threading
from dataclasses import dataclass
from typing import Any
from urllib.parse import parse_qsl, unquote

from cwt.cose_key_interface import COSEKeyInterface

from ..passphrase import PIN_ENV
from .errors import FirmwareError, KeyFileError

MODULE_ENV = "HCDF_TRUST_PKCS11_MODULE"
DEFAULT_MODULES = ("/usr/lib/softhsm/libsofthsm2.so", "/usr/lib/x86_64-linux-gnu/softhsm/libsofthsm2.so")
_ED25519_SPKI_PREFIX = bytes.fromhex("302a300506032b6570032100")


@dataclass(frozen=True)
class Pkcs11Uri:
    token: str | None
    object: str | None
    id: bytes | None
    module_path: str | None
    pin_source: str | None


def parse_uri(text: str) -> Pkcs11Uri:
    """The attributes of an RFC 7512 ``pkcs11:`` URI that name a signing key.

    Raises:
        KeyFileError: not a pkcs11 URI, an unknown attribute, or a PIN in the URI.
    """
    if not text.startswith("pkcs11:"):
        raise KeyFileError("not a pkcs11: URI", actual=text)
    body = text[len("pkcs11:") :]
    path, _, query = body.partition("?")
    attrs: dict[str, str] = {}
    for part in filter(None, path.split(";")):
        name, sep, value = part.partition("=")
        if not sep:
            raise KeyFileError(f"pkcs11 URI attribute {part!r} has no value", actual=text)
        attrs[name] = unquote(value)
    unknown = set(attrs) - {"token", "object", "id", "type", "manufacturer", "model", "serial", "library-description"}
    if unknown:
        raise KeyFileError(f"unknown pkcs11 URI attribute {sorted(unknown)[0]!r}", actual=text)
    if attrs.get("type", "private") != "private":
        raise KeyFileError("a signing key URI names a private key (type=private)", actual=attrs["type"])
    params = dict(parse_qsl(query, keep_blank_values=True))
    if "pin-value" in params:
        raise KeyFileError("a PIN on the command line is refused: use --pin-file or " + PIN_ENV)
    unknown = set(params) - {"module-path", "module-name", "pin-source"}
    if unknown:
        raise KeyFileError(f"unknown pkcs11 URI query attribute {sorted(unknown)[0]!r}")
    if not attrs.get("object") and not attrs.get("id"):
        raise KeyFileError("the pkcs11 URI names no key (object=… or id=…)", actual=text)
    raw_id = attrs.get("id")
    return Pkcs11Uri(
        token=attrs.get("token"),
        object=attrs.get("object"),
        id=raw_id.encode("latin-1") if raw_id is not None else None,
        module_path=params.get("module-path"),
        pin_source=params.get("pin-source"),
    )


def read_pin(uri: Pkcs11Uri, pin_file: str | None) -> str:
    """The user PIN: --pin-file, the URI's pin-source=file:…, or the environment.

    Raises:
        SecretFileError: none given, empty, several lines, a file others can read.
    """
    from ..passphrase import read_pin as read_secret_pin

    path = pin_file
    if path is None and uri.pin_source:
        path = uri.pin_source[len("file:") :] if uri.pin_source.startswith("file:") else uri.pin_source
    return read_secret_pin(path).decode("utf-8", "replace")


class HsmSigner:
    """A private key in a PKCS#11 token, used through one session for the whole run."""

    def __init__(self, uri: Pkcs11Uri, pin: str) -> None:
        import pkcs11
        from pkcs11 import Attribute, KeyType, ObjectClass

        module = (
            uri.module_path
            or os.environ.get(MODULE_ENV)
            or next((m for m in DEFAULT_MODULES if os.path.exists(m)), DEFAULT_MODULES[0])
        )
        try:
            lib = pkcs11.lib(module)
        except Exception as exc:
            raise KeyFileError(f"cannot load the PKCS#11 module: {exc}", file=module) from None
        try:
            token = lib.get_token(token_label=uri.token) if uri.token else next(iter(lib.get_tokens()))
        except (pkcs11.NoSuchToken, StopIteration):
            raise KeyFileError(f"no PKCS#11 token {uri.token!r}", file=module) from None
        except pkcs11.MultipleTokensReturned:
            raise KeyFileError(f"several PKCS#11 tokens match {uri.token!r}", file=module) from None
        try:
            self.session = token.open(user_pin=pin)
        except pkcs11.PinIncorrect:
            raise KeyFileError(f"wrong PIN for the PKCS#11 token {token.label!r}") from None
        except pkcs11.PKCS11Error as exc:
            raise KeyFileError(f"cannot log in to the PKCS#11 token {token.label!r}: {type(exc).__name__}") from None
        query: dict[Any, Any] = {}
        if uri.object:
            query["label"] = uri.object
        if uri.id:
            query["id"] = uri.id
        public: Any
        try:
            self.private: Any = self.session.get_key(object_class=ObjectClass.PRIVATE_KEY, **query)
            public = self.session.get_key(object_class=ObjectClass.PUBLIC_KEY, **query)
        except pkcs11.NoSuchKey:
            self.session.close()
            raise KeyFileError(f"no key pair {uri.object or uri.id!r} in the token {token.label!r}") from None
        except pkcs11.MultipleObjectsReturned:
            self.session.close()
            raise KeyFileError(f"several keys match {uri.object or uri.id!r} in the token {token.label!r}") from None
        self._lock = threading.Lock()
        from cryptography.hazmat.primitives.serialization import load_der_public_key

        from .keys import wrap_key

        if public.key_type == KeyType.EC:
            from pkcs11.util.ec import encode_ec_public_key

            spki = encode_ec_public_key(public)
        elif public.key_type == KeyType.EC_EDWARDS:
            point = bytes(public[Attribute.EC_POINT])
            raw = point[2:] if len(point) == 34 and point[:2] == b"\x04\x20" else point
            spki = _ED25519_SPKI_PREFIX + raw
        else:
            self.session.close()
            raise KeyFileError(f"unsupported key type in the token: {public.key_type!r} (use ecdsa-p256 or ed25519)")
        self.public = wrap_key(load_der_public_key(spki), "pkcs11 key")
        from .keys import key_type

        self.kind = key_type(self.public)

    def close(self) -> None:
        self.session.close()

    def _sign(self, data: bytes) -> bytes:
        """The token's raw signature: ECDSA r‖s over a digest, or EdDSA over ``data``."""
        from pkcs11 import Mechanism

        mechanism = Mechanism.ECDSA if self.kind == "ecdsa-p256" else Mechanism.EDDSA
        with self._lock:  # one session: PKCS#11 operations on it must not interleave
            signature: bytes = self.private.sign(data, mechanism=mechanism)
        return signature

    def create(self, img: Any, **kw: Any) -> None:
        """imgtool's external-signature path: export the digest, sign it here, fix the signature in."""
        from cryptography.hazmat.primitives.asymmetric.utils import encode_dss_signature

        probe = copy.deepcopy(img)
        probe.create(None, "hash", None, pub_key=self.public, vector_to_sign="digest", **kw)
        digest = bytes(probe.payload)
        raw = self._sign(digest)
        if self.kind == "ecdsa-p256":
            half = len(raw) // 2
            sig = encode_dss_signature(int.from_bytes(raw[:half], "big"), int.from_bytes(raw[half:], "big"))
        else:
            sig = raw
        img.create(None, "hash", None, pub_key=self.public, fixed_sig={"value": sig}, **kw)
        if img.image_hash != digest:
            raise FirmwareError(
                "imgtool's two passes disagree on the image digest", expected=digest.hex(), actual=img.image_hash.hex()
            )

    def cose_key(self, kid: bytes) -> COSEKeyInterface:
        """A cwt key whose ``sign`` is done by the token (cwt builds the Sig_structure)."""
        return _TokenCoseKey(self, kid)


class _TokenCoseKey(COSEKeyInterface):
    """cwt's key interface over a token key: ES256 signs SHA-256 of the Sig_structure
    (``CKM_ECDSA`` gives COSE's raw ``r‖s``), EdDSA signs the Sig_structure itself."""

    def __init__(self, signer: HsmSigner, kid: bytes) -> None:
        from .signer import COSE_ALGS

        kty = 2 if signer.kind == "ecdsa-p256" else 1  # EC2 / OKP
        super().__init__({1: kty, 2: kid, 3: COSE_ALGS[signer.kind][0]})
        self._signer = signer

    def sign(self, msg: bytes) -> bytes:
        if self._signer.kind == "ecdsa-p256":
            return self._signer._sign(hashlib.sha256(msg).digest())
        return self._signer._sign(msg)
