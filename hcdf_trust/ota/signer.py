"""Who signs a release: a key file (imgtool key + cwt), later a PKCS#11 token.

A signer does two things: complete an imgtool ``Image`` (``create``) and produce the
COSE_Sign1 over the release manifest's digest. :data:`COSE_ALGS` binds each key type
to the COSE algorithms a verifier accepts for it (cwt itself verifies with the key's
algorithm and ignores a mismatching protected ``alg``).
"""

from __future__ import annotations

import hashlib
from typing import Any, Protocol

# key type -> (the algorithm we sign with, every algorithm accepted for that key)
COSE_ALGS: dict[str, tuple[int, frozenset[int]]] = {
    "ecdsa-p256": (-7, frozenset({-7, -9})),  # ES256 / ESP256
    "ed25519": (-8, frozenset({-8, -19})),  # EdDSA / Ed25519
    "rsa-2048": (-37, frozenset({-37})),  # PS256
    "rsa-3072": (-37, frozenset({-37})),
}
ALG_NAMES = {-7: "ES256", -9: "ESP256", -8: "EdDSA", -19: "Ed25519", -37: "PS256"}
CWT_ALG = {"ecdsa-p256": "ES256", "ed25519": "EdDSA", "rsa-2048": "PS256", "rsa-3072": "PS256"}


class Signer(Protocol):
    kind: str  # one of keys.KEY_TYPES
    public: Any  # imgtool public key

    def create(self, img: Any, **kw: Any) -> None: ...

    def sign_cose(self, protected: bytes, payload: bytes) -> bytes:
        """The COSE signature bytes over Sig_structure(protected, payload)."""
        ...


def key_id(public: Any) -> bytes:
    """SHA-256 of the DER SubjectPublicKeyInfo: also MCUboot's KEYHASH TLV."""
    return hashlib.sha256(public.get_public_bytes()).digest()


class FileSigner:
    """A private key from a PEM file (see :func:`hcdf_trust.ota.keys.load_private`)."""

    def __init__(self, key: Any) -> None:
        from .keys import key_type

        self.key = key
        self.kind = key_type(key)
        self.public = key

    def create(self, img: Any, **kw: Any) -> None:
        img.create(self.key, "hash", None, **kw)

    def sign_cose(self, protected: bytes, payload: bytes) -> bytes:
        import cbor2
        from cryptography.hazmat.primitives import serialization
        from cwt import COSE, COSEKey

        pem = self.key.key.private_bytes(
            serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
        )
        header = cbor2.loads(protected)
        cose_key = COSEKey.from_pem(pem, alg=CWT_ALG[self.kind], kid=header.get(4))
        tag = COSE.new().encode(payload, cose_key, protected=header, out="cbor2/CBORTag")
        if tag.value[0] != protected:
            raise AssertionError("cwt re-encoded the protected header")
        signature: bytes = tag.value[3]
        return signature
