"""HCDF's JSON form (issue 19 §1): read through the schema, located by JSON Pointer, refused
rather than guessed wherever a reference or a pin could change.

Oracles: lxml's C14N of the original XML (XML -> JSON -> XML), the walker's references of
the upstream drone's two files, the lock's digests (a tampered GLB under a JSON robot), and
the strict reader's own refusals for each hostile input.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import pytest
from lxml import etree

from hcdf_trust import jsonform
from hcdf_trust.document import Document, Kind
from hcdf_trust.errors import InputError, Pointer

from .conftest import CORPUS, PROJECT

HCDFORMAT = CORPUS / "hcdformat"
XSD = HCDFORMAT / "hcdf.xsd"
VALID = sorted((HCDFORMAT / "tests" / "valid").glob("*.hcdf"))
ROBOT = PROJECT / "examples" / "robot"


@pytest.fixture(autouse=True)
def _schema(monkeypatch):
    monkeypatch.setenv("HCDF_TRUST_SCHEMA", str(XSD))
    jsonform.use_schemas([str(XSD)])
    yield
    jsonform.use_schemas([])


def _c14n(data: bytes) -> bytes:
    """The document as C14N 1.0 without comments, PIs and whitespace-only text between elements:
    what the JSON form keeps (docs/json-form.md)."""
    parser = etree.XMLParser(remove_blank_text=True, remove_comments=True, remove_pis=True)
    return etree.tostring(etree.fromstring(data, parser), method="c14n")


def _to_json(path: Path) -> bytes:
    return jsonform.convert(path.read_bytes(), source=path.name).data


def _refs(doc: Document) -> list[tuple[object, ...]]:
    return [(r.kind, r.uri, r.sha, r.name, r.domain, r.version) for r in doc.references()]


# --- XML -> JSON -> XML ------------------------------------------------------------------------

ROUND_TRIP = [*VALID, *sorted(ROBOT.rglob("*.hcdf")), *sorted((HCDFORMAT / "examples").glob("*.hcdf"))]


def test_the_round_trip_inputs_are_there():
    assert len(VALID) >= 13 and (ROBOT / "robot.hcdf") in ROUND_TRIP


@pytest.mark.parametrize("path", ROUND_TRIP, ids=lambda p: p.name)
def test_xml_to_json_to_xml_is_c14n_equal(path):
    as_json = _to_json(path)
    back = jsonform.convert(as_json, source=path.name + ".json")
    assert back.to == "xml"
    assert _c14n(back.data) == _c14n(path.read_bytes())


def test_the_json_has_upstreams_shape():
    """Root key hcdf, version a number, attributes and value elements as plain keys, $text beside
    attributes, one child an object and repeated children a list (drone-quadrotor.json's shape)."""
    value = json.loads(_to_json(HCDFORMAT / "examples" / "drone-quadrotor.hcdf"))
    body = value["hcdf"]
    assert list(value) == ["hcdf"] and body["version"] == 1.0 and body["name"] == "cogni-quadrotor"
    navq = body["comp"][1]
    assert navq["board"] == "navq95" and navq["inertial"]["mass"] == 0.045  # element values, typed
    assert isinstance(navq["visual"], dict) and isinstance(navq["port"], list)
    # <speed> is mixed content, its text untyped in hcdf.xsd: written as a string here, where
    # upstream writes the number 1000 (read here as the text "1000": every reader agrees on it)
    assert navq["port"][0]["capabilities"]["speed"] == {"unit": "Mbps", "$text": "1000"}
    upstream = json.loads((HCDFORMAT / "examples" / "drone-quadrotor.json").read_bytes())["hcdf"]
    assert upstream["comp"][1]["port"][0]["capabilities"]["speed"] == {"unit": "Mbps", "$text": 1000}
    read = Document.from_bytes((HCDFORMAT / "examples" / "drone-quadrotor.json").read_bytes(), source="j")
    assert read.root.find("comp/port/capabilities/speed").text == "1000"


def test_numbers_keep_their_literal():
    xml = b'<hcdf version="1.0" name="n"><comp name="c"><inertial><mass>0.0450</mass></inertial></comp></hcdf>'
    text = jsonform.convert(xml, source="n.hcdf").data
    assert b'"version": 1.0' in text and b'"mass": 0.0450' in text
    assert b'version="1.0"' in jsonform.convert(text, source="n.json").data


# --- the drone's two upstream files --------------------------------------------------------------


def test_the_drones_json_and_xml_give_the_same_references():
    """drone-quadrotor.json and .hcdf are not the same revision. Their difference, checked here:
    the XML (newer) adds the root's name, body-frame, world-frame, description, author and
    license, and navq95's ip-rating and <operating-temp>; in the Gazebo extension the XML writes
    vendor values as child elements (<engine>ode</engine>) where the JSON writes plain keys,
    which the JSON form reads as attributes (vendor content has no schema to say otherwise).
    Where they agree, the references are the same: the two extensions, org.ros2 1.0 and
    org.gazebosim 1.0 (neither file references a mesh or a file)."""
    as_json = Document.from_bytes((HCDFORMAT / "examples" / "drone-quadrotor.json").read_bytes(), source="j")
    as_xml = Document.from_bytes((HCDFORMAT / "examples" / "drone-quadrotor.hcdf").read_bytes(), source="x")
    assert as_json.is_json and not as_xml.is_json
    assert as_json.root.get("name") is None and as_xml.root.get("name") == "cogni-quadrotor"
    navq_j, navq_x = as_json.root.findall("comp")[1], as_xml.root.findall("comp")[1]
    assert navq_j.find("operating-temp") is None and navq_x.find("operating-temp") is not None
    physics_j = navq_j.findall("extension")[1].find("physics")
    physics_x = navq_x.findall("extension")[1].find("physics")
    assert physics_j.get("engine") == "ode" and physics_x.findtext("engine") == "ode"
    assert _refs(as_json) == _refs(as_xml)
    assert [(r.kind, r.domain, r.version) for r in as_json.references()] == [
        (Kind.EXTENSION, "org.ros2", "1.0"),
        (Kind.EXTENSION, "org.gazebosim", "1.0"),
    ]
    ext = as_json.references()[0]
    assert isinstance(ext.line, Pointer) and str(ext.line) == "/hcdf/comp/1/extension/0"


# --- every verb reads a JSON robot ----------------------------------------------------------------


@pytest.fixture
def json_robot(tmp_path):
    """The example robot with its root document and one include in the JSON form."""
    tree = tmp_path / "robot"
    shutil.copytree(ROBOT, tree)
    (tree / "robot.json").write_bytes(_to_json(tree / "robot.hcdf"))
    arm = tree / "assemblies" / "arm.hcdf"
    (tree / "assemblies" / "arm.json").write_bytes(_to_json(arm))
    root = (tree / "robot.json").read_text()
    old_sha, new_sha = (
        hashlib.sha256((tree / "assemblies" / n).read_bytes()).hexdigest() for n in ("arm.hcdf", "arm.json")
    )
    assert root.count('"assemblies/arm.hcdf"') == 2 and root.count(old_sha) == 2
    root = root.replace('"assemblies/arm.hcdf"', '"assemblies/arm.json"').replace(old_sha, new_sha)
    (tree / "robot.json").write_text(root)
    return tree


def test_a_json_robot_resolves_to_the_xml_robots_files(json_robot, cli):
    xml = cli("resolve", json_robot / "robot.hcdf", "--no-lock", "--json")
    jsn = cli("resolve", json_robot / "robot.json", "--no-lock", "--json")
    assert xml.exit_code == 0 and jsn.exit_code == 0, jsn.stderr
    files = {a["sha256"] for a in xml.json["artifacts"]}
    # arm.hcdf -> arm.json: one document differs, every mesh, model and firmware file is the same
    assert {a["sha256"] for a in jsn.json["artifacts"]} ^ files == {
        hashlib.sha256((json_robot / "assemblies" / p).read_bytes()).hexdigest() for p in ("arm.hcdf", "arm.json")
    }


def test_a_tampered_glb_under_a_json_robot_exits_1_naming_the_pointer(json_robot, cli):
    assert cli("resolve", json_robot / "robot.json").exit_code == 0
    assert cli("verify", json_robot / "robot.json").exit_code == 0
    glb = json_robot / "models" / "chassis.glb"
    glb.write_bytes(glb.read_bytes() + b"\0")
    r = cli("verify", json_robot / "robot.json")
    assert r.exit_code == 1
    assert "robot.json:/hcdf/comp/visual/model:" in r.stderr and "chassis.glb" in r.stderr
    r = cli("verify", json_robot / "robot.json", "--json")
    errors = r.json["errors"]
    assert r.exit_code == 1 and errors[0]["pointer"] == "/hcdf/comp/visual/model" and errors[0]["line"] is None


@pytest.mark.parametrize(
    "verb",
    [
        ("validate",),
        ("audit",),
        ("sbom", "--format", "cyclonedx", "-o", "{tmp}/bom.json"),
        ("macsec", "plan"),
        ("pin",),
    ],
    ids=lambda v: " ".join(v[:2]),
)
def test_every_verb_reads_a_json_robot_as_its_xml(json_robot, cli, verb):
    cmd, *rest = verb
    for doc in ("robot.hcdf", "robot.json"):
        assert cli("resolve", json_robot / doc).exit_code == 0
    args = [a.replace("{tmp}", str(json_robot)) for a in rest]
    sub = [cmd] if cmd != "macsec" else ["macsec", rest.pop(0)]
    args = args[1:] if cmd == "macsec" else args
    xml = cli(*sub, json_robot / "robot.hcdf", *args)
    jsn = cli(*sub, json_robot / "robot.json", *args)
    if cmd == "pin":  # the arm's weak pin: the XML is edited in place, the JSON form is not
        assert "does not edit in place" in jsn.stderr and "hcdf-trust convert" in jsn.stderr
        assert jsn.exit_code != 0
        return
    assert (xml.exit_code, jsn.exit_code) in {(0, 0), (1, 1)}, (xml.stderr, jsn.stderr)


def test_a_json_run_needs_a_schema(json_robot, cli, monkeypatch):
    monkeypatch.delenv("HCDF_TRUST_SCHEMA")
    r = cli("resolve", json_robot / "robot.json")
    assert r.exit_code == 3 and "--schema" in r.stderr and "HCDF_TRUST_SCHEMA" in r.stderr
    assert cli("resolve", json_robot / "robot.json", "--schema", XSD).exit_code == 0


# --- hostile JSON: each refused (exit 3), by the protection named ---------------------------------

GOOD = {"hcdf": {"version": 1.0, "name": "r", "comp": {"name": "c", "visual": {"model": {"uri": "m.glb"}}}}}
GOOD_TEXT = json.dumps(GOOD)
# m.glb's content: its SHA-256 starts with 8 decimal digits, so that a pin written as a JSON
# number would be a (weak) pin that matches, were numbers accepted there
GLB = next(
    b"glb%d" % i for i in range(10_000) if (h := hashlib.sha256(b"glb%d" % i).hexdigest())[:8].isdigit() and h[0] != "0"
)
DIGITS = int(hashlib.sha256(GLB).hexdigest()[:8])
VENDOR = {"hcdf": {"version": 1.0, "name": "r", "comp": {"name": "c", "extension": {"domain": "d", "version": "1"}}}}


def _doc(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "robot.json"
    path.write_text(text)
    (tmp_path / "m.glb").write_bytes(GLB)
    return path


def _with(model: object) -> str:
    doc = json.loads(json.dumps(GOOD))
    doc["hcdf"]["comp"]["visual"]["model"] = model
    return json.dumps(doc)


HOSTILE = {
    "duplicate key": GOOD_TEXT.replace('"uri": "m.glb"', '"uri": "m.glb", "uri": "x.glb"'),
    "NaN": GOOD_TEXT.replace("1.0", "NaN"),
    "infinite number": GOOD_TEXT.replace("1.0", "1e999"),
    "deep nesting": json.dumps(VENDOR).replace(
        '"version": "1"', '"version": "1", "a": ' + '{"a": ' * 80 + "{}" + "}" * 80
    ),
    "uri as a number": _with({"uri": 12}),
    "uri as null": _with({"uri": None}),
    "uri as an object": _with({"uri": {"$text": "m.glb"}}),
    "uri as a list": _with({"uri": ["m.glb", "x.glb"]}),
    "sha as a number": _with({"uri": "m.glb", "sha": DIGITS}),
    "sha as true": _with({"uri": "m.glb", "sha": True}),
    "unknown key carrying a reference": _with({"uri": "m.glb", "fallback-uri": "x.glb"}),
    "misspelled reference element": GOOD_TEXT.replace('"model"', '"modle"'),
    "text inside a reference": _with({"uri": "m.glb", "$text": "x.glb"}),
    "an empty list": GOOD_TEXT.replace('"comp": {', '"include": [], "comp": {'),
    "hash as a number": json.dumps(
        {"hcdf": {"version": 1.0, "name": "r", "comp": {"name": "c", "software": {"name": "fw", "hash": 1234}}}}
    ),
    "version 1.10 of an extension": json.dumps(
        {"hcdf": {"version": 1.0, "name": "r", "comp": {"name": "c", "extension": {"domain": "d", "version": 1.10}}}}
    ).replace("1.1", "1.10"),
    "two top-level keys": json.dumps({**GOOD, "x": {}}),
    "a NUL character in a uri": _with({"uri": "m.glb\u0000.x"}),
    "a control character in vendor text": json.dumps(VENDOR).replace(
        '"version": "1"', '"version": "1", "v": "\\u0001"'
    ),
    # vendor content is walked outside <comp>: an xmlns there would move the element into a namespace
    "xmlns in vendor content": json.dumps(VENDOR).replace('"version": "1"', '"version": "1", "v": {"xmlns": "urn:x"}'),
    "not an object": "[]",
}


def test_the_good_document_is_read(tmp_path, cli):
    r = cli("resolve", _doc(tmp_path, GOOD_TEXT), "--no-lock", "--json")
    assert r.exit_code == 0 and [a["uri"] for a in r.json["artifacts"]] == ["m.glb"]


@pytest.mark.parametrize("case", sorted(HOSTILE))
def test_hostile_json_is_refused(tmp_path, cli, case):
    r = cli("resolve", _doc(tmp_path, HOSTILE[case]), "--no-lock", "--json")
    assert r.exit_code == 3, (case, r.stdout, r.stderr)
    assert r.json["errors"] and not r.json.get("artifacts")


def test_a_huge_json_document_is_refused_before_parsing(tmp_path, cli, monkeypatch):
    monkeypatch.setattr(jsonform, "MAX_DOCUMENT_BYTES", 1000)
    r = cli("resolve", _doc(tmp_path, GOOD_TEXT + " " * 1000), "--no-lock")
    assert r.exit_code == 3 and "limit" in r.stderr


def test_a_refusal_names_the_json_pointer(tmp_path, cli):
    r = cli("resolve", _doc(tmp_path, _with({"uri": "m.glb", "sha": 1234})), "--no-lock")
    assert r.exit_code == 3 and "robot.json:/hcdf/comp/visual/model/sha:" in r.stderr
    r = cli("resolve", _doc(tmp_path, _with({"url": "x.glb"})), "--no-lock")
    assert "/hcdf/comp/visual/model/url" in r.stderr and "refused, not dropped" in r.stderr


# --- convert ------------------------------------------------------------------------------------


def test_convert_refuses_what_would_reorder_references(tmp_path, cli):
    """<include a/><comp/><include b/>: the JSON form groups the includes, which moves b before
    the comp's model; the conversion is refused, nothing written."""
    xml = tmp_path / "r.hcdf"
    xml.write_text(
        '<hcdf version="1.0" name="r"><include uri="a.hcdf"/>'
        '<comp name="c"><visual><model uri="m.glb"/></visual></comp><include uri="b.hcdf"/></hcdf>'
    )
    r = cli("convert", xml, tmp_path / "r.json")
    assert r.exit_code == 3 and "would change reference 2 of 3" in r.stderr
    assert not (tmp_path / "r.json").exists()


def test_convert_both_ways_through_output_plan(tmp_path, cli):
    src = tmp_path / "robot.hcdf"
    shutil.copy(ROBOT / "robot.hcdf", src)
    r = cli("convert", src, tmp_path / "robot.json", "--json")
    assert (
        r.exit_code == 0
        and r.json["to"] == "json"
        and r.json["schema_sha256"] == hashlib.sha256(XSD.read_bytes()).hexdigest()
    )
    r = cli("convert", tmp_path / "robot.json", "-")
    assert r.exit_code == 0 and _c14n(r.stdout.encode()) == _c14n(src.read_bytes())
    assert cli("convert", tmp_path / "robot.json", "-", "--json").exit_code == 2  # two things on stdout
    # the direction is the input's; OUT's name must agree
    assert cli("convert", src, tmp_path / "x.hcdf").exit_code == 2
    assert cli("convert", tmp_path / "robot.json", tmp_path / "x.json").exit_code == 2


def test_convert_never_writes_onto_its_input(tmp_path, cli):
    src = tmp_path / "robot.hcdf"
    shutil.copy(ROBOT / "robot.hcdf", src)
    (tmp_path / "link.json").symlink_to(src)
    before = src.read_bytes()
    r = cli("convert", src, tmp_path / "link.json")
    assert r.exit_code != 0 and "input" in r.stderr and src.read_bytes() == before


def test_json_locations_in_json_output():
    from hcdf_trust.errors import json_locations

    assert json_locations({"errors": [{"line": Pointer(3, "/hcdf/comp/2")}, {"line": 7}]}) == {
        "errors": [{"line": None, "pointer": "/hcdf/comp/2"}, {"line": 7}]
    }


def test_the_converter_refuses_an_unknown_key_in_the_library_too():
    with pytest.raises(InputError) as exc:
        Document.from_bytes(_with({"uri": "m.glb", "shaa": "x"}).encode(), source="r.json")
    assert exc.value.line is not None and str(exc.value.line) == "/hcdf/comp/visual/model/shaa"


def test_ota_update_hcdf_refuses_to_edit_a_json_document():
    from hcdf_trust.ota.hcdf_edit import replace_text

    text = json.dumps(
        {"hcdf": {"version": 1.0, "name": "r", "comp": {"name": "c", "software": {"name": "fw", "hash": "ab" * 32}}}}
    )
    doc = Document.from_bytes(text.encode(), source="r.json")
    with pytest.raises(InputError) as exc:
        replace_text(doc, doc.root.find("comp/software/hash"), "cd" * 32)
    assert "does not edit in place" in exc.value.message and "hcdf-trust convert r.json r.hcdf" in exc.value.message
    assert str(exc.value.line) == "/hcdf/comp/software/hash"


def test_no_message_about_a_json_robot_says_line_and_a_pointer(json_robot, cli):
    """Messages that name a place inside a sentence (``at line 42``, ``(lines 3, 7)``) name a JSON
    document's place by its bare pointer: never ``line /hcdf/...`` (errors.at_line)."""
    r = cli("validate", json_robot / "robot.json")  # the note naming the selected stream profile
    assert r.exit_code == 0 and "(/hcdf/network/stream-profile)" in r.stdout + r.stderr
    assert "line /" not in r.stdout + r.stderr
    assert cli("resolve", json_robot / "robot.json").exit_code == 0  # sbom reads the lock
    value = json.loads((json_robot / "robot.json").read_text())
    profile = value["hcdf"]["network"]["stream-profile"]
    value["hcdf"]["network"]["stream-profile"] = [profile, dict(profile)]  # two selected: refused
    (json_robot / "robot.json").write_text(json.dumps(value))
    runs = {
        verb: cli(*args)
        for verb, args in {
            "validate": ("validate", json_robot / "robot.json"),
            "audit": ("audit", json_robot / "robot.json", "--json"),
            "sbom": ("sbom", json_robot / "robot.json", "--format", "spdx", "-o", json_robot / "bom.json"),
        }.items()
    }
    for verb, r in runs.items():
        out = r.stdout + r.stderr
        assert r.exit_code != 0, (verb, out)
        assert "/hcdf/network/stream-profile/0, /hcdf/network/stream-profile/1" in out, (verb, out)
        assert "line /" not in out and "lines /" not in out, (verb, out)


def test_at_line_names_an_xml_line_or_a_bare_pointer():
    from hcdf_trust.errors import at_line, at_lines

    assert at_line(42) == "line 42" and at_line(Pointer(3, "/hcdf/comp/2")) == "/hcdf/comp/2"
    assert at_lines([3, 7]) == "lines 3, 7" and at_lines([7]) == "line 7"
    assert at_lines([Pointer(1, "/a/0"), Pointer(2, "/a/1")]) == "/a/0, /a/1"


def test_the_key_store_records_a_json_documents_pointer(json_robot, cli):
    """The key store (a JSON file, not ``--json``) names where each association is described:
    for a JSON robot its pointer, as a string, never the element's index in document order."""
    from hcdf_trust.macsec.backends import PassphraseWrapper
    from hcdf_trust.macsec.store import STORE_NAME, KeyStore

    assert cli("resolve", json_robot / "robot.json").exit_code == 0
    (json_robot / "pass").write_bytes(b"correct horse battery staple\n")
    store = json_robot / "keys-out"
    r = cli(
        "macsec",
        "generate",
        json_robot / "robot.json",
        "--store",
        store,
        "--passphrase-file",
        json_robot / "pass",
        "--now",
        "2026-01-01T00:00:00Z",
    )
    assert r.exit_code == 0, r.stderr
    sources = [json.loads(line)[1]["source"] for line in (store / STORE_NAME).read_text().splitlines()[1:]]
    ours = [s for s in sources if s["file"].endswith("robot.json")]
    assert ours and all(s["line"] is None and s["pointer"].startswith("/hcdf/network/") for s in ours), sources
    opened = KeyStore.open(store, PassphraseWrapper(b"correct horse battery staple"))
    read = {str(e.source_line) for e in opened.entries.values() if e.source_file.endswith("robot.json")}
    assert read == {s["pointer"] for s in ours}


def test_sbom_properties_name_a_json_documents_pointer(json_robot, cli):
    """hcdf:file is ``robot.json:/hcdf/comp`` (``path:line`` for XML) and hcdf:include-line the
    include's pointer, in both formats, which still pass their official validators."""
    import re

    from tests._sbom import cdx_components, cdx_props, spdx_graph, spdx_props, validate_cyclonedx, validate_spdx

    assert cli("resolve", json_robot / "robot.json").exit_code == 0
    for fmt in ("cyclonedx", "spdx"):
        out = json_robot / f"bom.{fmt}.json"
        r = cli("sbom", json_robot / "robot.json", "--format", fmt, "-o", out)
        assert r.exit_code == 0, r.stderr
        if fmt == "cyclonedx":
            validate_cyclonedx(out.read_text())
            props = [cdx_props(c) for c in cdx_components(json.loads(out.read_text())).values()]
        else:
            validate_spdx(out.read_bytes())
            props = [spdx_props(e) for e in spdx_graph(out.read_bytes())[0].values()]
        files = {p["hcdf:file"] for p in props if "hcdf:file" in p}
        assert "robot.json:/hcdf/comp" in files, files
        assert not any(re.fullmatch(r"robot\.json:\d+", f) for f in files), files
        includes = {p["hcdf:include-line"] for p in props if "hcdf:include-line" in p}
        assert includes and all(i.startswith("/hcdf/include/") for i in includes), includes
