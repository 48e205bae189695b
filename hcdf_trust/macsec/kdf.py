"""IEEE 802.1X-2010 key derivation (clause 6.2.1) with AES-CMAC, and key check values.

``KDF(K, Label, Context, L)`` concatenates ``AES-CMAC(K, i ‖ Label ‖ 0x00 ‖ Context ‖ L)`` for
``i = 1, 2, ...`` (``i`` one octet, ``L`` the output length in bits as two octets). The ICK and
KEK take as context the first 16 octets of the CKN, zero-padded (so only those octets of a
CKN matter, and :mod:`hcdf_trust.macsec.store` keeps them unique).
"""

from __future__ import annotations

from cryptography.hazmat.primitives.ciphers.algorithms import AES
from cryptography.hazmat.primitives.cmac import CMAC

ICK_LABEL = b"IEEE8021 ICK"
KEK_LABEL = b"IEEE8021 KEK"
SAK_LABEL = b"IEEE8021 SAK"


def kdf(key: bytes, label: bytes, context: bytes, bits: int) -> bytes:
    """The 802.1X AES-CMAC KDF: ``bits`` (a multiple of 8) bits of output."""
    out = b""
    i = 1
    while len(out) * 8 < bits:
        mac = CMAC(AES(key))
        mac.update(bytes([i]) + label + b"\x00" + context + bits.to_bytes(2, "big"))
        out += mac.finalize()
        i += 1
    return out[: bits // 8]


def _ckn_context(ckn: bytes) -> bytes:
    return ckn[:16].ljust(16, b"\x00")


def ick(cak: bytes, ckn: bytes) -> bytes:
    """The ICV Key: as long as the CAK."""
    return kdf(cak, ICK_LABEL, _ckn_context(ckn), len(cak) * 8)


def kek(cak: bytes, ckn: bytes) -> bytes:
    """The Key Encrypting Key: as long as the CAK."""
    return kdf(cak, KEK_LABEL, _ckn_context(ckn), len(cak) * 8)


def sak(cak: bytes, context: bytes, nbytes: int) -> bytes:
    """A Secure Association Key of ``nbytes`` from ``context`` (MKA: KS-nonce ‖ MI list ‖ KN)."""
    return kdf(cak, SAK_LABEL, context, nbytes * 8)


def key_check_value(cak: bytes, ckn: bytes) -> str:
    """A short public fingerprint of a CA's keys: the first 3 octets of ``AES-CMAC(ICK, 16 zero octets)``.

    Two devices holding the same CAK and CKN show the same value; it reveals no key.
    """
    mac = CMAC(AES(ick(cak, ckn)))
    mac.update(bytes(16))
    return mac.finalize()[:3].hex()
