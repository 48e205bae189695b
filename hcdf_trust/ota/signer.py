"""Who signs a release: a key file (imgtool key) or a PKCS#11 token (:mod:`.hsm`).

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
CWT_ALG = {"ecdsa-p256": "ES256", "ed25519": "EdDSA", "rsa-2048": "PS256", "rsa-3072": "PS256"}  # for verifying


class Signer(Protocol):
    kind: str  # one of keys.KEY_TYPES
    public: Any  # imgtool public key

    def create(self, img: Any, **kw: Any) -> None: ...

    def sign_cose(self, protected: bytes, payload: bytes) -> bytes:
        """The COSE signature bytes over Sig_structure(protected, payload)."""
        ...

    def close(self) -> None: ...


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

    def close(self) -> None:
        """Nothing to release (a token signer closes its session)."""

    def sign_cose(self, protected: bytes, payload: bytes) -> bytes:
        """RFC 9052 §4.4 over the Sig_structure, with the key's algorithm (cwt verifies it).

        Signed here with ``cryptography`` rather than through cwt, so that file keys and
        token keys build the COSE_Sign1 the same way and a build does not import cwt
        (~0.3 s, most of a release's fixed cost); cwt and pycose verify the result.
        """
        from cryptography.hazmat.primitives import hashes
        from cryptography.hazmat.primitives.asymmetric import ec, padding
        from cryptography.hazmat.primitives.asymmetric.utils import decode_dss_signature

        from .suit import sig_structure

        data = sig_structure(protected, payload)
        key = self.key.key
        if self.kind == "ecdsa-p256":
            r, s = decode_dss_signature(key.sign(data, ec.ECDSA(hashes.SHA256())))
            return r.to_bytes(32, "big") + s.to_bytes(32, "big")
        if self.kind == "ed25519":
            signature: bytes = key.sign(data)
            return signature
        signature = key.sign(data, padding.PSS(padding.MGF1(hashes.SHA256()), 32), hashes.SHA256())
        return signature
