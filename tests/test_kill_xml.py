"""xml.py: the one parser's bounds are exact and its refusals say why (mutation-testing killers)."""

from __future__ import annotations

import pytest
from lxml import etree

from hcdf_trust.errors import XmlError
from hcdf_trust.xml import MAX_DEPTH, MAX_DOCUMENT_BYTES, parse_bytes, sourceline


def nested(levels: int) -> bytes:
    """``levels`` elements nested, the root counted, one per line."""
    return ("".join(f"<e{i}>\n" for i in range(levels)) + "".join(f"</e{i}>" for i in reversed(range(levels)))).encode()


def test_the_depth_limit_is_200_levels_exactly():
    assert MAX_DEPTH == 200
    tree = parse_bytes(nested(200), source="ok.hcdf")
    assert tree.getroot().tag == "e0"
    with pytest.raises(XmlError) as info:
        parse_bytes(nested(201), source="deep.hcdf")
    err = info.value
    assert err.file == "deep.hcdf" and err.line == 201  # the first element too deep, on its own line
    assert "deeper than 200 levels" in str(err)


def _padded(size: int) -> bytes:
    """A well-formed document of exactly ``size`` bytes (comments of 4 KiB: no node over libxml2's limits)."""
    head, comment = b"<hcdf/>\n", b"<!--" + b"x" * 4089 + b"-->\n"
    body = head + comment * ((size - len(head)) // len(comment))
    return body + b" " * (size - len(body))


def test_the_size_limit_is_exact():
    assert MAX_DOCUMENT_BYTES == 32 << 20
    parse_bytes(_padded(MAX_DOCUMENT_BYTES), source="max.hcdf")
    with pytest.raises(XmlError) as info:
        parse_bytes(_padded(MAX_DOCUMENT_BYTES + 1), source="big.hcdf")
    assert info.value.file == "big.hcdf"
    assert f"{MAX_DOCUMENT_BYTES + 1} bytes, over the {MAX_DOCUMENT_BYTES}-byte limit" in str(info.value)


@pytest.mark.parametrize("data", [b"", b"   \n\t ", b"\n"])
def test_an_empty_document_is_refused(data):
    with pytest.raises(XmlError, match="empty document") as info:
        parse_bytes(data, source="e.hcdf")
    assert info.value.file == "e.hcdf"


def test_malformed_xml_names_the_line():
    with pytest.raises(XmlError) as info:
        parse_bytes(b"<hcdf>\n<a>\n</b>\n</hcdf>", source="m.hcdf")
    err = info.value
    assert err.file == "m.hcdf" and err.line == 3 and "malformed XML" in str(err)


def test_an_encoding_lxml_cannot_honour_is_malformed():
    with pytest.raises(XmlError, match="malformed XML"):
        parse_bytes(b'<?xml version="1.0" encoding="no-such-codec"?><hcdf/>', source="x")


@pytest.mark.parametrize(
    "doc",
    [
        b'<!DOCTYPE hcdf [<!ENTITY a "x">]><hcdf>&a;</hcdf>',
        b"<!DOCTYPE hcdf><hcdf/>",
        b'<!DOCTYPE hcdf PUBLIC "-//X//Y" "missing.dtd"><hcdf/>',
    ],
)
def test_any_doctype_is_refused(doc):
    with pytest.raises(XmlError, match="DOCTYPE") as info:
        parse_bytes(doc, source="d.hcdf")
    assert info.value.file == "d.hcdf"


def test_an_external_dtd_is_refused_before_it_is_opened(tmp_path):
    import os

    fifo = tmp_path / "hang.dtd"
    os.mkfifo(fifo)  # opening it would block for ever
    doc = f'<!DOCTYPE hcdf SYSTEM "{fifo}"><hcdf/>'.encode()
    with pytest.raises(XmlError) as info:
        parse_bytes(doc, source="d.hcdf")
    assert "DOCTYPE" in str(info.value)


def test_a_text_node_over_libxml2s_normal_limit_is_refused():
    """huge_tree stays off: libxml2 refuses a single text node over 10 MB."""
    doc = b"<hcdf>" + b"x" * (11 << 20) + b"</hcdf>"
    with pytest.raises(XmlError, match="malformed XML"):
        parse_bytes(doc, source="t.hcdf")


def test_whitespace_text_and_comments_are_kept():
    tree = parse_bytes(b"<hcdf>\n  <a/>\n  <!-- c -->\n</hcdf>", source="w")
    root = tree.getroot()
    assert root.text == "\n  "
    assert [type(c) for c in root] == [etree._Element, etree._Comment]


def test_entities_are_not_resolved_and_ids_are_plain_attributes():
    tree = parse_bytes(b'<hcdf><a xml:id="one"/><b xml:id="one"/></hcdf>', source="i")
    assert len(tree.getroot()) == 2


def test_sourceline():
    tree = parse_bytes(b"<hcdf>\n\n<a/>\n</hcdf>", source="s")
    assert sourceline(tree.getroot()[0]) == 3
    assert sourceline(etree.Element("x")) is None


def test_a_doctype_is_refused_on_line_1():
    with pytest.raises(XmlError) as info:
        parse_bytes(b'<!DOCTYPE hcdf>\n<hcdf version="1.0" name="t"/>', source="robot.hcdf")
    assert info.value.line == 1 and info.value.file == "robot.hcdf"
