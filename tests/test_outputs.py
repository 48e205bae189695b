"""Outputs never overwrite inputs, and a run's outputs land together or not at all.

Each hostile destination of ``resolve --lock`` / ``--out`` is tried on a copy of the
example robot; afterwards every document and artifact must be byte-identical
(SHA-256 before and after) and nothing else may have appeared. Read-only folders
and full disks are real: an immutable folder (``chattr +i``, since the tests run
as root and root ignores permission bits), a subprocess whose file size limit is
below the output's size (``RLIMIT_FSIZE``, SIGXFSZ ignored: writes fail with EFBIG)
and, where this machine allows mounting, a full tmpfs (ENOSPC).
"""

from __future__ import annotations

import hashlib
import os
import resource
import shutil
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from hcdf_trust.outputs import OutputError, OutputPlan

from .conftest import PROJECT

EXAMPLE = PROJECT / "examples" / "robot"

INPUTS = {
    "root document": "robot/robot.hcdf",
    "include": "robot/assemblies/arm.hcdf",
    "model": "robot/models/gripper.glb",
    "mesh": "robot/meshes/chassis-hull.stl",
    "stream profile": "robot/profiles/operational.streams.xml",
    "firmware manifest": "robot/firmware/arm-ctrl.latest.json",
}


def contents(*roots: Path) -> dict[str, str]:
    """Every file and link under ``roots``: its SHA-256 (files), target (links) or kind."""
    out: dict[str, str] = {}
    for root in roots:
        for dirpath, dirnames, filenames in os.walk(root):
            for name in dirnames + filenames:
                p = os.path.join(dirpath, name)
                if os.path.islink(p):
                    out[p] = "link -> " + os.readlink(p)
                elif os.path.isdir(p):
                    out[p] = "dir"
                elif os.path.isfile(p):
                    out[p] = hashlib.sha256(Path(p).read_bytes()).hexdigest()
                else:
                    out[p] = "special"
    return out


@pytest.fixture
def work(tmp_path, monkeypatch) -> Path:
    """A copy of the example robot in ``tmp_path/robot``, its lock moved out, the cwd at ``tmp_path``."""
    shutil.copytree(EXAMPLE, tmp_path / "robot")
    (tmp_path / "robot" / "robot.hcdf.lock").unlink()
    (tmp_path / "cache").mkdir()
    (tmp_path / "cache" / "blob").write_bytes(b"cached bytes")
    monkeypatch.chdir(tmp_path)
    return tmp_path


def run(cli, *extra, lock: str = "locks/robot.lock", out: str | None = "dist/robot.flat.hcdf"):
    # --root .: the flattened document may land outside robot/ (dist/) and still resolve again.
    args = ["resolve", "robot/robot.hcdf", "--offline", "--cache-dir", "cache", "--json", "--lock", lock, "--root", "."]
    if out is not None:
        args += ["--out", out]
    return cli(*args, *extra)


def assert_refused(result, flag: str) -> dict:
    assert result.exit_code == 3, result.stdout + result.stderr
    [error] = result.json["errors"]
    assert error["code"] == "output" and error["message"].startswith(flag), error
    return error


def test_the_example_robot_resolves_and_writes_both_outputs(cli, work):
    result = run(cli)
    assert result.exit_code == 0, result.stdout
    assert sorted(result.json["wrote"]) == ["dist/robot.flat.hcdf", "locks/robot.lock"]
    assert (work / "locks" / "robot.lock").read_bytes().startswith(b"{")
    assert b"<hcdf" in (work / "dist" / "robot.flat.hcdf").read_bytes()


# --- every input is refused as a destination, by either flag --------------------------


@pytest.mark.parametrize("flag", ["--lock", "--out"])
@pytest.mark.parametrize("what", sorted(INPUTS))
def test_an_input_is_never_a_destination(cli, work, flag, what):
    target = INPUTS[what]
    before = contents(work)
    result = run(cli, lock=target) if flag == "--lock" else run(cli, out=target)
    error = assert_refused(result, flag)
    assert "refusing to overwrite an input" in error["message"]
    assert contents(work) == before  # the input byte-identical; not the other output either


def _symlink(work: Path) -> str:
    (work / "link.hcdf").symlink_to(work / "robot" / "assemblies" / "arm.hcdf")
    return "link.hcdf"


def _relative_symlink_chain(work: Path) -> str:
    (work / "a").symlink_to("robot/models")
    (work / "b").symlink_to("a/chassis.glb")
    return "b"


def _dotdot_after_symlink(work: Path) -> str:
    # The kernel resolves elsewhere/.. to robot/ (the symlink first); a lexical
    # os.path.abspath would make it work/robot.hcdf, a file nobody named.
    (work / "elsewhere").symlink_to(work / "robot" / "assemblies")
    return "elsewhere/../robot.hcdf"


def _dotdot(work: Path) -> str:
    return "robot/assemblies/../models/./camera-head.glb"


def _hard_link(work: Path) -> str:
    os.link(work / "robot" / "models" / "arm-link.glb", work / "copy.glb")
    return "copy.glb"


def _hard_link_to_root(work: Path) -> str:
    os.link(work / "robot" / "robot.hcdf", work / "robot-copy.hcdf")
    return "robot-copy.hcdf"


def _in_cache(work: Path) -> str:
    return "cache/blob"


def _new_file_in_cache(work: Path) -> str:
    return "cache/sub/new.hcdf"


def _symlink_into_cache(work: Path) -> str:
    (work / "to-cache").symlink_to(work / "cache")
    return "to-cache/blob"


@pytest.mark.parametrize("flag", ["--lock", "--out"])
@pytest.mark.parametrize(
    "make",
    [
        _symlink,
        _relative_symlink_chain,
        _dotdot_after_symlink,
        _dotdot,
        _hard_link,
        _hard_link_to_root,
        _in_cache,
        _new_file_in_cache,
        _symlink_into_cache,
    ],
)
def test_no_spelling_gets_around_the_check(cli, work, flag, make):
    target = make(work)
    before = contents(work)
    result = run(cli, lock=target) if flag == "--lock" else run(cli, out=target)
    assert_refused(result, flag)
    assert contents(work) == before


def test_out_and_lock_are_the_same_file(cli, work):
    (work / "dist").mkdir()
    (work / "alias").symlink_to("dist")
    before = contents(work)
    for out in ("dist/robot.out", "alias/robot.out", "dist/../dist/robot.out"):
        result = run(cli, lock="dist/robot.out", out=out)
        error = assert_refused(result, "--out")
        assert "also the destination of --lock" in error["message"]
        assert contents(work) == before


def test_out_onto_the_lock_that_is_not_written_is_refused(cli, work):
    """With --no-lock the lock file is an input like any other."""
    assert run(cli, out=None).exit_code == 0
    before = contents(work)
    result = run(cli, "--no-lock", out="locks/robot.lock")
    assert "the lock file" in assert_refused(result, "--out")["message"]
    assert contents(work) == before


@pytest.mark.parametrize("flag", ["--lock", "--out"])
def test_an_existing_directory_is_a_usage_error(cli, work, flag):
    (work / "dir-link").symlink_to("robot/models")
    before = contents(work)
    for target in ("robot/models", "dir-link"):
        result = run(cli, lock=target) if flag == "--lock" else run(cli, out=target)
        assert result.exit_code == 2 and "directory" in result.stderr, result.stderr
    assert contents(work) == before


@pytest.mark.parametrize("target", ["new-folder/", "new-folder/.", "new-folder/.."])
def test_a_folder_name_is_refused(cli, work, target):
    before = contents(work)
    assert_refused(run(cli, out=target), "--out")
    assert contents(work) == before


@pytest.mark.parametrize("flag", ["--lock", "--out"])
def test_a_destination_under_a_regular_file(cli, work, flag):
    before = contents(work)
    target = "robot/models/chassis.glb/deeper/x"
    result = run(cli, lock=target) if flag == "--lock" else run(cli, out=target)
    assert "is not a folder" in assert_refused(result, flag)["message"]
    assert contents(work) == before


def test_a_fifo_is_not_replaced(cli, work):
    """An existing destination that is not a regular file (FIFO, device) is refused,
    not silently replaced: ``--out /dev/null`` as root would otherwise replace the device."""
    os.mkfifo(work / "pipe")
    before = contents(work)
    assert "not a regular file (a FIFO)" in assert_refused(run(cli, out="pipe"), "--out")["message"]
    assert contents(work) == before


def test_a_remote_blob_in_the_cache_is_protected(cli, work, https_server, tls):
    """A model fetched over https lives only in the cache: its blob is protected."""
    data = os.urandom(5000)
    digest = hashlib.sha256(data).hexdigest()
    url = https_server.add("/m.glb", data)
    doc = work / "remote.hcdf"
    doc.write_text(
        f'<hcdf version="1.0" name="r"><comp name="c"><visual><model uri="{url}" sha="{digest}"/>'
        "</visual></comp></hcdf>\n"
    )
    args = ["resolve", doc, "--ca-bundle", tls.ca_pem, "--cache-dir", "c2", "--json"]
    assert cli(*args, "--no-lock").exit_code == 0
    blob = work / "c2" / "sha256" / digest[:2] / digest
    assert blob.read_bytes() == data
    (work / "to-blob").symlink_to(blob)
    before = contents(work)
    for target in (blob, "to-blob"):
        assert_refused(cli(*args, "--lock", "l.lock", "--out", target), "--out")
        assert_refused(cli(*args, "--lock", target), "--lock")
    assert contents(work) == before


def test_a_local_mirror_file_is_protected(cli, work):
    mirror = work / "mirror"
    mirror.mkdir()
    data = b"mirrored model"
    (mirror / "m.glb").write_bytes(data)
    doc = work / "mirrored.hcdf"
    doc.write_text(
        '<hcdf version="1.0" name="r"><comp name="c"><visual>'
        f'<model uri="https://models.example/m.glb" sha="{hashlib.sha256(data).hexdigest()}"/>'
        "</visual></comp></hcdf>\n"
    )
    before = contents(work)
    result = cli(
        "resolve",
        doc,
        "--offline",
        "--mirror",
        f"https://models.example/={mirror}",
        "--cache-dir",
        "cache",
        "--json",
        "--lock",
        "l.lock",
        "--out",
        "mirror/m.glb",
    )
    assert "a verified model file" in assert_refused(result, "--out")["message"]
    assert contents(work) == before


def test_a_link_stub_and_its_target_are_both_protected(cli, work):
    """A root given as a git symlink stub (a file holding a sibling's name) and the file it names."""
    (work / "robot" / "stub.hcdf").write_text("robot.hcdf\n")
    before = contents(work)
    for target in ("robot/stub.hcdf", "robot/robot.hcdf"):
        result = cli(
            "resolve",
            "robot/stub.hcdf",
            "--offline",
            "--cache-dir",
            "cache",
            "--json",
            "--lock",
            "l.lock",
            "--out",
            target,
        )
        assert_refused(result, "--out")
    assert contents(work) == before


def test_the_ca_bundle_is_protected(cli, work, tls):
    shutil.copy(tls.ca_pem, work / "ca.pem")
    before = contents(work)
    result = run(cli, "--ca-bundle", "ca.pem", out="ca.pem")
    assert "the CA bundle" in assert_refused(result, "--out")["message"]
    assert contents(work) == before


# --- all or nothing ---------------------------------------------------------------------


def test_a_refused_lock_leaves_no_flat_file(cli, work):
    """Today's bug: --out was written, then --lock robot.hcdf replaced the document."""
    before = contents(work)
    assert_refused(run(cli, lock="robot/robot.hcdf", out="dist/robot.flat.hcdf"), "--lock")
    assert contents(work) == before
    assert not (work / "dist").exists()


def test_a_failed_rename_puts_back_what_was_already_replaced(tmp_path):
    """The renames come last, but one can still fail (the destination became a
    directory meanwhile): the outputs already renamed are put back as they were."""
    first, second = tmp_path / "a" / "first.json", tmp_path / "b" / "second.json"
    first.parent.mkdir()
    first.write_bytes(b"old first")
    (first.parent / "hard").hardlink_to(first)
    plan = OutputPlan()
    plan.add(first, b"new first", flag="--first")
    plan.add(second, b"new second", flag="--second")
    (second / "occupied").mkdir(parents=True)  # a non-empty directory: rename(2) fails
    before = contents(tmp_path)
    with pytest.raises(OutputError, match=r"cannot write --second .*second.json"):
        plan.commit()
    assert contents(tmp_path) == before
    assert first.read_bytes() == b"old first"
    assert os.path.samefile(first, first.parent / "hard")  # the very same file, not a copy


def test_an_interrupt_between_two_renames_puts_back_the_first(tmp_path, monkeypatch):
    """Ctrl-C is not an OSError, and must not leave half of the outputs renamed either."""
    first, second = tmp_path / "first.json", tmp_path / "new" / "second.json"
    first.write_bytes(b"old first")
    plan = OutputPlan()
    plan.add(first, b"new first", flag="--first")
    plan.add(second, b"new second", flag="--second")
    before = contents(tmp_path)
    real_replace, calls = os.replace, []

    def replace(src, dst, **kw):  # names relative to the folder's descriptor (dst_dir_fd)
        calls.append(dst)
        if os.fspath(dst) == second.name:
            raise KeyboardInterrupt
        return real_replace(src, dst, **kw)

    monkeypatch.setattr(os, "replace", replace)
    with pytest.raises(KeyboardInterrupt):
        plan.commit()
    monkeypatch.undo()
    assert [os.fspath(c) for c in calls[:2]] == [first.name, second.name]  # first renamed, then ^C
    assert contents(tmp_path) == before  # put back; no temporary file, no new folder left


def test_a_failed_commit_removes_the_folders_it_made(tmp_path):
    plan = OutputPlan()
    plan.add(tmp_path / "new" / "deeper" / "x.json", b"x", flag="--x")
    plan.add(tmp_path / "y.json", b"y", flag="--y")
    (tmp_path / "y.json").mkdir()  # made a directory after the plan was checked
    (tmp_path / "y.json" / "z").touch()
    with pytest.raises(OutputError):
        plan.commit()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["y.json"]


def test_modes_are_applied_and_an_edit_may_replace_its_input(tmp_path):
    doc = tmp_path / "doc.hcdf"
    doc.write_bytes(b"<old/>")
    plan = OutputPlan()
    plan.protect(doc, what="a document")
    with pytest.raises(OutputError, match="refusing to overwrite an input"):
        plan.add(doc, b"<new/>", flag="pin --write")
    plan.add(doc, b"<new/>", flag="pin --write", edit=True)
    plan.add(tmp_path / "key", b"secret", flag="--key", mode=0o600)
    assert plan.commit() == [doc, tmp_path / "key"]
    assert doc.read_bytes() == b"<new/>"
    assert (tmp_path / "key").stat().st_mode & 0o777 == 0o600


def test_an_edit_may_not_land_in_a_protected_tree(tmp_path):
    plan = OutputPlan()
    plan.protect_tree(tmp_path / "cache", what="the cache")
    with pytest.raises(OutputError, match="inside the cache"):
        plan.add(tmp_path / "cache" / "x", b"", flag="--x", edit=True)


# --- the disk refuses -------------------------------------------------------------------


@pytest.fixture
def read_only_dir(tmp_path) -> Iterator[Path]:
    """A folder nobody can create files in: ``chattr +i`` (root ignores mode bits), or mode 0555."""
    folder = tmp_path / "ro"
    folder.mkdir()
    (folder / "old.lock").write_bytes(b"old lock")
    immutable = False
    if os.geteuid() == 0:
        chattr = shutil.which("chattr")
        if chattr is None or subprocess.run([chattr, "+i", folder], capture_output=True).returncode != 0:
            pytest.skip("running as root and chattr +i is not available here")
        immutable = True
    else:
        folder.chmod(0o555)
    try:
        try:
            (folder / "probe").touch()
        except OSError:
            pass
        else:
            pytest.skip("this folder could not be made read-only")
        yield folder
    finally:
        if immutable:
            subprocess.run(["chattr", "-i", folder], check=True)
        folder.chmod(0o755)


def test_an_output_in_a_read_only_folder(cli, work, read_only_dir):
    before = contents(work)
    result = run(cli, lock=str(read_only_dir / "new.lock"), out="dist/robot.flat.hcdf")
    error = assert_refused(result, "cannot write")
    assert "new.lock" in error["message"]
    assert not (read_only_dir / "new.lock").exists()
    assert contents(work) == before  # --out is not written either
    assert (read_only_dir / "old.lock").read_bytes() == b"old lock"


def test_an_output_in_a_new_folder_under_a_read_only_one(cli, work, read_only_dir):
    before = contents(work)
    result = run(cli, lock="locks/robot.lock", out=str(read_only_dir / "new" / "flat.hcdf"))
    assert_refused(result, "cannot write --out")
    assert contents(work) == before
    assert sorted(p.name for p in read_only_dir.iterdir()) == ["old.lock"]


def _limit_file_size(limit: int):
    def apply() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # write(2) then fails with EFBIG
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    return apply


def test_a_full_disk_writes_nothing(cli, work, tmp_path):
    """A file size limit between the lock's size and the flat document's: the lock is
    staged, the flat document fails with EFBIG; neither is renamed into place, no
    temporary file is left, and there is no traceback."""
    scratch = tmp_path / "scratch"
    assert run(cli, lock=str(scratch / "robot.lock"), out=str(scratch / "robot.flat.hcdf")).exit_code == 0
    lock_size, flat_size = (scratch / "robot.lock").stat().st_size, (scratch / "robot.flat.hcdf").stat().st_size
    assert lock_size + 1024 < flat_size, "the test needs a flat document larger than the lock"
    shutil.rmtree(scratch)
    env = {**os.environ, "PYTHONDONTWRITEBYTECODE": "1"}
    before = contents(work)
    proc = subprocess.run(
        [sys.executable, "-m", "hcdf_trust.cli", "resolve", "robot/robot.hcdf", "--offline", "--cache-dir", "cache",
         "--lock", "locks/robot.lock", "--out", "dist/robot.flat.hcdf", "--root", "."],
        cwd=work, env=env, capture_output=True, text=True, timeout=60,
        preexec_fn=_limit_file_size((lock_size + flat_size) // 2),
    )  # fmt: skip
    assert proc.returncode == 3, proc.stderr
    assert "cannot write --out dist/robot.flat.hcdf: File too large" in proc.stderr
    assert "Traceback" not in proc.stderr
    assert contents(work) == before


@pytest.fixture
def full_tmpfs(tmp_path) -> Iterator[Path]:
    """An 8 KiB tmpfs (2 pages): the lock (1 page) fits, the flat document (over 4 KiB)
    then does not, a real ENOSPC. Needs the right to mount: skipped otherwise."""
    mnt = tmp_path / "full"
    mnt.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=8k", "tmpfs", mnt], capture_output=True).returncode:
        pytest.skip("cannot mount a tmpfs here")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", mnt], check=True)


def test_no_space_left_on_device_writes_nothing(cli, work, full_tmpfs):
    before = contents(work, full_tmpfs)
    result = run(cli, lock=str(full_tmpfs / "robot.lock"), out=str(full_tmpfs / "robot.flat.hcdf"))
    assert "No space left on device" in assert_refused(result, "cannot write")["message"]
    assert contents(work, full_tmpfs) == before


def test_an_input_known_by_its_inode_is_also_compared_by_path(tmp_path):
    """An input protected with the inode it was read from (no stat at planning time) is
    still refused by path after it was replaced by another file (a new inode)."""
    model = tmp_path / "m.glb"
    model.write_bytes(b"read and verified")
    st = model.stat()
    plan = OutputPlan()
    plan.protect(model, what="a verified model file", inode=(st.st_dev, st.st_ino))
    replaced = tmp_path / "new.glb"
    replaced.write_bytes(b"written since")
    os.replace(replaced, model)
    assert model.stat().st_ino != st.st_ino
    with pytest.raises(OutputError, match="is a verified model file"):
        plan.add(model, b"lock", flag="--lock")
    assert model.read_bytes() == b"written since"


def test_a_rolled_back_symlink_destination_is_a_symlink_again(tmp_path):
    """The backup is a link to the symlink itself, not to the file it names."""
    (tmp_path / "target.json").write_text("old")
    link = tmp_path / "link.json"
    link.symlink_to("target.json")
    plan = OutputPlan()
    plan.add(link, b"new", flag="--x")
    plan.add(tmp_path / "b" / "c.json", b"y", flag="--y")
    (tmp_path / "b" / "c.json" / "z").mkdir(parents=True)  # the second rename fails
    with pytest.raises(OutputError):
        plan.commit()
    assert link.is_symlink() and os.readlink(link) == "target.json"
    assert (tmp_path / "target.json").read_text() == "old"
