"""Attack: the lock file's name is a dangling symlink."""

from __future__ import annotations

import os
import shutil

from .conftest import PROJECT


def test_a_dangling_symlink_lock_is_refused_naming_the_link(cli, tmp_path, monkeypatch):
    shutil.copytree(PROJECT / "examples" / "robot", tmp_path / "robot")
    monkeypatch.chdir(tmp_path / "robot")
    os.unlink("robot.hcdf.lock")
    os.symlink("nowhere.lock", "robot.hcdf.lock")
    for args in (("resolve", "robot.hcdf"), ("verify", "robot.hcdf"), ("pin", "robot.hcdf")):
        r = cli(*args)
        assert r.exit_code == 3, r.stderr
        (line,) = [ln for ln in r.stderr.splitlines() if ln.startswith("error:")]
        # Not "does not exist (run resolve without --locked first)": plain resolve was run.
        assert "robot.hcdf.lock is a symlink to 'nowhere.lock', which does not exist" in line, line
        assert os.readlink("robot.hcdf.lock") == "nowhere.lock"  # left as it was


def test_the_cache_sweep_removes_only_its_own_partial_downloads(tmp_path):
    """--cache-dir ~ (or /) makes tmp/ a folder of the user's: the sweep must leave their files."""
    from hcdf_trust.store import ContentStore

    home = tmp_path / "home"
    (home / "tmp").mkdir(parents=True)
    (home / "tmp" / "notes.txt").write_text("mine")
    (home / "tmp" / "tmpabcd1234").write_text("mine too")
    store = ContentStore(home)
    _, path = store.ingest([b"blob"])
    assert path is not None and path.read_bytes() == b"blob"
    assert sorted(p.name for p in (home / "tmp").iterdir()) == ["notes.txt", "tmpabcd1234"]
