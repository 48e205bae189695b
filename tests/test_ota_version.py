"""Version normalisation against imgtool's own parser, and latest.json history, as properties."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st
from imgtool.version import decode_version

from hcdf_trust.ota.errors import FirmwareError
from hcdf_trust.ota.latest import Entry, Latest, advance
from hcdf_trust.ota.version import parse_version

field = st.integers(min_value=0, max_value=70000)


@given(field, field, field, st.integers(min_value=0, max_value=2**33), st.booleans())
def test_fitting_versions_equal_imgtools_and_others_are_refused(major, minor, rev, build, v):
    text = f"{'v' if v else ''}{major}.{minor}.{rev}+{build}"
    fits = major <= 255 and minor <= 255 and rev <= 0xFFFF and build < 2**32
    if fits:
        ours = parse_version(text, comp="c", app="a")
        assert tuple(ours.imgtool()) == tuple(decode_version(text.lstrip("v")))
        assert decode_version(str(ours)) == ours.imgtool()  # what we write back parses the same
    else:
        with pytest.raises(FirmwareError, match="mcuboot_version"):
            parse_version(text, comp="c", app="a")


@given(st.text(max_size=20))
def test_anything_we_accept_imgtool_accepts(text):
    try:
        ours = parse_version(text, comp="c", app="a")
    except FirmwareError as exc:
        assert "comp 'c'" in str(exc)
        return
    assert tuple(decode_version(str(ours))) == (ours.major, ours.minor, ours.revision, ours.build)


def _entry(version: str, h: str = "0" * 64) -> Entry:
    return Entry(version=version, date="2026-01-01T00:00:00Z", mcuboot_hash=h, size=1, url=f"{version}.bin")


@given(st.lists(st.integers(min_value=0, max_value=50), min_size=1, max_size=12, unique=True))
def test_history_is_never_lost(minors):
    versions = [f"1.{m}.0" for m in sorted(minors)]
    doc: Latest | None = None
    for i, version in enumerate(versions):
        doc = advance(doc, board="b", app="a", new=_entry(version, f"{i:064x}"))
    assert doc is not None
    assert [doc.latest.version, *(e.version for e in doc.previous)] == list(reversed(versions))
