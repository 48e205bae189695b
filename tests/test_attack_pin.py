"""Attacks on ``pin``, ``verify`` and the lock file, from an attacker's point of view.

The attacker can change files of the tree between runs (a compromised mirror, a
malicious merge request, a swapped cache blob) but not the root document; the user
runs ``pin --write`` with ``--update``/``--all`` to accept *their own* edits. The
promise under attack: a pin run changes only the lock entries whose content it was
told to accept, every other still-referenced entry stays byte-identical, ``verify``
passes after every successful ``pin --write`` and writes nothing itself, and a lock
that cannot be read as written (merge-conflict markers, a symlink onto an input) is
refused by every verb.

Oracles independent of the code under test: the lock read line by line with ``json``,
``hashlib`` over the files, and snapshots of every file's bytes (and of the cache).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path

import pytest

from hcdf_trust.store import ContentStore

from ._hostile import no_network, snapshot  # noqa: F401  (fixtures are used by name)
from .conftest import PROJECT

MANIFEST = "firmware/arm-ctrl.latest.json"  # pinned only by its lock entry (firmware manifests have no sha)
MESH = "meshes/chassis-hull.stl"  # pinned only by its lock entry (the schema has no sha on meshes)
ARM = "assemblies/arm.hcdf"  # included twice with a full sha
HEAD = "assemblies/sensor-head.hcdf"


def sha(path: str | Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def lock_lines(path: str | Path = "robot.hcdf.lock") -> dict[str, str]:
    """Each artifact line of the lock, by url (read with json, one line per artifact)."""
    out = {}
    for line in Path(path).read_text().splitlines():
        if line.startswith('{"kind"'):
            out[json.loads(line.rstrip(","))["url"]] = line.rstrip(",")
    return out


def files(folder: Path = Path(".")) -> dict[str, bytes]:
    return {str(p): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file() and not p.is_symlink()}


@pytest.fixture
def robot(tmp_path, monkeypatch):
    """The example robot, copied; the working folder is the robot's folder."""
    shutil.copytree(PROJECT / "examples" / "robot", tmp_path / "robot")
    monkeypatch.chdir(tmp_path / "robot")
    return tmp_path


@pytest.fixture
def run(cli, robot):
    cache = str(robot / "cache")

    def call(verb: str, *args: str | os.PathLike[str]):
        return cli(verb, "robot.hcdf", *args, "--cache-dir", cache)

    return call


# -- the user's edits, and the attacker's ----------------------------------------------


def edit_arm() -> None:
    """The user edits an included document (it is pinned by a full sha in robot.hcdf)."""
    text = Path(ARM).read_text()
    Path(ARM).write_text(text.replace("Two-link arm", "Two-link arm, revision B"))


def tamper(path: str) -> None:
    Path(path).write_bytes(Path(path).read_bytes() + b"\n ")


def tamper_manifest() -> None:
    Path(MANIFEST).write_text('{"board": "scout2_arm", "latest": {"url": "https://evil.example/fw.bin"}}\n')


# -- §1: a pin run changes only what it was told to accept ------------------------------

ACCEPT_ARM = {
    "uri": ["--update", ARM],
    "relative-path": ["--update", "./assemblies/../assemblies/arm.hcdf"],
    "url": ["--update", Path(ARM).as_posix()],
    "all": ["--all"],
}


@pytest.mark.parametrize("how", list(ACCEPT_ARM))
def test_accepting_an_edited_include_keeps_every_other_lock_entry(run, how):
    """The reported attack: the entries of everything arm.hcdf references used to be
    dropped, so verify failed and a tampered manifest then passed plain resolve."""
    before = lock_lines()
    docs = files()
    edit_arm()
    r = run("pin", "--write", *ACCEPT_ARM[how])
    assert r.exit_code == 0, r.stderr
    assert "(dropped)" not in r.stderr
    after = lock_lines()
    assert after.keys() == before.keys(), "an entry was added or dropped"
    edited = {url for url in after if docs.get(url) != Path(url).read_bytes()}
    assert edited == {ARM}  # the only document of the lock that changed on disk
    for url in after.keys() - edited:
        assert after[url] == before[url], url  # byte-identical
    assert json.loads(after[ARM])["sha256"] == sha(ARM)
    assert run("verify").exit_code == 0
    # The manifest is still pinned by its entry: tampering with it is caught.
    tamper_manifest()
    lock = Path("robot.hcdf.lock").read_bytes()
    r = run("resolve", "--json")
    assert r.exit_code == 1, r.stdout
    assert [(e["code"], e["url"]) for e in r.json["errors"]] == [("lock-drift", MANIFEST)]
    assert Path("robot.hcdf.lock").read_bytes() == lock


def test_naming_an_include_does_not_bless_what_it_references(run):
    """The user accepts arm.hcdf; the attacker changed the manifest it references meanwhile."""
    edit_arm()
    tamper_manifest()
    before = files()
    r = run("pin", "--write", "--update", ARM, "--json")
    assert r.exit_code == 1, r.stdout
    (err,) = r.json["errors"]
    assert err["code"] == "digest-mismatch" and err["url"].endswith(MANIFEST), err
    assert "changed since it was locked" in err["message"]
    assert err["expected"] == json.loads(lock_lines()[MANIFEST])["sha256"] and err["actual"] == sha(MANIFEST)
    assert files() == before  # nothing written


def test_tampering_between_pin_runs_is_refused(run):
    assert run("pin", "--write").exit_code == 0  # fills in gripper's weak pin
    assert run("verify").exit_code == 0
    tamper(MESH)
    before = files()
    for extra in ((), ("--update", "models/chassis.glb"), ("--update", ARM)):
        r = run("pin", "--write", *extra, "--json")
        assert r.exit_code == 1, (extra, r.stdout)
        assert {e["url"].rpartition("robot/")[2] for e in r.json["errors"]} == {MESH}, r.json["errors"]
        assert files() == before
    assert run("resolve").exit_code == 1 and run("verify").exit_code == 1


def test_a_lock_entry_edited_to_match_a_tampered_file_does_not_beat_a_full_sha(run):
    tamper("models/chassis.glb")
    lock = Path("robot.hcdf.lock")
    line = lock_lines()["models/chassis.glb"]
    forged = json.loads(line) | {"sha256": sha("models/chassis.glb"), "size": Path("models/chassis.glb").stat().st_size}
    lock.write_text(lock.read_text().replace(line, json.dumps(forged, sort_keys=True)))
    before = files()
    for verb, extra in (("pin", ("--write",)), ("pin", ("--write", "--update", MESH)), ("resolve", ()), ("verify", ())):
        r = run(verb, *extra, "--json")
        assert r.exit_code == 1, (verb, extra, r.stdout)
        assert {e["code"] for e in r.json["errors"]} == {"digest-mismatch"}, r.json["errors"]
        assert files() == before


def add_reference() -> None:
    Path("models/extra.glb").write_bytes(b"glTF extra")
    extra = '<visual name="x"><model uri="../models/extra.glb"/></visual></comp>'
    Path(HEAD).write_text(Path(HEAD).read_text().replace("</comp>", extra))


TAMPERS = {
    "include-edited": (edit_arm, ARM, set()),
    "mesh": (lambda: tamper(MESH), MESH, set()),
    "manifest": (tamper_manifest, MANIFEST, set()),
    "weakly-pinned-model": (lambda: tamper("models/gripper.glb"), "models/gripper.glb", set()),
    "fully-pinned-model": (lambda: tamper("models/chassis.glb"), "models/chassis.glb", set()),
    "reference-added": (add_reference, HEAD, set()),
    "reference-removed": (
        lambda: Path(ARM).write_text(
            Path(ARM).read_text().replace('<model uri="../models/gripper.glb" sha="adaa3b07"/>', "")
        ),
        ARM,
        {"models/gripper.glb"},
    ),
}


@pytest.mark.parametrize("accept", ["nothing", "named", "all"])
@pytest.mark.parametrize("change", list(TAMPERS))
def test_pin_write_changes_only_what_it_accepts_and_verify_passes_after(run, change, accept):
    """Every change × how much the user accepts: either nothing is written, or the lock
    changes only for the file accepted and the documents pin edited, and verify passes."""
    do, name, gone = TAMPERS[change]
    before, docs = lock_lines(), files()
    do()
    changed = files()
    flags = {"nothing": [], "named": ["--update", name], "all": ["--all"]}[accept]
    r = run("pin", "--write", *flags)
    if accept == "nothing":
        assert r.exit_code == 1, r.stderr
        assert files() == changed  # nothing written
        return
    assert r.exit_code == 0, r.stderr
    assert run("verify").exit_code == 0
    after = lock_lines()
    assert before.keys() - after.keys() == gone
    on_disk = {url for url in after if Path(url).exists() and docs.get(url) != Path(url).read_bytes()}
    for url in (before.keys() & after.keys()) - on_disk - {name}:
        assert after[url] == before[url], url
    for url in after:
        assert json.loads(after[url])["sha256"] == sha(url), url


# -- the guards behind the rule: they refuse even when resolve goes wrong ----------------


def test_a_lock_computed_without_reading_an_accepted_include_is_refused(run, monkeypatch):
    """Defence in depth: if resolve ever again skips a named include, pin must not write
    a lock without the entries of the files that include references."""
    from hcdf_trust.include import resolver

    acceptable = resolver._Run._acceptable

    def skip_arm(self, art, hashed=None):
        return False if art.url.endswith(ARM) else acceptable(self, art, hashed)

    monkeypatch.setattr(resolver._Run, "_acceptable", skip_arm)
    edit_arm()
    before = files()
    r = run("pin", "--write", "--update", ARM, "--json")
    assert r.exit_code == 3, r.stdout
    (err,) = r.json["errors"]  # named at its first reference (robot.hcdf includes it twice)
    assert (err["code"], err["file"], err["line"], err["url"].endswith(ARM)) == (
        "pin-edit",
        "robot.hcdf",
        88,
        True,
    )
    assert err["message"] == (
        f"{ARM} was not read, so the files it references are unknown: refusing to write a lock that would drop "
        "their entries"
    )
    assert files() == before


def test_a_lock_entry_changed_without_being_accepted_is_refused(run, monkeypatch):
    from hcdf_trust.include import resolver

    lock_entries = resolver.Resolution.lock_entries

    def forge(self, edited=None):
        return [e._replace(sha256="0" * 64) if e.url == MESH else e for e in lock_entries(self, edited)]

    monkeypatch.setattr(resolver.Resolution, "lock_entries", forge)
    edit_arm()
    before = files()
    r = run("pin", "--write", "--update", ARM, "--json")
    assert r.exit_code == 1, r.stdout
    (err,) = r.json["errors"]
    assert (err["code"], err["url"], err["file"]) == ("lock-kept", MESH, "robot.hcdf.lock"), err
    size = Path(MESH).stat().st_size
    assert (err["expected"], err["actual"]) == (f"{sha(MESH)} ({size} bytes)", f"{'0' * 64} ({size} bytes)")
    assert err["message"] == (
        f"{MESH}: this run would change its entry in robot.hcdf.lock though nothing it was told to accept changes "
        "it (name the file with --update to accept its content); nothing written"
    )
    assert files() == before


def test_kept_violations_is_about_digest_and_size_of_entries_not_accepted():
    from hcdf_trust.include.lockfile import LockEntry
    from hcdf_trust.include.pin import kept_violations

    a = LockEntry("mesh", "a", "a", "1" * 64, 1, ("r",))
    b = LockEntry("model", "b", "b", "2" * 64, 2, ("r",))
    old = {"a": a, "b": b}
    assert kept_violations(old, [a, b], may_change=set()) == []
    assert kept_violations(old, [a], may_change=set()) == []  # dropped: not a change of an entry
    assert kept_violations(old, [a._replace(referenced_from=("s",)), b], may_change=set()) == []
    grown = b._replace(size=3)
    assert kept_violations(old, [a, grown], may_change=set()) == [("b", b, grown)]
    assert kept_violations(old, [a, grown], may_change={"b"}) == []
    other = a._replace(sha256="3" * 64)
    assert kept_violations(old, [other, b], may_change={"b"}) == [("a", a, other)]


# -- verify writes nothing, not even a cache repair -------------------------------------

REMOTE = "https://models.example/remote.glb"
BLOB = b"glTF: the remote model the document pins"


@pytest.mark.usefixtures("no_network")
def test_verify_leaves_a_tampered_cache_blob_and_everything_else_as_it_was(cli, tmp_path, monkeypatch):
    work, cache = tmp_path / "work", tmp_path / "cache"
    work.mkdir()
    (work / "robot.hcdf").write_text(
        f'<hcdf version="1.0" name="r"><comp name="c"><visual name="v">'
        f'<model uri="{REMOTE}" sha="{hashlib.sha256(BLOB).hexdigest()}"/></visual></comp></hcdf>\n'
    )
    monkeypatch.chdir(work)
    _, blob = ContentStore(cache).ingest([BLOB])
    assert cli("resolve", "robot.hcdf", "--offline", "--cache-dir", cache).exit_code == 0
    before = snapshot(work, cache)
    assert cli("verify", "robot.hcdf", "--cache-dir", cache).exit_code == 0
    assert snapshot(work, cache) == before
    blob.chmod(0o644)
    blob.write_bytes(b"glTF: tampered in the cache")
    before = snapshot(work, cache)
    r = cli("verify", "robot.hcdf", "--cache-dir", cache, "--json")
    assert r.exit_code == 3, r.stdout  # not in the cache any more: offline, nothing to verify against
    assert [e["url"] for e in r.json["errors"]] == [REMOTE]
    assert snapshot(work, cache) == before  # the bad blob is not repaired (removed) by verify
    assert blob.read_bytes() == b"glTF: tampered in the cache"
    # resolve may repair: it drops the blob (and, offline, cannot fetch it again)
    assert cli("resolve", "robot.hcdf", "--offline", "--cache-dir", cache).exit_code == 3
    assert not blob.exists()


def test_verify_creates_no_cache_folder(run, robot):
    assert run("verify").exit_code == 0
    assert not (robot / "cache").exists()


# -- §8: a lock with merge-conflict markers ---------------------------------------------


def conflicted(lock: str = "robot.hcdf.lock", *, diff3: bool = False) -> tuple[str, str]:
    """The lock as git leaves it when two branches re-pinned the mesh differently."""
    text = Path(lock).read_text()
    ours = lock_lines()[MESH]
    theirs = ours.replace(json.loads(ours)["sha256"], "f" * 64)
    base = f"||||||| merged common ancestors\n{ours.replace(json.loads(ours)['sha256'], 'e' * 64)},\n" if diff3 else ""
    Path(lock).write_text(text.replace(ours + ",", f"<<<<<<< HEAD\n{ours},\n{base}=======\n{theirs},\n>>>>>>> other"))
    return ours, theirs


VERBS = {
    "resolve": ("resolve",),
    "resolve-update-one": ("resolve", "--update", MESH),
    "resolve-update-all": ("resolve", "--update"),
    "resolve-locked": ("resolve", "--locked"),
    "verify": ("verify",),
    "pin": ("pin",),
    "pin-write": ("pin", "--write"),
    "pin-update": ("pin", "--write", "--update", MESH),
    "pin-all": ("pin", "--write", "--all"),
}


@pytest.mark.parametrize("diff3", [False, True])
@pytest.mark.parametrize("verb", list(VERBS))
def test_a_lock_with_merge_conflict_markers_is_refused_by_every_verb(run, verb, diff3):
    conflicted(diff3=diff3)
    before = files()
    r = run(*VERBS[verb], "--json")
    assert r.exit_code == 3, r.stdout
    (err,) = r.json["errors"]
    assert err["code"] == "lock-file" and err["line"] == 5, err
    msg = err["message"]
    assert "merge-conflict markers" in msg and f"{MESH} (" in msg and "ffffffffffff" in msg, msg
    assert "Do not delete it" in msg and "--update" in msg, msg
    assert files() == before


def test_recovering_from_a_conflict_as_the_message_says_keeps_the_first_use_pins(run):
    """Take one side whole, then resolve: only the conflicting entry needs --update,
    and a file changed meanwhile is still caught."""
    ours, theirs = conflicted()
    lock = Path("robot.hcdf.lock")
    # "take one side whole": theirs (the other branch's pin, which the file does not match)
    text = lock.read_text()
    lock.write_text(text.replace(f"<<<<<<< HEAD\n{ours},\n=======\n{theirs},\n>>>>>>> other", theirs + ","))
    tamper_manifest()  # and an attacker's change arrived with the merge
    r = run("resolve", "--json")
    assert r.exit_code == 1
    assert sorted(e["url"] for e in r.json["errors"]) == sorted([MESH, MANIFEST])  # first-use pins still hold
    r = run("resolve", "--update", MESH, "--json")
    assert r.exit_code == 1 and [e["url"] for e in r.json["errors"]] == [MANIFEST]
    Path(MANIFEST).write_bytes((PROJECT / "examples" / "robot" / MANIFEST).read_bytes())
    assert run("resolve", "--update", MESH).exit_code == 0
    assert lock_lines()[MESH] == ours and run("verify").exit_code == 0


def test_merge_conflict_reading_is_pure_and_bounded():
    from hcdf_trust.include.lockfile import merge_conflict

    assert merge_conflict('{"artifacts": []}', "x.lock") is None
    assert merge_conflict("a line with <<<<<<< inside\n=======\n", "x.lock") is None  # not at a line start
    many = "".join(f'<<<<<<< a\n{{"sha256": "{i:064x}", "url": "u{i}"}},\n=======\n>>>>>>> b\n' for i in range(20))
    err = merge_conflict(many, "x.lock")
    assert err is not None and "20 conflict(s)" in err.message and "and 12 more" in err.message
    assert "u0 (" in err.message and "| absent)" in err.message


# -- a symlinked lock -------------------------------------------------------------------


@pytest.mark.parametrize("target", ["robot.hcdf", "models/chassis.glb", ARM])
def test_a_lock_symlinked_onto_an_input_is_refused_and_the_input_kept(run, target):
    Path("robot.hcdf.lock").unlink()
    os.symlink(target, "robot.hcdf.lock")
    before = files()
    for verb in (("pin", "--write"), ("pin", "--write", "--all"), ("resolve",), ("resolve", "--update")):
        r = run(*verb, "--json")
        assert r.exit_code == 3, (verb, r.stdout)
        (err,) = r.json["errors"]  # named as an input, not as a malformed lock
        assert err["code"] == "output" and "refusing to overwrite an input" in err["message"], err
        assert files() == before, verb
        assert os.readlink("robot.hcdf.lock") == target


def test_a_lock_symlinked_outside_is_replaced_never_written_through(run, robot):
    outside = robot / "elsewhere.lock"
    shutil.move("robot.hcdf.lock", outside)
    os.symlink(outside, "robot.hcdf.lock")
    kept = outside.read_bytes()
    r = run("pin", "--write")  # fills in gripper's weak pin: the lock changes
    assert r.exit_code == 0, r.stderr
    assert outside.read_bytes() == kept  # the link's target is not written
    assert not os.path.islink("robot.hcdf.lock") and run("verify").exit_code == 0


# -- a remote file: the new content accepted by pin is cached, so verify passes ----------


@pytest.mark.parametrize("accept", ["update", "all"])
def test_pin_update_of_a_remote_file_looks_at_the_server_and_caches_what_it_pins(
    cli, tls, https_server, tmp_path, accept
):
    """pin used to take a changed remote file from the cache by its old lock entry, as if
    --update had not named it (resolve was not told): the new content was never seen."""
    url = https_server.add("/m.glb", b"remote-v1")
    work, cache = tmp_path / "work", tmp_path / "cache"
    work.mkdir()
    doc = work / "robot.hcdf"
    doc.write_text(
        f'<hcdf version="1.0" name="r"><comp name="c"><visual name="v"><model uri="{url}"/></visual></comp></hcdf>\n'
    )
    tls_args = ("--ca-bundle", tls.ca_pem, "--cache-dir", cache)
    assert cli("resolve", doc, *tls_args).exit_code == 0
    https_server.add("/m.glb", b"remote-v2")
    r = cli("pin", doc, "--write", *(["--update", url] if accept == "update" else ["--all"]), *tls_args)
    assert r.exit_code == 0, r.stderr
    assert json.loads(lock_lines(work / "robot.hcdf.lock")[url])["sha256"] == hashlib.sha256(b"remote-v2").hexdigest()
    r = cli("verify", doc, "--cache-dir", cache)  # offline: the new content is in the cache
    assert r.exit_code == 0, r.stderr


@pytest.mark.parametrize(
    "argv",
    [
        ("audit", "robot.hcdf"),
        ("sbom", "robot.hcdf", "--format", "cyclonedx"),
        ("macsec", "plan", "robot.hcdf"),
    ],
)
def test_a_lock_with_merge_conflict_markers_is_refused_by_the_verbs_built_on_resolve(cli, robot, argv):
    conflicted()
    before = files()
    r = cli(*argv, "--cache-dir", robot / "cache") if argv[0] != "macsec" else cli(*argv)
    assert r.exit_code == 3, r.stdout + r.stderr
    assert "merge-conflict markers" in r.stderr and f"{MESH} (" in r.stderr, r.stderr
    assert files() == before
