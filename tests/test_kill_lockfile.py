"""The lock file, through resolve and verify only (its format is being changed elsewhere).

Mutation-testing killers for include/lockfile.py: what is recorded, what counts as
drift, how each difference is named, and which malformed locks are refused.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest

from ._kill import hcdf, include, model, sha


@pytest.fixture
def robot(tmp_path, cli):
    """root -> sub.hcdf (include, pinned) -> b.stl (unpinned); root -> a.glb (unpinned). Locked once."""
    root = tmp_path / "robot"
    (root / "m").mkdir(parents=True)
    (root / "m" / "a.glb").write_bytes(os.urandom(1500))
    (root / "m" / "b.stl").write_bytes(b"solid b")
    sub = hcdf(model("m/b.stl", name="b"), name="sub")
    (root / "sub.hcdf").write_text(sub)
    doc = root / "robot.hcdf"
    doc.write_text(hcdf(model("m/a.glb", name="a") + "\n" + include("sub.hcdf", sha(sub.encode()))))
    cache = tmp_path / "c"
    r = cli("resolve", doc, "--json", "--cache-dir", cache)
    assert r.exit_code == 0, r.stdout
    return {"root": root, "doc": doc, "cache": cache, "lock": root / "robot.hcdf.lock"}


def _artifacts(lock: Path) -> dict[str, dict]:
    return {a["url"]: a for a in json.loads(lock.read_text())["artifacts"]}


def test_the_lock_records_every_artifact_relative_to_its_folder(robot):
    assert json.loads(robot["lock"].read_text())["root"] == "robot.hcdf"
    arts = _artifacts(robot["lock"])
    assert set(arts) == {"m/a.glb", "m/b.stl", "sub.hcdf"}
    for url, art in arts.items():
        data = (robot["root"] / url).read_bytes()
        assert art["sha256"] == sha(data) and art["size"] == len(data)
    assert arts["m/a.glb"]["kind"] == "model" and arts["sub.hcdf"]["kind"] == "include"
    assert arts["m/a.glb"]["uri"] == "m/a.glb"
    assert arts["m/b.stl"]["referenced_from"] == ["sub.hcdf"]
    assert arts["m/a.glb"]["referenced_from"] == ["robot.hcdf"]


def test_the_lock_is_sorted_and_ends_with_a_newline(robot):
    text = robot["lock"].read_text()
    assert text.endswith("}\n")
    urls = [a["url"] for a in json.loads(text)["artifacts"]]
    assert urls == sorted(urls)


def test_a_lock_in_another_folder_records_paths_relative_to_it(robot, cli):
    lock = robot["root"].parent / "locks" / "robot.lock"
    r = cli("resolve", robot["doc"], "--json", "--cache-dir", robot["cache"], "--lock", lock)
    assert r.exit_code == 0, r.stdout
    assert set(_artifacts(lock)) == {"../robot/m/a.glb", "../robot/m/b.stl", "../robot/sub.hcdf"}
    r = cli("verify", robot["doc"], "--json", "--cache-dir", robot["cache"], "--lock", lock)
    assert r.exit_code == 0, r.stdout


def test_the_locked_tree_verifies_after_the_checkout_moves(robot, cli, tmp_path):
    moved = tmp_path / "elsewhere" / "robot"
    shutil.copytree(robot["root"], moved)
    r = cli("verify", moved / "robot.hcdf", "--json", "--cache-dir", robot["cache"])
    assert r.exit_code == 0, r.stdout


def test_drift_names_the_referencing_file_and_line(robot, cli):
    stl = robot["root"] / "m" / "b.stl"
    stl.write_bytes(b"solid B")  # same size
    r = cli("verify", robot["doc"], "--json", "--cache-dir", robot["cache"])
    assert r.exit_code == 1, r.stdout
    [e] = [e for e in r.json["errors"] if e["code"] == "lock-drift"]
    assert Path(e["file"]).name == "sub.hcdf" and e["line"] == 3
    assert e["expected"] == sha(b"solid b") and e["actual"] == sha(b"solid B")
    assert "changed since it was locked" in e["message"] and "m/b.stl" in e["message"]
    assert e["url"].endswith("m/b.stl")


def test_a_new_reference_is_not_in_the_lock(robot, cli):
    (robot["root"] / "m" / "c.glb").write_bytes(b"c")
    text = robot["doc"].read_text()
    robot["doc"].write_text(text.replace("</hcdf>", model("m/c.glb", name="c") + "\n</hcdf>"))
    r = cli("verify", robot["doc"], "--json", "--cache-dir", robot["cache"])
    assert r.exit_code == 1, r.stdout
    [e] = [e for e in r.json["errors"] if "not in the lock file" in e["message"]]
    assert e["code"] == "lock-drift" and Path(e["file"]).name == "robot.hcdf" and e["line"] == 5
    assert "m/c.glb" in e["message"] and e["url"].endswith("m/c.glb")


def test_a_removed_reference_is_no_longer_referenced(robot, cli):
    text = robot["doc"].read_text()
    robot["doc"].write_text(text.replace(model("m/a.glb", name="a"), ""))
    r = cli("verify", robot["doc"], "--json", "--cache-dir", robot["cache"])
    assert r.exit_code == 1, r.stdout
    [e] = r.json["errors"]
    assert e["code"] == "lock-drift" and "no longer referenced" in e["message"] and "a.glb" in e["message"]
    assert Path(e["file"]).name == "robot.hcdf.lock" and e["url"].endswith("m/a.glb")


def test_drift_in_a_folder_whose_name_has_a_colon(tmp_path, cli):
    root = tmp_path / "robot"
    (root / "a:b").mkdir(parents=True)
    (root / "a:b" / "m.stl").write_bytes(b"solid a")
    (root / "a:b" / "sub.hcdf").write_text(hcdf(model("m.stl"), name="sub"))
    doc = root / "robot.hcdf"
    doc.write_text(hcdf(include("./a:b/sub.hcdf")))
    assert cli("resolve", doc, "--json", "--cache-dir", tmp_path / "c").exit_code == 0
    (root / "a:b" / "m.stl").write_bytes(b"solid b")
    r = cli("verify", doc, "--json", "--cache-dir", tmp_path / "c")
    assert r.exit_code == 1, r.stdout
    [e] = [e for e in r.json["errors"] if e["code"] == "lock-drift" and "m.stl" in e["message"]]
    assert e["file"].endswith("a:b/sub.hcdf") and e["line"] == 3


def test_an_unchanged_tree_has_no_drift_and_verify_writes_nothing(robot, cli):
    before = robot["lock"].read_bytes()
    for args in (("resolve", "--locked"), ("verify",)):
        r = cli(args[0], robot["doc"], "--json", "--cache-dir", robot["cache"], *args[1:])
        assert r.exit_code == 0 and r.json["errors"] == [], r.stdout
    assert robot["lock"].read_bytes() == before


def test_an_upper_case_digest_in_the_lock_is_the_same_digest(robot, cli):
    doc = json.loads(robot["lock"].read_text())
    for art in doc["artifacts"]:
        art["sha256"] = art["sha256"].upper()
    robot["lock"].write_text(json.dumps(doc))
    r = cli("verify", robot["doc"], "--json", "--cache-dir", robot["cache"])
    assert r.exit_code == 0, r.stdout


def _edit(lock: Path, change) -> None:
    doc = json.loads(lock.read_text())
    change(doc)
    lock.write_text(json.dumps(doc))


@pytest.mark.parametrize(
    ("change", "words"),
    [
        (lambda d: d.update(lock_version=3), "unsupported lock_version 3"),
        (lambda d: d.update(lock_version="2"), 'unsupported lock_version "2"'),
        (lambda d: d.pop("lock_version"), "unsupported lock_version null"),
        (lambda d: d.pop("artifacts"), "malformed lock file"),
        (lambda d: d["artifacts"][0].pop("sha256"), "malformed lock file"),
        (lambda d: d["artifacts"][0].pop("url"), "malformed lock file"),
        (lambda d: d["artifacts"][0].pop("kind"), "malformed lock file"),
        (lambda d: d["artifacts"][0].pop("uri"), "malformed lock file"),
        (lambda d: d["artifacts"][0].pop("size"), "malformed lock file"),
        (lambda d: d["artifacts"][0].update(size="big"), "malformed lock file"),
        (lambda d: d["artifacts"][0].update(sha256="abc123"), "sha256 is not a full digest"),
        (lambda d: d["artifacts"][0].update(sha256="z" * 64), "sha256 is not a full digest"),
        (lambda d: d.update(artifacts=[1]), "malformed lock file"),
    ],
)
def test_a_malformed_lock_is_a_lock_file_error(robot, cli, change, words):
    _edit(robot["lock"], change)
    for verb in ("verify", "resolve"):
        extra = ("--locked",) if verb == "resolve" else ()
        r = cli(verb, robot["doc"], "--json", "--cache-dir", robot["cache"], *extra)
        assert r.exit_code == 3, r.stdout
        [e] = r.json["errors"]
        assert e["code"] == "lock-file" and words in e["message"], e
        assert Path(e["file"]).name == "robot.hcdf.lock"


@pytest.mark.parametrize("text", ["", "not json", "[]", "null", "{}"])
def test_a_lock_that_is_not_a_lock_object_is_a_lock_file_error(robot, cli, text):
    robot["lock"].write_text(text)
    r = cli("verify", robot["doc"], "--json", "--cache-dir", robot["cache"])
    assert r.exit_code == 3, r.stdout
    assert r.json["errors"][0]["code"] == "lock-file"


def test_a_missing_lock_under_locked_says_how_to_make_one(robot, cli):
    robot["lock"].unlink()
    r = cli("resolve", robot["doc"], "--json", "--cache-dir", robot["cache"], "--locked")
    assert r.exit_code == 3, r.stdout
    [e] = r.json["errors"]
    assert e["code"] == "lock-file" and "does not exist" in e["message"] and "without --locked" in e["message"]


def test_lock_file_errors_name_the_lock(robot, cli):
    robot["lock"].unlink()
    r = cli("resolve", robot["doc"], "--json", "--cache-dir", robot["cache"], "--locked")
    assert r.json["errors"][0]["file"] == str(robot["lock"])
    robot["lock"].mkdir()  # unreadable as a file
    for verb in ("verify", "resolve"):
        extra = ("--locked",) if verb == "resolve" else ()
        r = cli(verb, robot["doc"], "--json", "--cache-dir", robot["cache"], *extra)
        assert r.exit_code == 3, r.stdout
        [e] = r.json["errors"]
        assert e["code"] == "lock-file" and e["file"] == str(robot["lock"])


def test_an_unsupported_version_names_expected_and_actual(robot, cli):
    _edit(robot["lock"], lambda d: d.update(lock_version=7))
    r = cli("verify", robot["doc"], "--json", "--cache-dir", robot["cache"])
    [e] = r.json["errors"]
    assert e["expected"] == "2" and e["actual"] == "7" and e["file"] == str(robot["lock"])


def test_the_lock_keeps_non_ascii_names_readable(tmp_path, cli):
    (tmp_path / "modèle.glb").write_bytes(b"m")
    doc = tmp_path / "robot.hcdf"
    doc.write_text(hcdf(model("modèle.glb")))
    assert cli("resolve", doc, "--json", "--cache-dir", tmp_path / "c").exit_code == 0
    text = (tmp_path / "robot.hcdf.lock").read_bytes().decode("utf-8")
    assert '"uri": "modèle.glb"' in text


@pytest.mark.parametrize(
    ("body", "found"),
    [("[]", "a list"), ('"x"', "a string"), ("true", "a boolean"), ("7", "an integer"), ("null", "null")],
)
def test_a_lock_that_is_not_an_object_says_what_it_is(cli, tmp_path, body, found):
    (tmp_path / "m.glb").write_bytes(b"m")
    doc = tmp_path / "robot.hcdf"
    doc.write_text(hcdf(model("m.glb")))
    (tmp_path / "robot.hcdf.lock").write_text(body + "\n")
    r = cli("verify", doc, "--json")
    assert r.exit_code == 3, r.stdout
    [err] = r.json["errors"]
    assert err["code"] == "lock-file" and f"expected a JSON object, found {found}" in err["message"], err


def test_the_lock_of_another_root_names_both_and_the_rule(cli, tmp_path):
    (tmp_path / "m.glb").write_bytes(b"m")
    for name in ("a.hcdf", "b.hcdf"):
        (tmp_path / name).write_text(hcdf(model("m.glb")))
    assert cli("resolve", tmp_path / "a.hcdf", "--lock", tmp_path / "shared.lock").exit_code == 0
    r = cli("verify", tmp_path / "b.hcdf", "--lock", tmp_path / "shared.lock", "--json")
    assert r.exit_code == 3, r.stdout
    [err] = r.json["errors"]
    assert (err["expected"], err["actual"]) == ("b.hcdf", "a.hcdf")
    assert err["message"].endswith("(each root document has its own lock: <DOC>.lock, or pass --lock)")


def _negative_size(data):
    data["artifacts"][0]["size"] = -1


def _extra_key(data):
    data["extra"] = 1


@pytest.mark.parametrize(
    ("edit", "said"),
    [
        (_negative_size, "size must be a non-negative integer, found -1"),
        (_extra_key, "top-level keys must be ['artifacts', 'lock_version', 'root'], found ['artifacts', 'extra',"),
    ],
    ids=["negative-size", "extra-key"],
)
def test_a_malformed_lock_says_what_is_wrong(cli, tmp_path, edit, said):
    (tmp_path / "m.glb").write_bytes(b"m")
    doc = tmp_path / "robot.hcdf"
    doc.write_text(hcdf(model("m.glb")))
    assert cli("resolve", doc).exit_code == 0
    lock = tmp_path / "robot.hcdf.lock"
    data = json.loads(lock.read_text())
    edit(data)
    lock.write_text(json.dumps(data))
    r = cli("verify", doc, "--json")
    assert r.exit_code == 3, r.stdout
    [err] = r.json["errors"]
    assert said in err["message"], err
