"""outputs.py: no output lands on an input; all outputs or none (mutation-testing killers)."""

from __future__ import annotations

import contextlib
import errno
import os
import re
import resource
import signal
import stat
import tempfile
from pathlib import Path

import pytest

from hcdf_trust.errors import InputError
from hcdf_trust.outputs import OutputError, OutputPlan


def _files(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.is_file()}


def test_output_error_is_an_input_error_with_its_own_code():
    assert issubclass(OutputError, InputError)
    assert OutputError("x").code == "output" and OutputError("x").exit_code == 3


def test_commit_writes_every_output_with_its_mode_and_returns_the_paths(tmp_path):
    plan = OutputPlan()
    plan.add(tmp_path / "a" / "lock.json", b"lock", flag="--lock")
    plan.add(tmp_path / "flat.hcdf", b"flat", flag="--out", mode=0o600)
    assert plan.paths == [tmp_path / "a" / "lock.json", tmp_path / "flat.hcdf"]
    assert not (tmp_path / "flat.hcdf").exists()  # nothing is written before commit
    written = plan.commit()
    assert written == [tmp_path / "a" / "lock.json", tmp_path / "flat.hcdf"]
    assert (tmp_path / "a" / "lock.json").read_bytes() == b"lock"
    assert (tmp_path / "flat.hcdf").read_bytes() == b"flat"
    assert stat.S_IMODE((tmp_path / "a" / "lock.json").stat().st_mode) == 0o644
    assert stat.S_IMODE((tmp_path / "flat.hcdf").stat().st_mode) == 0o600
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "flat.hcdf"]


def test_a_large_output_is_written_whole(tmp_path):
    data = os.urandom((8 << 20) + 3)
    plan = OutputPlan()
    plan.add(tmp_path / "big", data, flag="--out")
    plan.commit()
    assert (tmp_path / "big").read_bytes() == data


def test_a_relative_destination_is_made_absolute(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    plan = OutputPlan()
    plan.add("rel.json", b"x", flag="--lock")
    assert plan.paths == [tmp_path / "rel.json"]
    plan.commit()
    assert (tmp_path / "rel.json").read_bytes() == b"x"


def test_a_protected_input_is_refused_by_path_symlink_dotdot_and_hard_link(tmp_path):
    doc = tmp_path / "robot.hcdf"
    doc.write_bytes(b"<hcdf/>")
    (tmp_path / "alias.hcdf").symlink_to(doc)
    os.link(doc, tmp_path / "hard.hcdf")
    (tmp_path / "sub").mkdir()
    plan = OutputPlan()
    plan.protect(doc, what="the root document")
    for dest in (doc, tmp_path / "alias.hcdf", tmp_path / "sub" / ".." / "robot.hcdf", tmp_path / "hard.hcdf"):
        with pytest.raises(OutputError) as info:
            plan.add(dest, b"{}", flag="--lock")
        msg = str(info.value)
        assert "--lock" in msg and "the root document" in msg and "refusing to overwrite an input" in msg
        assert info.value.file == os.fspath(dest)
    assert doc.read_bytes() == b"<hcdf/>" and plan.paths == []


def test_an_input_protected_through_a_symlink_is_protected_as_its_target(tmp_path):
    real = tmp_path / "real.glb"
    real.write_bytes(b"glb")
    (tmp_path / "link.glb").symlink_to(real)
    plan = OutputPlan()
    plan.protect(tmp_path / "link.glb", what="a verified artifact")
    with pytest.raises(OutputError, match="a verified artifact"):
        plan.add(real, b"x", flag="--out")


def test_the_first_description_of_an_input_is_kept(tmp_path):
    doc = tmp_path / "d.hcdf"
    doc.write_bytes(b"x")
    plan = OutputPlan()
    plan.protect(doc, what="the root document")
    plan.protect(doc, what="an include")
    with pytest.raises(OutputError, match="the root document"):
        plan.add(doc, b"y", flag="--out")
    os.link(doc, tmp_path / "h")
    with pytest.raises(OutputError, match="the root document"):
        plan.add(tmp_path / "h", b"y", flag="--out")


def test_a_destination_inside_a_protected_tree_is_refused(tmp_path):
    cache = tmp_path / "cache"
    plan = OutputPlan()
    plan.protect_tree(cache, what="the cache")
    for dest in (cache, cache / "x.lock", cache / "deep" / "er" / "x"):
        with pytest.raises(OutputError) as info:
            plan.add(dest, b"x", flag="--lock")
        assert "is inside the cache" in str(info.value) and str(cache) in str(info.value)
    # a sibling whose name starts with the tree's is not inside it
    plan.add(tmp_path / "cache-notes.json", b"x", flag="--lock")
    plan.add(tmp_path / "cachex" / "a", b"x", flag="--out")
    plan.commit()


def test_a_tree_protected_through_a_symlink(tmp_path):
    (tmp_path / "real").mkdir()
    (tmp_path / "alias").symlink_to(tmp_path / "real")
    plan = OutputPlan()
    plan.protect_tree(tmp_path / "alias", what="the cache")
    with pytest.raises(OutputError, match="inside the cache"):
        plan.add(tmp_path / "real" / "x", b"x", flag="--out")


def test_two_outputs_to_one_file_are_refused(tmp_path):
    plan = OutputPlan()
    plan.add(tmp_path / "same", b"a", flag="--lock")
    (tmp_path / "link").symlink_to(tmp_path / "same")
    for dest in (tmp_path / "same", tmp_path / "link"):
        with pytest.raises(OutputError, match="also the destination of --lock") as info:
            plan.add(dest, b"b", flag="--out")
        assert "--out" in str(info.value)


def test_a_directory_destination_is_refused(tmp_path):
    with pytest.raises(OutputError, match="is a directory") as info:
        OutputPlan().add(tmp_path, b"x", flag="--out")
    assert info.value.file == os.fspath(tmp_path)


def test_a_destination_under_a_regular_file_is_refused_at_once(tmp_path):
    (tmp_path / "README.md").write_bytes(b"readme")
    with pytest.raises(OutputError, match="README.md is not a folder"):
        OutputPlan().add(tmp_path / "README.md" / "x", b"x", flag="--out")
    with pytest.raises(OutputError, match="README.md is not a folder"):
        OutputPlan().add(tmp_path / "README.md" / "a" / "b", b"x", flag="--out")
    assert (tmp_path / "README.md").read_bytes() == b"readme"


def test_a_destination_under_an_unsearchable_folder_is_refused(tmp_path):
    if os.geteuid() == 0:
        # root ignores permissions; a symlink loop gives the same OSError (ELOOP) for stat
        (tmp_path / "loop").symlink_to("loop")
        dest, why = tmp_path / "loop" / "x", os.strerror(errno.ELOOP)
    else:
        (tmp_path / "locked").mkdir(mode=0)
        dest, why = tmp_path / "locked" / "sub" / "x", os.strerror(errno.EACCES)
    with pytest.raises(OutputError, match=re.escape(f"--out {dest}: {why}") + "$"):
        OutputPlan().add(dest, b"x", flag="--out")


def test_an_existing_output_is_replaced_and_a_symlink_destination_is_replaced_not_followed(tmp_path):
    (tmp_path / "old.lock").write_bytes(b"old")
    target = tmp_path / "target"
    target.write_bytes(b"target")
    (tmp_path / "link").symlink_to(target)
    plan = OutputPlan()
    plan.add(tmp_path / "old.lock", b"new", flag="--lock")
    plan.commit()
    assert (tmp_path / "old.lock").read_bytes() == b"new"


def test_when_one_output_cannot_be_staged_none_is_written_and_no_temporary_is_left(tmp_path):
    good, ro = tmp_path / "good", tmp_path / "ro"
    good.mkdir()
    ro.mkdir()
    (good / "flat.hcdf").write_bytes(b"previous")
    plan = OutputPlan()
    plan.add(good / "flat.hcdf", b"new flat", flag="--out")
    plan.add(ro / "sub" / "x.lock", b"lock", flag="--lock")
    (ro / "sub").write_bytes(b"")  # appears after planning: staging fails (ENOTDIR)
    with pytest.raises(OutputError) as info:
        plan.commit()
    err = info.value
    assert "cannot write --lock" in str(err) and err.file == str(ro / "sub" / "x.lock")
    assert _files(good) == {"flat.hcdf": b"previous"}
    assert _files(ro) == {"sub": b""}


def test_a_failure_while_staging_the_first_output_names_it(tmp_path):
    plan = OutputPlan()
    plan.add(tmp_path / "a" / "x", b"x", flag="--out")
    plan.add(tmp_path / "b", b"y", flag="--lock")
    (tmp_path / "a").write_bytes(b"")
    with pytest.raises(OutputError, match="cannot write --out"):
        plan.commit()
    assert not (tmp_path / "b").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a"]


def test_a_failed_rename_cleans_up_every_staged_file(tmp_path):
    plan = OutputPlan()
    plan.add(tmp_path / "first", b"1", flag="--lock")
    plan.add(tmp_path / "second", b"2", flag="--out")
    (tmp_path / "second").mkdir()  # rename onto a directory fails after both are staged
    (tmp_path / "second" / "keep").write_bytes(b"")
    with pytest.raises(OutputError, match="cannot write --out"):
        plan.commit()
    # (renames of several files cannot be one atomic step: "first" may already be in place)
    assert not any(p.name.endswith(".tmp") for p in tmp_path.iterdir())
    assert (tmp_path / "second" / "keep").exists()


def test_the_mode_is_applied_before_any_byte_is_written(tmp_path):
    """A secret is never readable by others, even while staged: umask or not."""
    old = os.umask(0)
    try:
        plan = OutputPlan()
        plan.add(tmp_path / "key", b"secret", flag="--out", mode=0o600)
        plan.commit()
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "key").stat().st_mode) == 0o600


def test_messages_name_the_input_as_protected_when_the_destination_spells_it_otherwise(tmp_path):
    doc = tmp_path / "robot.hcdf"
    doc.write_bytes(b"x")
    (tmp_path / "alias").symlink_to(doc)
    plan = OutputPlan()
    plan.protect(tmp_path / "alias", what="the root document")
    with pytest.raises(OutputError) as info:
        plan.add(doc, b"y", flag="--lock")
    assert f"is the root document ({tmp_path / 'alias'})" in str(info.value)


def test_every_refusal_names_the_destination_as_given(tmp_path):
    (tmp_path / "file").write_bytes(b"")
    plan = OutputPlan()
    plan.protect_tree(tmp_path / "cache", what="the cache")
    plan.add(tmp_path / "one", b"1", flag="--lock")
    for dest in (tmp_path / "cache" / "x", tmp_path / "one", tmp_path / "file" / "x"):
        with pytest.raises(OutputError) as info:
            plan.add(dest, b"2", flag="--out")
        assert info.value.file == str(dest)
        assert info.value.to_dict()["file"] == str(dest)
    (tmp_path / "loop").symlink_to("loop")
    with pytest.raises(OutputError) as info:
        plan.add(tmp_path / "loop" / "x", b"2", flag="--out")
    assert info.value.file == str(tmp_path / "loop" / "x") and str(info.value).startswith(f"{info.value.file}: --out ")


@pytest.mark.parametrize("name", ["boX", "cache ", "dir."])
def test_a_protected_tree_whose_name_ends_in_any_character(tmp_path, name):
    tree = tmp_path / name
    tree.mkdir()
    plan = OutputPlan()
    plan.protect_tree(tree, what="the cache")
    with pytest.raises(OutputError, match="inside the cache"):
        plan.add(tree / "x", b"x", flag="--out")


def test_the_filesystem_root_as_a_protected_tree_covers_everything(tmp_path):
    plan = OutputPlan()
    plan.protect_tree("/", what="everything")
    with pytest.raises(OutputError, match="inside everything"):
        plan.add(tmp_path / "x", b"x", flag="--out")


def test_missing_folders_are_made_at_any_depth(tmp_path):
    plan = OutputPlan()
    plan.add(tmp_path / "a" / "b" / "c" / "out", b"deep", flag="--out")
    plan.commit()
    assert (tmp_path / "a" / "b" / "c" / "out").read_bytes() == b"deep"


def test_outputs_are_staged_in_their_own_folder_not_in_the_temp_dir(tmp_path, monkeypatch):
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "no-such-tmp"))
    plan = OutputPlan()
    plan.add(tmp_path / "out", b"x", flag="--out")
    plan.commit()
    assert (tmp_path / "out").read_bytes() == b"x"


@contextlib.contextmanager
def small_disk():
    """While inside, files may grow to 4 KiB at most (RLIMIT_FSIZE): a write past it fails like a
    full disk. Kept to the one call under test: the limit applies to every file the process writes."""
    old_handler = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    old = resource.getrlimit(resource.RLIMIT_FSIZE)
    resource.setrlimit(resource.RLIMIT_FSIZE, (4096, old[1]))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, old)
        signal.signal(signal.SIGXFSZ, old_handler)


def test_a_full_disk_is_an_output_error_and_nothing_is_left(tmp_path):
    (tmp_path / "flat.hcdf").write_bytes(b"previous")
    plan = OutputPlan()
    plan.add(tmp_path / "flat.hcdf", b"f" * 100, flag="--out")
    plan.add(tmp_path / "x.lock", b"l" * 10_000, flag="--lock")
    with pytest.raises(OutputError) as info, small_disk():
        plan.commit()
    assert str(info.value).endswith(": File too large")
    assert "cannot write --lock" in str(info.value) and info.value.file == str(tmp_path / "x.lock")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["flat.hcdf"]
    assert (tmp_path / "flat.hcdf").read_bytes() == b"previous"


def test_a_full_disk_leaks_no_descriptor(tmp_path):
    before = len(os.listdir("/proc/self/fd"))
    for _ in range(5):
        plan = OutputPlan()
        plan.add(tmp_path / "x", b"l" * 10_000, flag="--out")
        with pytest.raises(OutputError), small_disk():
            plan.commit()
    assert len(os.listdir("/proc/self/fd")) == before
