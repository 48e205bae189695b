"""hcdf_trust/ota/mcuboot.py against imgtool's ``Image.verify``, the independent oracle.

Images signed by imgtool (every key type; KEYHASH and PUBKEY; with and without protected TLVs;
padded ECDSA; an HSM-style external signature; small and 300 KiB) are fed to ``ImageStream`` in
many chunkings: the verdict and image hash must be imgtool's, ``hexdigest()`` hashlib's. Then
every byte outside the payload's middle is flipped and the images truncated: where we differ
from imgtool, it must be one of the deviations mcuboot.py's docstring lists (each has its own
test below, naming bootutil's rule), and we are never the one saying OK.
"""

from __future__ import annotations

import random
import shutil
import struct
import subprocess

import pytest

from hcdf_trust.ota.mcuboot import ImageStream

from ._mcuboot import (
    HDR,
    INFO,
    KEYHASH,
    KINDS,
    PROT_INFO,
    PUBKEY,
    SEC_CNT,
    SHA256,
    SIG_TLV,
    area,
    build,
    header,
    imgtool_verify,
    key,
    keyhash,
    layout,
    other_key,
    ours,
    public,
    sha256,
    sign_digest,
    stream,
    tlv,
)

SMALL = bytes(range(256)) * 4
LARGE = random.Random(7).randbytes(300 << 10)
VARIANTS = {
    "small": {},
    "protected-pubkey": {"counter": 7, "dependencies": 2, "fmt": "full"},
    "hsm": {"counter": 3, "hsm": True},
}
NAMES = [f"{kind}/{v}" for kind in KINDS for v in VARIANTS] + ["ecdsa-p256/padded"]
NAMES += [f"{kind}/large" for kind in KINDS]


@pytest.fixture(scope="module")
def images() -> dict[str, bytes]:
    out = {}
    for kind in KINDS:
        for name, opts in VARIANTS.items():
            out[f"{kind}/{name}"] = build(key(kind), SMALL, **opts)
        out[f"{kind}/large"] = build(key(kind), LARGE, counter=9)
    out["ecdsa-p256/padded"] = build(key("ecdsa-p256"), SMALL, pad_sig=True)
    return out


def chunkings(data: bytes) -> dict[str, list[int]]:
    """Where to split ``data`` between ``update`` calls."""
    at = layout(data)
    rng = random.Random(len(data))
    tlv_heads = [v for k, v in at.items() if k.startswith("tlv") and k != "tlv_start"]
    return {
        "whole": [],
        "bytewise-then-large": [*range(1, 300), *range(300, len(data), 64 << 10)],
        "random": sorted(rng.randrange(1, len(data)) for _ in range(40)),
        "at-hash-end": [at["hash_end"]],
        "at-tlv-start": [at["tlv_start"]],
        "around-both": [at["tlv_start"] - 1, at["tlv_start"] + 1, at["hash_end"] - 1, at["hash_end"] + 1],
        "at-every-tlv": [at["hash_end"] + 4, *tlv_heads, *(t + 4 for t in tlv_heads)],
        "in-header": [1, 16, 31, 32, 33],
    }


@pytest.mark.parametrize("name", NAMES)
def test_every_chunking_gives_imgtools_verdict_and_hashlibs_digest(images, name):
    data = images[name]
    kind = name.split("/")[0]
    expected = imgtool_verify(data, public(key(kind)))
    assert expected[0] == "OK"
    assert imgtool_verify(data, key(kind)) == expected  # the private key object verifies too
    for label, cuts in chunkings(data).items():
        s = stream(data, cuts)
        assert s.hexdigest() == sha256(data), label
        assert s.size == len(data), label
        for pub in (public(key(kind)), key(kind)):
            verdict = s.verify(pub)
            assert (verdict.result, verdict.image_hash) == expected, label
            assert verdict.ok
    assert verdict.info is not None and verdict.info.image_size == len(SMALL if "large" not in name else LARGE)


def test_the_protected_tlvs_read_back(images):
    verdict = stream(images["ed25519/protected-pubkey"]).verify(public(key("ed25519")))
    assert verdict.info is not None
    assert (verdict.info.header_size, verdict.info.security_counter) == (HDR, 7)
    assert str(verdict.info.version) == "1.2.3+4"


def test_hexdigest_is_what_sha256sum_prints(images, tmp_path):
    if shutil.which("sha256sum") is None:
        pytest.skip("no sha256sum")
    data = images["rsa-3072/large"]
    (tmp_path / "img.bin").write_bytes(data)
    out = subprocess.run(["sha256sum", str(tmp_path / "img.bin")], capture_output=True, text=True, check=True)
    assert stream(data, range(0, len(data), 4093)).hexdigest() == out.stdout.split()[0]


def test_hexdigest_of_nothing_and_of_non_images():
    assert ImageStream().hexdigest() == sha256(b"")
    for data in (b"x", b"not an image at all " * 100):
        assert stream(data, [1]).hexdigest() == sha256(data)


# Where we and imgtool may differ: one name per deviation mcuboot.py's docstring lists, plus one it
# does not (a TLV running past the TLV area's declared total; see test_a_tlv_past_the_declared_area).
TYPE_IS_16_BITS = "a TLV's type is 16 bits"
HASH_REQUIRED = "a SHA-256 hash TLV is required"
KEY_MUST_BE_NAMED = "a signature counts only after a KEYHASH/PUBKEY naming the key"
TLV_WITHIN_AREA = "a TLV must end inside the area the TLV info declares"


def deviation(data: bytes, i: int) -> str | None:
    """Which deviation flipping byte ``i`` of the well-formed image ``data`` falls under."""
    at = layout(data)
    n = sum(1 for k in at if k.startswith("type"))
    for j in range(n):
        start, kind = at[f"tlv{j}"], at[f"type{j}"]
        length = struct.unpack_from("<H", data, start + 2)[0]
        if i == start + 1:
            return TYPE_IS_16_BITS
        if i == start and kind == SHA256:
            return HASH_REQUIRED
        if i in (start + 2, start + 3):
            return TLV_WITHIN_AREA
        if kind in (KEYHASH, PUBKEY) and start <= i < start + 4 + length:
            return KEY_MUST_BE_NAMED
    if i in (at["hash_end"] + 2, at["hash_end"] + 3):
        return TLV_WITHIN_AREA
    return None


FLIPPED = [n for n in NAMES if "large" not in n]


@pytest.mark.parametrize("name", FLIPPED)
def test_flipping_any_byte_never_lets_us_say_ok_where_imgtool_does_not(images, name):
    data = images[name]
    kind = name.split("/")[0]
    pub = public(key(kind))
    at = layout(data)
    middle = range(HDR + 64, at["tlv_start"] - 64)  # payload bytes alike: a few at each end suffice
    seen = set()
    for i in range(len(data)):
        if i in middle:
            continue
        for bit in (0x01, 0x80):
            mutated = bytearray(data)
            mutated[i] ^= bit
            theirs, mine = imgtool_verify(bytes(mutated), pub), ours(bytes(mutated), pub, [i])
            if mine[0] == "OK":
                assert theirs == mine, (i, bit)
            elif theirs[0] == "OK":
                why = deviation(data, i)
                assert why is not None, (i, bit, theirs, mine)
                seen.add(why)
            else:
                # both refuse; ours names imgtool's reason unless it says more (MALFORMED/UNSUPPORTED)
                # or imgtool could not read the image at all
                named = mine[0] == theirs[0] or mine[0].startswith(("MALFORMED (", "UNSUPPORTED ("))
                assert named or theirs[0] == "RAISED", (i, bit)
            assert mine[1] is None or mine[0] == "OK"
    assert seen >= {TYPE_IS_16_BITS, KEY_MUST_BE_NAMED, TLV_WITHIN_AREA}


@pytest.mark.parametrize("name", FLIPPED)
def test_trailing_bytes_are_ignored_by_both(images, name):
    data = images[name]
    pub = public(key(name.split("/")[0]))
    for tail in (b"\0", b"\xff" * 4096, struct.pack("<HH", INFO, 8) + b"junk"):
        assert ours(data + tail, pub) == imgtool_verify(data + tail, pub) == imgtool_verify(data, pub)


@pytest.mark.parametrize("name", FLIPPED)
def test_every_truncation_is_refused(images, name):
    data = images[name]
    pub = public(key(name.split("/")[0]))
    at = layout(data)
    points = {0, 1, 4, 31, 32, 33, HDR - 1, HDR, len(data) // 2, len(data) - 1}
    points |= {v + d for k, v in at.items() if not k.startswith("type") for d in (0, 2, 4)}
    for n in sorted(p for p in points if p < len(data)):
        theirs, mine = imgtool_verify(data[:n], pub), ours(data[:n], pub, [n // 2])
        assert mine[0] != "OK", n
        assert mine[1] is None
        assert mine[0] == theirs[0] or mine[0].startswith("MALFORMED ("), (n, theirs, mine)


@pytest.mark.parametrize("name", NAMES)
def test_a_wrong_key_never_gives_ok(images, name):
    data = images[name]
    kind = name.split("/")[0]
    wrong = [other_key(kind)] + [public(key(k)) for k in KINDS if k != kind]
    for pub in wrong:
        verdict = stream(data, [HDR, len(data) - 7]).verify(pub)
        assert not verdict.ok and verdict.image_hash is None
        assert verdict.result in ("INVALID_SIGNATURE",), (pub, verdict.result)
    assert imgtool_verify(data, other_key(kind))[0] != "OK"  # the oracle agrees for the same type


def test_a_key_of_an_unsupported_type_is_refused(images):
    from imgtool import keys

    for pub in (keys.ECDSA384P1.generate(), keys.X25519.generate(), object()):
        verdict = stream(images["ecdsa-p256/small"]).verify(pub)
        assert verdict.result.startswith("UNSUPPORTED (key type "), verdict.result


def test_no_key_is_a_caller_error(images):
    with pytest.raises(ValueError, match="^an MCUboot image is verified with a key$"):
        stream(images["ed25519/small"]).verify(None)


# One test per deviation mcuboot.py's docstring lists. Each builds an image imgtool says OK to and
# that MCUboot's bootloader (bootutil image_validate.c / tlv.c) would refuse, and checks we refuse it.


def resign(kind: str, hashed: bytes, *unprotected: bytes) -> bytes:
    """``hashed`` (header + payload + protected TLVs) followed by ``unprotected`` TLVs."""
    return hashed + area(INFO, *unprotected)


def digest_sig(kind: str, hashed: bytes) -> tuple[bytes, bytes]:
    import hashlib

    digest = hashlib.sha256(hashed).digest()
    return digest, sign_digest(key(kind), digest)


def test_deviation_a_sha256_hash_tlv_is_required():
    # bootutil_img_validate: "Verify the image hash. This must always be present." (image_hash_valid);
    # imgtool checks the ECDSA signature over the payload itself and says OK without any hash TLV.
    kind = "ecdsa-p256"
    hashed = header(size=len(SMALL)) + SMALL
    digest, sig = digest_sig(kind, hashed)
    data = resign(kind, hashed, tlv(KEYHASH, keyhash(key(kind))), tlv(SIG_TLV[kind], sig))
    assert imgtool_verify(data, public(key(kind)))[0] == "OK"
    assert ours(data, public(key(kind))) == ("INVALID_HASH", None)


@pytest.mark.parametrize("declared", [0, 4, 12 + 4])
def test_deviation_the_protected_area_must_be_the_one_the_header_declares(declared):
    # bootutil_tlv_iter_begin: a PROT_INFO_MAGIC area whose total is not ih_protect_tlv_size is an
    # error, and so is ih_protect_tlv_size != 0 without one. imgtool takes the area's own total.
    kind = "ed25519"
    prot = area(PROT_INFO, tlv(SEC_CNT, struct.pack("<I", 1)), tlv(0x7000, b"pad4"))  # 20 bytes
    hashed = header(size=len(SMALL), ptlv=declared) + SMALL + prot
    digest, sig = digest_sig(kind, hashed)
    data = resign(kind, hashed, tlv(SHA256, digest), tlv(KEYHASH, keyhash(key(kind))), tlv(SIG_TLV[kind], sig))
    assert imgtool_verify(data, public(key(kind)))[0] == "OK"
    mine = ours(data, public(key(kind)))
    if declared == 0:
        assert mine == ("MALFORMED (protected TLVs the header does not declare)", None)
    else:
        assert mine == ("MALFORMED (the protected TLV area is not the one the header declares)", None)


@pytest.mark.parametrize("which", ["hash", "signature"])
def test_deviation_a_tlv_type_is_16_bits(which):
    # struct image_tlv { uint16_t it_type; uint16_t it_len; }: 0x0110 is not IMAGE_TLV_SHA256. imgtool
    # unpacks 'BBH' and ignores the high byte.
    kind = "ecdsa-p256"
    hashed = header(size=len(SMALL)) + SMALL
    digest, sig = digest_sig(kind, hashed)
    hash_type = SHA256 | (0x100 if which == "hash" else 0)
    sig_type = SIG_TLV[kind] | (0x100 if which == "signature" else 0)
    data = resign(kind, hashed, tlv(hash_type, digest), tlv(KEYHASH, keyhash(key(kind))), tlv(sig_type, sig))
    assert imgtool_verify(data, public(key(kind)))[0] == "OK"
    assert ours(data, public(key(kind)))[0] == ("INVALID_HASH" if which == "hash" else "INVALID_SIGNATURE")


@pytest.mark.parametrize("naming", ["none", "other-key", "after-the-signature", "other-pubkey"])
@pytest.mark.parametrize("kind", ["ecdsa-p256", "ed25519"])
def test_deviation_a_signature_counts_only_after_the_key_is_named(kind, naming):
    # image_validate.c: EXPECTED_KEY_TLV sets key_id = bootutil_find_key(); a signature TLV while
    # key_id < 0 is skipped ("Ignore this signature if it is out of bounds"). imgtool never reads KEYHASH.
    hashed = header(size=len(SMALL)) + SMALL
    digest, sig = digest_sig(kind, hashed)
    other = other_key(kind)
    named = {
        "none": [tlv(SIG_TLV[kind], sig)],
        "other-key": [tlv(KEYHASH, keyhash(other)), tlv(SIG_TLV[kind], sig)],
        "after-the-signature": [tlv(SIG_TLV[kind], sig), tlv(KEYHASH, keyhash(key(kind)))],
        "other-pubkey": [tlv(PUBKEY, other.get_public_bytes()), tlv(SIG_TLV[kind], sig)],
    }[naming]
    data = resign(kind, hashed, tlv(SHA256, digest), *named)
    assert imgtool_verify(data, public(key(kind)))[0] == "OK"
    assert ours(data, public(key(kind))) == ("INVALID_SIGNATURE", None)
    # the control: the same signature after the right KEYHASH, or the right PUBKEY, is OK
    for right in (tlv(KEYHASH, keyhash(key(kind))), tlv(PUBKEY, key(kind).get_public_bytes())):
        good = resign(kind, hashed, tlv(SHA256, digest), right, tlv(SIG_TLV[kind], sig))
        assert ours(good, public(key(kind))) == imgtool_verify(good, public(key(kind))) == ("OK", digest.hex())


def test_deviation_sha512_image_hashes_are_refused():
    # releases name SHA-256 image hashes; imgtool signs and verifies Ed25519 over SHA-512 too.
    kind = "ed25519"
    data = build(key(kind), SMALL, sha="512")
    assert imgtool_verify(data, public(key(kind)))[0] == "OK"
    assert ours(data, public(key(kind))) == ("UNSUPPORTED (SHA-512 image hash)", None)


def test_deviation_sha384_image_hashes_are_refused():
    # imgtool says KEY_MISMATCH (SHA-384 goes with P-384 only); we name the hash.
    kind = "ecdsa-p256"
    hashed = header(size=len(SMALL)) + SMALL
    digest, sig = digest_sig(kind, hashed)
    import hashlib

    data = resign(
        kind, hashed, tlv(0x11, hashlib.sha384(hashed).digest()), tlv(KEYHASH, keyhash(key(kind))), tlv(0x22, sig)
    )
    assert ours(data, public(key(kind))) == ("UNSUPPORTED (SHA-384 image hash)", None)
    assert imgtool_verify(data, public(key(kind)))[0] != "OK"


def test_deviation_pure_signatures_are_refused():
    # imgtool's pure Ed25519 images carry a SHA-512 hash TLV (refused as such); with a SHA-256 one and
    # SIG_PURE, imgtool checks the signature over the image bytes themselves and says OK.
    kind = "ed25519"
    built = build(key(kind), SMALL, pure=True)
    assert imgtool_verify(built, public(key(kind)))[0] == "OK"
    assert ours(built, public(key(kind)))[0].startswith("UNSUPPORTED (")
    hashed = header(size=len(SMALL)) + SMALL
    digest, _ = digest_sig(kind, hashed)
    pure_sig = key(kind).key.sign(hashed)
    data = resign(
        kind, hashed, tlv(SHA256, digest), tlv(0x25, b"\1"), tlv(KEYHASH, keyhash(key(kind))), tlv(0x24, pure_sig)
    )
    assert imgtool_verify(data, public(key(kind)))[0] == "OK"
    assert ours(data, public(key(kind))) == ("UNSUPPORTED (pure signature)", None)


@pytest.mark.parametrize("where", ["info-total-short", "signature-length-long"])
def test_a_tlv_past_the_declared_area_is_refused(images, where):
    # NOT in mcuboot.py's docstring list (reported to the lead): _walk refuses a TLV that runs past
    # the total the TLV info declares; imgtool reads the signature on past it and says OK.
    data = bytearray(images["ecdsa-p256/padded"])
    at = layout(bytes(data))
    if where == "info-total-short":
        struct.pack_into("<H", data, at["hash_end"] + 2, at["end"] - at["hash_end"] - 1)
    else:
        struct.pack_into("<H", data, at["tlv2"] + 2, 73)
    pub = public(key("ecdsa-p256"))
    assert imgtool_verify(bytes(data), pub)[0] == "OK"
    assert ours(bytes(data), pub) == ("MALFORMED (a TLV overruns the TLV area)", None)


@pytest.mark.parametrize("hdr", [28, 31, 32])
def test_a_header_size_of_28_is_read_as_imgtool_reads_it(hdr):
    # the header's fields are 28 bytes (the 4-byte pad after them is not read); a header size of
    # 28..31 puts the payload over the pad, hashed and signed like any other byte: imgtool says OK too
    kind = "ed25519"
    hashed = header(size=len(SMALL), hdr=32)[:hdr] + SMALL
    hashed = hashed[:8] + struct.pack("<H", hdr) + hashed[10:]
    digest, sig = digest_sig(kind, hashed)
    data = resign(kind, hashed, tlv(SHA256, digest), tlv(KEYHASH, keyhash(key(kind))), tlv(SIG_TLV[kind], sig))
    assert ours(data, public(key(kind)), [27, 28]) == imgtool_verify(data, public(key(kind))) == ("OK", digest.hex())


@pytest.mark.parametrize("kind", KINDS)
def test_images_signed_as_ota_build_signs_them(kind, tmp_path):
    """The signing path of ``ota build`` (sign_image + FileSigner, a board's header size and
    alignment, a security counter, dependencies): imgtool's verdict, ours, SignedImage's fields."""
    from hcdf_trust.ota.config import BoardSettings, Dependency
    from hcdf_trust.ota.images import sign_image
    from hcdf_trust.ota.signer import FileSigner
    from hcdf_trust.ota.version import McubootVersion

    signed = sign_image(
        LARGE[:70001],
        name="flex-io",
        version=McubootVersion(2, 1, 0, 7),
        board=BoardSettings(header_size=0x400, align=8),
        security_counter=12,
        create=FileSigner(key(kind)).create,
        dependencies=(Dependency(1, "1.0.0"),),
        comp="test",
    )
    expected = imgtool_verify(signed.data, public(key(kind)))
    assert expected == ("OK", signed.image_hash)
    for cuts in chunkings(signed.data).values():
        s = stream(signed.data, cuts)
        verdict = s.verify(public(key(kind)))
        assert (verdict.result, verdict.image_hash) == expected
        assert s.hexdigest() == signed.sha256
        assert verdict.info is not None
        assert (verdict.info.version, verdict.info.security_counter) == (signed.version, 12)
        assert verdict.info.header_size == 0x400
