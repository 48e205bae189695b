"""Helpers shared by the hostile-input suites (tests/test_hostile_*.py, tests/test_property.py).

Every hostile case must end in a clear error, in bounded time and memory, without
touching the network and without writing anything. These helpers make each of
those four properties a one-line assertion.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import os
import socket
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from hcdf_trust.include import lockfile

HOSTILE_COMMANDS = ("resolve", "verify", "validate", "pin")


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def snapshot(*roots: Path) -> dict[str, tuple[str, int, int]]:
    """Every path under ``roots`` with its type, size and mtime: "nothing written" is equality."""
    out: dict[str, tuple[str, int, int]] = {}
    for root in roots:
        if not os.path.lexists(root):
            continue
        for dirpath, dirnames, filenames in os.walk(root, followlinks=False):
            for name in dirnames + filenames:
                p = os.path.join(dirpath, name)
                st = os.lstat(p)
                kind = "link" if os.path.islink(p) else "dir" if os.path.isdir(p) else "file"
                out[p] = (kind, st.st_size, st.st_mtime_ns)
    return out


def command_args(command: str, doc: Path, work: Path, *extra: str) -> list[str]:
    """The arguments that make ``command`` read ``doc`` and would make it write if it could."""
    cache = str(work / "cache")
    if command == "resolve":
        return ["resolve", str(doc), "--offline", "--cache-dir", cache, "--out", str(work / "flat.hcdf"), *extra]
    if command == "verify":
        return ["verify", str(doc), "--cache-dir", cache, *extra]
    if command == "pin":
        return ["pin", str(doc), "--write", "--offline", "--cache-dir", cache, *extra]
    if command == "validate":
        return ["validate", str(doc), *extra]
    raise ValueError(command)


def write_lock(lock_path: Path, root: str, entries: list[dict]) -> None:
    """A lock file as ``resolve`` would write it, for trees resolve refuses to lock."""
    items = [
        lockfile.LockEntry(
            kind=e.get("kind", "include"),
            uri=e["uri"],
            url=e.get("url", e["uri"]),
            sha256=e["sha256"],
            size=e["size"],
            referenced_from=tuple(e.get("referenced_from", ())),
        )
        for e in entries
    ]
    lock_path.write_bytes(lockfile.render(items, root=root))


# --- no network --------------------------------------------------------------------


@dataclass
class NetworkGuard:
    attempts: list[str] = field(default_factory=list)


@pytest.fixture
def no_network(monkeypatch) -> Iterator[NetworkGuard]:
    """Fail the test if Python code tries to resolve a name or open a connection."""
    guard = NetworkGuard()

    def refuse(*args, **kwargs):
        guard.attempts.append(repr(args[:2]))
        raise OSError(errno.ENETUNREACH, "network access is forbidden in hostile-input tests")

    monkeypatch.setattr(socket.socket, "connect", refuse)
    monkeypatch.setattr(socket.socket, "connect_ex", refuse)
    monkeypatch.setattr(socket, "create_connection", refuse)
    monkeypatch.setattr(socket, "getaddrinfo", refuse)
    yield guard
    assert guard.attempts == [], f"the tool tried to use the network: {guard.attempts}"


class LoopbackListener:
    """A listening socket on 127.0.0.1 that we own: anything that connects is caught.

    libxml2 opens its sockets in C, below any Python patch; this catches those too
    (the kernel completes the handshake into the accept queue even if nobody accepts).
    """

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(16)
        self.sock.setblocking(False)
        self.port = self.sock.getsockname()[1]

    def url(self, path: str) -> str:
        return f"http://127.0.0.1:{self.port}/{path}"

    def connections(self) -> int:
        n = 0
        while True:
            try:
                conn, _ = self.sock.accept()
            except BlockingIOError:
                return n
            conn.close()
            n += 1

    def close(self) -> None:
        self.sock.close()


@pytest.fixture
def listener() -> Iterator[LoopbackListener]:
    lst = LoopbackListener()
    yield lst
    lst.close()


# --- no hang ----------------------------------------------------------------------


@contextlib.contextmanager
def fifo_watchdog(fifo: Path, seconds: float = 5.0) -> Iterator[dict]:
    """Run the body; if it is still running after ``seconds``, it is blocked on ``fifo``:
    give it a writer that closes at once (EOF) so the test finishes, and record the hang."""
    state = {"hung": False, "elapsed": 0.0}
    done = threading.Event()

    def release() -> None:
        if done.wait(seconds):
            return
        state["hung"] = True
        while not done.is_set():
            try:
                fd = os.open(fifo, os.O_WRONLY | os.O_NONBLOCK)
            except OSError:  # ENXIO: nobody is reading right now
                time.sleep(0.02)
                continue
            os.close(fd)
            time.sleep(0.02)

    thread = threading.Thread(target=release, daemon=True)
    thread.start()
    started = time.monotonic()
    try:
        yield state
    finally:
        state["elapsed"] = time.monotonic() - started
        done.set()
        thread.join()
