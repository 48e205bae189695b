"""The content-addressed cache; the new temporary file and the folder fsync that every write uses.

A blob is written to a temporary file in the cache, checked, then renamed. Every
other output (lock file, flattened document, later images, manifests and key
stores) goes through :class:`hcdf_trust.outputs.OutputPlan`.
"""

from __future__ import annotations

import contextlib
import errno
import os
import stat
import threading
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import BinaryIO

from .digest import Hashed, Sha256, hash_chunks, hash_fd, is_full_sha256
from .errors import FetchError, InputError
from .flock import flock

_NEW_FILE = os.O_RDWR | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC


def create_temp(
    folder: str | os.PathLike[str], prefix: str, suffix: str = "", *, dir_fd: int | None = None
) -> tuple[int, str]:
    """A new empty file ``folder/prefix<random>suffix``, mode 0600: its descriptor (read-write,
    close-on-exec) and absolute path. With ``dir_fd`` (an open descriptor of ``folder``), the
    file is made in that very folder, whatever ``folder`` names by now, and the name alone is returned.

    What ``tempfile.mkstemp`` guarantees (``O_CREAT | O_EXCL | O_NOFOLLOW``: never an
    existing file, never through a symlink planted at the name; another random name on a
    collision) without importing tempfile, which brings shutil, random, bz2 and lzma
    (~4 ms of every run's start-up).

    Raises:
        OSError: as ``os.open`` (FileNotFoundError: ``folder`` does not exist).
    """
    folder = os.path.abspath(folder)
    for _ in range(100):
        name = f"{prefix}{os.urandom(6).hex()}{suffix}"
        try:
            if dir_fd is not None:
                return os.open(name, _NEW_FILE, 0o600, dir_fd=dir_fd), name
            path = os.path.join(folder, name)
            return os.open(path, _NEW_FILE, 0o600), path
        except FileExistsError:
            continue
    raise FileExistsError(errno.EEXIST, "no unused temporary file name", folder)


def fsync_dir(directory: Path) -> None:
    """Make a rename in ``directory`` durable (best effort: some filesystems refuse)."""
    try:
        fd = os.open(directory, os.O_RDONLY | os.O_DIRECTORY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


# The names of the cache's temporary files: the sweep removes nothing else, so a
# --cache-dir that is not a cache of ours (~, /) never loses a file of tmp/ to it.
PARTIAL_PREFIX = ".hcdf-trust-partial-"


def default_cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "hcdf-trust"


class ContentStore:
    """Blobs named by their SHA-256, verified on the way in and on the way out.

    Layout: ``ROOT/sha256/ab/abcdef…``. A blob is only ever created by renaming
    a fully written temporary file (in ``ROOT/tmp``) whose digest was checked, so a
    crash or a mismatch never leaves a partial or wrong entry. The writer holds an
    ``flock`` on its temporary file until it is renamed or removed, so the partial
    downloads of killed runs can be told from those of live ones and are removed
    (:meth:`sweep_tmp`, on the first blob a run stores); the cache may be shared by
    concurrent runs.
    """

    def __init__(self, root: str | os.PathLike[str]) -> None:
        self.root = Path(root)
        self._blobs = self.root / "sha256"
        self._swept = False
        self._sweep_lock = threading.Lock()
        self._writing: set[str] = set()  # temporary files this process's threads are writing

    @property
    def tmp_dir(self) -> Path:
        return self.root / "tmp"

    def path_for(self, sha256: str) -> Path:
        if not is_full_sha256(sha256):
            raise ValueError(f"not a full lower-case SHA-256: {sha256!r}")
        return self._blobs.joinpath(sha256[:2], sha256)  # one join, not three: ~6 µs less per blob

    def has(self, sha256: str) -> bool:
        return self.path_for(sha256).is_file()

    def verified_path(self, sha256: str, *, repair: bool = True) -> Path | None:
        """The blob's path if present and its content still hashes to its name.

        A blob that no longer matches (tampered, bit rot) is never returned; with
        ``repair`` it is also removed, so the next fetch can replace it (``verify``,
        which writes nothing, passes ``repair=False``).
        """
        path = self.path_for(sha256)
        try:
            # O_NONBLOCK: a FIFO planted in the cache must not hang us; only a
            # regular file can be a blob (a directory or device is not one).
            fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
        except OSError:  # missing, unreadable, a symlink loop: not usable
            return None
        try:
            st = os.fstat(fd)
            # straight from the descriptor (no file object; a small blob in one read)
            actual = hash_fd(fd, size=st.st_size).sha256 if stat.S_ISREG(st.st_mode) else None
        finally:
            os.close(fd)
        if actual != sha256:
            if repair:
                with contextlib.suppress(OSError):
                    path.unlink()
            return None
        return path

    def sweep_tmp(self) -> int:
        """Remove the temporary files no live run is writing (left by killed runs).

        A file whose ``flock`` can be taken has no writer: it is unlinked while the
        lock is held, so a writer that was about to lock it sees it gone and starts
        another (:meth:`_new_tmp`). Only regular files named by :data:`PARTIAL_PREFIX`
        are touched. Returns how many were removed; never raises.
        """
        try:
            names = os.listdir(self.tmp_dir)
        except OSError:
            return 0
        removed = 0
        for name in names:
            if not name.startswith(PARTIAL_PREFIX):
                continue  # not one of ours
            path = self.tmp_dir / name
            try:
                fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC)
            except OSError:
                continue
            try:
                st = os.fstat(fd)
                if not stat.S_ISREG(st.st_mode):
                    continue
                flock(fd, wait=False)  # OSError (EWOULDBLOCK): a live writer
                now = os.lstat(path)  # still the file we locked, not one renamed over its name?
                if (now.st_dev, now.st_ino) == (st.st_dev, st.st_ino):
                    os.unlink(path)
                    removed += 1
            except OSError:
                continue
            finally:
                os.close(fd)
        return removed

    def abandon(self) -> None:
        """Remove the temporary files still being written (an interrupted run): their
        writer threads die with the process and would leave them to the next sweep."""
        for tmp in list(self._writing):
            with contextlib.suppress(OSError):
                os.unlink(tmp)

    def _sweep_once(self) -> None:
        with self._sweep_lock:
            if self._swept:
                return
            self._swept = True
        self.sweep_tmp()

    def _new_tmp(self) -> tuple[int, str]:
        """A new temporary file in ``tmp/``, created and then locked for this writer."""
        while True:
            try:
                fd, tmp = create_temp(self.tmp_dir, PARTIAL_PREFIX)
            except FileNotFoundError:  # first blob of a new cache: one mkdir, not one per blob
                self.tmp_dir.mkdir(parents=True, exist_ok=True)
                fd, tmp = create_temp(self.tmp_dir, PARTIAL_PREFIX)
            # Blocks only while a sweeper that opened it first holds the lock; it then
            # unlinks it, and we see no link left and start over.
            flock(fd)
            if os.fstat(fd).st_nlink:
                return fd, tmp
            os.close(fd)

    def ingest(
        self,
        chunks: Iterable[bytes],
        *,
        accept: Callable[[Hashed], bool] | None = None,
        limit: int | None = None,
        source: str = "",
        sha256: Sha256 | None = None,
    ) -> tuple[Hashed, Path | None]:
        """Copy ``chunks`` into the store, hashing as they pass (through ``sha256`` when given,
        see :func:`~hcdf_trust.digest.hash_chunks`).

        ``accept`` sees the digest before the blob is committed; if it returns
        False (a pin mismatch) nothing is stored and the path is ``None``.

        Raises:
            FetchError: more than ``limit`` bytes.
            InputError: the cache cannot be written (read-only, full disk...).
        """
        self._sweep_once()
        try:
            fd, tmp = self._new_tmp()
        except OSError as exc:
            raise InputError(f"cannot write to the cache {self.tmp_dir}: {exc.strerror}", file=source) from None
        self._writing.add(tmp)
        try:
            # The file stays open (and locked) until it is renamed or removed.
            with os.fdopen(fd, "wb") as f:
                sink = _Copy(f)
                try:
                    hashed = hash_chunks(chunks, sink=sink, limit=limit, sha256=sha256)
                    sink.flush()
                except ValueError as exc:
                    raise FetchError(f"body {exc}", file=source, url=source) from None
                except _WriteFailed as exc:  # ENOSPC, EFBIG, EIO while writing the copy
                    raise InputError(f"cannot write to the cache {tmp}: {exc.reason}", file=source) from None
                # No fsync: a blob torn by a crash no longer hashes to its name, and
                # verified_path() re-hashes on every read, so it is dropped and fetched
                # again. Skipping it makes many small fetches ~2x faster (fsync per blob
                # was the largest client cost in the 200-file latency test).
                if accept is not None and not accept(hashed):
                    os.unlink(tmp)
                    return hashed, None
                dest = self.path_for(hashed.sha256)
                try:
                    os.fchmod(f.fileno(), 0o444)
                    try:
                        os.replace(tmp, dest)
                    except FileNotFoundError:  # the blob's fan-out folder is new
                        dest.parent.mkdir(parents=True, exist_ok=True)
                        os.replace(tmp, dest)
                except OSError as exc:  # e.g. a directory planted where the blob goes
                    raise InputError(f"cannot store cache blob {dest}: {exc.strerror}", file=str(dest)) from None
                return hashed, dest
        except BaseException:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)
            raise
        finally:
            self._writing.discard(tmp)


class _WriteFailed(Exception):
    """The cache copy could not be written (told apart from transport errors of the body)."""

    def __init__(self, exc: OSError) -> None:
        super().__init__(exc)
        self.reason = exc.strerror or str(exc)


class _Copy:
    """The sink of :meth:`ContentStore.ingest`: a file whose write errors are :class:`_WriteFailed`."""

    def __init__(self, f: BinaryIO) -> None:
        self.f = f

    def write(self, data: bytes, /) -> object:
        try:
            return self.f.write(data)
        except OSError as exc:
            raise _WriteFailed(exc) from None

    def flush(self) -> None:
        try:
            self.f.flush()
        except OSError as exc:
            raise _WriteFailed(exc) from None
