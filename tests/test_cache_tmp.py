"""The cache's temporary folder: partial downloads of killed runs are removed, those of
live runs never are, and a cache that cannot be written is an input error.

A writer holds an ``flock`` on its temporary file until the blob is renamed into
place; the first blob a run stores sweeps ``tmp/`` of every file whose lock it can take.
The runs here are real processes, killed with SIGKILL mid-download from a loopback server.
"""

from __future__ import annotations

import fcntl
import hashlib
import os
import resource
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

import hcdf_trust.store as store_module
from hcdf_trust.store import PARTIAL_PREFIX, ContentStore


def sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def write_doc(path: Path, url: str, digest: str) -> Path:
    path.write_text(
        '<?xml version="1.0"?>\n<hcdf version="1.0" name="t">\n'
        f'<comp name="c"><visual><model uri="{url}" sha="{digest}"/></visual></comp>\n</hcdf>\n'
    )
    return path


def start(doc: Path, cache: Path, ca: Path, **kw) -> subprocess.Popen:
    """``hcdf-trust resolve DOC`` in its own process."""
    return subprocess.Popen(
        [sys.executable, "-m", "hcdf_trust.cli", "resolve", str(doc), "--ca-bundle", str(ca),
         "--cache-dir", str(cache), "--no-lock", "--timeout", "60"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        env={**os.environ, "PYTHONDONTWRITEBYTECODE": "1"}, **kw,
    )  # fmt: skip


def wait_for(predicate, *, timeout: float = 30.0, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out waiting for {what}")
        time.sleep(0.02)


def temp_files(cache: Path) -> list[Path]:
    tmp = cache / "tmp"
    return sorted(tmp.iterdir()) if tmp.is_dir() else []


@pytest.fixture
def small(https_server, tmp_path) -> Path:
    """A document whose one model is fetched quickly (what "the next run" downloads)."""
    data = os.urandom(2000)
    return write_doc(tmp_path / "small.hcdf", https_server.add("/small.glb", data), sha(data))


def _kill_mid_download(doc: Path, cache: Path, ca: Path) -> None:
    before = set(temp_files(cache))
    proc = start(doc, cache, ca)
    try:
        wait_for(
            lambda: any(p.stat().st_size >= 1 << 20 for p in temp_files(cache) if p not in before),
            what="the partial download",
        )
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.communicate()
    assert proc.returncode == -signal.SIGKILL


@pytest.fixture
def stalled(https_server, tmp_path) -> Path:
    body = os.urandom(4 << 20)
    url = https_server.stall("/big.glb", after=1 << 20, body=body)  # headers and 1 MiB, then silence
    return write_doc(tmp_path / "big.hcdf", url, sha(body))


def test_a_killed_download_is_removed_by_the_next_run(cli, tls, tmp_path, small, stalled):
    cache = tmp_path / "cache"
    _kill_mid_download(stalled, cache, tls.ca_pem)
    [left] = temp_files(cache)
    assert left.stat().st_size >= 1 << 20

    result = cli("resolve", small, "--ca-bundle", tls.ca_pem, "--cache-dir", cache, "--no-lock")
    assert result.exit_code == 0, result.stderr
    assert temp_files(cache) == []
    assert len(list((cache / "sha256").rglob("*"))) == 2  # the small blob and its fan-out folder


def test_ctrl_c_mid_download_exits_130_at_once_and_leaves_nothing(tls, tmp_path, stalled):
    """SIGINT while a worker thread waits on a silent server (60 s timeout): the run stops
    now, not when the worker times out, says so with exit 130 (not 1, an integrity
    failure), and leaves no partial download and no lock behind."""
    cache = tmp_path / "c"
    proc = start(stalled, cache, tls.ca_pem, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        wait_for(lambda: any(p.stat().st_size >= 1 << 20 for p in temp_files(cache)), what="the partial download")
        interrupted = time.monotonic()
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=20)
    finally:
        proc.kill()
    assert time.monotonic() - interrupted < 5, "the run waited for its worker threads"
    assert proc.returncode == 130, err
    assert "interrupted" in err and "Traceback" not in err
    assert temp_files(cache) == []
    assert not (stalled.parent / (stalled.name + ".lock")).exists()


def test_killed_downloads_do_not_pile_up(tls, tmp_path, stalled):
    """As in the issue: three killed fetches. Each run removes the one before it."""
    cache = tmp_path / "cache"
    for _ in range(3):
        _kill_mid_download(stalled, cache, tls.ca_pem)
    assert len(temp_files(cache)) == 1


def test_a_live_download_is_never_removed(cli, https_server, tls, tmp_path, small):
    """Run A drips its body for ~3 s; run B stores a blob (and sweeps) meanwhile.
    A's temporary file survives B, and A ends well with its blob in the cache."""
    body = os.urandom(60)
    doc = write_doc(tmp_path / "slow.hcdf", https_server.drip("/slow.glb", body, every=0.05), sha(body))
    cache = tmp_path / "cache"
    proc = start(doc, cache, tls.ca_pem)
    try:
        wait_for(lambda: len(temp_files(cache)) == 1, what="run A's temporary file")
        [live] = temp_files(cache)
        result = cli("resolve", small, "--ca-bundle", tls.ca_pem, "--cache-dir", cache, "--no-lock")
        assert result.exit_code == 0, result.stderr
        assert temp_files(cache) == [live]
        assert proc.poll() is None, "run A finished before run B swept: the test proves nothing"
    finally:
        _, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 0, stderr
    assert (cache / "sha256" / sha(body)[:2] / sha(body)).read_bytes() == body
    assert temp_files(cache) == []


def test_sweep_takes_only_unlocked_regular_files(tmp_path):
    store = ContentStore(tmp_path / "cache")
    tmp = store.tmp_dir
    tmp.mkdir(parents=True)
    (tmp / f"{PARTIAL_PREFIX}dead").write_bytes(b"partial")
    (tmp / f"{PARTIAL_PREFIX}live").write_bytes(b"being written")
    (tmp / f"{PARTIAL_PREFIX}folder").mkdir()
    outside = tmp_path / "outside"
    outside.write_bytes(b"not ours")
    (tmp / f"{PARTIAL_PREFIX}link").symlink_to(outside)  # named like ours, still not a file
    fd = os.open(tmp / f"{PARTIAL_PREFIX}live", os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)  # another open file description: the sweep cannot take it
        assert store.sweep_tmp() == 1
        assert sorted(p.name for p in tmp.iterdir()) == [f"{PARTIAL_PREFIX}{n}" for n in ("folder", "link", "live")]
    finally:
        os.close(fd)
    assert outside.read_bytes() == b"not ours"
    assert store.sweep_tmp() == 1  # the writer is gone: now it goes too
    assert ContentStore(tmp_path / "no-cache").sweep_tmp() == 0


def test_ingest_holds_the_lock_while_it_writes(tmp_path):
    store = ContentStore(tmp_path / "cache")
    seen = []

    def chunks():
        yield b"first"
        [tmp] = list(store.tmp_dir.iterdir())
        seen.append(store.sweep_tmp())  # a concurrent run's sweep, mid-download
        seen.append(tmp.exists())
        yield b"second"

    hashed, path = store.ingest(chunks())
    assert seen == [0, True]
    assert path is not None and path.read_bytes() == b"firstsecond" and hashed.sha256 == sha(b"firstsecond")
    assert list(store.tmp_dir.iterdir()) == []


def test_a_writer_whose_new_file_is_swept_before_it_locks_it_takes_another(tmp_path, monkeypatch):
    """The race between creating a temporary file and locking it: a concurrent sweep
    that wins it unlinks the file, and the writer must notice, not write into the void."""
    store = ContentStore(tmp_path / "cache")
    real_create = store_module.create_temp
    made: list[str] = []

    def create_then_sweep(*args, **kw):
        fd, name = real_create(*args, **kw)
        made.append(name)
        if len(made) == 1:
            assert store.sweep_tmp() == 1  # another run's sweep, between creating and flock
        return fd, name

    monkeypatch.setattr(store_module, "create_temp", create_then_sweep)
    hashed, path = store.ingest([b"first", b"second"])
    assert len(made) == 2
    assert path is not None and path.read_bytes() == b"firstsecond"
    assert list(store.tmp_dir.iterdir()) == []


# --- a cache that cannot be written ------------------------------------------------------


def test_a_full_cache_disk_is_an_input_error(https_server, tls, tmp_path):
    body = os.urandom(1 << 20)
    doc = write_doc(tmp_path / "big.hcdf", https_server.add("/m.glb", body), sha(body))
    cache = tmp_path / "cache"

    def limit() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (64 << 10, 64 << 10))

    proc = start(doc, cache, tls.ca_pem, preexec_fn=limit)
    _, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 3, stderr
    assert "cannot write to the cache" in stderr and "File too large" in stderr
    assert "Traceback" not in stderr
    assert temp_files(cache) == []
    assert not (cache / "sha256").exists()


def test_a_read_only_cache_is_an_input_error(cli, https_server, tls, tmp_path):
    data = os.urandom(3000)
    doc = write_doc(tmp_path / "m.hcdf", https_server.add("/m.glb", data), sha(data))
    cache = tmp_path / "cache"
    cache.mkdir()
    chattr = shutil.which("chattr")
    if os.geteuid() != 0:
        cache.chmod(0o555)
    elif chattr is None or subprocess.run([chattr, "+i", cache], capture_output=True).returncode:
        pytest.skip("running as root and chattr +i is not available here")
    try:
        result = cli("resolve", doc, "--ca-bundle", tls.ca_pem, "--cache-dir", cache, "--no-lock", "--json")
    finally:
        if os.geteuid() == 0:
            subprocess.run([chattr, "-i", cache], check=True)
        cache.chmod(0o755)
    assert result.exit_code == 3, result.stdout
    assert "cannot write to the cache" in result.json["errors"][0]["message"]
    assert list(cache.iterdir()) == []
