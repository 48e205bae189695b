"""What the walker refuses, through every verb: roots that are not HCDF, hidden references,
and extensions that would hide the document's own references."""

from __future__ import annotations

import hashlib
import json

import pytest
from lxml import etree

from hcdf_trust.document import Document, Kind

from .conftest import HCDFORMAT

SCHEMA = HCDFORMAT / "hcdf.xsd"
NOT_HCDF = {
    "default-namespace": ('<hcdf xmlns="urn:x" version="1.0" name="t"/>', "<hcdf> in namespace 'urn:x'"),
    "prefixed": ('<h:hcdf xmlns:h="urn:h" version="1.0" name="t"/>', "<h:hcdf> in namespace 'urn:h'"),
    "robot": ('<robot version="1.0" name="t"/>', "<robot>"),
}
VERBS = {
    "resolve": ["resolve"],
    "verify": ["verify"],
    "pin": ["pin", "--offline"],
    "validate": ["validate"],
    "validate-schema": ["validate", "--schema", str(SCHEMA)],
}
GLB = b"glTF model bytes"
GLB_SHA = hashlib.sha256(GLB).hexdigest()


def _run(cli, tmp_path, verb, doc):
    args = [*VERBS[verb], doc, "--json"]
    if verb in ("resolve", "verify", "pin"):
        args += ["--cache-dir", tmp_path / "cache"]
    if verb == "verify":
        lock = tmp_path / "hcdf.lock"
        lock.write_text(json.dumps({"lock_version": 1, "artifacts": []}))
        args += ["--lock", lock]
    return cli(*args)


@pytest.mark.parametrize("verb", VERBS)
@pytest.mark.parametrize("root", NOT_HCDF)
def test_a_root_that_is_not_hcdf_in_no_namespace_is_exit_3_for_every_verb(cli, tmp_path, verb, root):
    text, shown = NOT_HCDF[root]
    doc = tmp_path / "doc.hcdf"
    doc.write_text(text + "\n")
    r = _run(cli, tmp_path, verb, doc)
    assert r.exit_code == 3, r.stdout + r.stderr
    [err] = r.json["errors"]
    assert err["code"] == "not-hcdf"
    assert err["file"].endswith("doc.hcdf") and err["line"] == 1
    assert shown in err["message"] and "not an HCDF document" in err["message"]
    assert err["actual"] == shown and err["expected"]


@pytest.mark.parametrize("verb", ["resolve", "verify", "pin"])
@pytest.mark.parametrize("root", NOT_HCDF)
def test_an_included_document_that_is_not_hcdf_is_exit_3(cli, tmp_path, verb, root):
    text, shown = NOT_HCDF[root]
    sub = tmp_path / "sub.hcdf"
    sub.write_text(text + "\n")
    sha = hashlib.sha256(sub.read_bytes()).hexdigest()
    doc = tmp_path / "doc.hcdf"
    doc.write_text(f'<hcdf version="1.0" name="t">\n  <include uri="sub.hcdf" sha="{sha}"/>\n</hcdf>\n')
    if verb == "verify":
        lock = tmp_path / "doc.hcdf.lock"
        entry = {"kind": "include", "uri": "sub.hcdf", "url": "sub.hcdf", "sha256": sha, "size": sub.stat().st_size}
        artifacts = [{**entry, "referenced_from": ["doc.hcdf"]}]
        lock.write_text(json.dumps({"lock_version": 2, "root": "doc.hcdf", "artifacts": artifacts}))
    r = cli(*VERBS[verb], doc, "--json", "--cache-dir", tmp_path / "cache")
    assert r.exit_code == 3, r.stdout + r.stderr
    errors = [e for e in r.json["errors"] if e["code"] == "not-hcdf"]
    assert errors and errors[0]["file"].endswith("sub.hcdf") and shown in errors[0]["message"], r.json["errors"]


def test_validate_reports_an_included_document_that_is_not_hcdf(cli, tmp_path):
    """validate reads includes only for its cross-file rules: one it refuses is an error finding."""
    (tmp_path / "sub.hcdf").write_text('<hcdf xmlns="urn:x" version="1.0" name="s"/>\n')
    doc = tmp_path / "doc.hcdf"
    doc.write_text('<hcdf version="1.0" name="t">\n  <include uri="sub.hcdf"/>\n</hcdf>\n')
    r = cli("validate", doc, "--json")
    assert r.exit_code == 1, r.stdout
    [finding] = [f for f in r.json["findings"] if f["code"] == "include-refused"]
    assert finding["line"] == 2 and "<hcdf> in namespace 'urn:x'" in finding["message"]


HIDDEN = {
    "uri-and-href-differ": '<visual><model uri="m.glb" href="evil.glb"/></visual>',
    "comment-in-manifest": (
        '<software name="fw"><firmware-manifest-uri><!-- -->https://x.example/fw.json</firmware-manifest-uri></software>'
    ),
    "pi-in-manifest": '<software name="fw"><firmware-manifest-uri>ev<?pi?>il.json</firmware-manifest-uri></software>',
    "comment-in-hash": f"<software name='fw'><hash>{GLB_SHA[:8]}<!-- -->{GLB_SHA[8:]}</hash></software>",
    "namespaced-include": '<x:include xmlns:x="urn:x" uri="evil.hcdf"/>',
    "namespaced-uri": '<visual><model xmlns:x="urn:x" x:uri="evil.glb" uri="m.glb"/></visual>',
}


@pytest.mark.parametrize("verb", VERBS)
@pytest.mark.parametrize("case", HIDDEN)
def test_a_hidden_reference_is_exit_3_for_every_verb(cli, tmp_path, verb, case):
    (tmp_path / "m.glb").write_bytes(GLB)
    doc = tmp_path / "doc.hcdf"
    doc.write_text(f'<hcdf version="1.0" name="t">\n  <comp name="c">\n    {HIDDEN[case]}\n  </comp>\n</hcdf>\n')
    r = _run(cli, tmp_path, verb, doc)
    assert r.exit_code == 3, r.stdout + r.stderr
    [err] = r.json["errors"]
    assert err["code"] == "ambiguous-reference" and err["file"].endswith("doc.hcdf") and err["line"] == 3, err
    assert not (tmp_path / "hcdf.lock").exists() or verb == "verify"


def test_the_text_value_is_the_whole_string():
    """CDATA and character references are ordinary text; XML whitespace around is dropped."""
    doc = Document.from_bytes(
        b'<hcdf version="1.0" name="t"><comp name="c"><software name="fw">\n'
        b"  <hash>\n    <![CDATA[ab]]>&#x63;d" + GLB_SHA[4:].encode() + b"\n  </hash>\n"
        b"  <firmware-manifest-uri> https://x.example/<![CDATA[fw]]>&#46;json\t</firmware-manifest-uri>\n"
        b"</software></comp></hcdf>",
        source="t.hcdf",
    )
    [fw, manifest] = doc.references()
    assert (fw.kind, fw.sha) == (Kind.FIRMWARE, "abcd" + GLB_SHA[4:])
    assert (manifest.kind, manifest.uri) == (Kind.FIRMWARE_MANIFEST, "https://x.example/fw.json")


def _refs(body: str) -> list[tuple[str, str | None]]:
    doc = Document.from_bytes(f'<hcdf version="1.0" name="t">{body}</hcdf>'.encode(), source="t.hcdf")
    return [(r.kind.value, r.uri or r.domain) for r in doc.references()]


def test_extension_content_is_opaque_only_inside_a_comp():
    vendor = '<extension domain="gazebo"><plugin><model uri="package://x/y.dae"/></plugin></extension>'
    # HCDF's extension point: the content is vendor data, and what follows it is still walked
    assert _refs(f'<comp name="c">{vendor}<visual><model uri="after.glb"/></visual></comp>') == [
        ("extension", "gazebo"),
        ("model", "after.glb"),
    ]
    # an <extension> anywhere else cannot hide the document's own references
    wrapped = '<extension domain="x"><comp name="c"><visual><model uri="hidden.glb"/></visual></comp></extension>'
    assert _refs(wrapped) == [("extension", "x"), ("model", "hidden.glb")]
    assert _refs('<comp name="c"><visual><extension domain="v"><model href="v.glb"/></extension></visual></comp>') == [
        ("extension", "v"),
        ("model", "v.glb"),
    ]
    # nor can one inside a text reference
    with pytest.raises(Exception, match="contains a <extension> element"):
        _refs('<comp name="c"><software name="f"><hash>ab<extension domain="e"/>cd</hash></software></comp>')


def test_equal_uri_and_href_are_one_reference_and_flattening_rebases_both(cli, tmp_path):
    (tmp_path / "parts").mkdir()
    (tmp_path / "parts" / "m.glb").write_bytes(GLB)
    (tmp_path / "out").mkdir()
    doc = tmp_path / "doc.hcdf"
    doc.write_text(
        '<hcdf version="1.0" name="t">\n  <comp name="c">\n'
        f'    <visual><model uri="parts/m.glb" href="parts/m.glb" sha="{GLB_SHA}"/></visual>\n  </comp>\n</hcdf>\n'
    )
    flat = tmp_path / "out" / "flat.hcdf"
    r = cli("resolve", doc, "--out", flat, "--root", tmp_path, "--cache-dir", tmp_path / "c", "--json")
    assert r.exit_code == 0, r.stdout
    [art] = r.json["artifacts"]
    assert (art["uri"], art["sha256"]) == ("parts/m.glb", GLB_SHA)
    [model] = etree.parse(str(flat)).iter("model")
    assert model.get("uri") == model.get("href") == "../parts/m.glb"
    r = cli("resolve", flat, "--root", tmp_path, "--lock", tmp_path / "flat.lock", "--cache-dir", tmp_path / "c")
    assert r.exit_code == 0, r.stderr


def test_several_hidden_references_are_one_error_naming_every_line(cli, tmp_path):
    """One error per document, as for any other unusable include; a namespaced subtree counts once."""
    (tmp_path / "sub.hcdf").write_text(
        '<hcdf version="1.0" name="s">\n'
        '  <comp name="a" xmlns="urn:x"><visual><model uri="m.glb"/></visual></comp>\n'
        '  <comp name="b"><visual><model uri="m.glb" href="n.glb"/></visual></comp>\n'
        '  <comp name="c"><visual><model uri=" m.glb"/></visual></comp>\n'
        "</hcdf>\n"
    )
    doc = tmp_path / "doc.hcdf"
    doc.write_text('<hcdf version="1.0" name="t">\n  <include uri="sub.hcdf"/>\n</hcdf>\n')
    r = cli("resolve", doc, "--json", "--cache-dir", tmp_path / "cache")
    assert r.exit_code == 3, r.stdout
    [err] = r.json["errors"]
    assert (err["code"], err["line"]) == ("ambiguous-reference", 2) and err["file"].endswith("sub.hcdf")
    assert "<comp> in namespace 'urn:x'" in err["message"] and err["message"].endswith("(and 2 more at lines 3, 4)")
