"""Builders and the imgtool oracle for tests/test_mcuboot_*.py (hcdf_trust/ota/mcuboot.py).

Images are signed by imgtool itself (``Image.create``); imgtool's ``Image.verify`` is the
independent oracle the streaming check is compared with. Keys are made once per process
(``key``): one of each type, RSA being slow to generate.
"""

from __future__ import annotations

import functools
import hashlib
import os
import random
import struct
import tempfile
from collections.abc import Iterable
from typing import Any

from hcdf_trust.ota.images import quiet
from hcdf_trust.ota.mcuboot import ImageStream, ImageVerdict

KINDS = ("ecdsa-p256", "ed25519", "rsa-2048", "rsa-3072")
HDR = 0x200  # header size of the images built here (pad_header, as ota build does)


@functools.cache
def key(kind: str) -> Any:
    """One imgtool private key of ``kind`` per process."""
    from hcdf_trust.ota.keys import generate

    return generate(kind)


@functools.cache
def other_key(kind: str) -> Any:
    """Another public key of the same type (not the one that signed). For RSA a public key
    with a random odd modulus: generating a second RSA key would cost seconds, and verifying
    needs only the public half."""
    from cryptography.hazmat.primitives.asymmetric import rsa
    from imgtool import keys

    if kind.startswith("rsa"):
        bits = int(kind[4:])
        n = random.Random(bits).getrandbits(bits) | (1 << (bits - 1)) | 1
        return keys.RSAPublic(rsa.RSAPublicNumbers(65537, n).public_key())
    from hcdf_trust.ota.keys import generate

    return public(generate(kind))


def public(private: Any) -> Any:
    """The imgtool public-key object of ``private`` (what ``ota verify`` loads from a PEM)."""
    from hcdf_trust.ota.keys import wrap_key

    return wrap_key(private.key.public_key(), "test key")


def build(
    signer: Any,
    payload: bytes,
    *,
    counter: int | None = None,
    dependencies: int = 0,
    fmt: str = "hash",
    sha: str = "auto",
    pure: bool = False,
    pad_sig: bool = False,
    hsm: bool = False,
    header_size: int = HDR,
) -> bytes:
    """An MCUboot image of ``payload`` signed by imgtool with ``signer`` (a private key).
    ``counter``/``dependencies`` add protected TLVs; ``fmt`` "hash" (KEYHASH) or "full" (PUBKEY);
    ``pad_sig`` pads an ECDSA signature to 72 bytes; ``hsm`` signs the digest outside imgtool
    and hands it in as ``fixed_sig`` (what an HSM signer does)."""
    from imgtool import image, keys
    from imgtool.version import decode_version

    img = image.Image(
        version=decode_version("1.2.3+4"),
        header_size=header_size,
        pad_header=True,
        security_counter=counter,
        pad=False,
        confirm=False,
    )
    img.infile_data = payload
    img.payload = bytes([img.erased_val] * header_size) + payload
    img.image_size = len(payload)
    deps = None
    if dependencies:
        deps = {
            image.DEP_IMAGES_KEY: [str(i + 1) for i in range(dependencies)],
            image.DEP_VERSIONS_KEY: [decode_version(f"0.{i}.1") for i in range(dependencies)],
        }
    if pad_sig:
        signer = keys.ECDSA256P1(signer.key)
        signer.pad_sig = True
    with quiet():
        if hsm:
            probe = image.Image(version=img.version, header_size=header_size, pad_header=True, security_counter=counter)
            probe.infile_data, probe.payload, probe.image_size = img.infile_data, img.payload, img.image_size
            probe.create(None, fmt, None, dependencies=deps, pub_key=public(signer), vector_to_sign="digest")
            img.create(
                None,
                fmt,
                None,
                dependencies=deps,
                pub_key=public(signer),
                fixed_sig={"value": sign_digest(signer, probe.payload)},
            )
        else:
            img.create(signer, fmt, None, dependencies=deps, user_sha=sha, is_pure=pure)
    return bytes(img.payload)


def sign_digest(signer: Any, digest: bytes) -> bytes:
    """A signature over an image digest made outside imgtool (as an HSM does)."""
    from cryptography.hazmat.primitives import hashes
    from cryptography.hazmat.primitives.asymmetric import ec, ed25519, padding, utils

    pk = signer.key
    prehashed = utils.Prehashed(hashes.SHA256())
    if isinstance(pk, ec.EllipticCurvePrivateKey):
        return pk.sign(digest, ec.ECDSA(prehashed))
    if isinstance(pk, ed25519.Ed25519PrivateKey):
        return pk.sign(digest)
    return pk.sign(digest, padding.PSS(mgf=padding.MGF1(hashes.SHA256()), salt_length=32), prehashed)


def imgtool_verify(data: bytes, pub: Any) -> tuple[str, str | None]:
    """imgtool's verdict on ``data``: (result name, image hash hex when OK), or ("RAISED", exception
    type) when imgtool could not read the image at all."""
    from imgtool import image

    fd, path = tempfile.mkstemp(suffix=".bin")
    try:
        os.write(fd, data)
        os.close(fd)
        try:
            with quiet():
                result, _version, digest, _sig = image.Image.verify(path, pub)
        except Exception as exc:  # struct.error, TypeError, IndexError on malformed images
            return "RAISED", type(exc).__name__
    finally:
        os.unlink(path)
    return result.name, (digest.hex() if result.name == "OK" and digest is not None else None)


def stream(data: bytes, cuts: Iterable[int] = ()) -> ImageStream:
    """``data`` fed to a new ImageStream in pieces split at ``cuts``."""
    s = ImageStream()
    prev = 0
    for cut in [*sorted(set(cuts)), len(data)]:
        s.update(data[prev:cut])
        prev = cut
    return s


def ours(data: bytes, pub: Any, cuts: Iterable[int] = ()) -> tuple[str, str | None]:
    verdict: ImageVerdict = stream(data, cuts).verify(pub)
    return verdict.result, verdict.image_hash


def layout(data: bytes) -> dict[str, int]:
    """Offsets in a well-formed image: hash end (where the protected TLVs end), TLV start
    (header + payload) and the start of each unprotected TLV (``tlv0``, ``tlv1``, ...)."""
    _magic, _addr, hdr, ptlv, size = struct.unpack_from("<IIHHI", data)
    out = {"tlv_start": hdr + size, "hash_end": hdr + size + ptlv}
    _imagic, total = struct.unpack_from("<HH", data, hdr + size + ptlv)
    pos, end, i = hdr + size + ptlv + 4, hdr + size + ptlv + total, 0
    while pos < end:
        kind, length = struct.unpack_from("<HH", data, pos)
        out[f"tlv{i}"] = pos
        out[f"type{i}"] = kind
        pos += 4 + length
        i += 1
    out["end"] = end
    return out


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


# Hand-made images (tests/test_mcuboot_attacks.py and the deviation tests): bootutil's layout,
# struct by struct, so that a test can put any field or TLV where imgtool never would.
IMAGE_MAGIC = 0x96F3B83D
INFO, PROT_INFO = 0x6907, 0x6908
SHA256, KEYHASH, PUBKEY, SEC_CNT = 0x10, 0x01, 0x02, 0x50
SIG_TLV = {"ecdsa-p256": 0x22, "ed25519": 0x24, "rsa-2048": 0x20, "rsa-3072": 0x23}


def header(*, size: int, ptlv: int = 0, hdr: int = 32, magic: int = IMAGE_MAGIC) -> bytes:
    """An image header (version 1.2.3+4) padded with zeros to ``hdr`` bytes (at least 32)."""
    return struct.pack("<IIHHIIBBHII", magic, 0, hdr, ptlv, size, 0, 1, 2, 3, 4, 0).ljust(hdr, b"\0")


def tlv(kind: int, value: bytes) -> bytes:
    return struct.pack("<HH", kind, len(value)) + value


def area(magic: int, *tlvs: bytes, total: int | None = None) -> bytes:
    """A TLV info (``magic``, ``total``, by default the right one) followed by ``tlvs``."""
    body = b"".join(tlvs)
    return struct.pack("<HH", magic, len(body) + 4 if total is None else total) + body


def keyhash(signer: Any) -> bytes:
    return hashlib.sha256(signer.get_public_bytes()).digest()


def signed_tlvs(kind: str, hashed: bytes) -> tuple[bytes, bytes, bytes]:
    """The hash, KEYHASH and signature TLVs imgtool would add for the bytes ``hashed``."""
    signer = key(kind)
    digest = hashlib.sha256(hashed).digest()
    return tlv(SHA256, digest), tlv(KEYHASH, keyhash(signer)), tlv(SIG_TLV[kind], sign_digest(signer, digest))


def crafted(kind: str, payload: bytes = b"payload " * 64, *, prot: bytes = b"") -> bytes:
    """A well-formed image built by hand (the control of every attack: ours and imgtool say OK)."""
    ptlv = len(prot)
    hashed = header(size=len(payload), ptlv=ptlv) + payload + prot
    return hashed + area(INFO, *signed_tlvs(kind, hashed))
