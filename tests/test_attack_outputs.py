"""Attacks on outputs (issue 16 §3, §7): every file every verb writes goes through OutputPlan.

- no output lands on a key, a passphrase file, a key store, a registry source, a document;
  an existing key or public-key file is replaced only with ``--force``, and only by a key;
- no output is written through a symlinked folder inside an output tree (``ota build --out``,
  ``registry publish --out``), even when the folder is swapped for a symlink after planning;
- a killed run's staged files and backups are removed by the next run that writes there;
- a full, closed or broken standard output is exit 3 with a message, never a traceback.
"""

from __future__ import annotations

import fcntl
import os
import subprocess
import sys
from pathlib import Path

import pytest

from hcdf_trust.ota.keys import generate, private_pem, public_pem
from hcdf_trust.outputs import (
    DOCUMENT,
    NEW_ONLY,
    PRIVATE_KEY,
    PUBLIC_KEY,
    REGISTRY_SOURCE,
    OutputError,
    OutputPlan,
    kind_of,
)

from ._macsec import KILLER, humanoid
from ._ota import make_robot, tree
from ._registry import PASSPHRASE, PROFILE, ROS2_XSD, Registry

PROJECT = Path(__file__).resolve().parents[1]
ROBOT = PROJECT / "examples" / "robot" / "robot.hcdf"
BOARD = "mr_mcxn_t1"


def hidden(folder: Path) -> list[str]:
    """Every file or folder under ``folder`` whose name starts with a dot (staged files, backups)."""
    return sorted(str(p.relative_to(folder)) for p in folder.rglob(".*"))


@pytest.fixture
def robot(tmp_path, cli):
    return make_robot(tmp_path, cli)


@pytest.fixture
def registry_env(tmp_path, monkeypatch, cli):
    monkeypatch.setenv("HCDF_TRUST_PASSPHRASE", PASSPHRASE)
    reg = Registry(tmp_path / "reg", cli)
    reg.run("init", reg.src, "--keys", reg.keys)
    return reg


# -- trees: no write through a symlinked folder -------------------------------------------------


@pytest.mark.parametrize("depth", ["board", "app"])
def test_ota_build_refuses_a_symlinked_folder_inside_the_release(robot, cli, tmp_path, depth):
    out, outside = tmp_path / "rel", tmp_path / "outside"
    (outside / "flex-io").mkdir(parents=True)
    (outside / "flex-io" / "notes.txt").write_text("someone else's file")
    if depth == "board":
        out.mkdir()
        (out / BOARD).symlink_to(outside)
    else:
        (out / BOARD).mkdir(parents=True)
        (out / BOARD / "flex-io").symlink_to(outside / "flex-io")
    r = robot.build(cli, out)
    assert r.exit_code == 3, r.stderr
    assert "is a symlink inside the output folder" in r.stderr
    assert tree(outside) == {"flex-io/notes.txt": b"someone else's file"}  # nothing written outside
    assert tree(out) == {}  # nor inside: all or nothing


def test_a_tree_folder_swapped_for_a_symlink_after_planning_is_not_followed(tmp_path):
    """The check at planning time is not enough: commit opens each folder with O_NOFOLLOW."""
    rel, outside = tmp_path / "rel", tmp_path / "outside"
    (rel / "board").mkdir(parents=True)
    outside.mkdir()
    plan = OutputPlan()
    plan.add(rel / "board" / "latest.json", b"new", flag="--out", under=rel)
    plan.add(rel / "release.suit", b"manifest", flag="--out", under=rel)
    (rel / "board").rmdir()
    (rel / "board").symlink_to(outside)
    with pytest.raises(OutputError, match=r"board is a symlink: refusing to write through it"):
        plan.commit()
    assert list(outside.iterdir()) == []
    assert sorted(p.name for p in rel.iterdir()) == ["board"]  # release.suit not renamed either


def test_a_missing_folder_planted_as_a_symlink_before_commit_is_not_followed(tmp_path):
    """A folder the commit has to make is made by mkdirat and opened with O_NOFOLLOW: a symlink
    planted at its name meanwhile is refused, for any output (not only tree outputs)."""
    outside = tmp_path / "outside"
    outside.mkdir()
    plan = OutputPlan()
    plan.add(tmp_path / "new" / "flat.hcdf", b"x", flag="--out")
    (tmp_path / "new").symlink_to(outside)
    with pytest.raises(OutputError, match="symlink"):
        plan.commit()
    assert list(outside.iterdir()) == []


def test_a_tree_output_may_not_leave_its_tree(tmp_path):
    plan = OutputPlan()
    with pytest.raises(OutputError, match="not inside the output folder"):
        plan.add(tmp_path / "rel" / ".." / "x", b"x", flag="--out", under=tmp_path / "rel")
    with pytest.raises(OutputError, match="not inside the output folder"):
        plan.add(tmp_path / "elsewhere" / "x", b"x", flag="--out", under=tmp_path / "rel")


def test_the_tree_root_itself_may_be_a_symlink_the_user_chose(tmp_path):
    (tmp_path / "real").mkdir()
    (tmp_path / "rel").symlink_to(tmp_path / "real")
    plan = OutputPlan()
    plan.add(tmp_path / "rel" / "b" / "x", b"x", flag="--out", under=tmp_path / "rel")
    plan.commit()
    assert (tmp_path / "real" / "b" / "x").read_bytes() == b"x"


def test_registry_publish_refuses_a_symlinked_folder_in_the_site(registry_env, tmp_path):
    reg = registry_env
    reg.run("add", reg.src, "--profile", PROFILE, "--content", reg.content)
    outside = tmp_path / "outside"
    outside.mkdir()
    reg.site.mkdir()
    (reg.site / "targets").symlink_to(outside)
    r = reg.publish(ok=False)
    assert r.exit_code == 3, r.stderr
    assert "targets is a symlink inside the output folder" in r.stderr
    assert list(outside.iterdir()) == []
    assert sorted(p.name for p in reg.site.iterdir()) == ["targets"]


# -- killed runs: leftovers are removed by the next run -----------------------------------------


def _killed(args: list[str], when: str, name: str) -> None:
    cmd = [sys.executable, "-c", KILLER, when, name, *args]
    proc = subprocess.run(cmd, cwd=PROJECT, capture_output=True, timeout=120)
    assert proc.returncode == -9, proc.stderr


def _build_args(robot, out: Path) -> list[str]:
    return [
        "ota",
        "build",
        str(robot.doc),
        "--firmware-dir",
        str(robot.fw),
        "--key",
        str(robot.key),
        "--out",
        str(out),
        "--base-url",
        "https://fw.example.com/r",
    ]


def test_a_killed_ota_build_leaves_nothing_behind_once_the_next_build_ran(robot, cli, tmp_path):
    out = tmp_path / "rel"
    assert robot.build(cli, out).exit_code == 0
    robot.rewrite(cli, flex_version="v0.3.0")
    # killed with every file staged and the first ones renamed (their backups made, not yet removed)
    _killed(_build_args(robot, out), "before", "release.suit")
    left = hidden(out)
    assert any(n.endswith(".tmp") for n in left) and any(n.endswith(".old") for n in left), left
    r = robot.build(cli, out)
    assert r.exit_code == 0, r.stderr
    assert hidden(out) == []
    assert cli("ota", "verify", out, "--key", robot.pub).exit_code == 0


def test_the_sweep_removes_only_leftovers_and_spares_a_live_commit(tmp_path):
    names = {
        ".latest.json.0123456789ab.tmp": "file",  # staged by a killed commit
        ".fw.bin.abcdef012345.old": "file",  # its backup of a replaced file
        ".gitkeep": "file",
        ".x.tmp": "file",  # not OutputPlan's name (no 12-hex token)
        ".y.0123456789ab.tmp.keep": "file",
        ".z.0123456789ab.old": "dir",  # named like one, but a folder
        ".w.0123456789ab.tmp": "link",  # named like one, but a symlink
    }
    for name, kind in names.items():
        path = tmp_path / name
        if kind == "file":
            path.write_bytes(b"x")
        elif kind == "dir":
            path.mkdir()
        else:
            path.symlink_to(tmp_path / ".gitkeep")
    # another commit is writing in this folder: it holds the folder's shared lock, nothing is swept
    live = os.open(tmp_path, os.O_RDONLY | os.O_DIRECTORY)
    fcntl.flock(live, fcntl.LOCK_SH)
    try:
        plan = OutputPlan()
        plan.add(tmp_path / "one", b"1", flag="--out")
        plan.commit()
        assert set(names) <= {p.name for p in tmp_path.iterdir()}
    finally:
        os.close(live)
    plan = OutputPlan()
    plan.add(tmp_path / "two", b"2", flag="--out")
    plan.commit()
    kept = {p.name for p in tmp_path.iterdir()}
    assert kept == set(names) - {".latest.json.0123456789ab.tmp", ".fw.bin.abcdef012345.old"} | {"one", "two"}


# -- what is never a destination ----------------------------------------------------------------


@pytest.fixture
def victims(tmp_path, cli):
    """Files an attacker (or a typo) points `-o` at: keys, a passphrase file, a registry source, a document."""
    key = generate("ecdsa-p256")
    (tmp_path / "fw.pem").write_bytes(private_pem(key, None))
    (tmp_path / "fw.pub.pem").write_bytes(public_pem(key))
    (tmp_path / "pass").write_text(PASSPHRASE + "\n")
    (tmp_path / "pass").chmod(0o600)
    (tmp_path / "robot.hcdf").write_text('<?xml version="1.0"?>\n<hcdf version="1.0" name="r"/>\n')
    return {name: (tmp_path / name).read_bytes() for name in ("fw.pem", "fw.pub.pem", "pass", "robot.hcdf")}


@pytest.mark.parametrize("force", [False, True])
@pytest.mark.parametrize("victim", ["fw.pem", "pass", "robot.hcdf", "src/root.toml", "owner.pub"])
def test_registry_keygen_never_replaces_a_key_passphrase_source_or_document(
    registry_env, tmp_path, victims, cli, force, victim
):
    reg = registry_env
    if victim == "owner.pub":
        reg.run("keygen", "--keys", tmp_path / "k0", "-o", tmp_path / "owner.pub")
    path = tmp_path / victim if victim != "src/root.toml" else reg.src / "root.toml"
    before = path.read_bytes()
    keys = tmp_path / "k1"
    args = ["registry", "keygen", "--keys", keys, "-o", path, "--passphrase-file", tmp_path / "pass"]
    r = cli(*args, *(["--force"] if force else []))
    if victim == "owner.pub" and force:  # an existing public key, replaced on purpose
        assert r.exit_code == 0, r.stderr
        assert path.read_bytes() != before and b"registry owner public key" in path.read_bytes()
        return
    assert r.exit_code == 3, r.stderr
    assert "refusing to" in r.stderr
    assert path.read_bytes() == before
    assert not keys.exists() or list(keys.iterdir()) == []  # no private key made either


def test_ota_keygen_force_replaces_only_keys(tmp_path, victims, cli):
    for victim in ("robot.hcdf", "pass"):
        r = cli("ota", "keygen", "-o", tmp_path / victim, "--force")
        assert r.exit_code == 3, r.stderr
        assert (tmp_path / victim).read_bytes() == victims[victim]
    r = cli("ota", "keygen", "-o", tmp_path / "fw.pem")
    assert r.exit_code == 3 and "use --force" in r.stderr
    assert (tmp_path / "fw.pem").read_bytes() == victims["fw.pem"]
    r = cli("ota", "keygen", "-o", tmp_path / "fw.pem", "--force")
    assert r.exit_code == 0, r.stderr
    assert (tmp_path / "fw.pem").read_bytes() != victims["fw.pem"]


@pytest.mark.parametrize("victim", ["fw.pem", "fw.pub.pem", "robot.hcdf", "src/root.toml"])
def test_registry_statement_never_replaces_a_key_a_document_or_a_registry_source(
    registry_env, tmp_path, victims, cli, victim
):
    path = tmp_path / victim if victim != "src/root.toml" else registry_env.src / "root.toml"
    before = path.read_bytes()
    args = ["registry", "statement", "--domain", "org.ros2", "--version", "1.0", "--schema", ROS2_XSD]
    r = cli(*args, "--content", ROS2_XSD.parents[1], "-o", path)
    assert r.exit_code == 3, r.stderr
    assert "refusing to replace it" in r.stderr
    assert path.read_bytes() == before
    # -o - is standard output: the same bytes as a file
    r = cli(*args, "--content", ROS2_XSD.parents[1], "-o", "-")
    assert r.exit_code == 0, r.stderr
    r2 = cli(*args, "--content", ROS2_XSD.parents[1], "-o", tmp_path / "statement")
    assert r2.exit_code == 0 and (tmp_path / "statement").read_text() == r.stdout


def test_macsec_export_refuses_the_key_store_folder(tmp_path, cli):
    (tmp_path / "doc").mkdir()
    doc = humanoid(tmp_path / "doc")
    (tmp_path / "pass").write_bytes(b"export passphrase")
    (tmp_path / "pass").chmod(0o600)
    base = ["--store", tmp_path / "keys", "--passphrase-file", tmp_path / "pass"]
    assert cli("macsec", "generate", doc, *base).exit_code == 0
    before = tree(tmp_path / "keys")
    r = cli("macsec", "export", doc, *base, "--device", "head", "--format", "json", "--out", tmp_path / "keys")
    assert r.exit_code == 3, r.stderr
    assert "inside the key store's folder" in r.stderr
    assert tree(tmp_path / "keys") == before


def test_the_marks_match_what_our_own_writers_put_first(registry_env, tmp_path):
    """The replace rule knows our formats by their first line: the writers must still write it."""
    reg = registry_env
    reg.run("keygen", "--keys", tmp_path / "k", "-o", tmp_path / "owner.pub")
    reg.add_domain("org.ros2", "1.0", ROS2_XSD)
    reg.run("add", reg.src, "--profile", PROFILE, "--content", reg.content)
    assert kind_of((tmp_path / "owner.pub").read_bytes()) == PUBLIC_KEY
    sources = [reg.src / "root.toml", *(p for p in reg.src.rglob("*.toml") if p.name != "root.toml")]
    assert len(sources) >= 3
    assert {kind_of(p.read_bytes()) for p in sources} == {REGISTRY_SOURCE}
    assert kind_of(next((tmp_path / "k").iterdir()).read_bytes()) == PRIVATE_KEY
    assert kind_of(ROBOT.read_bytes()) == DOCUMENT


def test_key_material_is_replaced_only_by_an_output_that_says_so(tmp_path):
    key = generate("ed25519")
    (tmp_path / "k.pem").write_bytes(private_pem(key, b"pw"))  # encrypted PEM
    (tmp_path / "k.pub").write_bytes(public_pem(key))
    (tmp_path / "age.txt").write_text("# created: now\nAGE-SECRET-KEY-1QQQQ\n")
    (tmp_path / "plain.txt").write_text("anything")
    for name in ("k.pem", "k.pub", "age.txt"):
        with pytest.raises(OutputError, match="refusing to replace it"):
            OutputPlan().add(tmp_path / name, b"x", flag="-o")
    OutputPlan().add(tmp_path / "plain.txt", b"x", flag="-o")  # any other file may be replaced
    with pytest.raises(OutputError, match="exists: refusing to replace it"):
        OutputPlan().add(tmp_path / "plain.txt", b"x", flag="-o", replaces=NEW_ONLY)
    with pytest.raises(OutputError, match="is not a public key"):
        OutputPlan().add(tmp_path / "plain.txt", b"x", flag="-o", replaces=(PUBLIC_KEY,))
    plan = OutputPlan()
    plan.add(tmp_path / "k.pub", b"new", flag="-o", replaces=(PUBLIC_KEY,))
    plan.commit()
    assert (tmp_path / "k.pub").read_bytes() == b"new"


# -- standard output ----------------------------------------------------------------------------

RUN = "from hcdf_trust.cli import main; main()"  # the console script's way in (no arguments given)


def _doc(tmp_path: Path) -> Path:
    doc = tmp_path / "x.hcdf"
    doc.write_text('<?xml version="1.0"?>\n<hcdf version="1.0" name="x"/>\n')
    return doc


def _run(args: list[str], **kw) -> subprocess.CompletedProcess[bytes]:
    return subprocess.run([sys.executable, "-c", RUN, *args], stderr=subprocess.PIPE, timeout=120, **kw)


@pytest.mark.parametrize("case", ["validate-json", "error-json", "help", "statement", "sbom"])
@pytest.mark.parametrize("stdout", ["full", "closed", "broken-pipe"])
def test_a_full_or_closed_stdout_is_exit_3_with_a_message(tmp_path, case, stdout):
    doc = _doc(tmp_path)
    args = {
        "validate-json": ["validate", str(doc), "--json"],
        "error-json": ["validate", str(tmp_path / "missing.hcdf"), "--json"],
        "help": ["--help"],
        "sbom": ["sbom", str(ROBOT), "--format", "cyclonedx"],
        "statement": [
            "registry",
            "statement",
            "--domain",
            "org.ros2",
            "--version",
            "1.0",
            "--schema",
            str(ROS2_XSD),
            "--content",
            str(ROS2_XSD.parents[1]),
            "-o",
            "-",
        ],
    }[case]
    if stdout == "full":
        with open("/dev/full", "wb") as full:
            proc = _run(args, stdout=full)
    elif stdout == "closed":
        proc = _run(args, stdout=subprocess.DEVNULL, preexec_fn=lambda: os.close(1))
    else:
        r, w = os.pipe()
        os.close(r)  # nobody reads: EPIPE (Python ignores SIGPIPE)
        try:
            proc = _run(args, stdout=w)
        finally:
            os.close(w)
    err = proc.stderr.decode()
    assert proc.returncode == 3, err
    assert "Traceback" not in err and "Exception ignored" not in err
    assert "cannot write to standard output" in err


def test_a_verb_that_prints_nothing_on_stdout_is_unaffected_by_a_closed_one(tmp_path):
    proc = _run(["validate", str(_doc(tmp_path))], stdout=subprocess.DEVNULL, preexec_fn=lambda: os.close(1))
    assert proc.returncode == 0, proc.stderr


# -- the registry client's downloads ------------------------------------------------------------

KILLED_DOWNLOAD = """
import os, signal, sys
from tuf.ngclient import Updater
real = Updater.download_target
def download_target(self, *args, **kwargs):
    real(self, *args, **kwargs)
    os.kill(os.getpid(), signal.SIGKILL)  # downloaded, not yet read back nor cleaned up
Updater.download_target = download_target
from hcdf_trust.cli import main
main(sys.argv[1:], prog_name="hcdf-trust")
"""


def test_a_killed_registry_fetch_leaves_no_partial_download_in_the_cache(registry_env, tmp_path):
    """A target is downloaded into memory: nothing in the client cache outlives a kill."""
    reg = registry_env
    reg.run("add", reg.src, "--profile", PROFILE, "--content", reg.content)
    reg.publish()
    name = PROFILE.name.removesuffix(".streams.xml")
    cache = reg.base / "client"
    args = ["registry", "fetch", "profile", name, "--from", str(reg.site), "--trusted-root", str(reg.root_json)]
    args += ["--cache-dir", str(cache), "-o", str(tmp_path / "got.xml")]
    proc = subprocess.run([sys.executable, "-c", KILLED_DOWNLOAD, *args], cwd=PROJECT, capture_output=True, timeout=120)
    assert proc.returncode == -9, proc.stderr
    assert [p for p in (cache / "targets").rglob("*")] == []
    assert not (tmp_path / "got.xml").exists()
    r = reg.fetch("profile", name, out=tmp_path / "got.xml")
    assert r.exit_code == 0, r.stderr
    assert (tmp_path / "got.xml").read_bytes() == PROFILE.read_bytes()


def test_a_killed_resolve_leaves_nothing_once_the_next_resolve_ran_even_with_nothing_to_change(robot, cli):
    """The lock beside the document: the next resolve finds it unchanged, and still sweeps its folder."""
    folder = robot.doc.parent
    lock = robot.doc.with_name(robot.doc.name + ".lock")
    canonical = lock.read_bytes()
    lock.write_bytes(canonical + b" ")  # so that resolve rewrites it (and is killed doing so)
    _killed(["resolve", str(robot.doc)], "before", lock.name)
    assert [n for n in hidden(folder) if n.startswith(f".{lock.name}.")], hidden(folder)
    lock.write_bytes(canonical)  # the next resolve has nothing to write
    r = cli("resolve", robot.doc)
    assert r.exit_code == 0, r.stderr
    assert lock.read_bytes() == canonical
    assert [n for n in hidden(folder) if n.startswith(f".{lock.name}.")] == []


def test_a_killed_registry_refresh_leaves_no_temporary_file_in_the_client_cache(registry_env):
    """python-tuf's metadata writes go through OutputPlan: the next refresh removes what a killed one staged."""
    reg = registry_env
    reg.run("add", reg.src, "--profile", PROFILE, "--content", reg.content)
    reg.publish()
    args = ["registry", "verify", *map(str, reg.client_args())]
    _killed(args, "before", "timestamp.json")
    metadata = reg.base / "client" / "metadata"
    strays = lambda: sorted(p.name for p in metadata.iterdir() if not p.name.endswith(".json") and p.is_file())  # noqa: E731
    assert strays() or hidden(metadata), sorted(p.name for p in metadata.iterdir())  # the kill left something
    r = reg.run("verify", *reg.client_args())
    assert r.exit_code == 0, r.stderr
    assert strays() == [] and hidden(metadata) == []


# -- held files (ota pull's and bundle pull's staged blobs): moved into place, not copied --------
def _held(stage: Path, data: bytes, name: str = "blob"):
    """A staged file as oci/blobs.py makes one: created O_EXCL in a private folder, held open."""
    import hashlib

    from hcdf_trust.outputs import HeldFile

    stage.mkdir(mode=0o700, exist_ok=True)
    fd = os.open(stage / name, os.O_RDWR | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o600)
    os.write(fd, data)
    return HeldFile(fd, str(stage / name), len(data), hashlib.sha256(data).hexdigest())


def test_a_held_file_is_moved_into_place_with_its_mode_and_nothing_left_behind(tmp_path):
    held = _held(tmp_path / "stage", b"image bytes")
    plan = OutputPlan()
    plan.add(tmp_path / "out" / "b" / "1.bin", held, flag="--out", under=tmp_path / "out")
    plan.add(tmp_path / "out" / "release.suit", b"manifest", flag="--out", under=tmp_path / "out")
    plan.commit()
    dest = tmp_path / "out" / "b" / "1.bin"
    st = dest.stat()
    assert dest.read_bytes() == b"image bytes" and oct(st.st_mode & 0o777) == "0o644"
    assert (st.st_dev, st.st_ino) == (os.fstat(held.fd).st_dev, os.fstat(held.fd).st_ino)  # moved, not copied
    assert st.st_nlink == 1 and list((tmp_path / "stage").iterdir()) == []
    assert hidden(tmp_path / "out") == []
    os.close(held.fd)


@pytest.mark.parametrize("swap", ["other file", "symlink to it", "symlink elsewhere"])
def test_a_held_file_whose_staged_name_was_swapped_is_refused_with_nothing_written(tmp_path, swap):
    """The staged name must still be the file held (and verified): a file of the same size put
    in its place, or a symlink (even to the held file), fails the whole commit."""
    from hcdf_trust.errors import IntegrityError

    held = _held(tmp_path / "stage", b"verified")
    os.rename(held.path, tmp_path / "stage" / "kept")
    if swap == "other file":
        Path(held.path).write_bytes(b"attacker")
    elif swap == "symlink to it":
        Path(held.path).symlink_to(tmp_path / "stage" / "kept")
    else:
        (tmp_path / "victim").write_bytes(b"attacker")
        Path(held.path).symlink_to(tmp_path / "victim")
    plan = OutputPlan()
    plan.add(tmp_path / "out" / "a.txt", b"small", flag="--out", under=tmp_path / "out")
    plan.add(tmp_path / "out" / "b.bin", held, flag="--out", under=tmp_path / "out")
    with pytest.raises(IntegrityError, match="no longer the file that was verified"):
        plan.commit()
    assert not (tmp_path / "out").exists()
    os.close(held.fd)


def test_a_held_file_with_another_link_or_another_size_is_refused(tmp_path):
    """Another hard link is a name through which the output could be rewritten later; a size
    other than the one verified (appended after the check) is not what was verified."""
    from hcdf_trust.errors import IntegrityError

    held = _held(tmp_path / "stage", b"verified")
    os.link(held.path, tmp_path / "elsewhere")
    plan = OutputPlan()
    plan.add(tmp_path / "out" / "b.bin", held, flag="--out", under=tmp_path / "out")
    with pytest.raises(IntegrityError, match="1 other link"):
        plan.commit()
    assert not (tmp_path / "out").exists()
    os.close(held.fd)
    held = _held(tmp_path / "stage", b"verified", "two")
    os.write(held.fd, b"+more")
    plan = OutputPlan()
    plan.add(tmp_path / "out" / "b.bin", held, flag="--out", under=tmp_path / "out")
    with pytest.raises(IntegrityError, match="not the 8 verified"):
        plan.commit()
    assert not (tmp_path / "out").exists() and Path(held.path).exists()
    os.close(held.fd)


def test_a_held_file_keeps_the_planners_refusals(tmp_path):
    """Inputs, key material and symlinked folders of the tree are refused for a held file as for
    any output, and the held file stays where it was."""
    key = tmp_path / "key.pem"
    key.write_bytes(private_pem(generate("ecdsa-p256"), None))
    held = _held(tmp_path / "stage", b"verified")
    plan = OutputPlan()
    plan.protect(tmp_path / "input.hcdf", what="the root document")
    (tmp_path / "input.hcdf").write_bytes(b"<hcdf/>")
    with pytest.raises(OutputError, match="refusing to overwrite an input"):
        plan.add(tmp_path / "input.hcdf", held, flag="--out")
    with pytest.raises(OutputError, match="is a private key: refusing to replace it"):
        plan.add(key, held, flag="--out")
    with pytest.raises(ValueError):
        plan.add(tmp_path / "x", held, flag="--out", if_changed=True)
    (tmp_path / "out").mkdir()
    (tmp_path / "outside").mkdir()
    plan.add(tmp_path / "out" / "board" / "1.bin", held, flag="--out", under=tmp_path / "out")
    (tmp_path / "out" / "board").symlink_to(tmp_path / "outside")
    with pytest.raises(OutputError, match="symlink"):
        plan.commit()
    assert list((tmp_path / "outside").iterdir()) == [] and Path(held.path).read_bytes() == b"verified"
    os.close(held.fd)


def test_a_held_file_on_another_filesystem_is_copied_and_hashed(tmp_path, monkeypatch):
    """Where no hard link can be made (EXDEV), the held file is copied from its descriptor and
    hashed against the digest it was verified with: changed bytes fail the commit."""
    import errno

    from hcdf_trust.errors import IntegrityError

    real_link = os.link

    def no_link(src, dst, **kw):
        if str(src).startswith(str(tmp_path / "stage")):
            raise OSError(errno.EXDEV, "Invalid cross-device link")
        return real_link(src, dst, **kw)

    monkeypatch.setattr(os, "link", no_link)
    held = _held(tmp_path / "stage", b"verified")
    plan = OutputPlan()
    plan.add(tmp_path / "out" / "b.bin", held, flag="--out", under=tmp_path / "out")
    plan.commit()
    dest = tmp_path / "out" / "b.bin"
    assert dest.read_bytes() == b"verified" and dest.stat().st_ino != os.fstat(held.fd).st_ino
    os.pwrite(held.fd, b"V", 0)
    plan = OutputPlan()
    plan.add(tmp_path / "out2" / "b.bin", held, flag="--out", under=tmp_path / "out2")
    with pytest.raises(IntegrityError, match="changed after it was verified"):
        plan.commit()
    assert not (tmp_path / "out2").exists()
    os.close(held.fd)
