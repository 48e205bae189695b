"""``pin --write`` never blesses tampered content, and updates the lock in the same run.

Oracles independent of the code under test: hashlib over the files on disk, the lock
file read as plain JSON, lxml for reading ``sha`` attributes back, and byte snapshots
of every file of the robot's folder and the lock.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest
from lxml import etree

Pin = str | None  # "full", "weak" or None (no sha)
KEYS_CHANGE = {"file", "line", "kind", "uri", "url", "reason", "old", "new", "lock", "lock_sha256"}


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def flip_one_byte(path: Path) -> None:
    """Change one byte: the middle one of a model, a comp's name in a document (still well-formed)."""
    data = bytearray(path.read_bytes())
    at = data.find(b'comp name="s"') + len('comp name="') if path.suffix == ".hcdf" else len(data) // 2
    data[at] ^= 0x01
    path.write_bytes(bytes(data))


class Robot:
    """robot.hcdf: models a.glb and b.glb, and sub.hcdf (which has model c.glb); the lock outside the folder."""

    def __init__(self, tmp_path: Path) -> None:
        self.tmp = tmp_path
        self.folder = tmp_path / "robot"
        self.models = self.folder / "models"
        self.models.mkdir(parents=True)
        for i, name in enumerate("abc"):
            (self.models / f"{name}.glb").write_bytes(b"glTF" + bytes([i]) * 3000 + name.encode() * 500)
        self.doc = self.folder / "robot.hcdf"
        self.sub = self.folder / "sub.hcdf"
        self.lock = tmp_path / "robot.lock"
        self.cache = tmp_path / "cache"

    def write(self, *, a: Pin = "full", b: Pin = "full", c: Pin = "full", sub: Pin = "full") -> Robot:
        """Write the documents with each pin ``full``, ``weak`` (16 hex digits) or None (no sha)."""

        def attr(path: Path, how: Pin) -> str:
            if how is None:
                return ""
            return f' sha="{sha(path) if how == "full" else sha(path)[:16]}"'

        def model(name: str, how: Pin) -> str:
            return f'<visual><model uri="models/{name}.glb"{attr(self.models / f"{name}.glb", how)}/></visual>'

        self.sub.write_text(f'<hcdf version="1.1" name="sub">\n  <comp name="s">{model("c", c)}</comp>\n</hcdf>\n')
        self.doc.write_text(
            '<?xml version="1.0"?>\n'
            "<!-- formatting and comments survive pin -->\n"
            '<hcdf version="1.1" name="bot">\n'
            f'  <comp name="base">{model("a", a)}</comp>\n'
            f'  <comp name="arm">{model("b", b)}</comp>\n'
            f'  <include uri="sub.hcdf"{attr(self.sub, sub)} name="sub"/>\n'
            "</hcdf>\n"
        )
        return self

    def args(self, *extra: str | os.PathLike[str]) -> list[str | os.PathLike[str]]:
        return [self.doc, "--lock", self.lock, "--cache-dir", self.cache, *extra]

    def snapshot(self) -> dict[str, bytes]:
        files = sorted(p for p in self.folder.rglob("*") if p.is_file())
        out = {str(p.relative_to(self.folder)): p.read_bytes() for p in files}
        if self.lock.exists():
            out["<lock>"] = self.lock.read_bytes()
        return out

    def locked(self) -> dict[str, str]:
        """The lock's digests by URL, read as plain JSON."""
        return {a["url"]: a["sha256"] for a in json.loads(self.lock.read_text())["artifacts"]}

    def pins(self, path: Path) -> dict[str, str | None]:
        return {el.get("uri"): el.get("sha") for el in etree.parse(str(path)).iter("model", "include")}


@pytest.fixture
def robot(tmp_path):
    return Robot(tmp_path)


def assert_lock_is_what_resolve_writes(cli, robot: Robot) -> None:
    """The oracle for "the lock pin writes": resolve --locked passes on it and leaves it as it is."""
    lock = robot.lock.read_bytes()
    r = cli("resolve", *robot.args("--locked"))
    assert r.exit_code == 0, r.stderr
    assert robot.lock.read_bytes() == lock
    r = cli("verify", robot.doc, "--lock", robot.lock, "--cache-dir", robot.cache)
    assert r.exit_code == 0, r.stderr
    for path in (robot.models / "a.glb", robot.models / "b.glb", robot.models / "c.glb", robot.sub):
        url = os.path.relpath(path, robot.lock.parent)
        assert robot.locked()[url] == sha(path), url


# -- the tamper scenario ----------------------------------------------------------------


@pytest.mark.parametrize("how", ["full", "weak", None])
@pytest.mark.parametrize("target", ["a.glb", "sub.hcdf"])
def test_tampered_content_is_not_pinned(cli, robot, target, how):
    """Locked tree, one byte of a file changed: pin --write refuses it (exit 1) and writes nothing;
    resolve (for a pinned reference) and verify still fail afterwards."""
    robot.write(**{"a" if target == "a.glb" else "sub": how})
    assert cli("resolve", *robot.args()).exit_code == 0
    flip_one_byte(robot.folder / ("models/a.glb" if target == "a.glb" else "sub.hcdf"))
    before = robot.snapshot()

    r = cli("pin", *robot.args("--write", "--json"))
    assert r.exit_code == 1, r.stdout + r.stderr
    (err,) = r.json["errors"]
    assert err["code"] == "digest-mismatch" and err["file"].endswith("robot.hcdf")
    assert err["url"].endswith(target) and "--update" in err["message"]
    tampered = sha(robot.folder / ("models/a.glb" if target == "a.glb" else "sub.hcdf"))
    old = json.loads(before["<lock>"])["artifacts"]
    locked = next(a["sha256"] for a in old if a["url"].endswith(target))
    assert err["actual"] == tampered
    assert err["expected"] == (locked if how != "weak" else locked[:16])
    assert r.json["wrote"] == [] and robot.snapshot() == before

    if how is not None:
        assert cli("resolve", *robot.args()).exit_code == 1
    assert cli("verify", robot.doc, "--lock", robot.lock, "--cache-dir", robot.cache).exit_code == 1


def test_tampered_content_message_says_the_lock_agreed(cli, robot):
    robot.write()
    assert cli("resolve", *robot.args()).exit_code == 0
    flip_one_byte(robot.models / "a.glb")
    r = cli("pin", *robot.args("--write"))
    assert r.exit_code == 1
    assert "the lock agrees with the sha" in r.stderr and "--update models/a.glb" in r.stderr


def test_weak_pin_that_disagrees_with_the_lock_is_refused(cli, robot):
    """The file and its weak pin both replaced: the prefix matches the new content, not the lock."""
    robot.write(a=None)
    assert cli("resolve", *robot.args()).exit_code == 0
    locked = robot.locked()["robot/models/a.glb"]
    flip_one_byte(robot.models / "a.glb")
    robot.write(a="weak")  # the weak pin of the replaced file
    before = robot.snapshot()
    r = cli("pin", *robot.args("--write", "--json"))
    assert r.exit_code == 1, r.stdout + r.stderr
    (err,) = r.json["errors"]
    assert err["code"] == "digest-mismatch" and "changed since it was locked" in err["message"]
    assert (err["expected"], err["actual"]) == (locked, sha(robot.models / "a.glb"))
    assert robot.snapshot() == before


# -- naming what may change ---------------------------------------------------------------


def test_update_names_one_of_two_mismatches(cli, robot, monkeypatch):
    robot.write()
    assert cli("resolve", *robot.args()).exit_code == 0
    old_a, old_b = sha(robot.models / "a.glb"), sha(robot.models / "b.glb")
    flip_one_byte(robot.models / "a.glb")
    flip_one_byte(robot.models / "b.glb")
    before = robot.snapshot()

    # naming one: the other is still refused, and nothing at all is written
    r = cli("pin", *robot.args("--write", "--update", "models/a.glb", "--json"))
    assert r.exit_code == 1, r.stdout + r.stderr
    assert [e["url"].rsplit("/", 1)[-1] for e in r.json["errors"]] == ["b.glb"]
    assert robot.snapshot() == before

    # naming both: a by the uri as written, b by its path from the working folder
    monkeypatch.chdir(robot.tmp)
    r = cli("pin", *robot.args("--write", "--update", "models/a.glb", "--update", "robot/models/b.glb", "--json"))
    assert r.exit_code == 0, r.stdout + r.stderr
    changes = {c["uri"]: c for c in r.json["changes"]}
    assert set(changes) == {"models/a.glb", "models/b.glb"}
    for name, old in (("a", old_a), ("b", old_b)):
        c = changes[f"models/{name}.glb"]
        new = sha(robot.models / f"{name}.glb")
        assert (c["reason"], c["old"], c["new"]) == ("outdated", old, new)
        assert (c["lock"], c["lock_sha256"]) == ("agreed with old", old)
        assert robot.pins(robot.doc)[f"models/{name}.glb"] == new
    assert sorted(Path(p).name for p in r.json["wrote"]) == ["robot.hcdf", "robot.lock"]
    assert_lock_is_what_resolve_writes(cli, robot)


def test_update_accepts_new_content_of_an_unpinned_file(cli, robot):
    """Without a sha the lock entry is the pin: refused until named, then pinned and locked anew."""
    robot.write(a=None)
    assert cli("resolve", *robot.args()).exit_code == 0
    locked = robot.locked()["robot/models/a.glb"]
    flip_one_byte(robot.models / "a.glb")
    assert cli("pin", *robot.args("--write")).exit_code == 1
    r = cli("pin", *robot.args("--write", "--update", "models/a.glb", "--json"))
    assert r.exit_code == 0, r.stdout + r.stderr
    (c,) = r.json["changes"]
    new = sha(robot.models / "a.glb")
    assert (c["uri"], c["reason"], c["old"], c["new"]) == ("models/a.glb", "outdated", None, new)
    assert (c["lock"], c["lock_sha256"]) == ("agreed with old", locked)
    assert r.json["lock_changes"] == [{"url": "robot/models/a.glb", "old": locked, "new": new}]
    assert robot.pins(robot.doc)["models/a.glb"] == new
    assert_lock_is_what_resolve_writes(cli, robot)


def test_update_by_resolved_url_and_absolute_path(cli, robot):
    robot.write()
    assert cli("resolve", *robot.args()).exit_code == 0
    flip_one_byte(robot.models / "a.glb")
    flip_one_byte(robot.models / "c.glb")
    r = cli("pin", *robot.args("--update", (robot.models / "a.glb").as_uri(), "--update", robot.models / "c.glb"))
    assert r.exit_code == 0, r.stderr
    assert "would pin models/a.glb (outdated)" in r.stderr and "would pin models/c.glb (outdated)" in r.stderr


def test_update_of_an_unknown_file_is_an_error(cli, robot):
    robot.write()
    before = robot.snapshot()
    r = cli("pin", *robot.args("--write", "--update", "models/nope.glb", "--json"))
    assert r.exit_code == 3, r.stdout + r.stderr
    assert [e["code"] for e in r.json["errors"]] == ["update-unknown"]
    assert "models/nope.glb" in r.json["errors"][0]["message"]
    assert robot.snapshot() == before


def test_all_replaces_every_mismatch_and_edited_includes(cli, robot):
    robot.write()
    assert cli("resolve", *robot.args()).exit_code == 0
    old = robot.locked()
    for name in ("a", "b", "c"):
        flip_one_byte(robot.models / f"{name}.glb")
    sub_before = sha(robot.sub)
    r = cli("pin", *robot.args("--write", "--all", "--json"))
    assert r.exit_code == 0, r.stdout + r.stderr
    got = {(Path(c["file"]).name, c["uri"]): (c["reason"], c["lock"]) for c in r.json["changes"]}
    assert got == {
        ("robot.hcdf", "models/a.glb"): ("outdated", "agreed with old"),
        ("robot.hcdf", "models/b.glb"): ("outdated", "agreed with old"),
        ("sub.hcdf", "models/c.glb"): ("outdated", "agreed with old"),
        ("robot.hcdf", "sub.hcdf"): ("include-edited", "agreed with old"),
    }
    assert sha(robot.sub) != sub_before and robot.pins(robot.doc)["sub.hcdf"] == sha(robot.sub)
    lock_changes = {c["url"]: (c["old"], c["new"]) for c in r.json["lock_changes"]}
    assert lock_changes == {url: (old[url], new) for url, new in robot.locked().items()}
    assert len(lock_changes) == 4
    assert_lock_is_what_resolve_writes(cli, robot)


# -- missing and weak pins: filled in, from the lock ------------------------------------------


def test_weak_and_missing_pins_are_filled_from_the_lock(cli, robot):
    robot.write(a="weak", b=None, c="weak", sub=None)
    assert cli("resolve", *robot.args()).exit_code == 0
    locked = robot.locked()
    r = cli("pin", *robot.args("--write", "--json"))
    assert r.exit_code == 0, r.stdout + r.stderr
    got = {c["uri"]: (c["reason"], c["lock"], c["new"]) for c in r.json["changes"]}
    url = {name: os.path.relpath(robot.folder / name, robot.lock.parent) for name in ("models/a.glb", "models/b.glb")}
    assert got["models/a.glb"] == ("weak", "agreed with new", locked[url["models/a.glb"]])
    assert got["models/b.glb"] == ("missing", "agreed with new", locked[url["models/b.glb"]])
    assert got["models/c.glb"][:2] == ("weak", "agreed with new")
    # sub.hcdf is edited (its c.glb pin), so its new digest is not the locked one
    assert got["sub.hcdf"][:2] == ("missing", "agreed with old")
    assert robot.pins(robot.doc) == {
        "models/a.glb": sha(robot.models / "a.glb"),
        "models/b.glb": sha(robot.models / "b.glb"),
        "sub.hcdf": sha(robot.sub),
    }
    assert_lock_is_what_resolve_writes(cli, robot)


def test_without_a_lock_pins_come_from_the_content_and_the_lock_is_created(cli, robot):
    robot.write(a=None, b="weak", c=None, sub=None)
    r = cli("pin", *robot.args("--write", "--json"))
    assert r.exit_code == 0, r.stdout + r.stderr
    assert {c["lock"] for c in r.json["changes"]} == {"no entry"}
    assert {c["old"] for c in r.json["lock_changes"]} == {None}
    assert robot.lock.exists()
    assert_lock_is_what_resolve_writes(cli, robot)


def test_full_pin_that_agrees_with_the_content_wins_over_a_stale_lock(cli, robot):
    """The author replaced a file and its pin: not tampering (resolve accepts it); the lock follows."""
    robot.write()
    assert cli("resolve", *robot.args()).exit_code == 0
    flip_one_byte(robot.models / "b.glb")
    robot.write()
    doc = robot.doc.read_bytes()
    r = cli("pin", *robot.args("--write", "--json"))
    assert r.exit_code == 0, r.stdout + r.stderr
    assert r.json["changes"] == [] and robot.doc.read_bytes() == doc
    assert [c["url"] for c in r.json["lock_changes"]] == ["robot/models/b.glb"]
    assert_lock_is_what_resolve_writes(cli, robot)


# -- dry run, all or nothing -----------------------------------------------------------------


def test_dry_run_writes_nothing_not_even_the_lock(cli, robot):
    robot.write(a=None, sub="weak")
    assert cli("resolve", *robot.args()).exit_code == 0
    flip_one_byte(robot.models / "b.glb")
    before = robot.snapshot()
    r = cli("pin", *robot.args("--all", "--json"))
    assert r.exit_code == 0, r.stdout + r.stderr
    assert r.json["changes"] and r.json["lock_changes"] and r.json["wrote"] == []
    assert sorted(Path(p).name for p in r.json["planned"]) == ["robot.hcdf", "robot.lock"]
    assert robot.snapshot() == before
    assert not robot.cache.exists() or not [p for p in robot.cache.rglob("*") if p.is_file()]


@contextlib.contextmanager
def read_only(folder: Path):
    """``folder`` refuses new entries, for root too (chattr +i) where chmod is not enough."""
    if os.geteuid() != 0:
        folder.chmod(0o555)
        try:
            yield
        finally:
            folder.chmod(0o755)
        return
    chattr = shutil.which("chattr")
    if chattr is None or subprocess.run([chattr, "+i", folder], capture_output=True).returncode != 0:
        pytest.skip("running as root without chattr +i: cannot make a folder read-only")
    try:
        yield
    finally:
        subprocess.run([chattr, "-i", folder], check=True)


def _stale_tree(cli, robot: Robot) -> dict[str, bytes]:
    """A locked tree where pin --all has documents and a lock to write."""
    robot.write(a=None, b="full")
    assert cli("resolve", *robot.args()).exit_code == 0
    flip_one_byte(robot.models / "b.glb")
    return robot.snapshot()


def test_read_only_lock_folder_writes_nothing(cli, robot):
    """The documents are staged first, the lock last: its failure leaves every document as it was."""
    locks = robot.tmp / "locks"
    locks.mkdir()
    robot.lock = locks / "robot.lock"
    before = _stale_tree(cli, robot)
    with read_only(locks):
        r = cli("pin", *robot.args("--write", "--all", "--json"))
    assert r.exit_code == 3, r.stdout + r.stderr
    assert [e["code"] for e in r.json["errors"]] == ["output"] and r.json["wrote"] == []
    assert "robot.lock" in r.json["errors"][0]["message"]
    assert robot.snapshot() == before  # no document edited, no temporary file left


def test_unwritable_lock_destination_writes_nothing(cli, robot):
    """The same on any machine: a folder no file can be created in."""
    before = _stale_tree(cli, robot)
    snapshot_lock = robot.lock
    robot.lock = Path("/proc/hcdf-trust-pin-test.lock")
    r = cli("pin", *robot.args("--write", "--all"))
    assert r.exit_code == 3, r.stderr
    assert "hcdf-trust-pin-test.lock" in r.stderr and "Traceback" not in r.stderr
    robot.lock = snapshot_lock
    assert robot.snapshot() == before


def test_read_only_document_folder_writes_nothing(cli, robot):
    before = _stale_tree(cli, robot)
    with read_only(robot.folder):
        r = cli("pin", *robot.args("--write", "--all"))
    assert r.exit_code == 3, r.stderr
    assert "robot.hcdf" in r.stderr
    assert robot.snapshot() == before


@pytest.mark.parametrize(
    "where",
    ["models/a.glb", "models/b.glb", "robot.hcdf", "sub.hcdf", "cache/x.lock", "hardlink-to-robot.hcdf", "lock-model"],
)
def test_lock_on_an_input_is_refused_and_nothing_is_written(cli, robot, where):
    before = _stale_tree(cli, robot)
    if where == "lock-model":  # a verified model that is itself a valid lock file: read as one, never replaced
        dest = robot.models / "c.glb"
        dest.write_bytes(robot.lock.read_bytes())
        robot.write(a=None, b="full")
        flip_one_byte(robot.models / "a.glb")
        before = robot.snapshot()
    elif where.startswith("cache/"):
        dest = robot.cache / "x.lock"
    elif where.startswith("hardlink"):
        dest = robot.tmp / where
        os.link(robot.doc, dest)
    else:
        dest = robot.folder / where
    kept = dest.read_bytes() if dest.exists() else None
    r = cli("pin", robot.doc, "--lock", dest, "--cache-dir", robot.cache, "--write", "--all")
    assert r.exit_code == 3, r.stderr
    assert dest.name in r.stderr and "Traceback" not in r.stderr
    if where == "cache/x.lock":
        assert "inside the cache" in r.stderr
    if where == "lock-model":  # refused as another root's lock, or as an input
        assert "refusing to overwrite an input" in r.stderr or "has its own lock" in r.stderr
    assert robot.snapshot() == before
    assert (dest.read_bytes() if dest.exists() else None) == kept


def test_lock_changed_while_pinning_is_not_overwritten(robot, cli, monkeypatch):
    from hcdf_trust.include import pin as pin_module
    from hcdf_trust.include.resolver import ResolveOptions

    _stale_tree(cli, robot)
    real_apply = pin_module.apply_pins

    def racing_apply(*args, **kwargs):
        with open(robot.lock, "a") as f:
            f.write(" ")
        return real_apply(*args, **kwargs)

    monkeypatch.setattr(pin_module, "apply_pins", racing_apply)
    before = robot.snapshot()
    options = ResolveOptions(lock_path=str(robot.lock), cache_dir=str(robot.cache))
    report = pin_module.pin_tree(robot.doc, options, write=True, update_all=True)
    assert [str(e) for e in report.errors] and "changed on disk" in str(report.errors[0])
    assert report.written == []
    after = robot.snapshot()
    assert after.pop("<lock>") == before.pop("<lock>") + b" "
    assert after == before


# -- the report ------------------------------------------------------------------------------


def test_json_shape(cli, robot):
    robot.write(a=None)
    assert cli("resolve", *robot.args()).exit_code == 0
    flip_one_byte(robot.models / "b.glb")
    r = cli("pin", *robot.args("--json"))
    assert r.exit_code == 1
    out = r.json
    assert out["ok"] is False and out["wrote"] == []
    (err,) = out["errors"]
    assert {"code", "message", "file", "line", "url", "expected", "actual"} <= set(err)
    assert err["line"] == 5

    r = cli("pin", *robot.args("--update", "models/b.glb", "--json"))
    assert r.exit_code == 0
    out = r.json
    assert set(out) == {"ok", "changes", "lock_changes", "planned", "wrote", "warnings", "errors", "config"}
    assert out["ok"] is True and out["errors"] == [] and out["warnings"] == []
    for c in out["changes"]:
        assert set(c) == KEYS_CHANGE
        assert c["lock"] in ("agreed with old", "agreed with new", "no entry", "disagreed with both")
    by_uri = {c["uri"]: c for c in out["changes"]}
    assert by_uri["models/a.glb"]["old"] is None and by_uri["models/a.glb"]["lock"] == "agreed with new"
    assert by_uri["models/b.glb"]["line"] == 5 and by_uri["models/b.glb"]["reason"] == "outdated"
    for c in out["lock_changes"]:
        assert set(c) == {"url", "old", "new"}


def test_human_report_shows_old_new_and_the_lock(cli, robot):
    robot.write()
    assert cli("resolve", *robot.args()).exit_code == 0
    old = sha(robot.models / "a.glb")
    flip_one_byte(robot.models / "a.glb")
    r = cli("pin", *robot.args("--write", "--update", "models/a.glb"))
    assert r.exit_code == 0, r.stderr
    new = sha(robot.models / "a.glb")
    assert f"pinned models/a.glb (outdated): {old} -> {new} [lock: agreed with old]" in r.stderr
    assert "wrote " in r.stderr and "robot.lock" in r.stderr
