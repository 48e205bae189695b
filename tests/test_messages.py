"""Error messages: each names its reference, shows paths as the user gave them, and is honest.

Honest means: ``expected``/``actual`` are printed only when known (never ``expected: None``),
a malformed digest shows the attribute as written, a mismatch shows the pin as expected and
the computed digest as actual.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from pathlib import Path

import pytest

from hcdf_trust.errors import DigestMismatchError, MalformedDigestError, Notice

from .conftest import HCDFORMAT, MODELS

NONE_FIELD = re.compile(r"(expected|actual):\s+None\b")


def sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def hcdf(body: str) -> str:
    return f'<?xml version="1.0"?>\n<hcdf version="1.0" name="t">\n{body}\n</hcdf>\n'


def line_of(path: Path, needle: str) -> int:
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        if needle in line:
            return number
    raise AssertionError(f"{needle!r} not in {path}")


def assert_honest(stderr: str, errors: list[dict]) -> None:
    assert not NONE_FIELD.search(stderr), stderr
    for e in errors:
        assert e.get("expected", "") is not None and e.get("actual", "") is not None, e
        assert ("expected" in e) == ("actual" in e) or e["code"] == "unpinned", e


# --- expected / actual ---------------------------------------------------------------------


def test_only_what_is_known_is_printed():
    one = MalformedDigestError("bad", file="a.hcdf", line=3, actual="abc")
    assert "expected" not in str(one) and "actual:   abc" in str(one)
    assert "expected" not in one.to_dict() and one.to_dict()["actual"] == "abc"
    other = DigestMismatchError("bad", expected="00")
    assert "actual" not in str(other) and "actual" not in other.to_dict()


def test_test_minimal_bad_sha_names_the_include_and_its_line(cli, tmp_path):
    doc = HCDFORMAT / "examples" / "test-minimal.hcdf"
    line = line_of(doc, 'sha="abc123"')
    assert line == 351  # the published file, unchanged
    r = cli("resolve", doc, "--offline", "--no-lock", "--cache-dir", tmp_path / "c", "--json")
    assert r.exit_code == 3
    (err,) = [e for e in r.json["errors"] if e["code"] == "bad-digest"]
    assert err["line"] == line and err["file"].endswith("test-minimal.hcdf")
    assert "components/sensor-module.hcdf" in err["message"] and 'sha="abc123"' in err["message"]
    assert err["actual"] == "abc123" and "64 hex digits" in err["expected"]
    human = cli("resolve", doc, "--offline", "--no-lock", "--cache-dir", tmp_path / "c")
    assert f"test-minimal.hcdf:{line}: components/sensor-module.hcdf: " in human.stderr
    assert_honest(human.stderr, r.json["errors"])


@pytest.mark.parametrize("written", ["abc123", " SHA256:xyz ", "0" * 65])
def test_a_malformed_digest_shows_the_attribute_as_written(cli, tmp_path, written):
    (tmp_path / "m.glb").write_bytes(b"m")
    doc = tmp_path / "robot.hcdf"
    doc.write_text(hcdf(f'<comp name="c"><visual name="v"><model uri="m.glb" sha="{written}"/></visual></comp>'))
    r = cli("resolve", doc, "--no-lock", "--json")
    assert r.exit_code == 3
    (err,) = r.json["errors"]
    assert err["actual"] == written and f'sha="{written}"' in err["message"] and "m.glb" in err["message"]
    assert_honest(r.stderr, r.json["errors"])


def test_a_mismatch_expects_the_pin_and_shows_the_computed_digest(cli, tmp_path):
    (tmp_path / "m.glb").write_bytes(b"real")
    pin = sha(b"pinned")
    doc = tmp_path / "robot.hcdf"
    doc.write_text(hcdf(f'<comp name="c"><visual name="v"><model uri="m.glb" sha="{pin}"/></visual></comp>'))
    r = cli("resolve", doc, "--no-lock", "--json")
    assert r.exit_code == 1
    (err,) = r.json["errors"]
    assert (err["expected"], err["actual"]) == (pin, sha(b"real"))
    human = cli("resolve", doc, "--no-lock")
    assert f"expected: {pin}\n  actual:   {sha(b'real')}" in human.stderr


# --- paths as the user gave them -------------------------------------------------------------


def _project(tmp_path: Path) -> Path:
    """tmp/outside.glb, tmp/proj/{robot.hcdf, m.glb}: run from tmp, name proj/robot.hcdf."""
    (tmp_path / "outside.glb").write_bytes(b"outside")
    proj = tmp_path / "proj"
    (proj / "models").mkdir(parents=True)
    (proj / "models" / "m.glb").write_bytes(b"model")
    os.symlink(tmp_path / "outside.glb", proj / "models" / "link.glb")
    return proj


CASES = {
    "missing": ('<model uri="models/gone.glb"/>', "not-found", "proj/models/gone.glb"),
    "escape": ('<model uri="../outside.glb"/>', "path-escape", "../outside.glb: outside.glb is outside the root proj"),
    "symlink-escape": ('<model uri="models/link.glb"/>', "path-escape", "proj/models/link.glb"),
    "mismatch": (f'<model uri="models/m.glb" sha="{sha(b"other")}"/>', "digest-mismatch", "models/m.glb"),
    "missing-include": (
        '</visual></comp><include uri="sub/gone.hcdf"/><comp name="d"><visual name="w">',
        "not-found",
        "proj/sub/gone.hcdf",
    ),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_no_absolute_path_when_run_from_a_folder_above(cli, tmp_path, monkeypatch, case):
    proj = _project(tmp_path)
    ref, code, named = CASES[case]
    (proj / "robot.hcdf").write_text(hcdf(f'<comp name="c"><visual name="v">{ref}</visual></comp>'))
    monkeypatch.chdir(tmp_path)
    args = ("resolve", "proj/robot.hcdf", "--no-lock", "--offline", "--cache-dir", "cache")
    human, machine = cli(*args), cli(*args, "--json")
    assert human.exit_code == machine.exit_code != 0
    (err,) = machine.json["errors"]
    assert err["code"] == code and err["file"] == "proj/robot.hcdf"
    assert named in err["message"], err
    for text in (human.stderr, machine.stdout, machine.stderr):
        assert str(tmp_path) not in text and "file://" not in text, text
    if "url" in err:
        assert not os.path.isabs(err["url"]), err
    assert_honest(human.stderr, machine.json["errors"])


def test_notices_show_paths_as_errors_do(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    notice = Notice("unpinned", "m.glb is unpinned", file=str(tmp_path / "a" / "robot.hcdf"), line=4)
    assert str(notice) == "a/robot.hcdf:4: m.glb is unpinned"
    assert notice.to_dict()["file"] == "a/robot.hcdf"


# --- a site-root-relative reference without --base ---------------------------------------------


def test_a_published_fragment_without_base_hints_at_base(cli, tmp_path, monkeypatch):
    fragment = MODELS / "mr_mcxn_t1" / "optical-flow" / "d9507e38-optical-flow.hcdf"
    monkeypatch.chdir(MODELS.parent)
    shown = os.path.relpath(fragment)
    r = cli("resolve", shown, "--no-lock", "--offline", "--cache-dir", tmp_path / "c", "--json")
    assert r.exit_code == 3
    errors = r.json["errors"]
    assert errors and {e["code"] for e in errors} == {"not-found"}
    for err in errors:
        uri = fragment.read_text().splitlines()[err["line"] - 1].split('href="')[1].split('"')[0]
        assert uri.startswith("models/") and uri in err["message"]
        assert f"exists under {MODELS.name}" in err["message"] and f"--base {MODELS.name}" in err["message"]
    again = cli("resolve", shown, "--no-lock", "--offline", "--cache-dir", tmp_path / "c", "--base", MODELS.name)
    assert again.exit_code == 0, again.stderr


def test_a_missing_relative_file_without_a_site_root_still_mentions_base(cli, tmp_path):
    doc = tmp_path / "robot.hcdf"
    doc.write_text(hcdf('<comp name="c"><visual name="v"><model uri="models/none.glb"/></visual></comp>'))
    r = cli("resolve", doc, "--no-lock", "--json")
    (err,) = r.json["errors"]
    assert "models/none.glb" in err["message"] and "--base DIR|URL" in err["message"]
    with_base = cli("resolve", doc, "--no-lock", "--json", "--base", tmp_path)
    (err,) = with_base.json["errors"]
    assert "--base" not in err["message"]  # the user already chose the base


def test_every_message_in_a_run_of_failures_is_honest(cli, tmp_path):
    """The upstream examples and schema tests, resolved as they are: whatever fails, says so honestly."""
    docs = sorted((HCDFORMAT / "examples").glob("*.hcdf")) + sorted((HCDFORMAT / "tests").glob("*/*.hcdf"))
    assert docs
    for doc in docs:
        r = cli("resolve", doc, "--offline", "--no-lock", "--cache-dir", tmp_path / "c", "--json")
        payload = json.loads(r.stdout)
        assert_honest(r.stderr, payload["errors"])
        human = cli("resolve", doc, "--offline", "--no-lock", "--cache-dir", tmp_path / "c")
        assert_honest(human.stderr, [])
