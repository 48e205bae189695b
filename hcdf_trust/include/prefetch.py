"""Hash the large local files the lock names while the tree is still being walked.

The lock of the last run lists every local artifact with its size. Hashing the large
ones can start as soon as the lock is read, on a thread per core, while the resolving
thread parses documents and collects references (hashing releases the GIL; the walk
is Python). The resolver takes a result only for the very path and root it would hash
itself, hashed through the same :class:`~hcdf_trust.localfile.ConfinedFolders` (the
same confinement, symlink and regular-file checks); everything else, and any file
whose prefetch failed, it hashes as usual and names the error. A lock that names
other files than the tree costs CPU, never a wrong result.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Iterable

from ..digest import Hashed
from ..localfile import ConfinedFolders


class Prefetch:
    """Hash ``(path, root)`` jobs, largest first, on ``threads`` threads, from construction on."""

    def __init__(self, folders: ConfinedFolders, jobs: Iterable[tuple[int, str, str]], *, threads: int) -> None:
        """``jobs``: (size hint, normalised absolute path, confinement root)."""
        ordered = sorted(jobs, key=lambda job: -job[0])
        self.paths = {(path, root) for _, path, root in ordered}
        self._folders = folders
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
        """Finish the files being hashed, start no other (before the folders are closed)."""
        self._stop = True
        self.join()
