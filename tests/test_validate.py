"""``hcdf-trust validate``: the upstream schema suite, the examples, the schema source, the CLI.

The upstream files are read from the shared corpus (``HCDFORMAT``), never copied
into the project; documents that need a change are mutated in memory and
written to a temporary folder.
"""

from __future__ import annotations

import re

import pytest

from hcdf_trust.errors import InputError, XmlError
from hcdf_trust.validate import (
    FileSchemaSource,
    SchemaSource,
    compile_schema,
    load_schema_file,
    validate_document,
)

from .conftest import HCDFORMAT

XSD = HCDFORMAT / "hcdf.xsd"
STREAM_XSD = HCDFORMAT / "hcdf-stream-profile.xsd"
VALID = sorted((HCDFORMAT / "tests" / "valid").glob("*.hcdf"))
INVALID = sorted((HCDFORMAT / "tests" / "invalid").glob("*.hcdf"))
EXAMPLES = sorted((HCDFORMAT / "examples").glob("*.hcdf"))
STREAMS = HCDFORMAT / "examples" / "profiles" / "operational.streams.xml"
HUMANOID = HCDFORMAT / "examples" / "humanoid-mobile-base.hcdf"


def _name(path) -> str:
    return path.name


def test_the_upstream_suite_is_there():
    # an empty glob would make the parametrized tests below pass vacuously
    assert len(VALID) >= 13 and len(INVALID) >= 10 and len(EXAMPLES) >= 3
    assert all(p.with_suffix(".expected").is_file() for p in INVALID)


@pytest.mark.parametrize("path", VALID, ids=_name)
def test_upstream_valid_documents_validate(path):
    report = validate_document(path, schema=XSD)
    assert report.checked == ["xsd", "semantic"]
    assert report.schema is not None and report.schema.endswith("hcdf.xsd")
    assert [str(f) for f in report.findings] == []
    assert report.ok


@pytest.mark.parametrize("path", INVALID, ids=_name)
def test_upstream_invalid_documents_fail_with_the_expected_message(path, cli):
    expected = path.with_suffix(".expected").read_text().strip()
    assert expected
    result = cli("validate", path, "--schema", XSD, "--json")
    errors = result.json["errors"]
    assert any(expected in e["message"] for e in errors), errors
    if result.exit_code == 3:  # not well-formed: an input error, as for every verb
        assert [e["code"] for e in errors] == ["xml"]
    else:
        assert result.exit_code == 1
        assert result.json["ok"] is False and "xsd" in result.json["checked"]


@pytest.mark.parametrize("path", [p for p in INVALID if p.stem != "wrong-version-type"], ids=_name)
def test_xsd_findings_point_at_the_offending_element(path):
    report = validate_document(path, schema=XSD)
    lines = path.read_text().splitlines()
    xsd = [f for f in report.findings if f.code == "xsd"]
    assert xsd
    for f in xsd:
        assert f.file == report.source and f.severity == "error" and f.path.startswith("/hcdf")
        element = re.match(r"Element '([\w-]+)'", f.message).group(1)
        assert f"<{element}" in lines[f.line - 1], (str(f), lines[f.line - 1])


def test_malformed_document_is_an_input_error():
    with pytest.raises(XmlError, match="Opening and ending tag mismatch") as info:
        validate_document(HCDFORMAT / "tests" / "invalid" / "wrong-version-type.hcdf", schema=XSD)
    assert info.value.exit_code == 3 and info.value.line == 4


@pytest.mark.parametrize("path", EXAMPLES, ids=_name)
def test_upstream_examples_validate(path, cli):
    result = cli("validate", path, "--schema", XSD, "--json")
    assert result.exit_code == 0, result.stdout
    assert result.json["ok"] is True and result.json["errors"] == []
    assert result.json["checked"] == ["xsd", "semantic"]


def test_humanoid_warnings_are_the_2_5g_t1_links_without_phy_roles():
    report = validate_document(HUMANOID, schema=XSD)
    assert report.ok
    assert [(f.code, f.severity) for f in report.findings] == [("t1-phy-role-missing", "warning")] * 4
    assert all("2.5gbase-t1" in f.message for f in report.findings)
    assert any("44 written comp/port, 0 written comp.port" in n for n in report.notes)


def test_stream_profile_validates_against_its_schema(cli):
    result = cli("validate", STREAMS, "--schema", STREAM_XSD, "--json")
    assert result.exit_code == 0, result.stdout
    assert result.json["checked"] == ["xsd"]
    assert result.json["schema"].endswith("hcdf-stream-profile.xsd")


def test_stream_profile_given_hcdf_xsd_uses_the_sibling_schema():
    report = validate_document(STREAMS, schema=XSD)
    assert report.ok and report.checked == ["xsd"]
    assert report.schema.endswith("hcdf-stream-profile.xsd")


def test_stream_profile_against_a_schema_without_its_root_fails(tmp_path):
    xsd = tmp_path / "only-hcdf.xsd"
    xsd.write_text(
        '<xs:schema xmlns:xs="http://www.w3.org/2001/XMLSchema" version="1.0"><xs:element name="hcdf"/></xs:schema>'
    )
    report = validate_document(STREAMS, schema=xsd)
    assert not report.ok
    assert any("No matching global declaration" in f.message for f in report.findings)


def test_without_schema_only_the_semantic_rules_run(cli):
    result = cli("validate", HUMANOID)
    assert result.exit_code == 0
    assert "only the semantic rules were checked" in result.stderr
    payload = cli("validate", HUMANOID, "--json").json
    assert payload["schema"] is None and payload["checked"] == ["semantic"]


# --- several findings at once, through the CLI -------------------------------------

MUTATIONS = [  # (old, new, code expected on the new text's line)
    ('<gate tc-mask="0x0F" duration-us="920"/>', '<gate tc-mask="0x0F" duration-us="900"/>', None),
    ("<port>agx-thor/mgbe0</port>", "<port>agx-thor/mgbe9</port>", "unresolved-port"),
    ('<limit lower="0" upper="2.5" effort="30"', '<limit lower="0" upper="-1" effort="30"', "joint-limit-order"),
    ('key-ref="link-n79-j100-1"', 'key-ref="link-n79-j100-0" confidentiality-offset="30"', None),
    (
        'cipher="gcm-aes-128" key-agreement="psk" key-ref="link-n79-j100-2"',
        'cipher="gcm-aes-256" key-agreement="psk" key-ref="link-n79-j100-0"',
        "macsec-key-ref-conflict",
    ),
    ('<port name="pwr_in" type="POWER">', '<port name="pwr_in" type="MAINS">', "xsd"),
]


def _mutated_humanoid(tmp_path):
    text = HUMANOID.read_text()
    for old, new, _ in MUTATIONS:
        assert text.count(old) >= 1, old
        text = text.replace(old, new, 1)
    # the head's PHY becomes a master too: j100_to_head then has two masters
    head = text.index('<comp name="head"')
    text = text[:head] + text[head:].replace('<phy role="slave"/>', '<phy role="master"/>', 1)
    path = tmp_path / "humanoid.hcdf"
    path.write_text(text)
    return path, text.splitlines()


def test_json_lists_every_error_at_once(tmp_path, cli):
    path, lines = _mutated_humanoid(tmp_path)
    result = cli("validate", path, "--schema", XSD, "--json")
    assert result.exit_code == 1
    payload = result.json
    assert payload["ok"] is False
    errors = payload["errors"]
    codes = {e["code"] for e in errors}
    assert {
        "xsd",
        "unresolved-port",
        "schedule-cycle-mismatch",
        "joint-limit-order",
        "macsec-key-ref-conflict",
        "t1-phy-roles",
    } <= codes, codes
    for e in errors:
        assert set(e) >= {"code", "severity", "message", "file", "line"}
        assert e["severity"] == "error" and e["file"].endswith("humanoid.hcdf") and e["line"] > 0
    for _, new, code in MUTATIONS:
        if code is not None:
            line = next(i for i, text in enumerate(lines, 1) if new in text)
            assert any(e["code"] == code and e["line"] == line for e in errors), (code, line)
    # findings come sorted by line; warnings are listed with the errors
    assert [f["line"] for f in payload["findings"]] == sorted(f["line"] for f in payload["findings"])
    assert any(f["code"] == "macsec-cipher-unsupported" for f in payload["findings"])


def test_human_output_names_file_line_and_code(tmp_path, cli):
    path, _ = _mutated_humanoid(tmp_path)
    result = cli("validate", path, "--schema", XSD)
    assert result.exit_code == 1
    assert re.search(r"humanoid\.hcdf:\d+: error\[schedule-cycle-mismatch\]: schedule 'uplink-1ms'", result.stderr)
    assert re.search(r"\d+ errors?, \d+ warnings?\b", result.stderr)


# --- input errors ---------------------------------------------------------------------


def test_missing_document_and_schema_are_input_errors(tmp_path, cli):
    assert cli("validate", tmp_path / "nope.hcdf").exit_code == 3
    result = cli("validate", HUMANOID, "--schema", tmp_path / "nope.xsd", "--json")
    assert result.exit_code == 3 and result.json["errors"][0]["code"] == "not-found"


def test_not_an_xsd_and_not_hcdf_are_input_errors(tmp_path, cli):
    assert cli("validate", HUMANOID, "--schema", HUMANOID).exit_code == 3
    other = tmp_path / "other.xml"
    other.write_text("<robot/>")
    result = cli("validate", other, "--json")
    assert result.exit_code == 3 and "not an HCDF document" in result.json["errors"][0]["message"]


def test_remote_or_hostile_schema_imports_are_refused(tmp_path):
    head = '<xs:schema xmlns:xs="http://www.w3.org/2001/XMLSchema">'
    remote = tmp_path / "remote.xsd"
    remote.write_text(f'{head}<xs:include schemaLocation="http://127.0.0.1:9/x.xsd"/></xs:schema>')
    with pytest.raises(InputError, match="refused"):
        load_schema_file(remote)
    (tmp_path / "evil.xsd").write_text(
        '<?xml version="1.0"?><!DOCTYPE x [<!ENTITY e SYSTEM "file:///etc/passwd">]>'
        f'{head}<xs:element name="hcdf"/></xs:schema>'
    )
    local = tmp_path / "local.xsd"
    local.write_text(f'{head}<xs:include schemaLocation="evil.xsd"/></xs:schema>')
    with pytest.raises(XmlError, match="DOCTYPE"):
        load_schema_file(local)
    escape = tmp_path / "sub" / "escape.xsd"
    escape.parent.mkdir()
    escape.write_text(f'{head}<xs:include schemaLocation="../local.xsd"/></xs:schema>')
    with pytest.raises(InputError, match="outside the root"):
        load_schema_file(escape)


def test_a_clean_local_schema_include_works(tmp_path):
    head = '<xs:schema xmlns:xs="http://www.w3.org/2001/XMLSchema" version="1.0">'
    (tmp_path / "types.xsd").write_text(f'{head}<xs:element name="hcdf"/></xs:schema>')
    top = tmp_path / "top.xsd"
    top.write_text(f'{head}<xs:include schemaLocation="types.xsd"/></xs:schema>')
    doc = tmp_path / "d.hcdf"
    doc.write_text('<hcdf version="1.0" name="d"/>')
    report = validate_document(doc, schema=top)
    assert report.ok and report.checked == ["xsd", "semantic"]


# --- the schema source ----------------------------------------------------------------


def test_built_schema_is_cached_by_content():
    first = load_schema_file(XSD)
    assert load_schema_file(XSD) is first
    assert compile_schema(XSD.read_bytes(), name=str(XSD), base=XSD.parent) is first
    other = compile_schema(XSD.read_bytes(), name="other name", base=XSD.parent)
    assert other.name == "other name" and other.sha256 == first.sha256  # reports name what was asked for
    assert load_schema_file(XSD).name == str(XSD)
    assert first.declares("hcdf") and not first.declares("stream-profile")
    assert first.version == "1.0" and len(first.sha256) == 64


def test_any_schema_source_can_supply_the_schema(tmp_path):
    class Registry:  # what a signed registry will look like: a schema per root and version
        def __init__(self):
            self.asked = []

        def schema_for(self, *, root, version):
            self.asked.append((root, version))
            if version != "1.0":
                return None
            return compile_schema(XSD.read_bytes(), name="registry:hcdf/1.0")

    registry = Registry()
    assert isinstance(registry, SchemaSource) and isinstance(FileSchemaSource(XSD), SchemaSource)
    report = validate_document(HUMANOID, schema=registry)
    assert report.schema == "registry:hcdf/1.0" and report.checked == ["xsd", "semantic"]
    assert registry.asked == [("hcdf", "1.0")]
    doc = tmp_path / "v9.hcdf"
    doc.write_text('<hcdf version="9.0" name="x"/>')
    report = validate_document(doc, schema=registry)
    assert report.schema is None and report.checked == ["semantic"]
    assert any("no schema is known" in n for n in report.notes)


def test_major_version_mismatch_is_a_warning(tmp_path):
    doc = tmp_path / "v2.hcdf"
    doc.write_text('<hcdf version="2.0" name="x"/>')
    report = validate_document(doc, schema=XSD)
    assert [(f.code, f.severity) for f in report.findings] == [
        ("foreign-major-version", "warning"),  # upstream's reader refuses it (issue 18)
        ("schema-version", "warning"),
    ]
