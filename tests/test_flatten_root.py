"""The flattened document resolves and verifies again, with the same --root/--base as the
run that wrote it: flatten refuses an --out whose rebased references would leave that root."""

from __future__ import annotations

import hashlib
import os
import re
import shlex
import shutil
import subprocess
from pathlib import Path

from .conftest import CORPUS, MODELS, PROJECT


def hcdf(body: str) -> str:
    return f'<?xml version="1.0"?>\n<hcdf version="1.0" name="t">\n{body}\n</hcdf>\n'


def sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def demo_lines(corpus: Path) -> list[str | list[str]]:
    """The demo recipe's lines after ``rm -rf``: hcdf-trust lines as argument lists, the others as shell text."""
    recipe = re.search(r"^demo:.*?\n((?:\t.*\n)+)", (PROJECT / "Makefile").read_text(), re.M)
    assert recipe is not None
    lines: list[str | list[str]] = []
    for line in recipe.group(1).splitlines():
        line = line.strip().replace("$(CORPUS)", str(corpus))
        if line.startswith("$(BIN)/hcdf-trust "):
            lines.append(shlex.split(line)[1:])
        elif not line.startswith(("rm -rf ", "@echo")):  # @echo: the closing how-to-run text
            lines.append(line)
    return lines


def demo_commands() -> list[list[str]]:
    """The hcdf-trust lines of the Makefile's demo recipe, as argument lists."""
    return [c for c in demo_lines(CORPUS) if isinstance(c, list)]


def test_the_demo_resolves_and_verifies_its_flattened_document(cli, tmp_path, monkeypatch):
    shutil.copytree(PROJECT / "examples", tmp_path / "examples", ignore=shutil.ignore_patterns("out"))
    monkeypatch.chdir(tmp_path)
    commands = demo_commands()
    flat = "examples/out/scout2.flat.hcdf"
    flat_commands = [c for c in commands if c[1:2] == [flat]]
    assert [c[0] for c in flat_commands] == ["validate", "resolve", "verify"], commands
    for args in demo_lines(CORPUS):
        if isinstance(args, str):  # the shell line making the throwaway passphrase files
            subprocess.run(args, shell=True, check=True)
            continue
        r = cli(*args)  # the cache is isolated by conftest
        assert r.exit_code == 0, (args, r.stderr)
        assert "outside the root" not in r.stderr
    # the flattened document references the very files the robot does (oracle: hashlib on disk)
    flat_run = cli(*flat_commands[1], "--no-lock", "--json")
    source_run = cli("resolve", "examples/robot/robot.hcdf", "--no-lock", "--json")
    source = {a["sha256"] for a in source_run.json["artifacts"] if a["kind"] != "include"}
    assert {a["sha256"] for a in flat_run.json["artifacts"]} == source
    robot = (tmp_path / "examples" / "robot").resolve()
    for art in flat_run.json["artifacts"]:
        path = (tmp_path / "examples" / "out" / art["url"]).resolve()
        assert path.is_relative_to(robot) and sha(path.read_bytes()) == art["sha256"]


def tree(tmp_path: Path) -> Path:
    root = tmp_path / "proj" / "robot"
    (root / "models").mkdir(parents=True)
    (root / "models" / "m.glb").write_bytes(b"model")
    (root / "parts").mkdir()
    (root / "parts" / "arm.hcdf").write_text(
        hcdf(f'<comp name="a"><visual name="v"><model uri="../models/m.glb" sha="{sha(b"model")}"/></visual></comp>')
    )
    doc = root / "robot.hcdf"
    doc.write_text(
        hcdf(
            '<comp name="c"><visual name="v"><model uri="models/m.glb"/></visual></comp>'
            '<include uri="parts/arm.hcdf" name="arm"/>'
        )
    )
    return doc


def test_an_output_whose_references_leave_its_folder_needs_a_named_root(cli, tmp_path, monkeypatch):
    doc = tree(tmp_path)
    monkeypatch.chdir(tmp_path)
    out = Path("proj/out/flat.hcdf")
    r = cli("resolve", doc, "--out", out, "--json")
    assert r.exit_code == 3
    (err,) = r.json["errors"]
    assert err["code"] == "flatten"
    assert "proj/out/flat.hcdf would reference 1 file outside its folder proj/out" in err["message"]
    assert "../robot/models/m.glb" in err["message"] and "--root DIR" in err["message"]
    assert (err["expected"], err["actual"]) == ("a file inside proj/out", "proj/robot/models/m.glb")
    assert not out.exists() and not (doc.parent / "hcdf.lock").exists()  # nothing written

    named = cli("resolve", doc, "--out", out, "--root", "proj", "--no-lock")
    assert named.exit_code == 0, named.stderr
    assert 'uri="../robot/models/m.glb"' in out.read_text()
    again = cli("resolve", out, "--root", "proj", "--no-lock", "--json")
    assert again.exit_code == 0, again.stdout
    assert {a["sha256"] for a in again.json["artifacts"]} == {sha(b"model")}
    # and a plain resolve of it would indeed have been refused: the rule is the resolver's own
    plain = cli("resolve", out, "--no-lock", "--json")
    assert plain.exit_code == 3 and plain.json["errors"][0]["code"] == "path-escape"


def test_a_root_that_does_not_hold_the_files_is_refused_too(cli, tmp_path):
    doc = tree(tmp_path)
    (tmp_path / "proj" / "out").mkdir()
    r = cli("resolve", doc, "--out", tmp_path / "proj" / "out" / "f.hcdf", "--root", doc.parent / "parts", "--json")
    assert r.exit_code == 3  # the resolve itself refuses ../models from parts/: nothing to flatten
    assert not (tmp_path / "proj" / "out" / "f.hcdf").exists()


def test_beside_or_above_the_root_document_no_flag_is_needed(cli, tmp_path):
    doc = tree(tmp_path)
    for out in (doc.parent / "flat.hcdf", tmp_path / "proj" / "flat.hcdf"):
        r = cli("resolve", doc, "--out", out, "--no-lock")
        assert r.exit_code == 0, r.stderr
        again = cli("resolve", out, "--no-lock", "--json")
        assert again.exit_code == 0, again.stdout
        assert {a["sha256"] for a in again.json["artifacts"]} == {sha(b"model")}


def test_with_base_the_flattened_fragment_resolves_with_the_same_base(cli, tmp_path):
    fragment = MODELS / "mr_mcxn_t1" / "optical-flow" / "d9507e38-optical-flow.hcdf"
    out = tmp_path / "dist" / "flat.hcdf"
    cache = ("--cache-dir", tmp_path / "c")
    r = cli("resolve", fragment, "--base", MODELS, "--out", out, "--no-lock", *cache, "--json")
    assert r.exit_code == 0, r.stdout
    first = {a["sha256"] for a in r.json["artifacts"]}
    again = cli("resolve", out, "--base", MODELS, "--no-lock", *cache, "--json")
    assert again.exit_code == 0, again.stdout
    assert {a["sha256"] for a in again.json["artifacts"]} == first
    assert not os.path.exists(MODELS / "hcdf.lock")
