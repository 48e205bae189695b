"""Hand-made MCUboot images that try to get "OK" from hcdf_trust/ota/mcuboot.py without a valid
signature over the bytes that are hashed. Each attack must be refused, never raise, and its
control (the same construction done honestly) must pass, so that a refusal is the attack's doing.
Plus the memory bound: a 64 MiB image keeps only its header and TLV areas.
"""

from __future__ import annotations

import hashlib
import struct
import tracemalloc

import pytest

from hcdf_trust.ota.mcuboot import MAX_TLV_AREAS, ImageStream

from ._mcuboot import (
    INFO,
    KEYHASH,
    KINDS,
    PROT_INFO,
    SEC_CNT,
    SHA256,
    SIG_TLV,
    area,
    crafted,
    header,
    key,
    keyhash,
    other_key,
    ours,
    public,
    sign_digest,
    signed_tlvs,
    stream,
    tlv,
)

PAYLOAD = b"payload " * 64
KIND = "ecdsa-p256"


def refused(data: bytes, kind: str = KIND) -> str:
    """Our verdict on ``data`` (whole, and split byte by byte over its first 100 bytes, then at
    every 97th), which must not be OK, carry no hash, and be the same however it streamed."""
    pub = public(key(kind))
    whole = stream(data).verify(pub)
    split = stream(data, [*range(1, min(100, len(data))), *range(100, len(data), 97)]).verify(pub)
    assert whole == split
    assert not whole.ok and whole.image_hash is None, whole
    return whole.result


def test_the_control_is_ok():
    for kind in KINDS:
        data = crafted(kind)
        assert ours(data, public(key(kind)))[0] == "OK"


def test_signature_tlv_before_the_hash_tlv_still_needs_the_right_hash():
    hashed = header(size=len(PAYLOAD)) + PAYLOAD
    h, k, s = signed_tlvs(KIND, hashed)
    assert ours(hashed + area(INFO, k, s, h), public(key(KIND)))[0] == "OK"  # order alone is no attack
    wrong_hash = tlv(SHA256, bytes(32))
    assert refused(hashed + area(INFO, k, s, wrong_hash)) == "INVALID_HASH"
    assert refused(hashed + area(INFO, k, s)) == "INVALID_HASH"


@pytest.mark.parametrize("right_first", [True, False])
def test_two_hash_tlvs_one_wrong(right_first):
    hashed = header(size=len(PAYLOAD)) + PAYLOAD
    h, k, s = signed_tlvs(KIND, hashed)
    wrong = tlv(SHA256, hashlib.sha256(b"other").digest())
    hashes = (h, wrong) if right_first else (wrong, h)
    assert refused(hashed + area(INFO, *hashes, k, s)) == "INVALID_HASH"


@pytest.mark.parametrize("cut", [0, 1, 31, 33, 64])
def test_hash_tlv_of_the_wrong_length(cut):
    hashed = header(size=len(PAYLOAD)) + PAYLOAD
    h, k, s = signed_tlvs(KIND, hashed)
    digest = h[4:]
    value = (digest + bytes(64))[:cut] if cut > 32 else digest[:cut]
    assert refused(hashed + area(INFO, tlv(SHA256, value), k, s)) == "INVALID_HASH"


@pytest.mark.parametrize("kind", KINDS)
def test_keyhash_of_another_key_before_a_valid_signature(kind):
    hashed = header(size=len(PAYLOAD)) + PAYLOAD
    h, _k, s = signed_tlvs(kind, hashed)
    assert refused(hashed + area(INFO, h, tlv(KEYHASH, keyhash(other_key(kind))), s), kind) == "INVALID_SIGNATURE"


@pytest.mark.parametrize("kind", KINDS)
def test_signature_and_hash_grafted_from_another_image(kind):
    donor = header(size=len(PAYLOAD)) + PAYLOAD
    tlvs = signed_tlvs(kind, donor)
    forged = b"malware " * 64
    assert refused(header(size=len(forged)) + forged + area(INFO, *tlvs), kind) == "INVALID_HASH"
    # the donor's hash re-computed for the new payload, its signature kept
    h2 = tlv(SHA256, hashlib.sha256(header(size=len(forged)) + forged).digest())
    result = refused(header(size=len(forged)) + forged + area(INFO, h2, tlvs[1], tlvs[2]), kind)
    assert result == "INVALID_SIGNATURE"


def test_a_signature_by_another_key_of_the_same_type_named_by_its_own_keyhash():
    from hcdf_trust.ota.keys import generate

    attacker = generate(KIND)
    hashed = header(size=len(PAYLOAD)) + PAYLOAD
    digest = hashlib.sha256(hashed).digest()
    data = hashed + area(
        INFO, tlv(SHA256, digest), tlv(KEYHASH, keyhash(attacker)), tlv(SIG_TLV[KIND], sign_digest(attacker, digest))
    )
    assert refused(data) == "INVALID_SIGNATURE"
    assert ours(data, public(attacker))[0] == "OK"  # the control: it is a valid image for its own key


def prot_area(total: int | None = None, magic: int = PROT_INFO) -> bytes:
    return area(magic, tlv(SEC_CNT, struct.pack("<I", 5)), total=total)


@pytest.mark.parametrize(
    ("declared", "prot", "expected"),
    [
        (12, prot_area(total=16), "MALFORMED (the protected TLV area is not the one the header declares)"),
        (16, prot_area(total=12), "MALFORMED (the protected TLV area is not the one the header declares)"),
        (12, prot_area(magic=INFO), "MALFORMED (the protected TLV area is not the one the header declares)"),
        (0, prot_area(), "MALFORMED (protected TLVs the header does not declare)"),
        (2, b"", "MALFORMED (the protected TLV area is not the one the header declares)"),
        (8, area(PROT_INFO, tlv(SEC_CNT, b"12345"), total=8), "MALFORMED (a protected TLV overruns its area)"),
    ],
)
def test_protected_area_not_the_one_declared(declared, prot, expected):
    hashed = header(size=len(PAYLOAD), ptlv=declared) + PAYLOAD + prot
    assert refused(hashed + area(INFO, *signed_tlvs(KIND, hashed))) == expected


def test_protected_area_control():
    prot = prot_area()
    hashed = header(size=len(PAYLOAD), ptlv=len(prot)) + PAYLOAD + prot
    verdict = stream(hashed + area(INFO, *signed_tlvs(KIND, hashed))).verify(public(key(KIND)))
    assert verdict.ok and verdict.info is not None and verdict.info.security_counter == 5


def unprotected(total: int | None = None, *, extra: bytes = b"") -> bytes:
    hashed = header(size=len(PAYLOAD)) + PAYLOAD
    return hashed + area(INFO, *signed_tlvs(KIND, hashed), total=total) + extra


@pytest.mark.parametrize(
    ("data", "expected"),
    [
        (unprotected(total=0xFFFF), "MALFORMED (the TLV area is truncated or its total is wrong)"),
        (unprotected(total=3), "MALFORMED (the TLV area is truncated or its total is wrong)"),
        (unprotected(total=0), "MALFORMED (the TLV area is truncated or its total is wrong)"),
        (unprotected(total=4 + 36 + 2), "MALFORMED (a TLV overruns the TLV area)"),
        (unprotected(total=4 + 36 + 36 + 40), "MALFORMED (a TLV overruns the TLV area)"),
        (unprotected(total=4), "INVALID_HASH"),
    ],
    ids=["past-the-end", "total-3", "total-0", "header-cut", "value-cut", "empty"],
)
def test_tlv_area_total_wrong(data, expected):
    assert refused(data) == expected


def test_tlv_length_overrunning_the_file():
    hashed = header(size=len(PAYLOAD)) + PAYLOAD
    h, k, s = signed_tlvs(KIND, hashed)
    long_sig = struct.pack("<HH", SIG_TLV[KIND], 0xFF00) + s[4:]
    data = hashed + area(INFO, h, k, total=4 + len(h) + len(k) + 4 + 0xFF00) + long_sig
    assert refused(data) == "MALFORMED (the TLV area is truncated or its total is wrong)"


def test_tlv_info_with_the_wrong_magic():
    hashed = header(size=len(PAYLOAD)) + PAYLOAD
    assert refused(hashed + area(0x6906, *signed_tlvs(KIND, hashed))) == "INVALID_TLV_INFO_MAGIC"


@pytest.mark.parametrize("hdr", [0, 8, 27])
def test_header_size_smaller_than_the_header(hdr):
    # 28..31 (the fields without the 4-byte pad) are read like imgtool does: hashed and signed as any
    # other header byte (see test_a_header_size_of_28_is_read_as_imgtool_reads_it)
    raw = bytearray(unprotected())
    struct.pack_into("<H", raw, 8, hdr)
    assert refused(bytes(raw)) == f"MALFORMED (header size {hdr} is smaller than the header)"


def test_a_signed_image_whose_header_says_hdr_size_below_32():
    # signed over a header that claims 16 bytes: the bytes are consistent, the header is not
    payload = PAYLOAD
    hashed = bytearray(header(size=len(payload)) + payload)
    struct.pack_into("<H", hashed, 8, 16)
    assert refused(bytes(hashed) + area(INFO, *signed_tlvs(KIND, bytes(hashed)))).startswith("MALFORMED (header size")


@pytest.mark.parametrize("size", [2**32 - 1, 2**31, 1 << 20])
def test_image_size_past_the_file(size):
    raw = bytearray(unprotected())
    struct.pack_into("<I", raw, 12, size)
    assert refused(bytes(raw)).startswith("MALFORMED (truncated: ")


def test_image_size_short_of_the_payload():
    raw = bytearray(unprotected())
    struct.pack_into("<I", raw, 12, len(PAYLOAD) - 4)
    assert refused(bytes(raw)) == "INVALID_TLV_INFO_MAGIC"


def test_wrong_image_magic():
    raw = bytearray(unprotected())
    raw[0] ^= 1
    assert refused(bytes(raw)) == "INVALID_MAGIC"


@pytest.mark.parametrize("which", ["hash", "keyhash", "signature"])
def test_tlv_types_with_a_nonzero_high_byte(which):
    hashed = header(size=len(PAYLOAD)) + PAYLOAD
    tlvs = list(signed_tlvs(KIND, hashed))
    i = ["hash", "keyhash", "signature"].index(which)
    kind, length = struct.unpack_from("<HH", tlvs[i])
    tlvs[i] = struct.pack("<HH", kind | 0x8000, length) + tlvs[i][4:]
    assert refused(hashed + area(INFO, *tlvs)) == ("INVALID_HASH" if which == "hash" else "INVALID_SIGNATURE")


@pytest.mark.parametrize(
    ("kind", "hashed_by", "expected"),
    [
        (0x11, hashlib.sha384, "UNSUPPORTED (SHA-384 image hash)"),
        (0x12, hashlib.sha512, "UNSUPPORTED (SHA-512 image hash)"),
    ],
)
def test_sha384_and_sha512_hash_tlvs(kind, hashed_by, expected):
    hashed = header(size=len(PAYLOAD)) + PAYLOAD
    h, k, s = signed_tlvs(KIND, hashed)
    assert refused(hashed + area(INFO, tlv(kind, hashed_by(hashed).digest()), k, s)) == expected
    assert refused(hashed + area(INFO, h, tlv(kind, hashed_by(hashed).digest()), k, s)) == expected


def test_sig_pure_tlv():
    hashed = header(size=len(PAYLOAD)) + PAYLOAD
    h, k, s = signed_tlvs("ed25519", hashed)
    assert refused(hashed + area(INFO, h, tlv(0x25, b"\1"), k, s), "ed25519") == "UNSUPPORTED (pure signature)"


@pytest.mark.parametrize("data", [b"", b"\x3d", bytes(27), crafted(KIND)[:27]], ids=["empty", "1", "27-zeros", "27"])
def test_too_short_for_a_header(data):
    assert refused(data) == "MALFORMED (too short for an MCUboot header)"


def test_31_bytes():
    assert refused(bytes(31)) == "INVALID_MAGIC"
    assert refused(crafted(KIND)[:31]).startswith("MALFORMED (truncated: 31 bytes, the header says ")


def test_header_only():
    assert refused(crafted(KIND)[:32]).startswith("MALFORMED (truncated: 32 bytes, the header says ")


@pytest.mark.parametrize(
    "signature",
    [b"", b"\x30", b"\x30\x00", b"\x30\xff" + bytes(70), bytes(72), b"\xff" * 600],
    ids=["empty", "1", "der-empty", "long-form", "zeros", "long"],
)
@pytest.mark.parametrize("kind", KINDS)
def test_signatures_of_no_shape(kind, signature):
    hashed = header(size=len(PAYLOAD)) + PAYLOAD
    h, k, _s = signed_tlvs(kind, hashed)
    assert refused(hashed + area(INFO, h, k, tlv(SIG_TLV[kind], signature)), kind) == "INVALID_SIGNATURE"


@pytest.mark.parametrize("kind", KINDS)
def test_a_bad_signature_then_a_good_one_after_the_keyhash(kind):
    # bootutil would check only the first signature after the KEYHASH; we and imgtool check each until
    # one verifies. Still only a valid signature by the named key over this image's digest counts.
    hashed = header(size=len(PAYLOAD)) + PAYLOAD
    h, k, s = signed_tlvs(kind, hashed)
    bad = tlv(SIG_TLV[kind], bytes(len(s) - 4))
    assert ours(hashed + area(INFO, h, k, bad, s), public(key(kind)))[0] == "OK"
    assert refused(hashed + area(INFO, h, k, bad, bad), kind) == "INVALID_SIGNATURE"


def test_a_signature_for_another_key_type_is_not_checked_with_this_key():
    # an Ed25519 signature TLV (0x24) in an image checked with a P-256 key: not our key's TLV
    hashed = header(size=len(PAYLOAD)) + PAYLOAD
    h, _k, s = signed_tlvs("ed25519", hashed)
    assert refused(hashed + area(INFO, h, tlv(KEYHASH, keyhash(key(KIND))), s)) == "INVALID_SIGNATURE"


def test_hostile_images_do_not_raise_for_any_key():
    hashed = header(size=len(PAYLOAD)) + PAYLOAD
    samples = [b"", bytes(31), unprotected(total=3), unprotected(total=0xFFFF), crafted(KIND)[:-1]]
    samples += [hashed + area(INFO, tlv(0xFFFF, b""), tlv(0, b""), tlv(SHA256, b""), tlv(KEYHASH, b""))]
    for data in samples:
        for kind in KINDS:
            assert not stream(data).verify(public(key(kind))).ok


def test_verify_twice_and_keep_streaming():
    """verify() reads the state without consuming it: asking again gives the same verdict."""
    data = crafted(KIND)
    s = stream(data)
    assert s.verify(public(key(KIND))) == s.verify(public(key(KIND)))
    s.update(b"trailing")
    assert s.verify(public(key(KIND))).ok
    assert s.hexdigest() == hashlib.sha256(data + b"trailing").hexdigest()


def test_a_64_mib_image_streams_in_bounded_memory():
    kind = "ed25519"
    chunk = bytes(range(256)) * 4096  # 1 MiB
    count = 64
    head = header(size=count * len(chunk))
    image_hash = hashlib.sha256(head)
    for _ in range(count):
        image_hash.update(chunk)
    digest = image_hash.digest()
    tail = area(INFO, tlv(SHA256, digest), tlv(KEYHASH, keyhash(key(kind))), tlv(0x24, sign_digest(key(kind), digest)))
    whole = hashlib.sha256(head)
    tracemalloc.start()
    try:
        s = ImageStream()
        s.update(head)
        for _ in range(count):
            s.update(chunk)
            whole.update(chunk)
        s.update(tail)
        whole.update(tail)
        _current, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 1 << 20, peak  # under one chunk: nothing of the payload is kept
    assert len(s._tlvs) <= MAX_TLV_AREAS and len(s._tlvs) == len(tail)
    assert len(s._head) <= 32
    verdict = s.verify(public(key(kind)))
    assert (verdict.result, verdict.image_hash) == ("OK", digest.hex())
    assert s.hexdigest() == whole.hexdigest() and s.size == len(head) + count * len(chunk) + len(tail)


def test_trailing_megabytes_after_the_tlvs_are_not_kept():
    data = crafted(KIND)
    s = stream(data)
    for _ in range(3):
        s.update(bytes(1 << 20))
    assert len(s._tlvs) <= MAX_TLV_AREAS
    assert s.verify(public(key(KIND))).ok


def refused_info(data: bytes, pub=None):
    verdict = stream(data).verify(pub if pub is not None else public(key(KIND)))
    assert not verdict.ok
    return verdict.result, verdict.info


@pytest.mark.parametrize(
    ("tlvs", "expected"),
    [
        ("wrong-hash", "INVALID_HASH"),
        ("no-hash", "INVALID_HASH"),
        ("no-signature", "INVALID_SIGNATURE"),
        ("sha512", "UNSUPPORTED (SHA-512 image hash)"),
        ("pure", "UNSUPPORTED (pure signature)"),
        ("bad-total", "MALFORMED (the TLV area is truncated or its total is wrong)"),
        ("bad-magic", "INVALID_TLV_INFO_MAGIC"),
    ],
)
def test_a_refusal_after_the_header_still_says_what_the_header_and_protected_tlvs_read(tlvs, expected):
    """ImageVerdict.info: "the header and protected TLVs, once those could be read (not trusted
    unless OK)": a refusal names the version and counter the image claims."""
    prot = prot_area()
    hashed = header(size=len(PAYLOAD), ptlv=len(prot)) + PAYLOAD + prot
    h, k, s = signed_tlvs(KIND, hashed)
    body = {
        "wrong-hash": area(INFO, tlv(SHA256, bytes(32)), k, s),
        "no-hash": area(INFO, k, s),
        "no-signature": area(INFO, h, k),
        "sha512": area(INFO, tlv(0x12, bytes(64)), k, s),
        "pure": area(INFO, h, tlv(0x25, b"\1"), k, s),
        "bad-total": area(INFO, h, k, s, total=3),
        "bad-magic": area(0x6906, h, k, s),
    }[tlvs]
    result, info = refused_info(hashed + body)
    assert result == expected
    assert info is not None
    assert (str(info.version), info.security_counter, info.image_size, info.header_size) == ("1.2.3+4", 5, 512, 32)
    assert info.protect_tlv_size == len(prot)


def test_a_key_of_an_unsupported_type_is_named_and_the_header_still_read():
    from imgtool import keys

    for pub, name in ((keys.ECDSA384P1.generate(), "ECDSA384P1"), (keys.X25519.generate(), "X25519")):
        result, info = refused_info(crafted(KIND), pub)
        assert result == f"UNSUPPORTED (key type {name})"
        assert info is not None and str(info.version) == "1.2.3+4"


def with_prot(*prot_tlvs: bytes, counter: int = 5) -> bytes:
    """A signed image with protected TLVs ``prot_tlvs`` (by default the security counter only)."""
    prot = area(PROT_INFO, *(prot_tlvs or (tlv(SEC_CNT, struct.pack("<I", counter)),)))
    hashed = header(size=len(PAYLOAD), ptlv=len(prot)) + PAYLOAD + prot
    return hashed + area(INFO, *signed_tlvs(KIND, hashed))


@pytest.mark.parametrize(
    ("prot_tlvs", "counter"),
    [
        ((tlv(SEC_CNT, struct.pack("<I", 2**31 + 5)),), 2**31 + 5),
        ((tlv(SEC_CNT, struct.pack("<I", 2**32 - 1)),), 2**32 - 1),
        ((tlv(SEC_CNT, struct.pack("<I", 7)), tlv(0x7000, b"four")), 7),
        ((tlv(0x7000, b"four"),), None),
        ((tlv(SEC_CNT, b"\1\0\0\0\0"),), None),
        ((tlv(SEC_CNT, b"\1\0\0"),), None),
    ],
    ids=["2^31+5", "2^32-1", "then-another-4-byte-tlv", "no-counter-4-byte-tlv", "5-bytes", "3-bytes"],
)
def test_the_security_counter_is_the_4_byte_sec_cnt_tlv_unsigned(prot_tlvs, counter):
    verdict = stream(with_prot(*prot_tlvs)).verify(public(key(KIND)))
    assert verdict.ok and verdict.info is not None
    assert verdict.info.security_counter == counter
    assert verdict.info.security_counter is None or isinstance(verdict.info.security_counter, int)


def test_no_protected_tlvs_no_counter():
    verdict = stream(crafted(KIND)).verify(public(key(KIND)))
    assert verdict.ok and verdict.info is not None
    assert verdict.info.security_counter is None and verdict.info.protect_tlv_size == 0


def test_truncated_before_the_hash_end_names_the_sizes():
    data = with_prot()  # header 32 + payload 512 + protected 12
    for n in (32, 100, 32 + 512 + 11):
        assert refused(data[:n]) == f"MALFORMED (truncated: {n} bytes, the header says {32 + 512 + 12} + TLVs)"


@pytest.mark.parametrize("prot", [b"", area(PROT_INFO), area(PROT_INFO, tlv(SEC_CNT, bytes(4)))], ids=["0", "4", "12"])
def test_truncated_at_the_hash_end_or_inside_the_tlv_info(prot):
    hashed = header(size=len(PAYLOAD), ptlv=len(prot)) + PAYLOAD + prot
    data = hashed + area(INFO, *signed_tlvs(KIND, hashed))
    for cut in (0, 1, 3):
        result, info = refused_info(data[: len(hashed) + cut])
        assert result == "MALFORMED (truncated: no TLV area)"
        assert info is not None and info.protect_tlv_size == len(prot) and str(info.version) == "1.2.3+4"


def test_a_tlv_info_alone_with_total_4_is_an_image_without_a_hash():
    hashed = header(size=len(PAYLOAD)) + PAYLOAD
    result, info = refused_info(hashed + area(INFO))
    assert result == "INVALID_HASH" and info is not None


def test_a_tlv_overrunning_its_area_still_reads_the_header():
    prot = prot_area()
    hashed = header(size=len(PAYLOAD), ptlv=len(prot)) + PAYLOAD + prot
    h, k, s = signed_tlvs(KIND, hashed)
    result, info = refused_info(hashed + area(INFO, h, k, s, total=4 + len(h) + len(k) + 8))
    assert result == "MALFORMED (a TLV overruns the TLV area)"
    assert info is not None and info.security_counter == 5


def test_magic_is_the_headers_first_word_once_a_header_is_in():
    """``ImageStream.magic`` (ota verify names it when it is not MCUboot's): None before a whole
    header (28 bytes of fields) arrived, then the first little-endian 32-bit word, whatever it is."""
    data = crafted(KIND)
    s = ImageStream()
    for i in range(27):
        s.update(data[i : i + 1])
        assert s.magic is None
    s.update(data[27:28])
    assert s.magic == 0x96F3B83D
    assert stream(b"\x01\x02\x03\x04" + bytes(24)).magic == 0x04030201
    assert stream(b"ELF\x7f" + bytes(100)).magic == int.from_bytes(b"ELF\x7f", "little")
    assert stream(b"").magic is None and stream(bytes(27)).magic is None
