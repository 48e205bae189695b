"""Mutation killers for pin's text editing (``scan_start_tags``, ``apply_pins``; see tests/MUTATION.md).

pin edits a document's bytes, never re-serialises it: each reference is located in the text
by a scanner that must agree with the parsed tree, and every disagreement is a refusal
naming the document and the line. These tests pin the scanner's positions and lines and
each refusal's message, file and line, through the two public functions.
"""

from __future__ import annotations

import dataclasses
import hashlib

import pytest

from hcdf_trust.document import Document
from hcdf_trust.include.pin import PinEditError, apply_pins, scan_start_tags

A = hashlib.sha256(b"a").hexdigest()


# --- scan_start_tags: names, offsets, lines, attributes -------------------------------------


def test_each_start_tag_has_its_first_and_last_line_after_multiline_markup():
    data = (
        b"<?xml version='1.0'?>\n"  # line 1
        b"<!-- a comment\n over two lines -->\n"  # lines 2-3
        b"<hcdf\n  a='1'>\n"  # lines 4-5
        b"  <![CDATA[\n\n]]>\n"  # lines 6-8
        b'  <x/><y\n\n b="2"/>\n'  # lines 9-11
        b"  <z c='3'/>\n"  # line 12
        b"</hcdf>\n"
    )
    tags = scan_start_tags(data)
    assert [(t.name, t.first_line, t.last_line) for t in tags] == [
        (b"hcdf", 4, 5),
        (b"x", 9, 9),
        (b"y", 9, 11),
        (b"z", 12, 12),
    ]
    assert [data[t.start : t.end] for t in tags] == [b"<hcdf\n  a='1'>", b"<x/>", b'<y\n\n b="2"/>', b"<z c='3'/>"]


def test_attributes_are_scanned_with_their_quotes_and_value_offsets():
    data = b'<m  uri = "a b.glb"\tsha=\'x\'\n name="" />'
    [tag] = scan_start_tags(data)
    assert [(a.name, a.quote, data[a.value_start : a.value_end], data[a.end - 1 : a.end]) for a in tag.attrs] == [
        (b"uri", b'"', b"a b.glb", b'"'),
        (b"sha", b"'", b"x", b"'"),
        (b"name", b'"', b"", b'"'),
    ]
    assert tag.attr("sha") is tag.attrs[1] and tag.attr("href") is None
    assert tag.attr("name").end == data.index(b'" />') + 1


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (b"<a>\n\n<\n</a>", "cannot scan the markup at line 3"),
        (b"<a\n b='1'>\n<b/>\n< c/></a>", "cannot scan the markup at line 4"),
        (b"<a>\n<b\n c='1' d/></a>", "cannot scan the attributes of the start tag at line 2"),
        (b"<a>\n\n<b c='1'x='2'/></a>", "cannot scan the attributes of the start tag at line 3"),
        (b"<a>\n<b c='1' / x/></a>", "cannot scan the attributes of the start tag at line 2"),
    ],
)
def test_text_that_does_not_scan_is_refused_naming_its_line(data, message):
    with pytest.raises(PinEditError) as info:
        scan_start_tags(data)
    assert info.value.message == message and info.value.exit_code == 3


# --- apply_pins: each reference is located, or refused by name --------------------------------

DOC = b"""<?xml version="1.0"?>
<hcdf>
  <visual>
    <model uri="a.glb"/>
  </visual>
  <visual><model
      uri='b.glb' sha="sha256:0"/></visual>
</hcdf>
"""


def _doc(data: bytes = DOC) -> Document:
    return Document.from_bytes(data, source="t.hcdf")


def _refused(doc: Document, edits) -> PinEditError:
    with pytest.raises(PinEditError) as info:
        apply_pins(doc, edits)
    return info.value


def test_a_reference_of_another_document_is_refused_naming_this_one():
    doc, other = _doc(), _doc()  # the same text, another tree
    ref = other.references()[0]
    e = _refused(doc, [(ref, A)])
    assert (e.message, e.file, e.line, e.exit_code) == ("cannot locate <model> in the text", "t.hcdf", 4, 3)


def test_a_reference_without_its_uri_attribute_is_refused():
    doc = _doc()
    ref = dataclasses.replace(doc.references()[1], uri_attr=None)
    e = _refused(doc, [(ref, A)])
    assert (e.message, e.file, e.line) == ("cannot locate <model> in the text", "t.hcdf", ref.line)


def test_a_reference_whose_uri_is_not_the_texts_is_refused():
    doc = _doc()
    real = doc.references()[0]
    ref = dataclasses.replace(real, uri="c.glb")
    e = _refused(doc, [(ref, A)])
    assert (e.message, e.file, e.line) == ("cannot locate the uri attribute of c.glb", "t.hcdf", 4)


def test_an_element_the_text_does_not_show_at_its_place_is_refused():
    doc = _doc()
    ref = doc.references()[1]
    ref.element.tag = "texture"  # the tree now disagrees with the text at that tag
    e = _refused(doc, [(ref, A)])
    assert (e.message, e.file, e.line) == ("the text at line 6 does not match <model>", "t.hcdf", ref.line)


def test_an_element_on_another_line_than_its_tag_is_refused():
    doc = _doc()
    ref = doc.references()[1]
    for moved in (5, 8):  # before the tag's first line (6), after its last (7)
        ref.element.sourceline = moved
        e = _refused(doc, [(ref, A)])
        assert (e.message, e.line) == ("the text at line 6 does not match <model>", ref.line)
    for inside in (6, 7):
        ref.element.sourceline = inside
        assert b'sha="sha256:' + A.encode() + b'"' in apply_pins(doc, [(ref, A)])


def test_a_tree_with_another_number_of_elements_than_the_text_is_refused():
    doc = _doc()
    doc.root.append(doc.root.makeelement("extra"))
    e = _refused(doc, [(doc.references()[0], A)])
    assert (e.message, e.file, e.line) == (
        "found 5 start tags in the text but 6 elements in the tree",
        "t.hcdf",
        None,
    )


def test_edits_keep_the_text_around_them_and_the_quote_style():
    doc = _doc()
    a, b = doc.references()
    out = apply_pins(doc, [(b, A), (a, A)])  # in any order
    assert out == DOC.replace(b'uri="a.glb"', b'uri="a.glb" sha="sha256:' + A.encode() + b'"').replace(
        b'sha="sha256:0"', b'sha="sha256:' + A.encode() + b'"'
    )


def test_an_upper_case_prefix_is_kept_as_a_prefix_and_no_prefix_stays_none():
    data = DOC.replace(b'sha="sha256:0"', b'sha=" SHA256:0"').replace(b'uri="a.glb"', b"uri='a.glb' sha='0'")
    doc = _doc(data)
    a, b = doc.references()
    out = apply_pins(doc, [(a, A), (b, A)])
    assert out == data.replace(b"sha='0'", b"sha='" + A.encode() + b"'").replace(
        b'sha=" SHA256:0"', b'sha="sha256:' + A.encode() + b'"'
    )


def test_a_uri_written_over_lines_is_located_as_the_parser_reads_it():
    """Attribute-value normalisation: CRLF, CR, LF and tab are one space each, as the parser reports."""
    data = b'<hcdf>\r\n  <visual><model uri="m\r\nx\ry\nz\tw&#x61;.glb"/></visual>\r\n</hcdf>\r\n'
    doc = _doc(data)
    [ref] = doc.references()
    assert ref.uri == "m x y z wa.glb"
    out = apply_pins(doc, [(ref, A)])
    assert out == data.replace(b'.glb"', b'.glb" sha="' + A.encode() + b'"')


def test_a_document_starting_with_a_newline_is_counted_from_its_first_byte():
    data = b"\n<hcdf>\n  <visual><model uri='m.glb'/></visual>\n</hcdf>\n"
    assert [(t.name, t.first_line) for t in scan_start_tags(data)] == [(b"hcdf", 2), (b"visual", 3), (b"model", 3)]
    doc = _doc(data)
    [ref] = doc.references()
    assert apply_pins(doc, [(ref, A)]) == data.replace(b"'m.glb'", b"'m.glb' sha='" + A.encode() + b"'")


def test_a_utf16_document_without_a_byte_order_mark_is_refused_by_its_encoding():
    data = '<?xml version="1.0" encoding="UTF-16"?>\n<hcdf><visual><model uri="a"/></visual></hcdf>'.encode("utf-16-le")
    doc = _doc(data)
    e = _refused(doc, [(doc.references()[0], A)])
    assert (e.message, e.file) == ("cannot edit a document encoded as UTF-16", "t.hcdf")
