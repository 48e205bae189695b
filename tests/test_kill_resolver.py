"""resolve / verify behaviour that a removed check would change (mutation-testing killers).

Through the CLI only, so the tests survive refactors of the resolver and the lock format.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from ._kill import flip_last_byte, hcdf, include, model, other_digest, sha


def _run(cli, doc: Path, cache: Path, *extra: str | os.PathLike[str]):
    return cli("resolve", doc, "--json", "--cache-dir", cache, *extra)


# -- lock drift is the digest, not the size --------------------------------------------


@pytest.fixture
def unpinned(tmp_path, cli):
    """A root with one unpinned mesh, locked by a first resolve."""
    root = tmp_path / "robot"
    root.mkdir()
    mesh = root / "m.stl"
    mesh.write_bytes(os.urandom(2000))
    doc = root / "robot.hcdf"
    doc.write_text(hcdf(model("m.stl")))
    r = _run(cli, doc, tmp_path / "c")
    assert r.exit_code == 0, r.stdout
    return {"root": root, "doc": doc, "mesh": mesh, "cache": tmp_path / "c"}


def test_same_size_change_of_a_locked_file_is_drift_under_locked(cli, unpinned):
    old = unpinned["mesh"].read_bytes()
    new = flip_last_byte(old)
    unpinned["mesh"].write_bytes(new)
    assert len(new) == len(old)
    r = _run(cli, unpinned["doc"], unpinned["cache"], "--locked")
    assert r.exit_code == 1, r.stdout
    drift = [e for e in r.json["errors"] if e["code"] == "lock-drift"]
    assert drift and drift[0]["expected"] == sha(old) and drift[0]["actual"] == sha(new)


def test_same_size_change_of_a_locked_file_fails_verify(cli, unpinned):
    old = unpinned["mesh"].read_bytes()
    unpinned["mesh"].write_bytes(flip_last_byte(old))
    r = cli("verify", unpinned["doc"], "--json", "--cache-dir", unpinned["cache"])
    assert r.exit_code == 1, r.stdout
    assert any(e["code"] == "lock-drift" and e["expected"] == sha(old) for e in r.json["errors"])


def test_an_unchanged_tree_is_not_drift(cli, unpinned):
    assert _run(cli, unpinned["doc"], unpinned["cache"], "--locked").exit_code == 0
    r = cli("verify", unpinned["doc"], "--json", "--cache-dir", unpinned["cache"])
    assert r.exit_code == 0 and r.json["ok"], r.stdout


def test_same_size_change_of_an_unpinned_include_is_drift_and_it_is_not_walked(cli, tmp_path):
    root = tmp_path / "robot"
    root.mkdir()
    sub = root / "sub.hcdf"
    sub.write_text(hcdf(model("a.stl", name="x"), name="sub"))
    (root / "a.stl").write_bytes(b"solid a")
    doc = root / "robot.hcdf"
    doc.write_text(hcdf(include("sub.hcdf")))
    assert _run(cli, doc, tmp_path / "c").exit_code == 0
    # same size: one reference renamed to a file that does not exist
    sub.write_text(hcdf(model("b.stl", name="x"), name="sub"))
    r = _run(cli, doc, tmp_path / "c", "--locked")
    assert r.exit_code == 1, r.stdout
    codes = [e["code"] for e in r.json["errors"]]
    assert "lock-drift" in codes
    assert "not-found" not in codes  # the changed include was not followed to b.stl


# -- an include whose pin fails is neither parsed nor followed -------------------------


@pytest.fixture
def bad_include(tmp_path):
    """root -> sub.hcdf (its pin is wrong) -> child.hcdf and missing.glb (neither exists)."""
    root = tmp_path / "robot"
    root.mkdir()
    sub = hcdf(include("child.hcdf", name="ch") + "\n" + model("missing.glb", name="mm"), name="sub")
    (root / "sub.hcdf").write_text(sub)
    return {"root": root, "sub": sub.encode(), "cache": tmp_path / "c"}


@pytest.mark.parametrize("how", ["full", "weak", "shared-prefix"])
def test_an_include_whose_pin_fails_is_not_followed(cli, bad_include, how):
    real = sha(bad_include["sub"])
    pin = {"full": sha(b"other"), "weak": sha(b"other")[:10], "shared-prefix": other_digest(real, 8)}[how]
    doc = bad_include["root"] / "robot.hcdf"
    doc.write_text(hcdf(include("sub.hcdf", pin)))
    r = _run(cli, doc, bad_include["cache"])
    assert r.exit_code == 1, r.stdout
    [e] = r.json["errors"]  # only the mismatch: nothing inside sub.hcdf was looked at
    assert e["code"] == "digest-mismatch" and e["actual"] == real and e["expected"] == pin
    urls = {a["url"] for a in r.json.get("artifacts", [])}
    assert not any("child" in u or "missing" in u for u in urls)


def test_an_include_with_a_good_pin_is_followed(cli, bad_include):
    doc = bad_include["root"] / "robot.hcdf"
    doc.write_text(hcdf(include("sub.hcdf", sha(bad_include["sub"]))))
    r = _run(cli, doc, bad_include["cache"])
    assert r.exit_code == 3, r.stdout
    assert {e["code"] for e in r.json["errors"]} == {"not-found"}
    assert len(r.json["errors"]) == 2


def test_a_remote_include_whose_pin_fails_is_not_followed_nor_cached(cli, tmp_path, https_server, tls):
    sub = hcdf(include("child.hcdf", name="ch"), name="sub").encode()
    url = https_server.add("/sub.hcdf", sub)
    doc = tmp_path / "robot.hcdf"
    doc.write_text(hcdf(include(url, sha(b"other"))))
    cache = tmp_path / "c"
    r = _run(cli, doc, cache, "--ca-bundle", tls.ca_pem)
    assert r.exit_code == 1, r.stdout
    [e] = r.json["errors"]
    assert e["code"] == "digest-mismatch" and e["actual"] == sha(sub)
    assert https_server.hits.get("/child.hcdf", 0) == 0
    blobs = [p for p in (cache / "sha256").rglob("*") if p.is_file()] if (cache / "sha256").exists() else []
    assert blobs == []
