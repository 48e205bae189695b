"""OutputPlan.commit's fsyncs: the staged files are fsynced together, every folder that
changed (and every folder that holds a folder the commit made) once, and a failed fsync
leaves every destination as it was."""

from __future__ import annotations

import errno
import os
import stat
import threading
from pathlib import Path

import pytest

import hcdf_trust.outputs as outputs
from hcdf_trust.outputs import OutputError, OutputPlan

from .test_outputs import contents


def _is_file(fd: int) -> bool:
    return stat.S_ISREG(os.fstat(fd).st_mode)


def test_the_staged_files_are_fsynced_together(tmp_path, monkeypatch):
    """Two fsyncs must be in progress at once to pass the barrier: one file at a time
    (each fsync waiting for the previous one) breaks it."""
    real = os.fsync
    barrier = threading.Barrier(2, timeout=10)

    def fsync(fd: int) -> None:
        if _is_file(fd):
            barrier.wait()
        real(fd)

    monkeypatch.setattr(os, "fsync", fsync)
    plan = OutputPlan()
    plan.add(tmp_path / "a" / "one.bin", b"1" * 4096, flag="--out")
    plan.add(tmp_path / "b" / "two.bin", b"2" * 4096, flag="--out")
    plan.commit()
    assert (tmp_path / "a" / "one.bin").read_bytes() == b"1" * 4096
    assert (tmp_path / "b" / "two.bin").read_bytes() == b"2" * 4096


def test_each_changed_folder_is_fsynced_once_with_the_parents_of_new_folders(tmp_path, monkeypatch):
    synced: list[Path] = []
    monkeypatch.setattr(outputs, "fsync_dir", synced.append)
    plan = OutputPlan()
    for name in ("x.bin", "y.bin", "latest.json"):
        plan.add(tmp_path / "new" / "deeper" / name, b"x", flag="--out")
    plan.add(tmp_path / "top.json", b"t", flag="--out")
    plan.commit()
    # deeper and tmp_path hold renamed files; new holds the new folder deeper; tmp_path the new folder new
    assert sorted(synced) == sorted([tmp_path, tmp_path / "new", tmp_path / "new" / "deeper"])


def test_a_failed_fsync_writes_nothing_and_names_the_file(tmp_path, monkeypatch):
    old = tmp_path / "rel" / "first.json"
    old.parent.mkdir()
    old.write_bytes(b"old")
    real = os.fsync

    def fsync(fd: int) -> None:
        if _is_file(fd) and os.readlink(f"/proc/self/fd/{fd}").split("/")[-1].startswith(".second.bin."):
            raise OSError(errno.EIO, os.strerror(errno.EIO))
        real(fd)

    monkeypatch.setattr(os, "fsync", fsync)
    plan = OutputPlan()
    plan.add(old, b"new", flag="--first")
    plan.add(tmp_path / "rel" / "sub" / "second.bin", b"2", flag="--second")
    plan.add(tmp_path / "rel" / "third.bin", b"3", flag="--third")
    before = contents(tmp_path)
    with pytest.raises(OutputError, match=r"cannot write --second .*second.bin: Input/output error"):
        plan.commit()
    assert contents(tmp_path) == before  # no temporary file, no new folder, first.json untouched


def test_more_outputs_than_are_held_open_at_once(tmp_path, monkeypatch):
    monkeypatch.setattr(outputs, "_OPEN_AT_ONCE", 3)
    plan = OutputPlan()
    for i in range(8):
        plan.add(tmp_path / f"d{i % 2}" / f"{i}.bin", bytes([i]) * 10, flag="--out")
    plan.commit()
    assert sorted(p.name for p in tmp_path.rglob("*") if p.is_file()) == sorted(f"{i}.bin" for i in range(8))
    assert all((tmp_path / f"d{i % 2}" / f"{i}.bin").read_bytes() == bytes([i]) * 10 for i in range(8))


def test_file_content_is_copied_hashed_and_refused_when_changed(tmp_path):
    """FileContent (ota pull's staged blobs): copied chunk by chunk at commit, never held whole;
    a source whose bytes are no longer the ones verified fails the commit with nothing written."""
    import hashlib

    from hcdf_trust.errors import IntegrityError
    from hcdf_trust.outputs import FileContent

    data = os.urandom(3 << 20)  # several copy chunks
    src = tmp_path / "blob"
    src.write_bytes(data)
    good = FileContent(str(src), len(data), hashlib.sha256(data).hexdigest())
    plan = OutputPlan()
    plan.add(tmp_path / "out" / "a.bin", good, flag="--out", under=tmp_path / "out")
    plan.add(tmp_path / "out" / "b.txt", b"small", flag="--out", under=tmp_path / "out")
    plan.commit()
    assert (tmp_path / "out" / "a.bin").read_bytes() == data
    for changed in (data[:-1] + bytes([data[-1] ^ 1]), data + b"x", data[:-1]):
        src.write_bytes(changed)
        plan = OutputPlan()
        plan.add(tmp_path / "out2" / "b.txt", b"small", flag="--out", under=tmp_path / "out2")
        plan.add(tmp_path / "out2" / "a.bin", good, flag="--out", under=tmp_path / "out2")
        with pytest.raises(IntegrityError, match="changed after it was verified"):
            plan.commit()
        assert not (tmp_path / "out2").exists()
    with pytest.raises(ValueError):
        OutputPlan().add(tmp_path / "x", good, flag="--out", if_changed=True)
