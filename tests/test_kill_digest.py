"""digest.py: every comparison, bound and copy is observable (mutation-testing killers).

Oracles are hashlib over the same bytes and the documented pin rules (64 hex digits
full, 8..63 a weak prefix), never the code under test.
"""

from __future__ import annotations

import io
import os

import pytest

from hcdf_trust.digest import (
    Pin,
    PinStrength,
    hash_bytes,
    hash_chunks,
    hash_fd,
    is_full_sha256,
    parse_pin,
    read_small,
)
from hcdf_trust.errors import MalformedDigestError

from ._kill import hcdf, model, sha
from ._kill import other_digest as _same_prefix_other_digest

# -- Pin.matches: a full pin is compared in full ---------------------------------------


@pytest.mark.parametrize("keep", [8, 16, 32, 63])
def test_a_full_pin_that_only_shares_a_prefix_does_not_match(keep):
    real = sha(b"model")
    wrong = _same_prefix_other_digest(real, keep)
    pin = parse_pin(wrong)
    assert pin is not None and pin.is_full
    assert not pin.matches(real)
    assert parse_pin(real).matches(real)  # type: ignore[union-attr]


def test_a_weak_pin_matches_by_prefix_only():
    real = sha(b"model")
    assert Pin(real[:8]).matches(real)
    assert Pin(real[:12]).matches(real)
    assert not Pin(_same_prefix_other_digest(real, 8)[:9]).matches(real)


def test_resolve_refuses_a_full_pin_that_shares_the_first_digits_of_the_content(cli, tmp_path):
    glb = os.urandom(500)
    (tmp_path / "m.glb").write_bytes(glb)
    wrong = _same_prefix_other_digest(sha(glb), 8)
    doc = tmp_path / "d.hcdf"
    doc.write_text(hcdf(model("m.glb", wrong)))
    r = cli("resolve", doc, "--json", "--no-lock", "--cache-dir", tmp_path / "c")
    assert r.exit_code == 1, r.stdout
    [e] = r.json["errors"]
    assert e["code"] == "digest-mismatch" and e["expected"] == wrong and e["actual"] == sha(glb)


# -- parse_pin: the accepted shapes and their bounds -----------------------------------


def test_parse_pin_blank_means_unpinned():
    assert parse_pin(None) is None
    assert parse_pin("") is None
    assert parse_pin("   \t\n") is None


def test_parse_pin_normalises_case_space_and_prefix():
    real = sha(b"x")
    assert parse_pin(f"  {real.upper()}  ") == Pin(real)
    assert parse_pin(f"sha256:{real}") == Pin(real)
    assert parse_pin(f"SHA256:{real[:10]}") == Pin(real[:10])


@pytest.mark.parametrize("digits", [8, 9, 63, 64])
def test_parse_pin_accepts_8_to_64_hex_digits(digits):
    text = sha(b"y")[:digits]
    pin = parse_pin(text)
    assert pin == Pin(text)
    assert pin.is_full is (digits == 64)
    assert pin.strength is (PinStrength.FULL if digits == 64 else PinStrength.WEAK)


@pytest.mark.parametrize("text", ["a" * 7, "a" * 65, "sha256:" + "a" * 7, "g" * 64, "abc-1234", "12 345678"])
def test_parse_pin_refuses_other_shapes_naming_them(text):
    with pytest.raises(MalformedDigestError) as info:
        parse_pin(text, file="d.hcdf", line=7)
    err = info.value
    assert err.file == "d.hcdf" and err.line == 7 and err.actual == text
    assert f'sha="{text}"' in str(err)


def test_parse_pin_length_message_counts_the_digits():
    with pytest.raises(MalformedDigestError) as info:
        parse_pin("a" * 7)
    assert "7 hex digits" in str(info.value) and "64" in str(info.value) and "8" in str(info.value)


def test_pin_strength_values_are_the_json_words():
    assert PinStrength.FULL == "full" and PinStrength.WEAK == "weak"


@pytest.mark.parametrize(
    ("text", "full"),
    [
        (sha(b"z"), True),
        (sha(b"z")[:63], False),
        (sha(b"z") + "0", False),
        (sha(b"z").upper(), False),  # the cache and the lock use lower case only
        ("g" * 64, False),
        ("X" * 64, False),
    ],
)
def test_is_full_sha256(text, full):
    assert is_full_sha256(text) is full


# -- hashing: digest and size agree with hashlib, limits are exact ---------------------


SIZES = [0, 1, 4096, (64 << 10) - 1, 64 << 10, (64 << 10) + 1, (1 << 20) + 3, (3 << 20) + 17]


@pytest.mark.parametrize("size", SIZES)
def test_hash_fd_equals_hashlib(tmp_path, size):
    data = os.urandom(size)
    path = tmp_path / "f"
    path.write_bytes(data)
    fd = os.open(path, os.O_RDONLY)
    try:
        got = hash_fd(fd)
    finally:
        os.close(fd)
    assert (got.sha256, got.size) == (sha(data), size)


def test_hash_fd_reads_on_when_the_file_grew_past_the_size_given(tmp_path):
    data = os.urandom(3000)
    path = tmp_path / "f"
    path.write_bytes(data)
    fd = os.open(path, os.O_RDONLY)
    try:
        got = hash_fd(fd, size=1000)
    finally:
        os.close(fd)
    assert (got.sha256, got.size) == (sha(data), 3000)


@pytest.mark.parametrize("size", [0, 1, 100, 2 << 20])
def test_read_small_returns_the_whole_file_even_when_it_grew(tmp_path, size):
    data = os.urandom(size + 5000)
    path = tmp_path / "f"
    path.write_bytes(data)
    for hint in (size, len(data), len(data) + 10):
        fd = os.open(path, os.O_RDONLY)
        try:
            assert read_small(fd, hint) == data
        finally:
            os.close(fd)


def test_hash_chunks_and_copy():
    chunks = [os.urandom(n) for n in (0, 10, 1 << 16, 3)]
    data = b"".join(chunks)
    sink = io.BytesIO()
    got = hash_chunks(iter(chunks), sink=sink)
    assert (got.sha256, got.size) == (sha(data), len(data))
    assert sink.getvalue() == data
    assert hash_chunks(iter(chunks)).sha256 == sha(data)


def test_hash_chunks_limit_is_exact_and_stops_before_copying_the_excess():
    sink = io.BytesIO()
    assert hash_chunks([b"ab", b"cd"], limit=4).size == 4
    with pytest.raises(ValueError, match="4-byte limit"):
        hash_chunks([b"ab", b"cd", b"e"], sink=sink, limit=4)
    assert sink.getvalue() == b"abcd"


def test_hash_bytes():
    data = os.urandom(77)
    got = hash_bytes(data)
    assert (got.sha256, got.size) == (sha(data), 77)


def test_a_malformed_pin_without_a_uri_is_named_by_the_attribute_alone():
    with pytest.raises(MalformedDigestError) as info:
        parse_pin("zz-not-hex")
    assert info.value.message.startswith('sha="zz-not-hex" is not a hex')
