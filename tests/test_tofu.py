"""Trust on first use: the lock is the pin of every reference without a full sha."""

from __future__ import annotations

import hashlib
import json

import pytest


def sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


HEAD = '<?xml version="1.0"?>\n<hcdf version="1.0" name="r">\n'


def model(uri: str, pin: str | None = None, name: str = "c") -> str:
    attr = f' sha="{pin}"' if pin else ""
    return f'<comp name="{name}"><visual><model uri="{uri}"{attr}/></visual></comp>\n'


@pytest.fixture
def tree(tmp_path):
    """robot.hcdf: a.glb unpinned, b.glb weakly pinned, c.glb fully pinned; one sub-assembly."""
    root = tmp_path / "robot"
    root.mkdir()
    files = {"a.glb": b"a-v1", "b.glb": b"b-v1", "c.glb": b"c-v1"}
    for name, data in files.items():
        (root / name).write_bytes(data)
    (root / "sub.hcdf").write_text(HEAD + model("a.glb", name="s") + "</hcdf>\n")
    doc = root / "robot.hcdf"
    doc.write_text(
        HEAD
        + model("a.glb", name="a")
        + model("b.glb", sha(b"b-v1")[:8], name="b")
        + model("c.glb", sha(b"c-v1"), name="c")
        + '<include uri="sub.hcdf" name="sub"/>\n</hcdf>\n'
    )
    return doc


def resolve(cli, doc, *extra):
    return cli("resolve", doc, "--json", *extra)


def lock_of(doc):
    return json.loads(doc.with_name(doc.name + ".lock").read_text())


def shas(doc):
    return {a["url"]: a["sha256"] for a in lock_of(doc)["artifacts"]}


def test_changed_unpinned_reference_fails_plain_resolve(cli, tree):
    assert resolve(cli, tree).exit_code == 0
    lock = tree.with_name("robot.hcdf.lock").read_bytes()
    (tree.parent / "a.glb").write_bytes(b"a-v2")
    r = resolve(cli, tree)
    assert r.exit_code == 1
    [e] = r.json["errors"]
    assert e["code"] == "lock-drift" and "changed since it was locked" in e["message"]
    assert (e["expected"], e["actual"]) == (sha(b"a-v1"), sha(b"a-v2"))
    assert e["file"].endswith("robot.hcdf") and e["line"] == 3  # from the current parse
    assert tree.with_name("robot.hcdf.lock").read_bytes() == lock  # not silently re-pinned


def test_changed_weakly_pinned_reference_fails_plain_resolve(cli, tree):
    assert resolve(cli, tree).exit_code == 0
    # same 32-bit prefix is not needed: a weak pin that still matches is the attack
    text = tree.read_text().replace(f'sha="{sha(b"b-v1")[:8]}"', f'sha="{sha(b"b-v2")[:8]}"')
    tree.write_text(text)
    (tree.parent / "b.glb").write_bytes(b"b-v2")
    r = resolve(cli, tree)
    assert r.exit_code == 1
    [e] = r.json["errors"]
    assert e["code"] == "lock-drift" and (e["expected"], e["actual"]) == (sha(b"b-v1"), sha(b"b-v2"))
    assert shas(tree)["b.glb"] == sha(b"b-v1")


def test_changed_unpinned_include_is_not_parsed(cli, tree):
    assert resolve(cli, tree).exit_code == 0
    (tree.parent / "evil.glb").write_bytes(b"evil")
    (tree.parent / "sub.hcdf").write_text(HEAD + model("evil.glb", name="s") + "</hcdf>\n")
    r = resolve(cli, tree)
    assert r.exit_code == 1
    assert {e["code"] for e in r.json["errors"]} == {"lock-drift"}
    assert "evil.glb" not in {a["url"] for a in r.json["artifacts"]}  # its references were not followed


def test_full_pin_in_the_document_is_authoritative(cli, tree):
    assert resolve(cli, tree).exit_code == 0
    (tree.parent / "c.glb").write_bytes(b"c-v2")
    tree.write_text(tree.read_text().replace(sha(b"c-v1"), sha(b"c-v2")))
    r = resolve(cli, tree)
    assert r.exit_code == 0, r.stdout
    assert shas(tree)["c.glb"] == sha(b"c-v2")


def test_update_all_and_update_one(cli, tree):
    assert resolve(cli, tree).exit_code == 0
    (tree.parent / "a.glb").write_bytes(b"a-v2")
    (tree.parent / "b.glb").write_bytes(b"b-v2")
    tree.write_text(tree.read_text().replace(sha(b"b-v1")[:8], sha(b"b-v2")[:8]))
    assert resolve(cli, tree).exit_code == 1
    # --update naming one entry accepts only that one: the other still fails, nothing written
    r = resolve(cli, tree, "--update", "a.glb")
    assert r.exit_code == 1 and [e["url"] for e in r.json["errors"]] == ["b.glb"]
    assert shas(tree)["a.glb"] == sha(b"a-v1")
    r = resolve(cli, tree, "--update", "a.glb", "--update", "b.glb")
    assert r.exit_code == 0, r.stdout
    assert shas(tree)["a.glb"] == sha(b"a-v2") and shas(tree)["b.glb"] == sha(b"b-v2")
    (tree.parent / "a.glb").write_bytes(b"a-v3")
    assert resolve(cli, tree).exit_code == 1
    assert resolve(cli, tree, "--update").exit_code == 0
    assert shas(tree)["a.glb"] == sha(b"a-v3")


def test_update_matches_the_uri_as_written_in_any_document(cli, tmp_path):
    (tmp_path / "models").mkdir()
    (tmp_path / "models" / "m.glb").write_bytes(b"v1")
    (tmp_path / "parts").mkdir()
    (tmp_path / "parts" / "p.hcdf").write_text(HEAD + model("../models/m.glb", name="p") + "</hcdf>\n")
    doc = tmp_path / "robot.hcdf"
    doc.write_text(HEAD + model("models/m.glb") + '<include uri="parts/p.hcdf" name="p"/>\n</hcdf>\n')
    assert resolve(cli, doc).exit_code == 0
    (tmp_path / "models" / "m.glb").write_bytes(b"v2")
    assert resolve(cli, doc).exit_code == 1
    assert resolve(cli, doc, "--update", "../models/m.glb").exit_code == 0
    assert shas(doc)["models/m.glb"] == sha(b"v2")


def test_update_of_an_unknown_name_is_an_error(cli, tree):
    assert resolve(cli, tree).exit_code == 0
    lock = tree.with_name("robot.hcdf.lock").read_bytes()
    r = resolve(cli, tree, "--update", "nope.glb")
    assert r.exit_code == 3 and "nope.glb" in r.json["errors"][0]["message"]
    assert tree.with_name("robot.hcdf.lock").read_bytes() == lock


def test_update_and_locked_is_a_usage_error(cli, tree):
    assert cli("resolve", tree, "--locked", "--update").exit_code == 2


def test_new_references_are_added_and_unreferenced_ones_dropped(cli, tree):
    assert resolve(cli, tree).exit_code == 0
    (tree.parent / "n.glb").write_bytes(b"new")
    tree.write_text(tree.read_text().replace('"c.glb"', '"n.glb"').replace(f' sha="{sha(b"c-v1")}"', ""))
    assert resolve(cli, tree).exit_code == 0
    assert set(shas(tree)) == {"a.glb", "b.glb", "n.glb", "sub.hcdf"}


def test_locked_and_verify_never_write_the_lock(cli, tree):
    assert resolve(cli, tree).exit_code == 0
    lock = tree.with_name("robot.hcdf.lock")
    # a lock that differs only in what --locked does not compare (uri spelling, order of
    # referenced_from) would be rewritten by a resolve that writes: --locked must not.
    doc = json.loads(lock.read_text())
    for a in doc["artifacts"]:
        a["referenced_from"] = list(reversed(a["referenced_from"])) + ["old.hcdf"]
    lock.write_text(json.dumps(doc))
    before = (lock.read_bytes(), lock.stat().st_mtime_ns)
    for argv in (["resolve", tree, "--locked"], ["verify", tree]):
        r = cli(*argv, "--json")
        assert r.exit_code == 0, r.stdout
        assert r.json.get("wrote", []) == []
        assert (lock.read_bytes(), lock.stat().st_mtime_ns) == before


def test_moving_a_reference_to_another_line_is_not_drift(cli, tree):
    assert resolve(cli, tree).exit_code == 0
    lock = tree.with_name("robot.hcdf.lock").read_bytes()
    tree.write_text(tree.read_text().replace("<comp", "<!-- a comment -->\n\n<comp", 1))
    assert cli("resolve", tree, "--locked", "--json").exit_code == 0
    assert resolve(cli, tree).exit_code == 0
    assert tree.with_name("robot.hcdf.lock").read_bytes() == lock  # no line numbers in the lock
    assert all(":" not in r for a in lock_of(tree)["artifacts"] for r in a["referenced_from"])


def test_drift_message_takes_the_line_from_the_current_parse(cli, tree):
    assert resolve(cli, tree).exit_code == 0
    tree.write_text(tree.read_text().replace("<comp", "<!-- a comment -->\n\n<comp", 1))
    (tree.parent / "a.glb").write_bytes(b"a-v2")
    for argv in (["resolve", tree], ["resolve", tree, "--locked"], ["verify", tree]):
        r = cli(*argv, "--json")
        drift = [e for e in r.json["errors"] if e["code"] == "lock-drift"]
        assert [(e["file"].rsplit("/", 1)[-1], e["line"]) for e in drift] == [("robot.hcdf", 5)], argv


@pytest.mark.parametrize("argv", [["resolve"], ["resolve", "--locked"], ["verify"]])
def test_recorded_size_is_checked_like_the_digest(cli, tree, argv):
    assert resolve(cli, tree).exit_code == 0
    lock = tree.with_name("robot.hcdf.lock")
    doc = json.loads(lock.read_text())
    for a in doc["artifacts"]:
        if a["url"] == "a.glb":
            a["size"] += 1  # right sha, wrong size
    lock.write_text(json.dumps(doc))
    r = cli(argv[0], tree, *argv[1:], "--json")
    assert r.exit_code == 1, r.stdout
    [e] = [e for e in r.json["errors"] if e["code"] == "lock-drift"]
    assert e["url"] == "a.glb" and (e["expected"], e["actual"]) == ("5 bytes", "4 bytes")


def test_digest_drift_with_the_same_size_is_caught(cli, tree):
    """Every drift test above changes the content; here the size stays the same."""
    assert resolve(cli, tree).exit_code == 0
    (tree.parent / "a.glb").write_bytes(b"a-v9")
    for argv in (["resolve", tree], ["resolve", tree, "--locked"], ["verify", tree]):
        r = cli(*argv, "--json")
        assert r.exit_code == 1 and "lock-drift" in {e["code"] for e in r.json["errors"]}, argv


def test_warnings_are_objects_in_json_and_lines_for_humans(cli, tree):
    r = cli("resolve", tree, "--no-lock")
    assert "warning: " in r.stderr and "robot.hcdf:4: b.glb has a weak pin (32 bits)" in r.stderr
    # a.glb is referenced twice (robot.hcdf and sub.hcdf): one line naming the other place
    assert r.stderr.count("a.glb is unpinned") == 1 and "(also at " in r.stderr, r.stderr
    r = resolve(cli, tree)
    assert r.exit_code == 0
    by_code = {w["code"]: w for w in r.json["warnings"]}
    assert set(by_code) == {"unpinned", "weak-pin"}
    w = by_code["weak-pin"]
    assert w["file"].endswith("robot.hcdf") and w["line"] == 4 and "32 bits" in w["message"]
    assert not any(w.get("repeated") for w in r.json["warnings"])
    r = resolve(cli, tree)  # the lock now pins the unpinned reference
    assert {w["code"] for w in r.json["warnings"]} == {"lock-pins", "weak-pin"}
    assert all(w["repeated"] for w in r.json["warnings"])  # the lock, written by the run that said them, covers them
    r = cli("verify", tree)  # so a person is not told again, by this verb or the next (the summary counts them)
    assert r.exit_code == 0 and "warning" not in r.stderr and "1 weak, 2 unpinned" in r.stderr, r.stderr


def test_update_matches_the_lock_url_when_no_uri_is_spelled_that_way(cli, tmp_path):
    (tmp_path / "models").mkdir()
    (tmp_path / "models" / "m.glb").write_bytes(b"v1")
    (tmp_path / "parts").mkdir()
    (tmp_path / "parts" / "p.hcdf").write_text(HEAD + model("../models/m.glb", name="p") + "</hcdf>\n")
    doc = tmp_path / "robot.hcdf"
    doc.write_text(HEAD + '<include uri="parts/p.hcdf" name="p"/>\n</hcdf>\n')
    assert resolve(cli, doc).exit_code == 0
    (tmp_path / "models" / "m.glb").write_bytes(b"v2")
    assert resolve(cli, doc).exit_code == 1
    assert resolve(cli, doc, "--update", "models/m.glb").exit_code == 0
    assert shas(doc)["models/m.glb"] == sha(b"v2")


def test_remote_unpinned_reference_is_pinned_by_the_lock(cli, tls, https_server, tmp_path):
    url = https_server.add("/m.glb", b"remote-v1")
    doc = tmp_path / "robot.hcdf"
    doc.write_text(HEAD + model(url) + "</hcdf>\n")

    def run(cache: str, *extra: str):
        return cli("resolve", doc, "--ca-bundle", tls.ca_pem, "--cache-dir", tmp_path / cache, "--json", *extra)

    assert run("c1").exit_code == 0
    assert shas(doc)[url] == sha(b"remote-v1")
    https_server.add("/m.glb", b"remote-v2")  # the server now serves other bytes
    assert run("c1").exit_code == 0  # the cache holds what the lock pins: no fetch
    assert https_server.hits["/m.glb"] == 1
    r = run("c2")  # a fresh cache fetches the new bytes: refused, not re-pinned, not cached
    assert r.exit_code == 1
    [e] = r.json["errors"]
    assert e["code"] == "lock-drift" and (e["expected"], e["actual"]) == (sha(b"remote-v1"), sha(b"remote-v2"))
    assert not (tmp_path / "c2" / "sha256").exists() or not any((tmp_path / "c2" / "sha256").rglob(sha(b"remote-v2")))
    assert shas(doc)[url] == sha(b"remote-v1")
    r = run("c1", "--update")  # an update looks at the server, not at the cache
    assert r.exit_code == 0, r.stdout
    assert shas(doc)[url] == sha(b"remote-v2")
