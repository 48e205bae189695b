"""Blobs of a pull: fetched by digest, hashed while they stream, staged as files of our own.

``ota pull`` and ``bundle pull`` share this: a private staging folder in the cache
(:class:`Stage`: made by this pull, locked for its life, swept by the next pull once it died),
and :func:`fetch_blob`, which streams one blob from the registry into the content store *and*
into a new file of the staging folder at once, hashing the bytes as they pass; a blob whose
SHA-256 or size is not the manifest's enters neither (the staged copy is removed). The staged
file is created with ``O_EXCL`` (mode 0600) and held open: after verification it is moved into
``--out`` by the output planner (:class:`~hcdf_trust.outputs.HeldFile`), not copied and hashed
a second time. A blob already in the content store (a resumed pull) is copied from there into
the staging folder, hashed again as it is copied.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import re
import shutil
from collections.abc import Callable, Iterable, Iterator
from typing import Any

from ..digest import Sha256, hash_chunks
from ..errors import DigestMismatchError
from ..flock import flock
from ..outputs import HeldFile

SEGMENT = re.compile(r"[A-Za-z0-9][A-Za-z0-9._+-]{0,254}")  # one segment of a layer title
STAGE_PREFIX = ".oci-pull-"
_STAGE_LOCK = ".lock"
_STALE_UNLOCKED = 600.0  # a staging folder with no lock file yet, older than this: its pull died
_NEW_FILE = os.O_RDWR | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC


class Stage:
    """A private staging folder in ``cache_dir`` for one pull (mode 0700), locked until
    :meth:`close`, which removes it with whatever is left in it and closes the held files.
    Making one first sweeps the folders killed pulls left (:func:`sweep_stages`)."""

    def __init__(self, cache_dir: str) -> None:
        import tempfile

        os.makedirs(cache_dir, exist_ok=True)
        sweep_stages(cache_dir)
        self.path = tempfile.mkdtemp(prefix=STAGE_PREFIX, dir=cache_dir)
        self._lock = _hold(self.path)
        self._held: list[int] = []

    def new_file(self, rel: str) -> tuple[int, str]:
        """A new empty file at the relative POSIX path ``rel`` (checked plain by the caller), its
        folders made as needed: its descriptor (held until :meth:`close`) and path."""
        path = os.path.join(self.path, *rel.split("/"))
        os.makedirs(os.path.dirname(path), mode=0o700, exist_ok=True)
        fd = os.open(path, _NEW_FILE, 0o600)
        self._held.append(fd)
        return fd, path

    def close(self) -> None:
        for fd in self._held:
            with contextlib.suppress(OSError):
                os.close(fd)
        self._held.clear()
        shutil.rmtree(self.path, ignore_errors=True)
        os.close(self._lock)

    def __enter__(self) -> Stage:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _hold(stage: str) -> int:
    """Lock the staging folder for the life of this pull (a killed pull's lock goes with it)."""
    fd = os.open(os.path.join(stage, _STAGE_LOCK), os.O_CREAT | os.O_RDWR | os.O_NOFOLLOW | os.O_CLOEXEC, 0o600)
    flock(fd)
    return fd


def sweep_stages(cache_dir: str) -> int:
    """Remove the staging folders killed pulls left in ``cache_dir`` (those whose lock no
    live pull holds); returns how many."""
    import time

    removed = 0
    with os.scandir(cache_dir) as entries:
        for entry in entries:
            if not entry.name.startswith(STAGE_PREFIX) or not entry.is_dir(follow_symlinks=False):
                continue
            try:
                fd = os.open(os.path.join(entry.path, _STAGE_LOCK), os.O_RDWR | os.O_NOFOLLOW | os.O_CLOEXEC)
            except FileNotFoundError:
                if time.time() - entry.stat(follow_symlinks=False).st_mtime > _STALE_UNLOCKED:
                    shutil.rmtree(entry.path, ignore_errors=True)
                    removed += 1
                continue
            except OSError:
                continue
            try:
                flock(fd, wait=False)
            except BlockingIOError:  # a pull is running there
                continue
            finally:
                os.close(fd)  # (releases the lock we may have taken; the folder goes next)
            shutil.rmtree(entry.path, ignore_errors=True)
            removed += 1
    return removed


def _tee(chunks: Iterable[bytes], fd: int) -> Iterator[bytes]:
    """``chunks``, each also written to ``fd`` (the very bytes the store then hashes)."""
    for chunk in chunks:
        view = memoryview(chunk)
        while view:
            view = view[os.write(fd, view) :]
        yield chunk


def fetch_blob(
    client: Any,
    store: Any,
    layer: dict[str, Any],
    *,
    title: str,
    where: str,
    stage: Stage,
    rel: str,
    sha256: Callable[[], Sha256] = hashlib.sha256,
) -> tuple[HeldFile, bool, Sha256]:
    """The layer's blob from the content store (hashed again as it is staged) or from the
    registry (hashed as it streams into the store and the staged file), staged at ``rel``;
    whether it came from the store; and the hash that saw its bytes, made by ``sha256`` (for an
    MCUboot image an :class:`~hcdf_trust.ota.mcuboot.ImageStream`: checked in the same pass).

    Raises:
        DigestMismatchError: the bytes are not the manifest's (size or SHA-256); nothing of
            them is left in the store or the staging folder.
        RegistryError / FetchError / InputError: the transfer or the cache failed.
    """
    want = layer["digest"].split(":", 1)[1]
    size = layer["size"]
    fd, path = stage.new_file(rel)
    try:
        hasher = sha256()
        if _from_store(store, want, size, fd, hasher):
            return HeldFile(fd, path, size, want), True, hasher
        hasher = sha256()  # (what a stale copy in the store fed it is gone)
        with client.blob(layer["digest"], size) as chunks:
            hashed, stored = store.ingest(
                _tee(chunks, fd),
                accept=lambda h: h.sha256 == want and h.size == size,
                limit=size,
                source=title,
                sha256=hasher,
            )
    except BaseException:
        os.unlink(path)
        raise
    if stored is None:
        os.unlink(path)
        if hashed.size != size:
            raise DigestMismatchError(
                f"{title}: the blob is shorter than the manifest says",
                file=where,
                expected=str(size),
                actual=str(hashed.size),
            )
        raise DigestMismatchError(
            f"{title}: the blob's SHA-256 is not its digest in the manifest",
            file=where,
            expected=layer["digest"],
            actual=f"sha256:{hashed.sha256}",
        )
    return HeldFile(fd, path, size, want), False, hasher


def _from_store(store: Any, sha256: str, size: int, fd: int, hasher: Sha256) -> bool:
    """Copy the store's blob ``sha256`` into ``fd``, hashed by ``hasher`` as it is copied; False
    (``fd`` left empty) when the store has no such blob of ``size`` bytes, or it changed since it
    was checked."""
    from ..localfile import read_chunks

    cached = store.verified_path(sha256)
    if cached is None:
        return False
    try:
        src = os.open(cached, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC)
    except OSError:
        return False
    try:
        hashed = hash_chunks(_tee(read_chunks(src), fd), limit=size, sha256=hasher)
        if hashed.sha256 == sha256 and hashed.size == size:
            return True
    except ValueError:  # longer than the manifest says
        pass
    finally:
        os.close(src)
    os.ftruncate(fd, 0)
    os.lseek(fd, 0, os.SEEK_SET)
    return False
