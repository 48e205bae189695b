"""include/prefetch.py: the lock's large files are hashed during the walk, with the resolver's own checks."""

from __future__ import annotations

import json
import os
import threading
from pathlib import Path

import pytest

import hcdf_trust.include.prefetch as prefetch_module
from hcdf_trust.include.prefetch import Prefetch
from hcdf_trust.include.resolver import PARALLEL_MIN_BYTES, ResolveOptions, resolve
from hcdf_trust.localfile import ConfinedFolders

from ._kill import hcdf, include, model, sha

BIG = PARALLEL_MIN_BYTES


def _tree(tmp_path: Path) -> Path:
    """robot.hcdf: two large models, one small, an include with one more large model."""
    root = tmp_path / "robot"
    (root / "m").mkdir(parents=True)
    files = {f"m/big{i}.glb": bytes([i]) * (BIG + i) for i in range(3)}
    files["m/small.glb"] = b"small"
    for rel, data in files.items():
        (root / rel).write_bytes(data)
    sub = root / "sub.hcdf"
    sub.write_text(hcdf(model("m/big2.glb", sha(files["m/big2.glb"]))))
    body = [model(rel, sha(data), name=rel) for rel, data in files.items() if rel != "m/big2.glb"]
    body.append(include("sub.hcdf", sha(sub.read_bytes())))
    doc = root / "robot.hcdf"
    doc.write_text(hcdf("\n".join(body)))
    return doc


@pytest.fixture
def taken(monkeypatch):
    """Every Prefetch.result the resolver asked for: (path, whether it had a result)."""
    calls: list[tuple[str, bool]] = []
    real = Prefetch.result

    def spy(self, path, root):
        got = real(self, path, root)
        calls.append((Path(path).name, got is not None))
        return got

    monkeypatch.setattr(Prefetch, "result", spy)
    return calls


def test_the_locks_large_files_are_prefetched_and_the_lock_is_the_same(tmp_path, taken):
    doc = _tree(tmp_path)
    first = resolve(doc, ResolveOptions(cache_dir=str(tmp_path / "c")))  # no lock yet: nothing to prefetch
    assert first.ok and not taken
    first.write_lock()
    lock = doc.with_name("robot.hcdf.lock").read_bytes()
    again = resolve(doc, ResolveOptions(cache_dir=str(tmp_path / "c")))
    assert again.ok, again.errors
    assert sorted(name for name, hit in taken if hit) == ["big0.glb", "big1.glb", "big2.glb"]  # not the small one
    assert again.render_lock() == lock
    serial = resolve(doc, ResolveOptions(cache_dir=str(tmp_path / "c"), jobs=1))  # --jobs 1: no threads at all
    assert serial.render_lock() == lock and sum(hit for _, hit in taken) == 3


def test_a_file_changed_since_the_lock_is_still_drift(tmp_path):
    doc = _tree(tmp_path)
    resolve(doc, ResolveOptions(cache_dir=str(tmp_path / "c"))).write_lock()
    # the document names no sha for it: the lock is its pin
    (doc.parent / "m" / "big0.glb").write_bytes(b"\x07" * BIG)
    doc.write_text(doc.read_text().replace(f'sha="{sha(bytes([0]) * BIG)}"', ""))
    res = resolve(doc, ResolveOptions(cache_dir=str(tmp_path / "c")))
    [err] = res.errors
    assert err.code == "lock-drift" and err.actual == sha(b"\x07" * BIG)


def test_a_lock_naming_files_outside_the_root_reads_none_of_them(tmp_path, monkeypatch):
    """A hostile lock: its entries go through the same confinement as references."""
    doc = _tree(tmp_path)
    resolve(doc, ResolveOptions(cache_dir=str(tmp_path / "c"))).write_lock()
    secret = tmp_path / "secret.glb"
    secret.write_bytes(b"s" * BIG)
    (doc.parent / "m" / "link.glb").symlink_to(secret)
    lock_path = doc.with_name("robot.hcdf.lock")
    lock = json.loads(lock_path.read_text())
    for url in ("../secret.glb", "m/link.glb"):
        lock["artifacts"].append(
            {
                "kind": "model",
                "uri": url,
                "url": url,
                "sha256": "0" * 64,
                "size": BIG,
                "referenced_from": ["robot.hcdf"],
            }
        )
    lock_path.write_text(json.dumps(lock))
    hashed = []
    real = ConfinedFolders.hash
    monkeypatch.setattr(ConfinedFolders, "hash", lambda self, p, r, **kw: hashed.append(p) or real(self, p, r, **kw))
    results = []
    real_work = Prefetch._work

    def work(self):
        real_work(self)
        results.append(dict(self._results))

    monkeypatch.setattr(Prefetch, "_work", work)
    res = resolve(doc, ResolveOptions(cache_dir=str(tmp_path / "c")))
    assert res.ok, res.errors  # both extra entries are simply no longer referenced
    assert str(secret) in hashed and str(doc.parent / "m" / "link.glb") in hashed  # tried...
    assert all(Path(path).name not in ("secret.glb", "link.glb") for r in results for path, _ in r)  # ...refused


def test_prefetch_results_follow_confined_folders(tmp_path):
    root = tmp_path / "robot"
    root.mkdir()
    (root / "a.glb").write_bytes(b"a" * 10)
    (root / "fifo").parent.mkdir(exist_ok=True)
    os.mkfifo(root / "fifo")
    (tmp_path / "out.glb").write_bytes(b"o")
    folders = ConfinedFolders()
    jobs = [
        (10, str(root / "a.glb"), str(root)),
        (1, str(root / "fifo"), str(root)),
        (1, str(tmp_path / "out.glb"), str(root)),
    ]
    pre = Prefetch(folders, jobs, threads=2)
    try:
        got = pre.result(str(root / "a.glb"), root)
        assert got is not None and got.sha256 == sha(b"a" * 10)
        assert pre.result(str(root / "fifo"), root) is None
        assert pre.result(str(tmp_path / "out.glb"), root) is None
        assert pre.result(str(root / "a.glb"), tmp_path) is None  # another root: not this job
        assert pre.result(str(root / "none.glb"), root) is None
    finally:
        pre.stop()
        folders.close()


def test_stop_lets_no_thread_run_past_it(tmp_path, monkeypatch):
    """The run closes its folder descriptors after stop(): no prefetch thread may still use them."""
    started, release = threading.Event(), threading.Event()
    real = ConfinedFolders.hash

    def slow(self, path, root, **kw):
        started.set()
        release.wait(5)
        return real(self, path, root, **kw)

    monkeypatch.setattr(ConfinedFolders, "hash", slow)
    (tmp_path / "a").write_bytes(b"a")
    folders = ConfinedFolders()
    pre = Prefetch(folders, [(1, str(tmp_path / "a"), str(tmp_path))] * 50, threads=2)
    assert started.wait(5)
    threading.Timer(0.2, release.set).start()
    pre.stop()
    assert not any(t.is_alive() for t in pre._threads)
    folders.close()


def test_the_prefetch_module_needs_no_thread_pool():
    assert "concurrent" not in prefetch_module.__dict__
