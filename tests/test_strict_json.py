"""``localfile.parse_json``: the one JSON reader, at its edges (what it accepts, what it names)."""

from __future__ import annotations

import json

import pytest

from hcdf_trust.localfile import MAX_JSON_DEPTH, JsonError, parse_json


def parse(data: bytes | str, **kw):
    raw = data.encode() if isinstance(data, str) else data
    return parse_json(raw, source="f.json", limit=kw.pop("limit", 1 << 20), **kw)


def refused(data: bytes | str, **kw) -> JsonError:
    with pytest.raises(JsonError) as info:
        parse(data, **kw)
    return info.value


def nested(depth: int) -> str:
    return "[" * depth + "]" * depth


def test_what_json_reads_the_same_everywhere_is_read_as_json_reads_it():
    text = '{"a": [1, -2.5, true, null, "\\ud83d\\ude00 \\u00e9"], "b": {"c": {}}, "": 0}'
    assert parse(text) == json.loads(text)
    assert parse("5") == 5 and parse('"x"') == "x" and parse("[]") == []


def test_nesting_up_to_the_limit_is_read_one_more_is_named():
    assert parse(nested(MAX_JSON_DEPTH)) is not None
    exc = refused(nested(MAX_JSON_DEPTH + 1))
    assert "nested too deeply at /0/0" in exc.message and exc.expected == f"at most {MAX_JSON_DEPTH} levels"
    assert "nested too deeply" in refused(nested(100_000)).message  # the parser's own recursion limit


def test_depth_counts_objects_and_lists_alike():
    assert parse('{"a":' * MAX_JSON_DEPTH + "1" + "}" * MAX_JSON_DEPTH) is not None
    assert "nested too deeply" in refused('{"a":' * (MAX_JSON_DEPTH + 1) + "1" + "}" * (MAX_JSON_DEPTH + 1)).message


@pytest.mark.parametrize(
    ("text", "pointer"),
    [
        ('{"k": 1, "k": 2}', "(the document)"),
        ('{"a": {"k": 1, "k": 1}}', "/a"),
        ('[0, {"k": 1, "k": 2}]', "/1"),
        ('{"a/b": {"~": {"k": 1, "k": 2}}}', "/a~1b/~0"),
    ],
)
def test_a_key_twice_is_named_with_its_json_pointer(text, pointer):
    assert refused(text).message == f"document: key 'k' appears twice in the object at {pointer} " + (
        "(parsers disagree on which one counts)"
    )


@pytest.mark.parametrize("token", ["NaN", "Infinity", "-Infinity"])
def test_constants_no_other_parser_reads_are_refused(token):
    assert refused(f'{{"a": {token}}}').message == f"document: {token} is not a JSON number"


def test_floats_out_of_range_are_refused_and_integers_only_when_asked():
    assert "out of range" in refused('{"a": 1e400}').message
    assert "out of range" in refused('{"a": -1e400}').message
    assert parse('{"a": 1.5}') == {"a": 1.5}
    assert refused('{"a": 1.5}', floats=False).message == "document: number 1.5 is not an integer"
    assert parse('{"a": 15}', floats=False) == {"a": 15}


@pytest.mark.parametrize(
    ("text", "where"),
    [
        ('"\\ud800"', "the string"),
        ('["ok", "a\\udfffb"]', "the string at /1"),
        ('{"x": {"y": "\\ud83d"}}', "the string at /x/y"),
        ('{"\\udc00": 1}', "a key at (the document)"),
        ('"\\ude00\\ud83d"', "the string"),  # a low surrogate before a high one pairs nothing
    ],
)
def test_lone_surrogates_are_refused_wherever_they_are(text, where):
    assert refused(text).message == f"document: {where} holds a lone surrogate"


def test_an_escaped_backslash_before_u_is_not_a_surrogate():
    assert parse('"\\\\ud800"') == "\\ud800"


@pytest.mark.parametrize(
    ("data", "why"),
    [
        ('{"a": 1}'.encode("utf-16"), "not UTF-8"),
        (b'{"a": "\xed\xa0\x80"}', "not UTF-8"),  # a surrogate encoded in UTF-8
        (b"\xef\xbb\xbf{}", "not JSON"),  # a byte-order mark
        (b'{"a": 1} x', "not JSON"),
        (b"", "not JSON"),
        (b"1" * 5000, "not JSON"),  # an integer longer than Python converts
    ],
)
def test_bytes_that_are_not_one_utf8_json_document_are_refused(data, why):
    assert why in refused(data).message


def test_a_syntax_error_names_its_line_and_column():
    exc = refused('{\n  "a": 1,\n  "b": }')
    assert exc.line == 3 and "(column 8)" in exc.message and exc.file == "f.json"


def test_the_size_limit_is_checked_before_parsing():
    assert parse("[1]", limit=3) == [1]
    assert refused("[1] ", limit=3).message == "document is over the 3-byte limit"
