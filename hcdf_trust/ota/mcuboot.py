"""MCUboot image verification that hashes each byte once, as the image streams past.

Why not imgtool's ``Image.verify`` (imgtool stays our signer, and its verify is the oracle of
tests/test_mcuboot_oracle.py): it needs the whole image in memory and hashes it twice, once for
the hash TLV and once more inside the signature check over the same bytes. ``ota pull`` already
hashes each blob for its OCI digest as it arrives, so imgtool made that three passes over every
byte, on one thread, after the download. Here an image's bytes go through :class:`ImageStream`
once, in any chunks: one SHA-256 of the whole file (the file's ``sha256``, the blob digest) and,
copied from that same SHA-256 state where the protected TLVs end, MCUboot's image hash. The
signature is then checked over that digest, as MCUboot's bootutil does (ECDSA and RSA-PSS with
the digest as a pre-hashed message; Ed25519 signs the digest itself). Memory: the header and the
TLV areas (at most 128 KiB), whatever the image's size.

Where the bootloader (bootutil ``image_validate.c``, ``tlv.c``) is stricter than imgtool's
``verify``, we follow the bootloader, the real consumer:

- a SHA-256 hash TLV is required (imgtool says OK for a signed image without one);
- a protected TLV area must be exactly the size the header declares, and none may be present
  that the header does not declare;
- a TLV's type is 16 bits (imgtool reads a type byte and ignores the next);
- a signature counts only after a ``KEYHASH`` (or ``PUBKEY``) TLV naming the key it is checked
  with: bootutil selects the key that way and skips a signature no key was selected for;
- SHA-384/SHA-512 image hashes and "pure" signatures are refused (releases name SHA-256 image
  hashes; nothing here builds the others).

And one rule of our own: a TLV that runs past the total its TLV area declares is refused
(bootutil's iterator reads on, unchecked; imgtool too).

Bytes after the TLV area are ignored, as both do (the file's SHA-256 in the signed manifest covers
them).
"""

from __future__ import annotations

import hashlib
import struct
from dataclasses import dataclass
from typing import Any

from .images import HEADER, IMAGE_MAGIC, TLV_INFO_MAGIC, TLV_PROT_INFO_MAGIC, TLV_SEC_CNT, ImageInfo
from .version import McubootVersion

TLV = struct.Struct("<HH")  # type, length (bootutil's struct image_tlv; also the TLV info's magic, total)
TLV_KEYHASH = 0x01
TLV_PUBKEY = 0x02
TLV_SHA256 = 0x10
TLV_SHA384 = 0x11
TLV_SHA512 = 0x12
TLV_RSA2048_PSS = 0x20
TLV_ECDSA_SIG = 0x22
TLV_RSA3072_PSS = 0x23
TLV_ED25519 = 0x24
TLV_SIG_PURE = 0x25
MAX_TLV_AREAS = 2 * (TLV.size + 0xFFFF)  # protected + unprotected, each at most a 16-bit total


@dataclass(frozen=True)
class ImageVerdict:
    """What :meth:`ImageStream.verify` found. ``result`` is "OK" or why not, in imgtool's words
    where imgtool has one (INVALID_MAGIC, INVALID_TLV_INFO_MAGIC, INVALID_HASH, INVALID_SIGNATURE,
    KEY_MISMATCH), else "MALFORMED (…)" or "UNSUPPORTED (…)". ``image_hash`` (hex): only when OK.
    ``info``: the header and protected TLVs, once those could be read (not trusted unless OK)."""

    result: str
    image_hash: str | None = None
    info: ImageInfo | None = None

    @property
    def ok(self) -> bool:
        return self.result == "OK"


class ImageStream:
    """An MCUboot image fed in chunks (:meth:`update`), hashed once; :meth:`hexdigest` is the
    SHA-256 of every byte fed (a drop-in for ``hashlib.sha256()`` where a stream is hashed
    anyway), :meth:`verify` checks the image once every byte is in."""

    def __init__(self) -> None:
        self._sha = hashlib.sha256()
        self._head = bytearray()  # the first HEADER.size bytes
        self._hash_end: int | None = None  # header + payload + protected TLVs, once the header is in
        self._image_hash: bytes | None = None  # SHA-256 of those bytes, when the stream got there
        self._tlv_start: int | None = None  # header + payload: where the TLV areas begin
        self._tlvs = bytearray()  # the bytes from there, at most MAX_TLV_AREAS
        self.size = 0

    def update(self, chunk: bytes | bytearray | memoryview) -> None:
        view = memoryview(chunk).cast("B")
        start = self.size
        self.size += len(view)
        if len(self._head) < HEADER.size:
            self._head += view[: HEADER.size - len(self._head)]
            if len(self._head) == HEADER.size:
                self._read_header()
        end = self._hash_end
        if end is not None and self._image_hash is None and end <= self.size:
            cut = end - start  # >= 0: end >= HEADER.size, and this chunk is the one that got there
            self._sha.update(view[:cut])
            self._image_hash = self._sha.copy().digest()
            self._sha.update(view[cut:])
        else:
            self._sha.update(view)
        if self._tlv_start is not None:
            lo = max(self._tlv_start + len(self._tlvs), start)
            hi = min(self.size, self._tlv_start + MAX_TLV_AREAS)
            if lo < hi:
                self._tlvs += view[lo - start : hi - start]

    def _read_header(self) -> None:
        magic, _addr, hdr, ptlv, size, *_ = HEADER.unpack(self._head)
        if magic == IMAGE_MAGIC and hdr >= HEADER.size:
            self._tlv_start = hdr + size
            self._hash_end = hdr + size + ptlv

    def hexdigest(self) -> str:
        return self._sha.hexdigest()

    @property
    def magic(self) -> int | None:
        """The header's magic number (None: fewer bytes than a header)."""
        return HEADER.unpack(self._head)[0] if len(self._head) == HEADER.size else None

    def verify(self, public_key: Any) -> ImageVerdict:
        """Check the image fed so far (all of it) with ``public_key`` (an imgtool key: P-256,
        Ed25519, RSA-2048/3072)."""
        if public_key is None:
            raise ValueError("an MCUboot image is verified with a key")
        if len(self._head) < HEADER.size:
            return ImageVerdict("MALFORMED (too short for an MCUboot header)")
        magic, _addr, hdr, ptlv, size, _flags, major, minor, rev, build = HEADER.unpack(self._head)
        if magic != IMAGE_MAGIC:
            return ImageVerdict("INVALID_MAGIC")
        if hdr < HEADER.size:
            return ImageVerdict(f"MALFORMED (header size {hdr} is smaller than the header)")
        if self._image_hash is None:
            return ImageVerdict(f"MALFORMED (truncated: {self.size} bytes, the header says {hdr + size + ptlv} + TLVs)")
        tlvs = bytes(self._tlvs)
        version = McubootVersion(major, minor, rev, build)
        counter = None
        if ptlv:
            if len(tlvs) < TLV.size or TLV.unpack_from(tlvs) != (TLV_PROT_INFO_MAGIC, ptlv):
                return ImageVerdict("MALFORMED (the protected TLV area is not the one the header declares)")
            found = _walk(tlvs, TLV.size, ptlv)
            if found is None:
                return ImageVerdict("MALFORMED (a protected TLV overruns its area)")
            for kind, value in found:
                if kind == TLV_SEC_CNT and len(value) == 4:
                    counter = struct.unpack("<I", value)[0]
        elif tlvs[: TLV.size // 2] == struct.pack("<H", TLV_PROT_INFO_MAGIC):
            return ImageVerdict("MALFORMED (protected TLVs the header does not declare)")
        info = ImageInfo(hdr, ptlv, size, version, counter)
        if len(tlvs) < ptlv + TLV.size:
            return ImageVerdict("MALFORMED (truncated: no TLV area)", info=info)
        imagic, total = TLV.unpack_from(tlvs, ptlv)
        if imagic != TLV_INFO_MAGIC:
            return ImageVerdict("INVALID_TLV_INFO_MAGIC", info=info)
        if total < TLV.size or ptlv + total > len(tlvs):
            return ImageVerdict("MALFORMED (the TLV area is truncated or its total is wrong)", info=info)
        found = _walk(tlvs, ptlv + TLV.size, ptlv + total)
        if found is None:
            return ImageVerdict("MALFORMED (a TLV overruns the TLV area)", info=info)
        return _check_tlvs(found, self._image_hash, public_key, info)


def _walk(data: bytes, pos: int, end: int) -> list[tuple[int, bytes]] | None:
    """The TLVs in ``data[pos:end]``; None if one overruns ``end`` (or bytes are left over)."""
    out = []
    while pos < end:
        if pos + TLV.size > end:
            return None
        kind, length = TLV.unpack_from(data, pos)
        pos += TLV.size
        if pos + length > end:
            return None
        out.append((kind, data[pos : pos + length]))
        pos += length
    return out


def _check_tlvs(found: list[tuple[int, bytes]], image_hash: bytes, public_key: Any, info: ImageInfo) -> ImageVerdict:
    sig_tlv, check = _signature_check(public_key)
    if sig_tlv is None:
        return ImageVerdict(f"UNSUPPORTED (key type {type(public_key).__name__})", info=info)
    public = public_key.get_public_bytes()
    key_named = False  # the last KEYHASH / PUBKEY TLV names this key
    hashed = signed = False
    for kind, value in found:
        if kind == TLV_SHA256:
            if value != image_hash:
                return ImageVerdict("INVALID_HASH", info=info)
            hashed = True
        elif kind in (TLV_SHA384, TLV_SHA512):
            return ImageVerdict(f"UNSUPPORTED (SHA-{384 if kind == TLV_SHA384 else 512} image hash)", info=info)
        elif kind == TLV_SIG_PURE:
            return ImageVerdict("UNSUPPORTED (pure signature)", info=info)
        elif kind == TLV_KEYHASH:
            key_named = value == hashlib.sha256(public).digest()
        elif kind == TLV_PUBKEY:
            key_named = value == public
        elif kind == sig_tlv and key_named and not signed:
            signed = check(value, image_hash)
    if not hashed:
        return ImageVerdict("INVALID_HASH", info=info)
    if not signed:
        return ImageVerdict("INVALID_SIGNATURE", info=info)
    return ImageVerdict("OK", image_hash.hex(), info)


def _signature_check(public_key: Any) -> tuple[int | None, Any]:
    """The signature TLV type for ``public_key`` and a ``check(tlv_value, digest) -> bool``."""
    from cryptography.exceptions import InvalidSignature
    from cryptography.hazmat.primitives import hashes
    from cryptography.hazmat.primitives.asymmetric import ec, ed25519, padding, rsa, utils

    key = getattr(public_key, "key", None)
    if isinstance(key, ec.EllipticCurvePrivateKey | ed25519.Ed25519PrivateKey | rsa.RSAPrivateKey):
        key = key.public_key()
    prehashed = utils.Prehashed(hashes.SHA256())

    def guarded(verify: Any) -> Any:
        def check(value: bytes, digest: bytes) -> bool:
            try:
                verify(value, digest)
            except (InvalidSignature, ValueError):  # ValueError: not even a signature's shape
                return False
            return True

        return check

    if isinstance(key, ec.EllipticCurvePublicKey) and key.curve.name == "secp256r1":
        ecdsa = ec.ECDSA(prehashed)
        # imgtool may pad a DER signature with zeros to a fixed 72 bytes: the DER length says where it ends
        return TLV_ECDSA_SIG, guarded(lambda v, d: key.verify(v[: v[1] + 2] if len(v) > 1 else v, d, ecdsa))
    if isinstance(key, ed25519.Ed25519PublicKey):
        return TLV_ED25519, guarded(lambda v, d: key.verify(v, d))
    if isinstance(key, rsa.RSAPublicKey) and key.key_size in (2048, 3072):
        pss = padding.PSS(mgf=padding.MGF1(hashes.SHA256()), salt_length=32)
        kind = TLV_RSA2048_PSS if key.key_size == 2048 else TLV_RSA3072_PSS
        return kind, guarded(lambda v, d: key.verify(v, d, pss, prehashed))
    return None, None
