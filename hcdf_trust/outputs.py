"""Output planning: no output lands on an input, and a run's outputs land together or not at all.

Every verb that writes (resolve's lock and flattened document, pin's edits, and later
ota images and manifests, macsec key stores and exports, registry metadata) plans
its outputs here first:

1. :meth:`OutputPlan.protect` / :meth:`OutputPlan.protect_tree` name the inputs
   (documents, verified artifacts, the cache, keys) that no output may replace;
   :func:`protect_inputs` names every input of a :class:`~hcdf_trust.include.resolver.Resolution`.
2. :meth:`OutputPlan.add` checks a destination at once: its folder is resolved as
   the kernel resolves it, and an existing file is compared with the inputs by
   inode, so neither a symlink nor ``..`` nor a hard link gets around the check.
3. :meth:`OutputPlan.commit` writes every output to a temporary file in its
   destination folder, then fsyncs them all (together, on a few threads); only when
   all are ready is each renamed into place, and each folder is fsynced once. A
   failure before the renames leaves every destination as it was; a rename that
   fails puts back the files already replaced. An output added with ``if_changed``
   that is already in place, byte for byte, is not written at all.
"""

from __future__ import annotations

import contextlib
import os
import stat
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple, TypeVar

from .errors import InputError, display_path, display_place
from .store import create_temp, default_cache_dir, fsync_dir

if TYPE_CHECKING:
    from .include.resolver import Resolution, ResolveOptions


class OutputError(InputError):
    """An output cannot be written: it would replace an input, or the disk refused it."""

    code = "output"


class _Output(NamedTuple):  # a tuple: a frozen dataclass costs ~1 ms of start-up to define
    path: Path  # the real folder + the name as given (a symlink at the destination is replaced, not followed)
    data: bytes
    mode: int
    flag: str  # how the user named it, for messages: "--lock", "--out", ...
    shown: str  # the path as the user gave it
    if_changed: bool = False  # left as it is when it already holds exactly ``data`` with ``mode``


class _Input(NamedTuple):  # a tuple: 10,000 of them per run
    path: str
    what: str
    inode: tuple[int, int] | None = None  # (st_dev, st_ino) when the caller knows it


class OutputPlan:
    """The outputs of one run, checked against its inputs, written all or nothing.

    Inputs are compared with a destination by inode (``os.stat`` follows symlinks,
    and a hard link shares the inode), so a spelling with symlinks, ``..`` or another
    link to the same file is caught. Protecting costs no system call: the inputs are
    stat'ed once, and only when a destination already exists (a destination that
    does not exist cannot be an input); an input protected with the ``inode`` of the
    descriptor it was read from is not stat'ed at all, and is also compared by path
    (it may have been replaced since). That keeps a 10,000-file tree cheap.
    """

    def __init__(self) -> None:
        self._inputs: list[_Input] = []
        self._inodes: dict[tuple[int, int], _Input] = {}
        self._names: dict[str, _Input] = {}  # inputs protected with their inode, by path
        self._statted = 0  # how many of _inputs are in _inodes
        self._trees: list[_Input] = []
        self._outputs: dict[str, _Output] = {}  # realpath -> output
        self.unchanged: list[Path] = []  # outputs added with if_changed that commit() found already in place

    # -- inputs ----------------------------------------------------------------------

    def protect(self, path: str | os.PathLike[str], *, what: str, inode: tuple[int, int] | None = None) -> None:
        """``path`` is an input of this run (``what`` says which, e.g. "the root document").

        ``inode``: (st_dev, st_ino) of the descriptor it was read from, when the caller has it.
        """
        self._inputs.append(_Input(os.fspath(path), what, inode))

    def protect_tree(self, path: str | os.PathLike[str], *, what: str) -> None:
        """No output may lie inside the folder ``path`` (e.g. the cache)."""
        self._trees.append(_Input(os.path.realpath(path), what))

    def _input_at(self, st: os.stat_result, real: str) -> _Input | None:
        """The input that is the file ``st`` (at the real path ``real``) describes, if any."""
        for entry in self._inputs[self._statted :]:
            key = entry.inode
            if key is None:
                try:
                    ist = os.stat(entry.path)
                except (OSError, ValueError):
                    continue
                key = (ist.st_dev, ist.st_ino)
            else:
                self._names.setdefault(entry.path, entry)
            self._inodes.setdefault(key, entry)
        self._statted = len(self._inputs)
        return self._inodes.get((st.st_dev, st.st_ino)) or self._names.get(real)

    def protected(self, path: str | os.PathLike[str]) -> str | None:
        """What ``path`` is ("the root document", "the cache", ...) when it is a protected
        input or lies inside a protected folder; None otherwise."""
        real = os.path.realpath(path)
        with contextlib.suppress(OSError):
            hit = self._input_at(os.stat(real), real)
            if hit is not None:
                return hit.what
        for tree in self._trees:
            if real == tree.path or real.startswith(tree.path.rstrip("/") + "/"):
                return tree.what
        return None

    # -- outputs ---------------------------------------------------------------------

    def add(
        self,
        path: str | os.PathLike[str],
        data: bytes,
        *,
        flag: str,
        mode: int = 0o644,
        edit: bool = False,
        if_changed: bool = False,
    ) -> None:
        """Plan to write ``data`` to ``path``, refusing at once a destination that is an input.

        ``edit`` marks an in-place edit of an input (``pin --write`` rewriting a
        document it read): it may replace a protected file, but nothing else below.
        ``if_changed``: a destination that already is a regular file (not a symlink)
        holding exactly ``data`` with ``mode`` is left as it is, inode and mtime
        untouched (a build system then sees no change); :attr:`unchanged` lists it.

        Raises:
            OutputError: ``path`` is an input, inside a protected folder, another
                output of this run, a directory or other non-regular file, or under
                a regular file.
        """
        dest, real, shown = self._check(path, flag=flag, edit=edit)
        self._outputs[real] = _Output(dest, data, mode, flag, shown, if_changed)

    def check(self, path: str | os.PathLike[str], *, flag: str) -> None:
        """Refuse now what :meth:`add` would refuse, before the work of making the data.

        Raises:
            OutputError: as :meth:`add`.
        """
        self._check(path, flag=flag, edit=False)

    def _check(self, path: str | os.PathLike[str], *, flag: str, edit: bool) -> tuple[Path, str, str]:
        """The destination, its real path and how messages show it, or an OutputError."""
        dest = _destination(os.fspath(path), flag=flag)
        shown = display_place(os.fspath(path))  # an absolute path inside the working folder shown relative
        real = os.path.realpath(dest)
        try:
            st: os.stat_result | None = os.stat(real)
        except (FileNotFoundError, NotADirectoryError):  # a new file (under a file: _check_parent says so)
            st = None
        except OSError as exc:  # ELOOP, EACCES: the folder cannot be used either
            raise OutputError(f"{flag} {shown}: {exc.strerror}", file=shown) from None
        if st is not None and stat.S_ISDIR(st.st_mode):
            raise OutputError(f"{flag} {shown} is a directory", file=shown)
        hit = self._input_at(st, real) if st is not None and not edit else None
        if hit is not None:
            named = display_path(hit.path)
            also = f" ({named})" if named != os.path.normpath(shown) else ""
            raise OutputError(f"{flag} {shown} is {hit.what}{also}: refusing to overwrite an input", file=shown)
        if st is not None and not stat.S_ISREG(st.st_mode):
            raise OutputError(f"{flag} {shown} exists and is not a regular file ({_kind(st.st_mode)})", file=shown)
        for tree in self._trees:
            if real == tree.path or real.startswith(tree.path.rstrip("/") + "/"):
                raise OutputError(f"{flag} {shown} is inside {tree.what} ({display_path(tree.path)})", file=shown)
        if real in self._outputs:
            other = self._outputs[real]
            raise OutputError(f"{flag} {shown} is also the destination of {other.flag}", file=shown)
        _check_parent(dest, flag=flag, shown=shown)
        return dest, real, shown

    @property
    def paths(self) -> list[Path]:
        return [o.path for o in self._outputs.values()]

    def commit(self) -> list[Path]:
        """Write every planned output; rename them into place only when all are written.
        Returns the paths written (not those found :attr:`unchanged`).

        Every file is written to a temporary file beside its destination first, then the
        temporary files are fsynced together (a few threads: fsync releases the GIL and
        the filesystem can commit them in one journal transaction); only then is each
        renamed into place, and each folder that changed is fsynced once.

        Raises:
            OutputError: a folder could not be made or written (read-only, full disk...);
                then no destination has changed and no temporary file or new folder is left.
        """
        outputs = []
        for out in self._outputs.values():
            if out.if_changed and _holds(out):
                self.unchanged.append(out.path)
            else:
                outputs.append(out)
        made: list[Path] = []  # folders this commit created, outermost first
        staged: list[tuple[str, _Output]] = []
        done: list[tuple[_Output, str | None]] = []  # renamed so far, with a link to the file they replaced
        current: _Output | None = None
        try:
            folders: set[Path] = set()
            for current in outputs:
                if current.path.parent not in folders:
                    made += _make_folders(current.path.parent)
                    folders.add(current.path.parent)
            for start in range(0, len(outputs), _OPEN_AT_ONCE):
                batch = outputs[start : start + _OPEN_AT_ONCE]
                fds: list[int] = []
                try:
                    for current in batch:
                        fd, tmp = _stage(current)
                        fds.append(fd)
                        staged.append((tmp, current))
                    failed = _in_parallel(_fsync, fds)
                finally:
                    for fd in fds:
                        os.close(fd)
                for i, err in enumerate(failed):
                    if err is not None:
                        current = batch[i]  # the message names the file whose fsync failed
                        raise err
            for tmp, current in staged:
                backup = _keep_previous(current.path)
                try:
                    os.replace(tmp, current.path)
                except OSError:
                    _discard(backup)
                    raise
                done.append((current, backup))
        except BaseException as exc:  # an interrupt (Ctrl-C) is rolled back like a full disk
            _roll_back(done, staged, made)
            if not isinstance(exc, OSError):
                raise
            assert current is not None
            raise OutputError(
                f"cannot write {current.flag} {current.shown}: {exc.strerror or exc}", file=current.shown
            ) from None
        for _, backup in done:
            _discard(backup)
        # the renamed files' folders, and the folders that hold a folder this commit made
        _in_parallel(fsync_dir, sorted(folders | {folder.parent for folder in made}))
        return [out.path for out in outputs]


def protect_inputs(
    plan: OutputPlan,
    res: Resolution,
    *,
    doc: str | os.PathLike[str] | None = None,
    options: ResolveOptions | None = None,
) -> None:
    """Protect everything a resolve run read, for every verb that writes after one.

    That is the root document ``doc`` as given on the command line (it may be a link
    stub) and the file it names, every local document of the include tree, every
    local artifact (models, meshes, profiles, manifests, mirror copies), the CA
    bundle and the cache folder (``options.cache_dir``, else the default cache). Not
    the lock file: whether it is an output is the caller's choice (protect it with
    :meth:`OutputPlan.protect` when it is not).
    """
    if doc is not None:
        plan.protect(doc, what="the root document")
    if res.root_location.path is not None:
        plan.protect(res.root_location.path, what="the root document")
    names: dict[str, str] = {}  # what each kind of artifact is called, once per kind (10,000 artifacts)
    for art in res.artifacts.values():
        if art.location.path is not None:
            kind = art.kind._value_  # Enum's .value is a Python-level descriptor
            what = names.get(kind)
            if what is None:
                what = names[kind] = artifact_role(kind)
            plan.protect(art.location.path, what=what, inode=art.inode)
    if options is not None and options.ca_bundle:
        plan.protect(options.ca_bundle, what="the CA bundle")
    cache = options.cache_dir if options is not None else None
    plan.protect_tree(cache or default_cache_dir(), what="the cache")


def artifact_role(kind: str) -> str:
    """What an output that would replace a verified file of ``kind`` is told it is."""
    return "an included document" if kind == "include" else f"a verified {kind} file"


def _destination(text: str, *, flag: str) -> Path:
    """Where ``text`` names, as the kernel resolves it: the real folder and the last name.

    ``os.path.abspath`` would collapse ``link/..`` lexically, naming a different file
    than the one the kernel opens when ``link`` is a symlink.
    """
    name = os.path.basename(text)
    if name in ("", ".", ".."):
        raise OutputError(f"{flag} {text} is a directory", file=text)
    folder = os.path.dirname(os.path.join(os.getcwd(), text))
    return Path(os.path.realpath(folder)) / name


def _kind(mode: int) -> str:
    if stat.S_ISFIFO(mode):
        return "a FIFO"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    return "a socket" if stat.S_ISSOCK(mode) else "special"


def _check_parent(dest: Path, *, flag: str, shown: str) -> None:
    """Refuse early a destination under a regular file (``--out README.md/x``)."""
    for parent in dest.parents:
        try:
            st = os.stat(parent)
        except (FileNotFoundError, NotADirectoryError):  # look further up for the file in the way
            continue
        except OSError as exc:
            raise OutputError(
                f"{flag} {shown}: cannot use folder {display_path(parent)}: {exc.strerror}", file=shown
            ) from None
        if not stat.S_ISDIR(st.st_mode):
            raise OutputError(f"{flag} {shown}: {display_path(parent)} is not a folder", file=shown)
        return


def _make_folders(folder: Path) -> list[Path]:
    """Create ``folder`` and its missing parents; return those created, outermost first."""
    missing = []
    for candidate in (folder, *folder.parents):
        if candidate.is_dir():
            break
        missing.append(candidate)
    made = []
    try:
        for candidate in reversed(missing):
            candidate.mkdir()
            made.append(candidate)
    except OSError:
        for candidate in reversed(made):
            with contextlib.suppress(OSError):
                candidate.rmdir()
        raise
    return made


_OPEN_AT_ONCE = 256  # temporary files held open while their fsyncs run (bounded: RLIMIT_NOFILE)
_FSYNC_THREADS = 8  # fsyncs wait on the disk, not the CPU
_T = TypeVar("_T")
_R = TypeVar("_R")


def _fsync(fd: int) -> OSError | None:
    try:
        os.fsync(fd)
    except OSError as exc:
        return exc
    return None


def _in_parallel(fn: Callable[[_T], _R], items: Sequence[_T]) -> list[_R]:
    """``fn`` over ``items`` on a few threads (inline for one item), results in order.

    Every call has returned when this returns or raises (the pool is shut down with
    ``wait``), so the caller may then close what the calls use.
    """
    if len(items) <= 1:
        return [fn(item) for item in items]
    from concurrent.futures import ThreadPoolExecutor  # ~10 ms of imports a one-file run never needs

    with ThreadPoolExecutor(max_workers=min(_FSYNC_THREADS, len(items))) as pool:
        return list(pool.map(fn, items))


def _holds(out: _Output) -> bool:
    """Is ``out.path`` already a regular file (not a symlink) holding exactly ``out.data``, with ``out.mode``?"""
    try:
        fd = os.open(out.path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError:  # missing, a symlink (ELOOP), unreadable: written as usual
        return False
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode) or stat.S_IMODE(st.st_mode) != out.mode or st.st_size != len(out.data):
            return False
        view = memoryview(out.data)
        while view:  # compared read by read: a file that changes size meanwhile differs somewhere
            chunk = os.read(fd, len(view))
            if not chunk or view[: len(chunk)] != chunk:
                return False
            view = view[len(chunk) :]
        return os.read(fd, 1) == b""
    except OSError:
        return False
    finally:
        os.close(fd)


def _stage(out: _Output) -> tuple[int, str]:
    """Write ``out`` to a temporary file beside its destination, with its mode from the first
    byte; return the open descriptor (to fsync) and the path."""
    fd, tmp = create_temp(out.path.parent, f".{out.path.name}.", ".tmp")  # 0600
    try:
        os.fchmod(fd, out.mode)
        view = memoryview(out.data)
        while view:
            view = view[os.write(fd, view) :]
    except BaseException:
        os.close(fd)
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    return fd, tmp


def _keep_previous(dest: Path) -> str | None:
    """A hard link to the file ``dest`` names now, so a failed commit can put it back.

    None when there is no such file, or the filesystem cannot link it (then that one
    destination cannot be restored; the others still are).
    """
    for _ in range(8):
        backup = os.fspath(dest.parent / f".{dest.name}.{os.urandom(6).hex()}.old")
        try:
            os.link(dest, backup, follow_symlinks=False)
        except FileExistsError:
            continue
        except OSError:
            return None
        return backup
    return None


def _discard(backup: str | None) -> None:
    if backup is not None:
        with contextlib.suppress(OSError):
            os.unlink(backup)


def _roll_back(done: list[tuple[_Output, str | None]], staged: list[tuple[str, _Output]], made: list[Path]) -> None:
    """Undo a failed commit: restore replaced files, drop new ones, temporaries and new folders."""
    for out, backup in reversed(done):
        with contextlib.suppress(OSError):
            if backup is not None:
                os.replace(backup, out.path)
            else:
                os.unlink(out.path)
    renamed = {id(out) for out, _ in done}
    for tmp, out in staged:
        if id(out) not in renamed:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
    for folder in reversed(made):
        with contextlib.suppress(OSError):
            folder.rmdir()
