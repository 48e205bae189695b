"""Output planning: no output lands on an input, and a run's outputs land together or not at all.

Every verb that writes (resolve's lock and flattened document, pin's edits, and later
ota images and manifests, macsec key stores and exports, registry metadata) plans
its outputs here first:

1. :meth:`OutputPlan.protect` / :meth:`OutputPlan.protect_tree` name the inputs
   (documents, verified artifacts, the cache, keys) that no output may replace.
2. :meth:`OutputPlan.add` checks a destination at once, by resolved path and by
   inode, so neither a symlink nor ``..`` nor a hard link gets around the check.
3. :meth:`OutputPlan.commit` writes every output to a temporary file in its
   destination folder and fsyncs it; only when all are ready is each renamed into
   place. A failure before the renames leaves every destination as it was.
"""

from __future__ import annotations

import contextlib
import os
import stat
import tempfile
from dataclasses import dataclass
from pathlib import Path

from .errors import InputError
from .store import fsync_dir


class OutputError(InputError):
    """An output cannot be written: it would replace an input, or the disk refused it."""

    code = "output"


@dataclass(frozen=True)
class _Output:
    path: Path  # absolute, as given (not resolved: a symlink at the destination is replaced, not followed)
    data: bytes
    mode: int
    flag: str  # how the user named it, for messages: "--lock", "--out", ...


@dataclass(frozen=True)
class _Input:
    real: str
    what: str


class OutputPlan:
    """The outputs of one run, checked against its inputs, written all or nothing."""

    def __init__(self) -> None:
        self._files: dict[str, _Input] = {}  # realpath -> input
        self._inodes: dict[tuple[int, int], _Input] = {}
        self._trees: list[_Input] = []
        self._outputs: dict[str, _Output] = {}  # realpath -> output

    # -- inputs ----------------------------------------------------------------------

    def protect(self, path: str | os.PathLike[str], *, what: str) -> None:
        """``path`` is an input of this run (``what`` says which, e.g. "the root document")."""
        real = os.path.realpath(path)
        entry = _Input(real, what)
        self._files.setdefault(real, entry)
        with contextlib.suppress(OSError):
            st = os.stat(real)
            self._inodes.setdefault((st.st_dev, st.st_ino), entry)

    def protect_tree(self, path: str | os.PathLike[str], *, what: str) -> None:
        """No output may lie inside the folder ``path`` (e.g. the cache)."""
        self._trees.append(_Input(os.path.realpath(path), what))

    # -- outputs ---------------------------------------------------------------------

    def add(self, path: str | os.PathLike[str], data: bytes, *, flag: str, mode: int = 0o644) -> None:
        """Plan to write ``data`` to ``path``, refusing at once a destination that is an input.

        Raises:
            OutputError: ``path`` is an input, inside a protected folder, another
                output of this run, a directory, or under a regular file.
        """
        dest = Path(os.path.abspath(path))
        shown = os.fspath(path)
        real = os.path.realpath(dest)
        hit = self._files.get(real)
        if hit is None:
            try:
                st = os.stat(real)
            except OSError:
                st = None
            if st is not None:
                if stat.S_ISDIR(st.st_mode):
                    raise OutputError(f"{flag} {shown} is a directory", file=shown)
                hit = self._inodes.get((st.st_dev, st.st_ino))
        if hit is not None:
            raise OutputError(f"{flag} {shown} is {hit.what} ({hit.real}): refusing to overwrite an input", file=shown)
        for tree in self._trees:
            if real == tree.real or real.startswith(tree.real.rstrip("/") + "/"):
                raise OutputError(f"{flag} {shown} is inside {tree.what} ({tree.real})", file=shown)
        if real in self._outputs:
            other = self._outputs[real]
            raise OutputError(f"{flag} {shown} is also the destination of {other.flag}", file=shown)
        _check_parent(dest, flag=flag, shown=shown)
        self._outputs[real] = _Output(dest, data, mode, flag)

    @property
    def paths(self) -> list[Path]:
        return [o.path for o in self._outputs.values()]

    def commit(self) -> list[Path]:
        """Write every planned output; rename them into place only when all are written.

        Raises:
            OutputError: a folder could not be made or written (read-only, full disk...);
                then no destination has changed and no temporary file is left.
        """
        staged: list[tuple[str, _Output]] = []
        current: _Output | None = None
        try:
            for current in self._outputs.values():
                staged.append((_stage(current), current))
            for tmp, current in staged:
                os.replace(tmp, current.path)
        except OSError as exc:
            for tmp, _ in staged:
                with contextlib.suppress(OSError):
                    os.unlink(tmp)
            assert current is not None
            raise OutputError(
                f"cannot write {current.flag} {current.path}: {exc.strerror or exc}", file=os.fspath(current.path)
            ) from None
        for folder in {o.path.parent for o in self._outputs.values()}:
            fsync_dir(folder)
        return self.paths


def _check_parent(dest: Path, *, flag: str, shown: str) -> None:
    """Refuse early a destination under a regular file (``--out README.md/x``)."""
    for parent in dest.parents:
        try:
            st = os.stat(parent)
        except FileNotFoundError:
            continue
        except OSError as exc:
            raise OutputError(f"{flag} {shown}: cannot use folder {parent}: {exc.strerror}", file=shown) from None
        if not stat.S_ISDIR(st.st_mode):
            raise OutputError(f"{flag} {shown}: {parent} is not a folder", file=shown)
        return


def _stage(out: _Output) -> str:
    """Write ``out`` to a fsynced temporary file beside its destination, with its mode from the first byte."""
    out.path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{out.path.name}.", suffix=".tmp", dir=out.path.parent)  # 0600
    try:
        os.fchmod(fd, out.mode)
        view = memoryview(out.data)
        while view:
            view = view[os.write(fd, view) :]
        os.fsync(fd)
    except BaseException:
        os.close(fd)
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    os.close(fd)
    return tmp
