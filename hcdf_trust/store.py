"""Atomic writes and the content-addressed cache.

Every output (lock file, flattened document, cache blob, later images,
manifests and key stores) is written to a temporary file in the destination
folder, fsynced, then renamed: a failed run leaves the previous state intact.
"""

from __future__ import annotations

import contextlib
import os
import stat
import tempfile
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import BinaryIO

from .digest import Hashed, hash_chunks, hash_stream, is_full_sha256
from .errors import FetchError, InputError


@contextlib.contextmanager
def atomic_writer(path: str | os.PathLike[str], *, mode: int = 0o644) -> Iterator[BinaryIO]:
    """Yield a binary file; on clean exit it replaces ``path`` atomically, else vanishes."""
    dest = Path(path)
    dest.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{dest.name}.", suffix=".tmp", dir=dest.parent)
    try:
        os.fchmod(fd, mode)
        with os.fdopen(fd, "wb") as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, dest)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    fsync_dir(dest.parent)


def atomic_write(path: str | os.PathLike[str], data: bytes, *, mode: int = 0o644) -> None:
    with atomic_writer(path, mode=mode) as f:
        f.write(data)


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


def default_cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "hcdf-trust"


class ContentStore:
    """Blobs named by their SHA-256, verified on the way in and on the way out.

    Layout: ``ROOT/sha256/ab/abcdef…``. A blob is only ever created by renaming
    a fully written temporary file whose digest was checked, so a crash or a
    mismatch never leaves a partial or wrong entry.
    """

    def __init__(self, root: str | os.PathLike[str]) -> None:
        self.root = Path(root)

    def path_for(self, sha256: str) -> Path:
        if not is_full_sha256(sha256):
            raise ValueError(f"not a full lower-case SHA-256: {sha256!r}")
        return self.root / "sha256" / sha256[:2] / sha256

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
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            os.close(fd)
            actual = None
        else:
            with os.fdopen(fd, "rb", buffering=0) as f:
                actual = hash_stream(f).sha256
        if actual != sha256:
            if repair:
                with contextlib.suppress(OSError):
                    path.unlink()
            return None
        return path

    def ingest(
        self,
        chunks: Iterable[bytes],
        *,
        accept: Callable[[Hashed], bool] | None = None,
        limit: int | None = None,
        source: str = "",
    ) -> tuple[Hashed, Path | None]:
        """Copy ``chunks`` into the store, hashing as they pass.

        ``accept`` sees the digest before the blob is committed; if it returns
        False (a pin mismatch) nothing is stored and the path is ``None``.

        Raises:
            InputError: more than ``limit`` bytes.
        """
        tmpdir = self.root / "tmp"
        try:
            fd, tmp = tempfile.mkstemp(dir=tmpdir)
        except FileNotFoundError:  # first blob of a new cache: one mkdir, not one per blob
            tmpdir.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(dir=tmpdir)
        try:
            with os.fdopen(fd, "wb") as f:
                try:
                    hashed = hash_chunks(chunks, sink=f, limit=limit)
                except ValueError as exc:
                    raise FetchError(f"body {exc}", file=source, url=source) from None
                # No fsync: a blob torn by a crash no longer hashes to its name, and
                # verified_path() re-hashes on every read, so it is dropped and fetched
                # again. Skipping it makes many small fetches ~2x faster (fsync per blob
                # was the largest client cost in the 200-file latency test).
            if accept is not None and not accept(hashed):
                os.unlink(tmp)
                return hashed, None
            dest = self.path_for(hashed.sha256)
            os.chmod(tmp, 0o444)
            try:
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
