"""Attacks on HCDF's JSON form (issue 19 §1), through the CLI, beyond tests/test_jsonform.py.

The example robot is converted once (``convert``) and then edited as text, so each case differs
from a document every verb reads in what it names. Passing cases document a defence; a case
marked ``xfail(strict=True)`` is a hole found by this attack, with the finding in its reason.
"""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from hcdf_trust import jsonform

from .conftest import CORPUS, PROJECT

XSD = CORPUS / "hcdformat" / "hcdf.xsd"
CHASSIS_SHA = "14662db9eb3db5be8bc90a5a14deb58563ef31e605e14dd598b5a6341163f22f"


@pytest.fixture(autouse=True)
def _schema(monkeypatch):
    monkeypatch.setenv("HCDF_TRUST_SCHEMA", str(XSD))
    jsonform.use_schemas([str(XSD)])
    yield
    jsonform.use_schemas([])


@pytest.fixture
def robot(tmp_path, cli):
    """The example robot, its root converted to JSON (robot.json, locked), its includes still XML."""
    shutil.copytree(PROJECT / "examples", tmp_path / "examples", ignore=shutil.ignore_patterns("out"))
    folder = tmp_path / "examples" / "robot"
    r = cli("convert", folder / "robot.hcdf", folder / "robot.json")
    assert r.exit_code == 0, r.stderr
    assert cli("resolve", folder / "robot.json").exit_code == 0
    return folder


def _model(text: str, new: str) -> str:
    """``text`` with the chassis <model> object replaced by ``new`` (JSON)."""
    found = re.search(r'"model": \{\s*"uri": "models/chassis.glb",\s*"sha": "[0-9a-f]{64}"\s*\}', text)
    assert found, "the chassis model is not where the test expects it"
    return text[: found.start()] + '"model": ' + new + text[found.end() :]


def _resolve(cli, folder: Path, text: str | bytes):
    path = folder / "hostile.json"
    path.write_bytes(text if isinstance(text, bytes) else text.encode("utf-8", "surrogatepass"))
    return cli("resolve", path, "--no-lock", "--json")


# --- hostile JSON the builder's tests do not cover: exit 3, never "0 references" -----------------


MODEL = '{"uri": "models/chassis.glb", %s "sha": "' + CHASSIS_SHA + '"}'
CASES: dict[str, Callable[[str], str | bytes]] = {
    # duplicates: spelt with an escape, at the root, at the top
    "duplicate key spelt with an escape": lambda base: _model(base, MODEL % '"\\u0075ri": "models/gripper.glb",'),
    "duplicate key in <hcdf>": lambda base: base.replace('"name": "scout2",', '"name": "scout2", "name": "scout3",', 1),
    "duplicate top-level key": lambda base: base.rstrip()[:-1] + ', "hcdf": {}}',
    # numbers
    "Infinity": lambda base: base.replace('"mass": 4.5', '"mass": Infinity', 1),
    "-Infinity": lambda base: base.replace('"mass": 4.5', '"mass": -Infinity', 1),
    "1e999": lambda base: base.replace('"mass": 4.5', '"mass": -1e999', 1),
    # strings XML cannot hold, or that no UTF-8 writer wrote
    "lone surrogate in a uri": lambda base: _model(
        base, '{"uri": "models/chassis\\ud800.glb", "sha": "' + CHASSIS_SHA + '"}'
    ),
    "lone surrogate in a key": lambda base: base.replace('"license":', '"lic\\udc80ense":', 1),
    "U+FFFE in text": lambda base: base.replace('"hcdf-trust example robot"', '"x\\ufffey"', 1),
    "vertical tab in a uri": lambda base: _model(
        base, '{"uri": "models/chassis.glb\\u000b", "sha": "' + CHASSIS_SHA + '"}'
    ),
    "UTF-8 BOM": lambda base: b"\xef\xbb\xbf" + base.encode(),
    "UTF-16": lambda base: base.encode("utf-16"),
    "not UTF-8": lambda base: base.replace("example robot", "example rob\udcffot").encode("utf-8", "surrogateescape"),
    # shapes
    "100,000 nested lists": lambda base: '{"hcdf": ' + "[" * 100_000 + "]" * 100_000 + "}",
    "hcdf is a list": lambda base: '{"hcdf": [' + base.strip()[len('{\n  "hcdf": ') : -1].strip() + "]}",
    "hcdf is null": lambda base: '{"hcdf": null}',
    "version is an object": lambda base: base.replace('"version": 1.0', '"version": {"$text": "1.0"}', 1),
    "version is null": lambda base: base.replace('"version": 1.0', '"version": null', 1),
    "model is a string": lambda base: _model(base, '"models/chassis.glb"'),
    "model holds $text": lambda base: _model(base, '{"$text": "models/chassis.glb", "sha": "' + CHASSIS_SHA + '"}'),
    "sha is an object": lambda base: _model(
        base, '{"uri": "models/chassis.glb", "sha": {"$text": "' + CHASSIS_SHA + '"}}'
    ),
    "sha is null": lambda base: _model(base, '{"uri": "models/chassis.glb", "sha": null}'),
    "uri is true": lambda base: _model(base, '{"uri": true}'),
    # keys that would move a reference if they were kept, or hide one if dropped
    "href beside uri": lambda base: _model(base, MODEL % '"href": "models/gripper.glb",'),
    "xml:base": lambda base: _model(base, MODEL % '"xml:base": "https://evil.example/",'),
    "xmlns on hcdf": lambda base: base.replace('"name": "scout2",', '"name": "scout2", "xmlns": "urn:x",', 1),
    "$text beside elements": lambda base: base.replace('"license":', '"$text": "x", "license":', 1),
    "a key with a space": lambda base: _model(base, MODEL % '"uri ": "models/gripper.glb",'),
    "a key with a slash (a Pointer step)": lambda base: _model(base, MODEL % '"a/b": "models/gripper.glb",'),
    # not JSON at all, though it starts like it
    "a comment": lambda base: base.replace('"license":', '/* x */ "license":', 1),
    "a trailing comma": lambda base: base.replace('"Apache-2.0"', '"Apache-2.0",', 1),
}


@pytest.mark.parametrize("case", list(CASES))
def test_hostile_json_beyond_the_builders_cases_is_refused(cli, robot, case):
    base = (robot / "robot.json").read_text()
    text = CASES[case](base)
    r = _resolve(cli, robot, text)
    assert r.exit_code == 3, (case, r.exit_code, r.stdout[-500:], r.stderr[-500:])
    errors = r.json["errors"]
    assert errors and not r.json.get("artifacts"), errors
    assert all("hostile.json" in (e.get("file") or "") + e["message"] for e in errors), errors


# --- the root's version: a number every reader must read alike ------------------------------------


@pytest.mark.parametrize("literal", ["1.10", "1.00", "1e0", "10e-1", "1" + "0" * 400])
def test_a_root_version_other_readers_read_differently_is_refused(cli, robot, literal):
    text = (robot / "robot.json").read_text().replace('"version": 1.0', f'"version": {literal}', 1)
    r = _resolve(cli, robot, text)
    assert r.exit_code == 3, (literal, r.stderr)
    assert r.json["errors"][0].get("pointer") == "/hcdf/version", r.json["errors"]


@pytest.mark.parametrize("literal", ['"1.0"', "1.0", "1", "2.0"])
def test_a_root_version_every_reader_reads_alike_is_read(cli, robot, literal):
    text = (robot / "robot.json").read_text().replace('"version": 1.0', f'"version": {literal}', 1)
    assert _resolve(cli, robot, text).exit_code == 0


# --- mixed trees: a JSON include under an XML robot, an XML include under a JSON robot -------------


def _repin_include(doc: Path, old: str, new: str) -> None:
    """Point ``doc``'s includes of ``old`` at ``new``, pinned by ``new``'s bytes."""
    sha = hashlib.sha256((doc.parent / new).read_bytes()).hexdigest()
    text = doc.read_text()
    text, n = re.subn(rf'"{re.escape(old)}" sha="[0-9a-f]{{64}}"', f'"{new}" sha="{sha}"', text)
    assert n == 2, "the example robot includes the arm twice"
    doc.write_text(text)


def test_a_tampered_mesh_under_a_json_include_of_an_xml_robot_fails_alike(cli, robot):
    assert cli("convert", robot / "assemblies" / "arm.hcdf", robot / "assemblies" / "arm.json").exit_code == 0
    mixed = robot / "mixed.hcdf"
    shutil.copy(robot / "robot.hcdf", mixed)
    _repin_include(mixed, "assemblies/arm.hcdf", "assemblies/arm.json")
    tree = cli("resolve", robot / "robot.hcdf", "--json")
    r = cli("resolve", mixed, "--json")
    assert tree.exit_code == r.exit_code == 0, r.stderr
    files = {a["sha256"] for a in tree.json["artifacts"] if a["kind"] != "include"}
    assert files == {a["sha256"] for a in r.json["artifacts"] if a["kind"] != "include"}
    glb = robot / "models" / "gripper.glb"
    glb.write_bytes(glb.read_bytes() + b"\0")
    tree, r = cli("verify", robot / "robot.hcdf", "--json"), cli("verify", mixed, "--json")
    assert tree.exit_code == r.exit_code == 1
    [error] = [e for e in r.json["errors"] if e["code"] == "digest-mismatch"]
    assert error["file"].endswith("arm.json") and error["pointer"].endswith("/model"), error
    assert error["line"] is None


def test_a_json_robot_bundled_verifies_as_its_xml_robot(cli, robot, tmp_path):
    from_json, from_xml = tmp_path / "j.hcdfz", tmp_path / "x.hcdfz"
    assert cli("bundle", robot / "robot.json", from_json).exit_code == 0
    assert cli("bundle", robot / "robot.hcdf", from_xml).exit_code == 0
    a, b = cli("verify", from_json, "--json"), cli("verify", from_xml, "--json")
    assert a.exit_code == b.exit_code == 0
    assert {x["sha256"] for x in a.json["artifacts"]} == {x["sha256"] for x in b.json["artifacts"]}


# --- convert: what it writes, and where -----------------------------------------------------------


def test_convert_does_not_write_xml_under_a_bundles_name(cli, robot, tmp_path):
    """Fixed here: `convert robot.json X.hcdfz` wrote XML under a bundle's name (exit 0); every reading verb
    then took it for a broken ZIP (OUT's name was checked for .json only)."""
    out = tmp_path / "robot.hcdfz"
    r = cli("convert", robot / "robot.json", out)
    assert r.exit_code == 2 and "not a bundle" in r.stderr and not out.exists(), r.stderr


def test_convert_of_a_bundle_says_it_is_a_bundle(cli, robot, tmp_path):
    bundled = tmp_path / "scout2.hcdfz"
    assert cli("bundle", robot / "robot.hcdf", bundled).exit_code == 0
    r = cli("convert", bundled, tmp_path / "out.json")
    assert r.exit_code == 2 and "malformed XML" not in r.stderr and "bundle" in r.stderr, r.stderr


# --- cost: a JSON document is bounded as its XML is ------------------------------------------------

# The peak of this process's own memory (VmHWM, reset by exec): ru_maxrss is not, and starts at
# the forking pytest's size (~65 MB once the schema is built), which hid the XML's cost.
_RSS = """
import re, sys
from hcdf_trust.cli import main
try:
    main(sys.argv[1:], prog_name="hcdf-trust")
finally:
    with open("/proc/self/status") as status:
        print("maxrss", re.search(r"VmHWM:\\s*(\\d+)", status.read())[1], file=sys.stderr)
"""


def _maxrss_kb(tmp_path: Path, *args: str | Path) -> tuple[int, int]:
    env = {**os.environ, "XDG_CACHE_HOME": str(tmp_path / "cache"), "HCDF_TRUST_SCHEMA": str(XSD)}
    r = subprocess.run(
        [sys.executable, "-c", _RSS, *map(str, args)], capture_output=True, text=True, timeout=300, env=env, check=False
    )
    return r.returncode, int(r.stderr.rsplit("maxrss ", 1)[1].split()[0])


def test_a_flood_of_empty_objects_costs_no_more_than_the_same_xml(tmp_path):
    n = 300_000
    for name, many in (("tiny", 1), ("flood", n)):
        (tmp_path / f"{name}.json").write_text(
            '{"hcdf": {"version": 1.0, "name": "f", "comp": [' + ", ".join(["{}"] * many) + "]}}"
        )
        (tmp_path / f"{name}.hcdf").write_text('<hcdf version="1.0" name="f">' + "<comp/>" * many + "</hcdf>")
    cost = {}
    for form in ("hcdf", "json"):  # over the same run with one element: imports and the schema built
        codes, (tiny, flood) = zip(*(_maxrss_kb(tmp_path, "resolve", tmp_path / f"{name}.{form}", "--no-lock")
                                    for name in ("tiny", "flood")), strict=True)  # fmt: skip
        assert codes[0] == 0 and codes[1] in (0, 3), codes
        cost[form] = flood - tiny
    assert cost["hcdf"] > 10_000, cost  # the oracle measures something: 300,000 elements of XML
    assert cost["json"] <= 2 * cost["hcdf"], f"over one element: JSON {cost['json']} KB, XML {cost['hcdf']} KB"


@pytest.mark.parametrize(
    "flood",
    [
        '"comp": [' + ", ".join(["{}"] * 250_001) + "]",  # objects: stopped while parsed
        '"comp": [{"extension": {"x": {"y": [' + ", ".join(['""'] * 250_001) + "]}}}]",  # strings: before built
        '"comp": [{"name": "c", "frame": ['  # scalar child elements, 3 a frame: while built
        + ", ".join(['{"name": "f", "description": "d", "pose": "0 0 0 0 0 0"}'] * 85_000)
        + "]}]",
    ],
    ids=["objects", "strings", "scalar-children"],
)
def test_a_json_document_over_the_element_cap_is_refused_naming_it(cli, tmp_path, flood):
    r = _resolve(cli, tmp_path, '{"hcdf": {"version": 1.0, "name": "f", ' + flood + "}}")
    assert r.exit_code == 3, r.stderr[-500:]
    assert "250,000" in r.json["errors"][0]["message"], r.json["errors"]


def test_a_flood_of_strings_is_refused_before_it_is_built(tmp_path):
    (tmp_path / "tiny.json").write_text('{"hcdf": {"version": 1.0, "name": "f", "comp": [{}]}}')
    (tmp_path / "flood.json").write_text(
        '{"hcdf": {"version": 1.0, "name": "f", "comp": [{"extension": {"x": {"y": ['
        + ", ".join(['""'] * 300_000)
        + "]}}}]}}"
    )
    (tiny_code, tiny), (code, flood) = (
        _maxrss_kb(tmp_path, "resolve", tmp_path / f, "--no-lock") for f in ("tiny.json", "flood.json")
    )
    assert (tiny_code, code) == (0, 3)
    assert flood - tiny < 20_000, f"{flood - tiny} KB over one element (measured 186 MB when built, then refused)"
