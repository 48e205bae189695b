"""store.py: atomic writes and the content-addressed cache (mutation-testing killers)."""

from __future__ import annotations

import contextlib
import os
import resource
import signal
import stat
from pathlib import Path

import pytest

from hcdf_trust.errors import FetchError, InputError
from hcdf_trust.store import ContentStore, default_cache_dir, fsync_dir

from ._kill import sha


def _mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def _leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.endswith(".tmp"))


def test_fsync_dir_tolerates_a_missing_folder(tmp_path):
    fsync_dir(tmp_path / "missing")  # best effort: no exception
    fsync_dir(tmp_path)


# -- the default cache folder ----------------------------------------------------------


def test_default_cache_dir_follows_xdg_then_home(monkeypatch, tmp_path):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert default_cache_dir() == tmp_path / "xdg" / "hcdf-trust"
    monkeypatch.setenv("XDG_CACHE_HOME", "")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert default_cache_dir() == tmp_path / "home" / ".cache" / "hcdf-trust"
    monkeypatch.delenv("XDG_CACHE_HOME")
    assert default_cache_dir() == tmp_path / "home" / ".cache" / "hcdf-trust"


# -- ContentStore ----------------------------------------------------------------------


def test_path_for_is_the_fan_out_layout_and_refuses_non_digests(tmp_path):
    store = ContentStore(tmp_path)
    d = sha(b"x")
    assert store.path_for(d) == tmp_path / "sha256" / d[:2] / d
    for bad in (d[:63], d.upper(), "g" * 64, d + "0"):
        with pytest.raises(ValueError, match="not a full lower-case SHA-256"):
            store.path_for(bad)


def test_ingest_stores_a_read_only_blob_under_its_digest(tmp_path):
    store = ContentStore(tmp_path / "cache")
    data = os.urandom(3 << 20)
    hashed, path = store.ingest(iter([data[:100], data[100:]]))
    assert (hashed.sha256, hashed.size) == (sha(data), len(data))
    assert path == store.path_for(sha(data)) and path.read_bytes() == data
    assert _mode(path) == 0o444
    assert store.has(sha(data)) and store.verified_path(sha(data)) == path
    assert list((tmp_path / "cache" / "tmp").iterdir()) == []


def test_ingest_writes_its_partial_file_in_the_caches_own_tmp_folder(tmp_path):
    store = ContentStore(tmp_path / "cache")
    seen: list[list[Path]] = []

    def chunks():
        yield b"part one"
        seen.append(list((tmp_path / "cache" / "tmp").iterdir()))
        yield b"part two"

    store.ingest(chunks())
    [[partial]] = seen
    assert partial.parent == tmp_path / "cache" / "tmp"
    assert list((tmp_path / "cache" / "tmp").iterdir()) == []


def test_ingest_refused_by_accept_stores_nothing(tmp_path):
    store = ContentStore(tmp_path / "cache")
    offered = []

    def accept(h):
        offered.append(h)
        return False

    hashed, path = store.ingest([b"wrong"], accept=accept)
    assert path is None and hashed.sha256 == sha(b"wrong") and offered == [hashed]
    assert not store.has(sha(b"wrong"))
    assert list((tmp_path / "cache" / "tmp").iterdir()) == []
    hashed, path = store.ingest([b"right"], accept=lambda h: True)
    assert path is not None and path.read_bytes() == b"right"


def test_ingest_over_the_limit_is_a_fetch_error_naming_the_source_and_stores_nothing(tmp_path):
    store = ContentStore(tmp_path / "cache")
    assert store.ingest([b"12345"], limit=5)[1] is not None
    with pytest.raises(FetchError) as info:
        store.ingest([b"123", b"456"], limit=5, source="https://h.example/a.glb")
    err = info.value
    assert err.file == err.url == "https://h.example/a.glb" and "5-byte limit" in str(err)
    assert not store.has(sha(b"123456"))
    assert list((tmp_path / "cache" / "tmp").iterdir()) == []


def test_ingest_that_fails_mid_stream_leaves_nothing(tmp_path):
    store = ContentStore(tmp_path / "cache")

    def chunks():
        yield b"half"
        raise ConnectionError("reset")

    with pytest.raises(ConnectionError):
        store.ingest(chunks())
    assert list((tmp_path / "cache" / "tmp").iterdir()) == []
    assert not (tmp_path / "cache" / "sha256").exists() or not any((tmp_path / "cache" / "sha256").rglob("*"))


def test_ingest_into_a_planted_directory_is_an_input_error(tmp_path):
    store = ContentStore(tmp_path / "cache")
    dest = store.path_for(sha(b"blob"))
    (dest / "inner").mkdir(parents=True)
    with pytest.raises(InputError, match="cannot store cache blob") as info:
        store.ingest([b"blob"])
    assert info.value.file == str(dest)
    assert list((tmp_path / "cache" / "tmp").iterdir()) == []


def test_verified_path_drops_a_tampered_blob_only_when_repairing(tmp_path):
    store = ContentStore(tmp_path / "cache")
    _, path = store.ingest([b"good"])
    assert path is not None
    os.chmod(path, 0o644)
    path.write_bytes(b"evil")
    assert store.verified_path(sha(b"good"), repair=False) is None
    assert path.exists()
    assert store.verified_path(sha(b"good")) is None
    assert not path.exists()
    assert store.verified_path(sha(b"good")) is None  # missing


def test_verified_path_refuses_non_regular_blobs_without_hanging(tmp_path):
    store = ContentStore(tmp_path / "cache")
    fifo = store.path_for(sha(b"f"))
    fifo.parent.mkdir(parents=True)
    os.mkfifo(fifo)
    assert store.verified_path(sha(b"f"), repair=False) is None
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode)
    folder = store.path_for(sha(b"d"))
    folder.mkdir(parents=True)
    assert store.verified_path(sha(b"d")) is None and not store.has(sha(b"d"))


def test_verified_path_of_a_large_blob(tmp_path):
    store = ContentStore(tmp_path / "cache")
    data = os.urandom((2 << 20) + 1)
    _, path = store.ingest([data])
    assert store.verified_path(sha(data)) == path


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


def test_ingest_on_a_full_disk_leaves_nothing(tmp_path):
    store = ContentStore(tmp_path / "cache")
    with pytest.raises(OSError), small_disk():
        store.ingest([b"x" * 3000, b"y" * 3000])
    assert list((tmp_path / "cache" / "tmp").iterdir()) == []
