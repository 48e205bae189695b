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


# -- what resolve reports about each artifact ------------------------------------------


def _words(items) -> str:
    """Warnings as one text, whether they are strings or objects."""
    import json

    return json.dumps(items)


@pytest.fixture
def mixed(tmp_path):
    root = tmp_path / "robot"
    root.mkdir()
    blobs = {name: os.urandom(100 + i) for i, name in enumerate(["full.glb", "weak.glb", "none.glb"])}
    for name, data in blobs.items():
        (root / name).write_bytes(data)
    doc = root / "robot.hcdf"
    doc.write_text(
        hcdf(
            "\n".join(
                [
                    model("full.glb", sha(blobs["full.glb"]), name="f"),
                    model("weak.glb", sha(blobs["weak.glb"])[:12], name="w"),
                    model("none.glb", name="n"),
                    '<comp name="fw"><software name="boot"><version>1</version><hash>abc</hash></software></comp>',
                ]
            )
        )
    )
    return {"root": root, "doc": doc, "blobs": blobs, "cache": tmp_path / "c"}


def test_pin_strength_source_and_summary(cli, mixed):
    r = _run(cli, mixed["doc"], mixed["cache"], "--no-lock")
    assert r.exit_code == 0, r.stdout
    arts = {a["url"]: a for a in r.json["artifacts"]}
    assert {u: a["pin"] for u, a in arts.items()} == {"full.glb": "full", "weak.glb": "weak", "none.glb": "unpinned"}
    assert all(a["source"] == "file" for a in arts.values())
    for name, data in mixed["blobs"].items():
        assert arts[name]["sha256"] == sha(data) and arts[name]["size"] == len(data)
    s = r.json["summary"]
    assert (s["references"], s["files"], s["pinned"], s["weak"], s["unpinned"]) == (3, 3, 1, 1, 1)
    assert s["bytes_verified"] == sum(len(d) for d in mixed["blobs"].values())
    assert (s["local"], s["from_cache"], s["fetched"]) == (3, 0, 0)


def test_weak_and_unpinned_references_are_warned_about(cli, mixed):
    r = _run(cli, mixed["doc"], mixed["cache"], "--no-lock")
    text = _words(r.json["warnings"])
    assert "weak.glb has a weak pin (48 bits)" in text and sha(mixed["blobs"]["weak.glb"]) in text
    assert "none.glb is unpinned" in text and sha(mixed["blobs"]["none.glb"]) in text
    assert "full.glb" not in text
    where = {Path(w["url"]).name: (Path(w["file"]).name, w["line"]) for w in r.json["warnings"] if w.get("url")}
    assert where["weak.glb"] == ("robot.hcdf", 4) and where["none.glb"] == ("robot.hcdf", 5)


def test_a_malformed_firmware_hash_is_a_warning_not_an_error(cli, mixed):
    r = _run(cli, mixed["doc"], mixed["cache"], "--no-lock")
    assert r.exit_code == 0
    assert "firmware 'boot'" in _words(r.json["warnings"])
    [fw] = r.json["firmware"]
    assert fw["name"] == "boot" and fw["hash"] == "abc"


def test_strict_refuses_a_weak_pin_naming_it(cli, mixed):
    r = _run(cli, mixed["doc"], mixed["cache"], "--no-lock", "--strict")
    assert r.exit_code == 1, r.stdout
    [e] = r.json["errors"]
    assert e["code"] == "weak-pin" and e["line"] == 4
    assert e["actual"] == sha(mixed["blobs"]["weak.glb"])[:12] and "64" in e["expected"]
    assert "12 hex digits (48 bits)" in e["message"]


def test_locked_unpinned_needs_the_lock_and_then_only_warns(cli, mixed):
    assert _run(cli, mixed["doc"], mixed["cache"]).exit_code == 0  # writes the lock
    r = _run(cli, mixed["doc"], mixed["cache"], "--locked")
    assert r.exit_code == 0, r.stdout
    assert "none.glb has no sha; the lock file pins it" in _words(r.json["warnings"])


def test_each_use_of_a_file_is_checked_against_its_own_pin(cli, tmp_path):
    data = os.urandom(300)
    (tmp_path / "a.glb").write_bytes(data)
    doc = tmp_path / "d.hcdf"
    doc.write_text(hcdf(model("a.glb", sha(data), name="good") + "\n" + model("a.glb", sha(b"x"), name="bad")))
    r = _run(cli, doc, tmp_path / "c", "--no-lock")
    assert r.exit_code == 1
    [e] = r.json["errors"]
    assert e["code"] == "digest-mismatch" and e["line"] == 4 and e["expected"] == sha(b"x")
    assert e["message"].startswith("a.glb: digest mismatch") or "a.glb: digest mismatch" in e["message"]


def test_nothing_is_written_when_a_check_fails(cli, tmp_path):
    (tmp_path / "a.glb").write_bytes(b"a")
    doc = tmp_path / "d.hcdf"
    doc.write_text(hcdf(model("a.glb", sha(b"b"))))
    r = _run(cli, doc, tmp_path / "c")
    assert r.exit_code == 1 and not r.json["ok"]
    assert not (tmp_path / "d.hcdf.lock").exists()


# -- remote trees ----------------------------------------------------------------------


def test_a_remote_include_is_parsed_and_its_relative_references_are_fetched(cli, tmp_path, https_server, tls):
    glb = os.urandom(400)
    https_server.add("/pkg/m/a.glb", glb)
    sub = hcdf(model("m/a.glb", sha(glb)), name="sub").encode()
    url = https_server.add("/pkg/sub.hcdf", sub)
    doc = tmp_path / "robot.hcdf"
    doc.write_text(hcdf(include(url, sha(sub))))
    cache = tmp_path / "c"
    r = _run(cli, doc, cache, "--ca-bundle", tls.ca_pem)
    assert r.exit_code == 0, r.stdout
    arts = {a["url"]: a for a in r.json["artifacts"]}
    assert set(arts) == {url, https_server.url("/pkg/m/a.glb")}
    assert {a["source"] for a in arts.values()} == {"network"}
    assert r.json["summary"]["fetched"] == 2
    # the second run reads both from the cache, the include re-parsed from its blob
    r = _run(cli, doc, cache, "--ca-bundle", tls.ca_pem, "--offline")
    assert r.exit_code == 0, r.stdout
    assert {a["source"] for a in r.json["artifacts"]} == {"cache"}
    assert r.json["summary"]["from_cache"] == 2
    assert https_server.hits["/pkg/sub.hcdf"] == 1


def test_offline_names_why_an_unpinned_remote_file_cannot_be_found(cli, tmp_path, https_server):
    url = https_server.add("/a.glb", b"a")
    doc = tmp_path / "d.hcdf"
    doc.write_text(hcdf(model(url)))
    r = _run(cli, doc, tmp_path / "c", "--offline", "--no-lock")
    assert r.exit_code == 3, r.stdout
    [e] = r.json["errors"]
    assert e["code"] == "offline" and "no full pin or lock entry" in e["message"] and e["line"] == 3
    doc.write_text(hcdf(model(url, sha(b"a"))))
    r = _run(cli, doc, tmp_path / "c", "--offline", "--no-lock")
    assert r.exit_code == 3 and "no full pin" not in r.json["errors"][0]["message"]
    assert https_server.total_hits == 0


def test_the_lock_digest_finds_an_unpinned_remote_file_in_the_cache(cli, tmp_path, https_server, tls):
    url = https_server.add("/a.glb", b"remote")
    doc = tmp_path / "d.hcdf"
    doc.write_text(hcdf(model(url)))
    cache = tmp_path / "c"
    assert _run(cli, doc, cache, "--ca-bundle", tls.ca_pem).exit_code == 0
    r = cli("verify", doc, "--json", "--cache-dir", cache)
    assert r.exit_code == 0, r.stdout
    assert r.json["artifacts"][0]["source"] == "cache"
    assert https_server.hits["/a.glb"] == 1


def test_a_remote_include_over_max_size_is_refused(cli, tmp_path, https_server, tls):
    sub = hcdf("<comp name='x'/>" * 50, name="sub").encode()
    url = https_server.add("/sub.hcdf", sub)
    doc = tmp_path / "d.hcdf"
    doc.write_text(hcdf(include(url, sha(sub))))
    r = _run(cli, doc, tmp_path / "c", "--ca-bundle", tls.ca_pem, "--max-size", "100", "--no-lock")
    assert r.exit_code == 3, r.stdout
    [e] = r.json["errors"]
    assert e["code"] == "fetch" and "100-byte limit" in e["message"] and e["line"] == 3


def test_plain_http_is_refused_without_a_full_pin_even_with_allow_http(cli, tmp_path, http_server):
    url = http_server.add("/a.glb", b"a")
    doc = tmp_path / "d.hcdf"
    for pin in (None, sha(b"a")[:8]):
        doc.write_text(hcdf(model(url, pin)))
        r = _run(cli, doc, tmp_path / "c", "--allow-http", "--no-lock")
        assert r.exit_code == 3, r.stdout
        assert "plain http is refused" in r.json["errors"][0]["message"]
    doc.write_text(hcdf(model(url, sha(b"a"))))
    assert _run(cli, doc, tmp_path / "c", "--allow-http", "--no-lock").exit_code == 0
    assert http_server.hits["/a.glb"] == 1


# -- link stubs ------------------------------------------------------------------------


def test_link_stubs_are_followed_only_to_a_sibling_file(tmp_path):
    from hcdf_trust.include.resolver import link_stub_target

    (tmp_path / "real.hcdf").write_text("<hcdf/>")
    (tmp_path / "dir").mkdir()
    stub = tmp_path / "stub.hcdf"
    assert link_stub_target(stub, b"real.hcdf") == tmp_path / "real.hcdf"
    assert link_stub_target(stub, b"real.hcdf\n") == tmp_path / "real.hcdf"
    for data in (b"", b"  ", b"../real.hcdf", b"sub/real.hcdf", b"sub\\real.hcdf", b".", b"..", b"dir", b"missing"):
        assert link_stub_target(stub, data) is None, data
    assert link_stub_target(stub, b"<hcdf/>") is None
    assert link_stub_target(stub, b"real.hcdf\nreal.hcdf") is None
    long = "a" * 250 + ".hcdf"
    (tmp_path / long).write_text("<hcdf/>")
    assert len(long) == 255 and link_stub_target(stub, long.encode()) == tmp_path / long
    assert link_stub_target(stub, b" " + long.encode()) is None  # over 255 bytes


def test_a_stub_root_document_resolves_its_target(cli, tmp_path):
    (tmp_path / "a.glb").write_bytes(b"a")
    (tmp_path / "real.hcdf").write_text(hcdf(model("a.glb", sha(b"a"))))
    (tmp_path / "stub.hcdf").write_text("real.hcdf")
    r = _run(cli, tmp_path / "stub.hcdf", tmp_path / "c", "--no-lock")
    assert r.exit_code == 0, r.stdout
    assert r.json["root"].endswith("real.hcdf") and r.json["summary"]["files"] == 1


def test_a_missing_locked_file_is_reported_once_as_missing_not_as_unreferenced(cli, unpinned):
    unpinned["mesh"].unlink()
    r = _run(cli, unpinned["doc"], unpinned["cache"], "--locked")
    assert r.exit_code == 3, r.stdout
    [e] = r.json["errors"]
    assert e["code"] == "not-found" and e["line"] == 3


def test_an_include_of_itself_is_a_cycle(cli, tmp_path):
    doc = tmp_path / "a.hcdf"
    doc.write_text(hcdf(include("a.hcdf")))
    r = _run(cli, doc, tmp_path / "c", "--no-lock")
    assert r.exit_code == 3, r.stdout
    [e] = r.json["errors"]
    assert e["code"] == "include-cycle" and e["line"] == 3


def test_max_depth_one_allows_one_level_of_includes(cli, tmp_path):
    (tmp_path / "b.hcdf").write_text(hcdf('<comp name="b"/>', name="b"))
    (tmp_path / "a.hcdf").write_text(hcdf(include("b.hcdf"), name="a"))
    doc = tmp_path / "r.hcdf"
    doc.write_text(hcdf(include("a.hcdf")))
    r = _run(cli, tmp_path / "a.hcdf", tmp_path / "c", "--no-lock", "--max-depth", "1")
    assert r.exit_code == 0, r.stdout
    r = _run(cli, doc, tmp_path / "c", "--no-lock", "--max-depth", "1")
    assert r.exit_code == 3, r.stdout
    [e] = r.json["errors"]
    assert e["code"] == "include-depth" and Path(e["file"]).name == "a.hcdf" and e["line"] == 3
