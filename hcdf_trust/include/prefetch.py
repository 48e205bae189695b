"""Hash the large local files the lock names while the rest of the run is still under way.

The lock of the last run lists every local artifact with its size. Hashing the large
ones can start as soon as the lock is read, on a thread per core, while the resolving
thread walks and parses the include tree (hashing releases the GIL; the walk is Python).
For a plain ``hcdf-trust resolve DOC`` the console script starts it even before the
CLI's own imports (:func:`start_early`: click and its dependencies take ~30 ms on one core).
Only when a core is free (:func:`idle_core`): on a busy machine it would slow the walk.

The resolver takes a result only for the very path and root it would hash itself,
hashed through a :class:`~hcdf_trust.localfile.ConfinedFolders` (the same confinement,
symlink and regular-file checks); everything else, and any file whose prefetch failed,
it hashes as usual and names the error. A lock that names other files than the tree
costs CPU, never a wrong result.
"""

from __future__ import annotations

import os
import sys
import threading
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

from ..digest import Hashed
from ..localfile import ConfinedFolders, absolute
from . import lockfile

# Local files at least this large are hashed on a thread per core (resolver._Run._plan).
PARALLEL_MIN_BYTES = 256 << 10
# The hashing threads wait for the GIL while the resolving thread runs Python: hand it over
# every 0.5 ms, not every 5 (1.07 GB robot, measured before this module: 0.59 s -> 0.53 s).
SWITCH_INTERVAL = 0.0005


def idle_core(threads: int) -> bool:
    """Is a core free for hashing ahead: fewer tasks runnable right now than ``threads``
    cores, this one included (/proc/loadavg)? Only then does it pay: on a busy machine the
    extra threads take the GIL from the walk (1 GB robot at load 4: 1.69 s -> 2.14 s)."""
    try:
        with open("/proc/loadavg", "rb") as f:
            running = int(f.read().split()[3].split(b"/")[0])
    except (OSError, ValueError, IndexError):
        return False
    return 1 < threads and running < threads


def lock_jobs(
    entries: Mapping[str, lockfile.LockEntry], lock_dir: str | os.PathLike[str], root: str
) -> list[tuple[int, str, str]]:
    """(size, path, root) of the lock's large local files that are not includes (read whole)."""
    return [
        (e.size, os.path.normpath(os.path.join(lock_dir, e.url)), root)
        for e in entries.values()
        if e.size >= PARALLEL_MIN_BYTES and e.kind != "include" and "://" not in e.url
    ]


class Prefetch:
    """Hash ``(size, path, root)`` jobs, largest first, on ``threads`` threads, from construction on."""

    def __init__(self, jobs: Iterable[tuple[int, str, str]], *, threads: int) -> None:
        ordered = sorted(jobs, key=lambda job: -job[0])
        self.paths = {(path, root) for _, path, root in ordered}
        self._folders = ConfinedFolders()
        self._jobs = iter(ordered)
        self._take = threading.Lock()
        self._stop = False
        self._results: dict[tuple[str, str], Hashed] = {}
        self._threads = [threading.Thread(target=self._work, daemon=True) for _ in range(min(threads, len(ordered)))]
        for thread in self._threads:
            thread.start()

    def _work(self) -> None:
        while not self._stop:
            with self._take:
                job = next(self._jobs, None)
            if job is None:
                return
            _, path, root = job
            try:
                self._results[(path, root)] = self._folders.hash(path, root)
            except Exception:  # noqa: BLE001, S112 -- the resolver hashes it again and reports what is wrong
                continue

    def result(self, path: str, root: str | os.PathLike[str]) -> Hashed | None:
        """The hash of ``path`` under ``root``, once every job is done; None if it was not
        prefetched or failed."""
        key = (path, os.fspath(root))
        if key not in self.paths:
            return None
        self.join()
        return self._results.get(key)

    def join(self) -> None:
        for thread in self._threads:
            thread.join()

    def stop(self) -> None:
        """Finish the files being hashed, start no other, close the folders."""
        self._stop = True
        self.join()
        self._folders.close()


# Started by start_early, for the resolver to adopt: (lock file, root, prefetch).
_early: tuple[str, str, Prefetch] | None = None
# Options of resolve and verify that change neither the lock, the root nor what is local.
_EARLY_FLAGS = frozenset({"--offline", "--json", "--no-lock", "--locked", "--strict", "--allow-http"})


def start_early(argv: Sequence[str]) -> None:
    """For ``hcdf-trust resolve|verify DOC`` with DOC's own lock and root and no option that
    changes them (a command line this simple check does not recognise only starts later,
    in the resolver), start the prefetch now, before the CLI's imports. Never raises."""
    global _early
    args = list(argv[1:])
    if os.path.basename(argv[0] if argv else "") != "hcdf-trust" or not args or args[0] not in ("resolve", "verify"):
        return
    positional, rest = [], iter(args[1:])
    for arg in rest:
        if arg == "--cache-dir":
            next(rest, None)
        elif arg not in _EARLY_FLAGS:
            if arg.startswith("-"):
                return
            positional.append(arg)
    threads = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    if len(positional) != 1 or not idle_core(threads):
        return
    try:
        doc = Path(absolute(positional[0]))
        lock = lockfile.default_path(doc)
        entries = lockfile.load(lock).entries if os.path.isfile(lock) else {}
        jobs = lock_jobs(entries, lock.parent, os.fspath(doc.parent))
    except Exception:  # noqa: BLE001 -- the resolver reads the lock again and reports what is wrong
        return
    if jobs:
        sys.setswitchinterval(min(sys.getswitchinterval(), SWITCH_INTERVAL))
        _early = (os.fspath(lock), os.fspath(doc.parent), Prefetch(jobs, threads=threads))


def take_early(lock: str | os.PathLike[str], root: str | os.PathLike[str]) -> Prefetch | None:
    """The prefetch :func:`start_early` started, if it was for this lock and root (else it is stopped)."""
    global _early
    early, _early = _early, None
    if early is None:
        return None
    if (early[0], early[1]) == (os.fspath(lock), os.fspath(root)):
        return early[2]
    early[2].stop()
    return None
