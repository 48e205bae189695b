"""Who signs a release: a key file (imgtool key) or a PKCS#11 token (:mod:`.hsm`).

A signer does two things: complete an imgtool ``Image`` (``create``) and give cwt a
signing key (``cose_key``) for the COSE_Sign1 over the release manifest's digest: cwt's
own key for a file, a :class:`cwt.cose_key_interface.COSEKeyInterface` whose ``sign``
asks the token for a token key. cwt builds the Sig_structure and the COSE_Sign1 either way.

:data:`COSE_ALGS` binds each key type to the COSE algorithms a verifier accepts for it
(cwt itself verifies with the key's algorithm and ignores a mismatching protected ``alg``).
"""

from __future__ import annotations

import hashlib
from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:
    from cwt.cose_key_interface import COSEKeyInterface

# key type -> (the algorithm we sign with, every algorithm accepted for that key)
COSE_ALGS: dict[str, tuple[int, frozenset[int]]] = {
    "ecdsa-p256": (-7, frozenset({-7, -9})),  # ES256 / ESP256
    "ed25519": (-8, frozenset({-8, -19})),  # EdDSA / Ed25519
    "rsa-2048": (-37, frozenset({-37})),  # PS256
    "rsa-3072": (-37, frozenset({-37})),
}
ALG_NAMES = {-7: "ES256", -9: "ESP256", -8: "EdDSA", -19: "Ed25519", -37: "PS256"}
# cwt's names for COSE_ALGS[kind][0]
CWT_ALG = {"ecdsa-p256": "ES256", "ed25519": "EdDSA", "rsa-2048": "PS256", "rsa-3072": "PS256"}

# The public API (docs/api.md); everything else here is internal.
__all__ = ["FileSigner", "Signer"]


class Signer(Protocol):
    """What signs a release: :class:`FileSigner` (a key file) or the PKCS#11 signer of
    :mod:`hcdf_trust.ota.hsm`. ``kind`` is the key type, ``public`` the imgtool public key.

    Example:
        >>> from hcdf_trust.ota.keys import generate
        >>> from hcdf_trust.ota.signer import FileSigner, Signer
        >>> signer: Signer = FileSigner(generate("ecdsa-p256"))
        >>> signer.kind
        'ecdsa-p256'
    """

    kind: str  # one of keys.KEY_TYPES
    public: Any  # imgtool public key

    def create(self, img: Any, **kw: Any) -> None: ...

    def cose_key(self, kid: bytes) -> COSEKeyInterface:
        """A cwt signing key for the release manifest's COSE_Sign1 (alg ``COSE_ALGS[kind][0]``)."""
        ...

    def close(self) -> None: ...


def key_id(public: Any) -> bytes:
    """SHA-256 of the DER SubjectPublicKeyInfo: also MCUboot's KEYHASH TLV."""
    return hashlib.sha256(public.get_public_bytes()).digest()


class FileSigner:
    """A :class:`Signer` holding a private key (from :func:`hcdf_trust.ota.keys.load_private`
    or :func:`~hcdf_trust.ota.keys.generate`), for :class:`~hcdf_trust.ota.release.BuildOptions`.

    Example:
        >>> from hcdf_trust.ota.keys import generate
        >>> from hcdf_trust.ota.signer import FileSigner
        >>> FileSigner(generate("ed25519")).kind
        'ed25519'
    """

    def __init__(self, key: Any) -> None:
        from .keys import key_type

        self.key = key
        self.kind = key_type(key)
        self.public = key

    def create(self, img: Any, **kw: Any) -> None:
        img.create(self.key, "hash", None, **kw)

    def close(self) -> None:
        """Nothing to release (a token signer closes its session)."""

    def cose_key(self, kid: bytes) -> COSEKeyInterface:
        """cwt's own key object for this private key: cwt signs the Sig_structure."""
        from cwt import COSEKey

        from .keys import private_pem

        return COSEKey.from_pem(private_pem(self.key, None), alg=CWT_ALG[self.kind], kid=kid)
