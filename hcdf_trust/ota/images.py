"""MCUboot images through imgtool as a library: sign, hash, read back.

imgtool's ``Image.load`` takes a file path; the bytes here come from the bounded reader,
so :func:`sign_image` fills ``Image`` the way ``load`` does. imgtool prints to stdout while
signing: callers that emit JSON run it under :func:`quiet`. Images are verified by
:mod:`.mcuboot` (hashing each byte once), not by imgtool's ``Image.verify``.

The **image hash** (what MCUmgr's image list reports, ``mcuboot_hash`` in
``latest.json``) is SHA-256 over header + payload + protected TLVs. It is not the
SHA-256 of the file a device downloads (that one also covers the unprotected TLVs:
hash, key hash, signature).
"""

from __future__ import annotations

import contextlib
import copy
import hashlib
import io
import struct
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

from .config import BoardSettings, Dependency
from .errors import FirmwareError, MalformedReleaseError
from .version import McubootVersion, parse_version

IMAGE_MAGIC = 0x96F3B83D
TLV_INFO_MAGIC = 0x6907
TLV_PROT_INFO_MAGIC = 0x6908
TLV_SEC_CNT = 0x50
HEADER = struct.Struct("<IIHHIIBBHI")  # magic, load_addr, hdr_size, protect_tlv_size, img_size, flags, version


@dataclass(frozen=True)
class SignedImage:
    data: bytes  # the file a device downloads
    image_hash: str  # MCUboot image hash (hex): header + payload + protected TLVs
    version: McubootVersion
    security_counter: int | None
    sha256: str = ""  # of ``data``: computed once, by __post_init__ when not given

    def __post_init__(self) -> None:
        if not self.sha256:
            object.__setattr__(self, "sha256", hashlib.sha256(self.data).hexdigest())

    @property
    def size(self) -> int:
        return len(self.data)


@dataclass(frozen=True)
class ImageInfo:
    """What an image's header and protected TLVs say (read back, not trusted until verified)."""

    header_size: int
    protect_tlv_size: int
    image_size: int
    version: McubootVersion
    security_counter: int | None


@contextlib.contextmanager
def quiet() -> Iterator[None]:
    """imgtool's ``create()`` prints ("sign the payload"): keep stdout clean for ``--json``."""
    with contextlib.redirect_stdout(io.StringIO()):
        yield


# Signs one prepared image in place: ``create(img, dependencies=...)``.
Create = Callable[..., None]


def sign_image(
    payload: bytes,
    *,
    name: str,
    version: McubootVersion,
    board: BoardSettings,
    security_counter: int | str,
    create: Create,
    dependencies: tuple[Dependency, ...] = (),
    intel_hex: bool = False,
    comp: str = "",
) -> SignedImage:
    """Prepend an MCUboot header to ``payload``, add TLVs and sign through ``create``.

    Raises:
        FirmwareError: imgtool refused (slot too small, bad counter, malformed HEX...).
    """
    from imgtool import image

    counter = version.auto_security_counter if isinstance(security_counter, str) else security_counter
    try:
        img = image.Image(
            version=version.imgtool(),
            header_size=board.header_size,
            pad_header=True,
            slot_size=board.slot_size,
            align=board.align,
            max_align=board.max_align,
            security_counter=counter,
            pad=False,
            confirm=False,
        )
        _load(img, payload, intel_hex=intel_hex)
        deps = None
        if dependencies:
            deps = {
                image.DEP_IMAGES_KEY: [str(d.image) for d in dependencies],
                image.DEP_VERSIONS_KEY: [
                    parse_version(d.version, comp=comp, app=name, source="dependency version").imgtool()
                    for d in dependencies
                ],
            }
        create(img, dependencies=deps)
    except FirmwareError:
        raise
    except Exception as exc:  # click.UsageError, struct.error, ValueError from imgtool / intelhex
        raise FirmwareError(f"comp {comp!r}: imgtool cannot build {name}: {exc}") from None
    data = bytes(img.payload)
    return SignedImage(data=data, image_hash=img.image_hash.hex(), version=version, security_counter=counter)


def _load(img: Any, payload: bytes, *, intel_hex: bool) -> None:
    """``Image.load`` over bytes instead of a path (same steps)."""
    if intel_hex:
        from intelhex import IntelHex

        ih = IntelHex(io.StringIO(payload.decode("ascii")))
        img.infile_data = ih.tobinarray()
        img.payload = copy.copy(img.infile_data)
        img.base_addr = ih.minaddr()
    else:
        img.infile_data = payload
        img.payload = copy.copy(payload)
    if img.pad_header and img.header_size > 0:
        if img.base_addr:
            img.base_addr -= img.header_size
        img.payload = bytes([img.erased_val] * img.header_size) + bytes(img.payload)
    img.image_size = len(img.payload) - img.header_size
    img.check_header()


def read_info(data: bytes, *, source: str) -> ImageInfo:
    """The header fields and the security counter of an MCUboot image.

    Raises:
        MalformedReleaseError: too short, wrong magic, or a protected TLV area that
            does not fit.
    """
    if len(data) < HEADER.size:
        raise MalformedReleaseError("too short for an MCUboot header", file=source, actual=f"{len(data)} bytes")
    magic, _load_addr, hdr, ptlv, size, _flags, major, minor, rev, build = HEADER.unpack_from(data)
    if magic != IMAGE_MAGIC:
        raise MalformedReleaseError(
            "not an MCUboot image (header magic)", file=source, expected=f"{IMAGE_MAGIC:#010x}", actual=f"{magic:#010x}"
        )
    end = hdr + size + ptlv
    if end + 4 > len(data):
        raise MalformedReleaseError("image is truncated", file=source, expected=f"> {end} bytes", actual=str(len(data)))
    counter = None
    if ptlv:
        off = hdr + size
        pmagic, total = struct.unpack_from("<HH", data, off)
        if pmagic != TLV_PROT_INFO_MAGIC or total != ptlv:
            raise MalformedReleaseError("malformed protected TLV area", file=source)
        pos = off + 4
        while pos + 4 <= end:
            kind, length = struct.unpack_from("<HH", data, pos)
            if pos + 4 + length > end:
                raise MalformedReleaseError("protected TLV overruns its area", file=source)
            if kind == TLV_SEC_CNT and length == 4:
                counter = struct.unpack_from("<I", data, pos + 4)[0]
            pos += 4 + length
    return ImageInfo(hdr, ptlv, size, McubootVersion(major, minor, rev, build), counter)
