"""Registry keys: ed25519 signers whose private halves live passphrase-encrypted in a keys folder.

A keys folder holds one ``<keyid>.key`` per private key (PEM PKCS#8, encrypted with the
passphrase, mode 0600); the public halves are in the registry source. A run reads a
key only when it must sign with it, through the bounded local reader.
The passphrase comes from ``--passphrase-file`` or ``HCDF_TRUST_PASSPHRASE`` (:mod:`hcdf_trust.passphrase`).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import TYPE_CHECKING

from ..errors import counted
from ..localfile import read_secret
from ..outputs import NEW_ONLY, OutputPlan
from .errors import KeyFileError, RefusedError
from .source import PublicKey, compute_keyid

if TYPE_CHECKING:
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
    from securesystemslib.signer import CryptoSigner, Signature

KEY_LIMIT = 64 << 10


def read_passphrase(path: str | None) -> bytes:
    """The keys' passphrase: :func:`hcdf_trust.passphrase.read_passphrase` (the one rule)."""
    from ..passphrase import read_passphrase as read_one

    data = read_one(path)
    assert data is not None
    return data


def generate() -> Ed25519PrivateKey:
    """A fresh ed25519 private key."""
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

    return Ed25519PrivateKey.generate()


def public_of(private: Ed25519PrivateKey) -> PublicKey:
    from cryptography.hazmat.primitives.serialization import Encoding, PublicFormat

    public = private.public_key().public_bytes(Encoding.Raw, PublicFormat.Raw).hex()
    return PublicKey(compute_keyid("ed25519", "ed25519", public), "ed25519", "ed25519", public)


def plan_private(plan: OutputPlan, keydir: Path, private: Ed25519PrivateKey, passphrase: bytes) -> PublicKey:
    """Plan ``<keydir>/<keyid>.key``: the private key, encrypted with ``passphrase``, mode 0600."""
    from cryptography.hazmat.primitives.serialization import BestAvailableEncryption, Encoding, PrivateFormat

    pem = private.private_bytes(Encoding.PEM, PrivateFormat.PKCS8, BestAvailableEncryption(passphrase))
    key = public_of(private)
    plan.add(keydir / f"{key.keyid}.key", pem, flag="--keys", mode=0o600, replaces=NEW_ONLY, folder_mode=0o700)
    return key


class KeyRing:
    """Private keys found in one or more keys folders, decrypted on first use."""

    def __init__(self, folders: Iterable[str | os.PathLike[str]], passphrase: bytes | Callable[[], bytes]) -> None:
        """``passphrase`` may be a function: it is then called once, when a key is first decrypted."""
        self.folders = [Path(f) for f in folders]
        self._passphrase = passphrase
        self._cache: dict[str, CryptoSigner | None] = {}

    def _secret(self) -> bytes:
        if callable(self._passphrase):
            self._passphrase = self._passphrase()
        return self._passphrase

    def has(self, keyid: str) -> bool:
        return any((f / f"{keyid}.key").is_file() for f in self.folders)

    def signer(self, key: PublicKey) -> CryptoSigner | None:
        """The signer for ``key``, or None when no folder holds its private key.

        Raises:
            KeyFileError: the key file is unreadable, not a key, or the passphrase is wrong.
        """
        if key.keyid not in self._cache:
            self._cache[key.keyid] = self._load(key)
        return self._cache[key.keyid]

    def _load(self, key: PublicKey) -> CryptoSigner | None:
        from cryptography.hazmat.primitives.serialization import load_pem_private_key
        from securesystemslib.signer import CryptoSigner, SSlibKey

        for folder in self.folders:
            path = folder / f"{key.keyid}.key"
            if not path.exists():
                continue
            pem = read_secret(path, limit=KEY_LIMIT, what="private key file")
            try:
                private = load_pem_private_key(pem, self._secret())
            except (ValueError, TypeError) as exc:
                wrong = "password" in str(exc).lower() or "decrypt" in str(exc).lower()
                why = "wrong passphrase" if wrong else "not an encrypted PEM private key"
                raise KeyFileError(f"{path}: {why}", file=str(path)) from None
            try:
                return CryptoSigner(private, SSlibKey.from_dict(key.keyid, key.to_dict()))
            except Exception:  # securesystemslib's KeyMismatchError, ValueError on a foreign key type
                raise KeyFileError(
                    f"{path}: the private key does not match the public key {key.keyid}", file=str(path)
                ) from None
        return None

    def sign_threshold(
        self, keys: dict[str, PublicKey], threshold: int, payload: bytes, *, what: str
    ) -> list[Signature]:
        """Signatures over ``payload`` by every held key of ``keys``; at least ``threshold``.

        Raises:
            RefusedError: fewer than ``threshold`` of the keys are held.
        """
        sigs = [s.sign(payload) for s in (self.signer(k) for k in keys.values()) if s is not None]
        if len(sigs) < threshold:
            raise RefusedError(
                f"{what}: the keys folder holds {len(sigs)} of the {counted(threshold, 'key')} needed "
                f"(keys {', '.join(k[:12] for k in keys)}); only the owner can sign this",
                expected=counted(threshold, "signature"),
                actual=f"{len(sigs)}",
            )
        return sigs


def verify(key: PublicKey, signature_hex: str, payload: bytes) -> bool:
    """Whether ``signature_hex`` is ``key``'s signature over ``payload``."""
    from securesystemslib.exceptions import UnverifiedSignatureError
    from securesystemslib.signer import Signature, SSlibKey

    try:
        SSlibKey.from_dict(key.keyid, key.to_dict()).verify_signature(Signature(key.keyid, signature_hex), payload)
    except UnverifiedSignatureError:
        return False
    return True
