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

What no output may replace, whoever writes it:

- an input of the run (step 1), and a file that is a private or public key, a MACsec key
  store, a registry source file or an HCDF document (:func:`kind_of` reads its first bytes)
  unless the output says it ``replaces`` that kind (``--force`` of a keygen, a store
  rewriting itself, a flattened document replacing the previous one);
- a file reached through a symlinked folder inside an output tree: an output added
  ``under`` a tree root is written by opening each folder below the root relative to its
  parent's descriptor with ``O_NOFOLLOW | O_DIRECTORY`` (checked when planned, and again
  when committed), so ``rel/<board>`` pointing elsewhere is refused, never followed.

A killed run leaves its staged (``.NAME.<hex>.tmp``) and backup (``.NAME.<hex>.old``) files
behind: a commit holds a shared ``flock`` on every folder it writes to, and the next commit
that can take that folder's lock exclusively (no run is writing there) removes them first.
``-`` as a destination (where a verb allows it: ``stdout=True``) is standard output.
"""

from __future__ import annotations

import contextlib
import errno
import os
import stat
from collections.abc import Callable, Sequence
from pathlib import Path, PurePath
from typing import TYPE_CHECKING, NamedTuple, TypeVar

from .errors import InputError, display_path, display_place
from .flock import flock
from .store import create_temp, default_cache_dir, fsync_dir

if TYPE_CHECKING:
    from .include.resolver import Resolution, ResolveOptions

# The public API (docs/api.md); everything else here is internal.
__all__ = ["OutputError", "OutputPlan", "protect_inputs"]


class OutputError(InputError):
    """An output cannot be written: it would replace an input, or the disk refused it."""

    code = "output"


ORDINARY = "an ordinary file"  # none of the kinds below
PRIVATE_KEY = "a private key"
PUBLIC_KEY = "a public key"
KEY_STORE = "a MACsec key store"
DOCUMENT = "an HCDF document"
BUNDLE = "an HCDF bundle"  # a .hcdfz: a ZIP whose first entry is a .hcdf (bundle.py)
REGISTRY_SOURCE = "a registry source file"
NEW_ONLY: tuple[str, ...] = ()  # ``replaces=NEW_ONLY``: an existing destination is never replaced

# What a file that no output may replace by default holds within its first 4 KiB (the first
# mark found names it). Our own formats are named by the first line their writer puts there
# (registry/source.py ``dump``, registry/edit.py ``keygen``): tests check the two agree.
_MARKS = (
    (b"PRIVATE KEY-----", PRIVATE_KEY),  # PEM: PKCS#8, encrypted, EC, RSA, OpenSSH
    (b"AGE-SECRET-KEY-1", PRIVATE_KEY),
    (b'"hcdf-trust-macsec-store"', KEY_STORE),
    (b"-----BEGIN PUBLIC KEY-----", PUBLIC_KEY),
    (b"# hcdf-trust registry owner public key", PUBLIC_KEY),
    (b"# An HCDF extension domain: only its owner's keys", REGISTRY_SOURCE),
    (b"# Signed by the registry's targets key;", REGISTRY_SOURCE),
    (b"# The registry's root of trust:", REGISTRY_SOURCE),
    (b"<hcdf ", DOCUMENT),
    (b"<hcdf>", DOCUMENT),
    (b"<hcdf\n", DOCUMENT),
    (b"<hcdf\t", DOCUMENT),
    (b"<hcdf\r", DOCUMENT),
)
_SNIFF_BYTES = 4096

# The names of OutputPlan's staged files and backups: the sweep removes nothing else.
_LEFTOVER = None  # compiled on first use (re costs start-up)
_LEFTOVER_PATTERN = r"\..+\.[0-9a-f]{12}\.(?:tmp|old)"


class FileContent(NamedTuple):
    """An output's bytes that are a file already on disk (``ota pull``'s verified blobs): copied
    at commit a chunk at a time, never held in memory, and refused unless the copy has exactly
    ``size`` bytes whose SHA-256 is ``sha256`` (the file may have changed since it was checked)."""

    path: str
    size: int
    sha256: str

    def read(self) -> bytes:
        with open(self.path, "rb") as f:
            return f.read()


class HeldFile(NamedTuple):
    """An output's bytes that are a file this run made itself and still holds open (``ota pull``
    and ``bundle pull`` write each blob, as it is hashed, into a private staging folder and
    verify it there): committed by *moving that very file* into place, not by copying it.

    At commit the file at ``path`` is hard-linked under a temporary name in its destination
    folder (held open as every output's folder is, so never through a symlink), and adopted only
    if that name is the inode ``fd`` holds, a regular file of ``size`` bytes; its staging name is
    then removed and it must have no other link (nobody keeps a name through which it could be
    rewritten); from there it is committed as any staged output (mode, fsync, rename, roll-back).
    Its bytes are not hashed again: the caller wrote them from the bytes it hashed, into a file
    it created (``O_EXCL``, mode 0600, in a folder only it uses) and still holds. On another
    filesystem (no hard link possible) the file is copied from ``fd`` instead, hashed as it is
    copied against ``sha256``, as a :class:`FileContent` is. The caller closes ``fd`` after the
    commit."""

    fd: int
    path: str
    size: int
    sha256: str

    def read(self) -> bytes:
        return os.pread(self.fd, self.size + 1, 0)


class _Output(NamedTuple):  # a tuple: a frozen dataclass costs ~1 ms of start-up to define
    path: Path  # the real folder + the name as given (a symlink at the destination is replaced, not followed)
    data: bytes | FileContent | HeldFile
    mode: int
    flag: str  # how the user named it, for messages: "--lock", "--out", ...
    shown: str  # the path as the user gave it
    if_changed: bool = False  # left as it is when it already holds exactly ``data`` with ``mode``
    base: str = ""  # an existing real folder, opened as named (symlinks the user chose are followed)
    parts: tuple[str, ...] = ()  # the folders below ``base``, each opened with O_NOFOLLOW, made when missing
    folder_mode: int = 0o777  # for the folders made (before the umask)


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

    Example:
        >>> from hcdf_trust.include import verify
        >>> from hcdf_trust.outputs import OutputError, OutputPlan, protect_inputs
        >>> plan = OutputPlan()
        >>> protect_inputs(plan, verify("examples/robot/robot.hcdf"))
        >>> try:
        ...     plan.add("examples/robot/models/chassis.glb", b"x", flag="--out")
        ... except OutputError as e:
        ...     print(e.message)
        --out examples/robot/models/chassis.glb is a verified model file: refusing to overwrite an input
        >>> plan.add("out/report.txt", b"ok\\n", flag="--out")
        >>> [p.name for p in plan.commit()]
        ['report.txt']
    """

    def __init__(self) -> None:
        self._inputs: list[_Input] = []
        self._inodes: dict[tuple[int, int], _Input] = {}
        self._names: dict[str, _Input] = {}  # inputs protected with their inode, by path
        self._statted = 0  # how many of _inputs are in _inodes
        self._trees: list[_Input] = []
        self._outputs: dict[str, _Output] = {}  # realpath -> output
        self._stdout: list[bytes] = []  # outputs added as "-": written to standard output by commit()
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
        data: bytes | FileContent | HeldFile,
        *,
        flag: str,
        mode: int = 0o644,
        edit: bool = False,
        if_changed: bool = False,
        under: str | os.PathLike[str] | None = None,
        replaces: tuple[str, ...] | None = None,
        stdout: bool = False,
        folder_mode: int = 0o777,
    ) -> None:
        """Plan to write ``data`` to ``path``, refusing at once a destination that is an input.

        ``edit`` marks an in-place edit of an input (``pin --write`` rewriting a
        document it read): it may replace a protected file, but nothing else below.
        ``if_changed``: a destination that already is a regular file (not a symlink)
        holding exactly ``data`` with ``mode`` is left as it is, inode and mtime
        untouched (a build system then sees no change); :attr:`unchanged` lists it.
        ``under``: the root of the output tree ``path`` lies in (as the caller spelled
        it: ``path`` must start with it); no folder below it may be a symlink.
        ``replaces``: the kinds (:func:`kind_of`) of existing file this output may replace:
        None is ``(ORDINARY,)`` (never a key, key store, registry source or document);
        ``NEW_ONLY`` is nothing (the destination must not exist).
        ``stdout``: ``path`` ``-`` means standard output. ``folder_mode``: of folders made.
        ``data`` a :class:`FileContent`: copied from that file at commit; a :class:`HeldFile`:
        that file moved into place at commit (neither with ``if_changed`` nor to standard output).

        Raises:
            OutputError: ``path`` is an input, inside a protected folder, another
                output of this run, a directory or other non-regular file, under
                a regular file or a symlinked folder of its tree, or key material.
        """
        if isinstance(data, (FileContent, HeldFile)) and (if_changed or stdout):
            raise ValueError("a file output is written as a new file, not if_changed nor to stdout")
        if stdout and os.fspath(path) == "-":
            assert isinstance(data, bytes)
            self._stdout.append(data)
            return
        dest, real, shown, base, parts = self._check(path, flag=flag, edit=edit, under=under, replaces=replaces)
        self._outputs[real] = _Output(dest, data, mode, flag, shown, if_changed, base, parts, folder_mode)

    def check(
        self,
        path: str | os.PathLike[str],
        *,
        flag: str,
        under: str | os.PathLike[str] | None = None,
        replaces: tuple[str, ...] | None = None,
    ) -> None:
        """Refuse now what :meth:`add` would refuse, before the work of making the data.

        Raises:
            OutputError: as :meth:`add`.
        """
        self._check(path, flag=flag, edit=False, under=under, replaces=replaces)

    def _check(
        self,
        path: str | os.PathLike[str],
        *,
        flag: str,
        edit: bool,
        under: str | os.PathLike[str] | None,
        replaces: tuple[str, ...] | None,
    ) -> tuple[Path, str, str, str, tuple[str, ...]]:
        """The destination, its real path, how messages show it, and the existing folder and
        the folders below it that commit opens one by one; or an OutputError."""
        shown = display_place(os.fspath(path))  # an absolute path inside the working folder shown relative
        below: tuple[str, ...] = ()
        if under is None:
            dest = _destination(os.fspath(path), flag=flag)
            top = dest.parent
        else:
            top, below = _in_tree(os.fspath(path), os.fspath(under), flag=flag, shown=shown)
            dest = top.joinpath(*below, os.path.basename(path))
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
        if st is not None and not edit:
            _check_replace(real, replaces, flag=flag, shown=shown)
        for tree in self._trees:
            if real == tree.path or real.startswith(tree.path.rstrip("/") + "/"):
                raise OutputError(f"{flag} {shown} is inside {tree.what} ({display_path(tree.path)})", file=shown)
        if real in self._outputs:
            other = self._outputs[real]
            raise OutputError(f"{flag} {shown} is also the destination of {other.flag}", file=shown)
        _check_parent(dest, flag=flag, shown=shown)
        base, missing = _existing(top)  # the tree's root (or its deepest existing folder), then every folder below
        return dest, real, shown, base, (*missing, *below)

    @property
    def paths(self) -> list[Path]:
        return [o.path for o in self._outputs.values()]

    def planned(self, under: str | os.PathLike[str]) -> dict[str, bytes]:
        """The outputs planned so far inside the folder ``under``: relative POSIX path -> bytes
        (what a release's provenance lists as its subjects, whoever added them)."""
        root = os.path.realpath(under)
        found = {}
        for o in self._outputs.values():
            rel = os.path.relpath(o.path, root)
            if rel != ".." and not rel.startswith("../"):
                found[rel.replace(os.sep, "/")] = o.data if isinstance(o.data, bytes) else o.data.read()
        return found

    def commit(self) -> list[Path]:
        """Write every planned output; rename them into place only when all are written.
        Returns the paths written (not those found :attr:`unchanged`, nor standard output).

        Each destination folder is opened from its existing real folder down, one folder
        at a time with ``O_NOFOLLOW`` (made when missing), and held open: every file is
        staged, renamed and backed up relative to that descriptor, so a folder swapped
        for a symlink meanwhile is never written through. Every folder is held with a
        shared ``flock`` during the commit; a folder whose lock can be taken exclusively
        first loses the staged files and backups a killed commit left there. Every file
        is written to a temporary file beside its destination, then the temporary files
        are fsynced together (a few threads: fsync releases the GIL and the filesystem
        can commit them in one journal transaction); only then is each renamed into
        place, and each folder that changed is fsynced once. Outputs added as ``-`` are
        written to standard output last.

        Raises:
            OutputError: a folder could not be made or written (read-only, full disk...),
                or is a symlink below a tree's root; then no destination has changed and no
                temporary file or new folder is left. Standard output cannot be written.
        """
        outputs = []
        for out in self._outputs.values():
            if out.if_changed and _holds(out):
                self.unchanged.append(out.path)
            else:
                outputs.append(out)
        # a folder whose outputs are all in place already is still swept (the lock beside a
        # document, after a resolve killed while rewriting it)
        for folder in {path.parent for path in self.unchanged} - {out.path.parent for out in outputs}:
            sweep_folder(folder)
        folders = _Folders()
        staged: list[tuple[int, str, _Output]] = []  # (folder descriptor, temporary name, output)
        done: list[tuple[int, _Output, str | None]] = []  # renamed so far, with a link to the file they replaced
        current: _Output | None = None
        try:
            try:
                dirs = []
                for current in outputs:
                    dirs.append(folders.open(current))
                for start in range(0, len(outputs), _OPEN_AT_ONCE):
                    batch = outputs[start : start + _OPEN_AT_ONCE]
                    fds: list[int] = []
                    try:
                        for i, current in enumerate(batch):
                            dfd = dirs[start + i]
                            fd, tmp = _stage(current, dfd)
                            fds.append(fd)
                            staged.append((dfd, tmp, current))
                        failed = _in_parallel(_fsync, fds)
                    finally:
                        for fd in fds:
                            os.close(fd)
                    for i, err in enumerate(failed):
                        if err is not None:
                            current = batch[i]  # the message names the file whose fsync failed
                            raise err
                for dfd, tmp, current in staged:
                    name = current.path.name
                    backup = _keep_previous(dfd, name)
                    try:
                        os.replace(tmp, name, src_dir_fd=dfd, dst_dir_fd=dfd)
                    except OSError:
                        _discard(dfd, backup)
                        raise
                    done.append((dfd, current, backup))
            except BaseException as exc:  # an interrupt (Ctrl-C) is rolled back like a full disk
                _roll_back(done, staged, folders.made)
                if isinstance(exc, _SymlinkedFolder):
                    raise OutputError(str(exc), file=exc.file) from None
                if not isinstance(exc, OSError):
                    raise
                assert current is not None
                raise OutputError(
                    f"cannot write {current.flag} {current.shown}: {exc.strerror or exc}", file=current.shown
                ) from None
            for dfd, _, backup in done:
                _discard(dfd, backup)
        finally:
            folders.close()
        # the renamed files' folders, and the folders that hold a folder this commit made
        changed = {out.path.parent for out in outputs} | {path.parent for _, _, path in folders.made}
        _in_parallel(fsync_dir, sorted(changed))
        for data in self._stdout:
            write_stdout(data)
        return [out.path for out in outputs]


def write_stdout(data: bytes) -> None:
    """``data`` on standard output, flushed.

    Raises:
        OutputError: standard output is closed, full, or a closed pipe.
    """
    import sys

    stream = sys.stdout
    try:
        if stream is None:
            raise OSError(errno.EBADF, "standard output is closed")
        stream.flush()
        stream.buffer.write(data)
        stream.buffer.flush()
    except (OSError, ValueError) as exc:  # ValueError: the stream object was closed
        why = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        raise OutputError(f"cannot write to standard output: {why}") from None


class _SymlinkedFolder(Exception):
    """A folder below a tree's root turned out to be a symlink (or no folder) when opened."""

    def __init__(self, message: str, file: str) -> None:
        super().__init__(message)
        self.file = file


class _Folders:
    """The destination folders of one commit, opened one component at a time and held open
    (with a shared ``flock``) until the commit ends."""

    def __init__(self) -> None:
        self._fds: dict[tuple[str, tuple[str, ...]], int] = {}
        self.made: list[tuple[int, str, Path]] = []  # (parent descriptor, name, path), outermost first
        self._locked: set[int] = set()

    def open(self, out: _Output) -> int:
        """The descriptor of ``out``'s folder, locked and swept of a killed commit's leftovers."""
        fd = self._open(out, len(out.parts))
        if fd not in self._locked:
            self._locked.add(fd)
            _claim(fd)
        return fd

    def _open(self, out: _Output, depth: int) -> int:
        key = (out.base, out.parts[:depth])
        fd = self._fds.get(key)
        if fd is not None:
            return fd
        if depth == 0:
            fd = os.open(out.base, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
        else:
            parent = self._open(out, depth - 1)
            name = out.parts[depth - 1]
            flags = os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC
            try:
                fd = os.open(name, flags, dir_fd=parent)
            except FileNotFoundError:
                os.mkdir(name, out.folder_mode, dir_fd=parent)
                self.made.append((parent, name, Path(out.base, *out.parts[:depth])))
                fd = os.open(name, flags, dir_fd=parent)
            except OSError as exc:
                if exc.errno not in (errno.ELOOP, errno.ENOTDIR):
                    raise
                real = Path(out.base, *out.parts[:depth])
                folder = display_path(real)
                what = "a symlink" if os.path.islink(real) else "not a folder"
                raise _SymlinkedFolder(
                    f"cannot write {out.flag} {out.shown}: {folder} is {what}: refusing to write through it",
                    out.shown,
                ) from None
        self._fds[key] = fd
        return fd

    def close(self) -> None:
        for fd in self._fds.values():
            os.close(fd)  # releases its flock
        self._fds.clear()


def _claim(dfd: int) -> None:
    """Hold a shared ``flock`` on the folder ``dfd`` for this commit. When no other commit
    holds one (the exclusive lock is free), first remove the staged files and backups
    (``.NAME.<12 hex>.tmp|.old``, regular files only) that a killed commit left there."""
    try:
        flock(dfd, wait=False)
    except OSError:  # EWOULDBLOCK: a live commit in this folder; else a filesystem without flock
        with contextlib.suppress(OSError):
            flock(dfd, shared=True)
        return
    sweep_leftovers(dfd)
    flock(dfd, shared=True)  # not atomic: another commit may sweep in between; nothing of ours is there yet


def sweep_folder(folder: str | os.PathLike[str]) -> int:
    """Remove the staged files and backups a killed commit left in ``folder``, unless a commit
    is writing there now (its folder lock is held). Returns how many; never raises."""
    try:
        dfd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    except OSError:
        return 0
    try:
        flock(dfd, wait=False)
        return sweep_leftovers(dfd)
    except OSError:
        return 0
    finally:
        os.close(dfd)


def sweep_leftovers(dfd: int) -> int:
    """Remove OutputPlan's staged files and backups from the folder ``dfd`` (the caller holds its
    exclusive lock: no commit is writing there). Returns how many; never raises."""
    global _LEFTOVER
    if _LEFTOVER is None:
        import re

        _LEFTOVER = re.compile(_LEFTOVER_PATTERN)
    removed = 0
    try:
        names = os.listdir(dfd)
    except OSError:
        return 0
    for name in names:
        if name[:1] != "." or not _LEFTOVER.fullmatch(name):
            continue
        with contextlib.suppress(OSError):
            if stat.S_ISREG(os.lstat(name, dir_fd=dfd).st_mode):
                os.unlink(name, dir_fd=dfd)
                removed += 1
    return removed


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

    Example:
        >>> from hcdf_trust.include import verify
        >>> from hcdf_trust.outputs import OutputPlan, protect_inputs
        >>> res = verify("examples/robot/robot.hcdf")
        >>> plan = OutputPlan()
        >>> protect_inputs(plan, res)
        >>> plan.protect(res.lock_path, what="the lock file")  # this run only reads the lock
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


def _in_tree(text: str, root: str, *, flag: str, shown: str) -> tuple[Path, tuple[str, ...]]:
    """The real folder of the tree root ``root`` and the folders from it to ``text``'s folder.

    The root is the user's: a symlink there is followed. Below it, every existing folder
    must be a real folder, not a symlink (``rel/<board>`` -> elsewhere would write outside).

    Raises:
        OutputError: ``text`` does not lie below ``root`` by name, passes ``..``, or
            a folder below the root is a symlink or not a folder.
    """
    cwd = os.getcwd()
    parts, top = PurePath(os.path.join(cwd, text)).parts, PurePath(os.path.join(cwd, root)).parts
    if parts[: len(top)] != top or len(parts) <= len(top) or ".." in parts[len(top) :]:
        raise OutputError(f"{flag} {shown} is not inside the output folder {display_place(root)}", file=shown)
    below = parts[len(top) : -1]
    real_root = Path(os.path.realpath(os.path.join(cwd, root)))
    folder = real_root
    for name in below:
        folder = folder / name
        try:
            st = os.lstat(folder)
        except (FileNotFoundError, NotADirectoryError):
            break  # made by commit (which opens each with O_NOFOLLOW, in case one appears meanwhile)
        except OSError as exc:
            raise OutputError(f"{flag} {shown}: {exc.strerror}", file=shown) from None
        if stat.S_ISLNK(st.st_mode):
            raise OutputError(
                f"{flag} {shown}: {display_place(os.path.join(root, *folder.relative_to(real_root).parts))} "
                "is a symlink inside the output folder: refusing to write through it",
                file=shown,
            )
    return real_root, below


def _existing(folder: Path) -> tuple[str, tuple[str, ...]]:
    """The deepest existing ancestor of the real path ``folder`` (itself if it exists), and the
    names of the folders below it that do not exist yet."""
    missing: list[str] = []
    while not os.path.isdir(folder) and folder.parent != folder:
        missing.append(folder.name)
        folder = folder.parent
    return os.fspath(folder), tuple(reversed(missing))


def kind_of(data: bytes) -> str:
    """What ``data`` (a file's first bytes) is, for the replace rule: :data:`PRIVATE_KEY`,
    :data:`PUBLIC_KEY`, :data:`KEY_STORE`, :data:`REGISTRY_SOURCE`, :data:`BUNDLE`, :data:`DOCUMENT`,
    else :data:`ORDINARY`."""
    head = data[:_SNIFF_BYTES]
    # A bundle (before the marks: its first entry holds "<hcdf "): a local header whose name ends .hcdf.
    if head[:4] == b"PK\x03\x04" and len(head) >= 30:
        name_len = int.from_bytes(head[26:28], "little")
        if head[30 : 30 + name_len].endswith(b".hcdf"):
            return BUNDLE
    for mark, kind in _MARKS:
        if mark in head:
            return kind
    return ORDINARY


def _check_replace(real: str, replaces: tuple[str, ...] | None, *, flag: str, shown: str) -> None:
    """Refuse to replace the existing regular file ``real`` unless the output may (see :meth:`OutputPlan.add`)."""
    if replaces == NEW_ONLY:
        raise OutputError(f"{flag} {shown} exists: refusing to replace it (use --force)", file=shown)
    try:
        fd = os.open(real, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError:
        head = None  # unreadable: it cannot be told apart from what it must not be
    else:
        try:
            head = os.read(fd, _SNIFF_BYTES)
        except OSError:
            head = None
        finally:
            os.close(fd)
    kind = kind_of(head) if head is not None else "a file that cannot be read"
    allowed = (ORDINARY,) if replaces is None else replaces
    if kind not in allowed:
        what = f"is not {' or '.join(allowed)}" if kind == ORDINARY else f"is {kind}"
        raise OutputError(f"{flag} {shown} {what}: refusing to replace it", file=shown)


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
    assert isinstance(out.data, bytes)  # add() refuses if_changed with a file output
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


def _stage(out: _Output, dfd: int) -> tuple[int, str]:
    """Write ``out`` to a temporary file in the folder ``dfd``, with its mode from the first
    byte; return the open descriptor (to fsync) and the temporary file's name."""
    if isinstance(out.data, HeldFile):
        adopted = _adopt(out.data, out, dfd)
        if adopted is not None:
            return adopted
    fd, tmp = create_temp(out.path.parent, f".{out.path.name}.", ".tmp", dir_fd=dfd)  # 0600
    try:
        os.fchmod(fd, out.mode)
        if isinstance(out.data, FileContent):
            src = os.open(out.data.path, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC)
            try:
                _copy(src, out.data, fd, shown=out.shown)
            finally:
                os.close(src)
        elif isinstance(out.data, HeldFile):  # on another filesystem than its destination
            _copy(out.data.fd, out.data, fd, shown=out.shown)
        else:
            view = memoryview(out.data)
            while view:
                view = view[os.write(fd, view) :]
    except BaseException:
        os.close(fd)
        with contextlib.suppress(OSError):
            os.unlink(tmp, dir_fd=dfd)
        raise
    return fd, tmp


_COPY_CHUNK = 1 << 20


def _adopt(held: HeldFile, out: _Output, dfd: int) -> tuple[int, str] | None:
    """Link the held file under a temporary name in the folder ``dfd`` and take it as ``out``'s
    staged file (see :class:`HeldFile`): a new descriptor of it and the temporary name; None
    when it lies on another filesystem (the caller copies it).

    Raises:
        IntegrityError: the file at ``held.path`` is not the one held, not ``held.size`` bytes,
            or has another link (nothing is left in ``dfd``).
    """
    from .errors import IntegrityError

    held_st = os.fstat(held.fd)
    for _ in range(8):
        tmp = f".{out.path.name}.{os.urandom(6).hex()}.tmp"
        try:
            os.link(held.path, tmp, dst_dir_fd=dfd, follow_symlinks=False)  # never replaces a file
        except FileExistsError:
            continue
        except OSError as exc:
            if exc.errno in (errno.EXDEV, errno.EPERM, errno.EMLINK, errno.EOPNOTSUPP):
                return None  # another filesystem, or one without hard links
            raise
        break
    else:
        raise FileExistsError(errno.EEXIST, "no unused temporary file name", os.fspath(out.path.parent))
    try:
        st = os.stat(tmp, dir_fd=dfd, follow_symlinks=False)
        if (st.st_dev, st.st_ino) != (held_st.st_dev, held_st.st_ino) or not stat.S_ISREG(st.st_mode):
            why = "is no longer the file that was verified"
        elif held_st.st_size != held.size:
            why = f"holds {held_st.st_size} bytes, not the {held.size} verified"
        else:
            os.unlink(held.path)
            links = os.fstat(held.fd).st_nlink
            why = f"has {links - 1} other link(s) through which it could be rewritten" if links != 1 else ""
        if why:
            raise IntegrityError(
                f"{out.shown}: its staged file {display_path(held.path)} {why} (nothing written)", file=out.shown
            )
        os.fchmod(held.fd, out.mode)
        return os.dup(held.fd), tmp
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp, dir_fd=dfd)
        raise


def _copy(src: int, source: FileContent | HeldFile, fd: int, *, shown: str) -> None:
    """Copy the file ``src`` (``source``'s) into ``fd`` a chunk at a time from its start,
    hashing what is written.

    Raises:
        IntegrityError: the bytes copied are not ``source.size`` bytes of ``source.sha256``.
        OSError: reading or writing failed.
    """
    import hashlib

    from .errors import IntegrityError

    h = hashlib.sha256()
    size = 0
    while chunk := os.pread(src, _COPY_CHUNK, size):
        h.update(chunk)
        size += len(chunk)
        if size > source.size:
            break
        view = memoryview(chunk)
        while view:
            view = view[os.write(fd, view) :]
    if size != source.size or h.hexdigest() != source.sha256:
        raise IntegrityError(
            f"{shown}: its source {display_path(source.path)} changed after it was verified (nothing written)",
            file=shown,
            expected=f"{source.sha256} ({source.size} bytes)",
            actual=f"{h.hexdigest()} ({size}{'+' if size > source.size else ''} bytes)",
        )


def _keep_previous(dfd: int, name: str) -> str | None:
    """A hard link to the file ``name`` in the folder ``dfd`` names now, so a failed commit can
    put it back.

    None when there is no such file, or the filesystem cannot link it (then that one
    destination cannot be restored; the others still are).
    """
    for _ in range(8):
        backup = f".{name}.{os.urandom(6).hex()}.old"
        try:
            os.link(name, backup, src_dir_fd=dfd, dst_dir_fd=dfd, follow_symlinks=False)
        except FileExistsError:
            continue
        except OSError:
            return None
        return backup
    return None


def _discard(dfd: int, backup: str | None) -> None:
    if backup is not None:
        with contextlib.suppress(OSError):
            os.unlink(backup, dir_fd=dfd)


def _roll_back(
    done: list[tuple[int, _Output, str | None]],
    staged: list[tuple[int, str, _Output]],
    made: list[tuple[int, str, Path]],
) -> None:
    """Undo a failed commit: restore replaced files, drop new ones, temporaries and new folders."""
    for dfd, out, backup in reversed(done):
        with contextlib.suppress(OSError):
            if backup is not None:
                os.replace(backup, out.path.name, src_dir_fd=dfd, dst_dir_fd=dfd)
            else:
                os.unlink(out.path.name, dir_fd=dfd)
    renamed = {id(out) for _, out, _ in done}
    for dfd, tmp, out in staged:
        if id(out) not in renamed:
            with contextlib.suppress(OSError):
                os.unlink(tmp, dir_fd=dfd)
    for parent, name, _ in reversed(made):
        with contextlib.suppress(OSError):
            os.rmdir(name, dir_fd=parent)
