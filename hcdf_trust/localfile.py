"""Reading local files safely: regular files only, never blocking, always bounded.

Every local input — documents, includes, model files, the lock file, and later
keys, configurations, manifests and metadata — is opened here. A FIFO, a device,
a directory or a symlink to ``/dev/zero`` is refused at once (``O_NONBLOCK`` and an
``fstat`` on the opened descriptor), and whole-file reads stop at a size cap.
Kept apart from the HTTPS fetcher so that an offline run never imports ``ssl``.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import os
import re
import stat
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from .digest import CHUNK, SMALL_FILE, Hashed, hash_fd, read_small
from .errors import InputError, NotFoundError, PathEscapeError, SecretFileError, display_path

# O_NONBLOCK: opening a FIFO must not wait for a writer. It has no effect on
# reads from a regular file, the only kind we go on to read.
_FLAGS = os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC
_ENTRY_FLAGS = _FLAGS | os.O_NOFOLLOW  # ConfinedFolders: an entry of the checked folder, never a link


def open_regular(
    path: Path | str, *, file: str | None = None, line: int | None = None, what: str = "file"
) -> tuple[int, os.stat_result]:
    """Open ``path`` read-only without blocking; refuse anything but a regular file.

    The caller closes the descriptor. Symlinks are followed (confinement is
    :func:`open_checked`'s job), but what they lead to must be a regular file.

    Raises:
        NotFoundError: it does not exist.
        InputError: unreadable, a directory, FIFO, socket or device.
    """
    fd = _open(path, file=file, line=line, what=what)
    try:
        return fd, _regular(fd, path, file=file, line=line)
    except BaseException:
        os.close(fd)
        raise


def open_checked(
    path: Path | str, root: Path | str, *, file: str | None = None, line: int | None = None
) -> tuple[int, os.stat_result]:
    """Open a regular file that really lies inside ``root``; return its descriptor and stat.

    The symlink check is made on the opened descriptor (``/proc/self/fd``), so a
    link swapped in between check and use cannot lead outside the root. The caller
    closes the descriptor (or uses :func:`open_local`).

    Raises:
        NotFoundError, PathEscapeError, InputError (not a regular file, unreadable).
    """
    fd = _open(path, file=file, line=line, what="file")
    try:
        real = os.readlink(f"/proc/self/fd/{fd}")
        if not _inside(real, root):
            shown_root = display_path(_realpath(os.path.abspath(root)))
            raise PathEscapeError(
                f"{display_path(path)} resolves to {display_path(real)}, outside the root {shown_root} "
                "(symlink escape)",
                file=file,
                line=line,
                expected=f"a file inside {shown_root}",
                actual=display_path(real),
            )
        return fd, _regular(fd, path, file=file, line=line)
    except BaseException:
        os.close(fd)
        raise


def _open(path: Path | str, *, file: str | None, line: int | None, what: str) -> int:
    try:
        return os.open(path, _FLAGS)
    except FileNotFoundError:
        raise NotFoundError(f"{display_path(path)}: no such {what}", file=file, line=line, url=str(path)) from None
    except OSError as exc:  # ELOOP (a symlink loop), EACCES, ENOTDIR, ...
        raise InputError(f"{display_path(path)}: cannot open: {exc.strerror}", file=file, line=line) from None


def _regular(fd: int, path: Path | str, *, file: str | None, line: int | None) -> os.stat_result:
    st = os.fstat(fd)
    if stat.S_ISREG(st.st_mode):
        return st
    mode = st.st_mode
    if stat.S_ISDIR(mode):
        raise InputError(f"{display_path(path)} is a directory", file=file, line=line)
    kind = "a FIFO" if stat.S_ISFIFO(mode) else "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode) else "special"
    raise InputError(f"{display_path(path)} is not a regular file ({kind})", file=file, line=line)


@contextlib.contextmanager
def open_local(
    path: Path | str, root: Path | str, *, file: str | None = None, line: int | None = None
) -> Iterator[int]:
    """:func:`open_checked` as a context manager that yields the descriptor."""
    fd, _ = open_checked(path, root, file=file, line=line)
    try:
        yield fd
    finally:
        os.close(fd)


def hash_local(path: Path | str, root: Path | str, *, file: str | None = None, line: int | None = None) -> Hashed:
    """Hash a confined local file in constant memory (the hot path for model files)."""
    fd, st = open_checked(path, root, file=file, line=line)
    try:
        return hash_fd(fd, size=st.st_size, inode=(st.st_dev, st.st_ino))
    finally:
        os.close(fd)


class ConfinedFolders:
    """:func:`open_checked` for many files of a few folders, with a quarter of its system calls.

    The first file of a folder opens the folder (``O_PATH``) and checks the real path of
    that descriptor against the root, once; each of its files is then opened relative
    to the descriptor with ``O_NOFOLLOW``, so it is an entry of the very folder that
    was checked and not a link: as strict as the check on each file's descriptor, with
    no path looked up twice. Anything else (a file that is a symlink, a folder outside
    the root or that cannot be opened, a missing file) goes through :func:`open_checked`,
    which follows links that stay inside and names what it refuses. Thread-safe;
    :meth:`close` once the run's files are all read.
    """

    # Folders kept open per run; the files of further folders take open_checked's path.
    MAX_FOLDERS = 128

    def __init__(self) -> None:
        self._folders: dict[tuple[str, str], int | None] = {}  # (folder, root) -> descriptor
        self._lock = threading.Lock()
        self._last: tuple[str | None, Path | str | None, int | None] = (None, None, None)  # hash_entry's folder

    def open(
        self, path: str, root: Path | str, *, file: str | None = None, line: int | None = None
    ) -> tuple[int, os.stat_result]:
        """:func:`open_checked` (same result, same errors)."""
        folder, sep, name = path.rpartition("/")
        dirfd = self._folder(folder or "/", root) if sep and name not in ("", ".", "..") else None
        if dirfd is not None:
            try:
                fd = os.open(name, _ENTRY_FLAGS, dir_fd=dirfd)
            except OSError:
                pass  # ELOOP (a symlink), ENOENT, ...: open_checked follows it or names the error
            else:
                st = os.fstat(fd)
                if stat.S_ISREG(st.st_mode):
                    return fd, st
                try:
                    _regular(fd, path, file=file, line=line)  # raises, naming what it is
                finally:
                    os.close(fd)
        return open_checked(path, root, file=file, line=line)

    def hash(self, path: str, root: Path | str, *, file: str | None = None, line: int | None = None) -> Hashed:
        """:func:`hash_local` through :meth:`open`."""
        fd, st = self.open(path, root, file=file, line=line)
        try:
            return hash_fd(fd, size=st.st_size, inode=(st.st_dev, st.st_ino))
        finally:
            os.close(fd)

    def hash_entry(self, path: str, root: Path | str) -> tuple[str, int, tuple[int, int]] | None:
        """(sha256, size, inode) of a regular file that is an entry of a checked folder, with
        nothing but the system calls and the hash: ``None`` for anything else (no folder
        descriptor, a link, a missing or special file, a read error), for which :meth:`hash`
        takes the general path and names the error.

        The resolver's loop over 10,000 small files: as strict as :meth:`open` (the very
        same descriptor check and ``O_NOFOLLOW`` open), a third of :meth:`hash`'s Python work.
        """
        folder, sep, name = path.rpartition("/")
        if not sep or name in ("", ".", ".."):
            return None
        last_folder, last_root, dirfd = self._last  # the files of a folder come in a row
        if folder != last_folder or root is not last_root:
            dirfd = self._folder(folder or "/", root)
            self._last = (folder, root, dirfd)
        if dirfd is None:
            return None
        try:
            fd = os.open(name, _ENTRY_FLAGS, dir_fd=dirfd)
        except OSError:
            return None
        try:
            st = os.fstat(fd)
            size = st.st_size
            if not stat.S_ISREG(st.st_mode):
                return None
            if size > SMALL_FILE:  # hash_fd's chunked reads, on the descriptor already checked
                hashed = hash_fd(fd, size=size)
                return hashed.sha256, hashed.size, (st.st_dev, st.st_ino)
            data = read_small(fd, size)  # hash_fd's small-file read, without building a Hashed
        except OSError:
            return None
        finally:
            os.close(fd)
        return hashlib.sha256(data).hexdigest(), len(data), (st.st_dev, st.st_ino)

    def _folder(self, folder: str, root: Path | str) -> int | None:
        """A descriptor of ``folder`` when its real path lies inside ``root``; else None."""
        key = (folder, os.fspath(root))
        try:
            return self._folders[key]
        except KeyError:
            pass
        with self._lock:
            if key in self._folders or len(self._folders) >= self.MAX_FOLDERS:
                return self._folders.get(key)
            dirfd: int | None = None
            try:
                dirfd = os.open(folder, os.O_PATH | os.O_DIRECTORY | os.O_CLOEXEC)
                inside = _inside(os.readlink(f"/proc/self/fd/{dirfd}"), root)
            except OSError:
                inside = False
            if dirfd is not None and not inside:
                os.close(dirfd)
                dirfd = None
            self._folders[key] = dirfd
            return dirfd

    def close(self) -> None:
        with self._lock:
            for dirfd in self._folders.values():
                if dirfd is not None:
                    os.close(dirfd)
            self._folders.clear()
            self._last = (None, None, None)


def _inside(real: str, root: Path | str) -> bool:
    """Is the real path ``real`` the root or below it (by the root's real path)?"""
    real_root = _realpath(os.path.abspath(root))  # absolute: the cache must not outlive a chdir
    return real == real_root or real.startswith(real_root.rstrip("/") + "/")


@functools.lru_cache(maxsize=64)
def _realpath(root: str) -> str:
    """A root's real path, once per run: every file under it is checked against it."""
    return os.path.realpath(root)


def read_bounded(fd: int, limit: int, *, source: str, what: str = "document") -> bytes:
    """A regular file's whole content, refused (never truncated) past ``limit`` bytes.

    Checked before reading (no large read for an oversize file) and after (it may
    have grown meanwhile).

    Raises:
        InputError: over the limit.
    """
    return b"".join(stream_bounded(fd, limit, source=source, what=what))


def stream_bounded(fd: int, limit: int, *, source: str, what: str = "document") -> Iterator[bytes]:
    """:func:`read_bounded` as chunks, for a file hashed or checked as it is read and never
    held whole (an MCUboot image through :class:`~hcdf_trust.ota.mcuboot.ImageStream`).

    Raises:
        InputError: over the limit (before the first read, or once it grew past it).
    """
    if os.fstat(fd).st_size > limit:
        raise InputError(f"{what} is over the {limit}-byte limit", file=source)
    got = 0
    for chunk in read_chunks(fd):
        got += len(chunk)
        if got > limit:
            raise InputError(f"{what} is over the {limit}-byte limit", file=source)
        yield chunk


def read_whole(fd: int, limit: int, *, source: str, what: str) -> bytearray:
    """:func:`read_bounded` into one buffer of the file's size, without its copy (for inputs
    of up to gigabytes that are kept whole: a bundle). A file that shrinks or grows while it
    is read is refused: what is checked must be all of what was there.

    Raises:
        InputError: over the limit, or changed while read.
    """
    size = os.fstat(fd).st_size
    if size > limit:
        raise InputError(f"{what} is over the {limit}-byte limit", file=source)
    buf = bytearray(size)
    view = memoryview(buf)
    done = 0
    while done < size and (got := os.readv(fd, [view[done:]])):
        done += got
    view.release()
    if done != size or os.read(fd, 1):
        raise InputError(f"{what} changed size while it was read ({size} bytes when opened)", file=source)
    return buf


def read_input(path: Path | str, *, limit: int, what: str = "file", source: str | None = None) -> bytes:
    """The whole content of a local input that is not confined to a root (a lock file,
    a key, a configuration, a manifest): regular file only, never blocking, at most
    ``limit`` bytes. ``source`` is how errors name it (default: ``path``).

    Raises:
        NotFoundError: it does not exist.
        InputError: not a regular file, unreadable, or over ``limit``.
    """
    name = source or str(path)
    fd, _ = open_regular(path, file=name, what=what)
    try:
        return read_bounded(fd, limit, source=name, what=what)
    except OSError as exc:
        raise InputError(f"{name}: cannot read {what}: {exc.strerror}", file=name) from None
    finally:
        os.close(fd)


def read_secret(path: Path | str, *, limit: int, what: str, public_ok: bool = False) -> bytes:
    """The whole content of a private key, passphrase or PIN file (:func:`read_input`), refused
    when its group or others have any access to it, the way ssh refuses an unprotected private
    key: a secret others could read is no longer a secret, and one they could write is not ours.
    ``public_ok``: a PEM public key given in its place is returned as it is, for the caller to
    say that it is not the private key.

    Raises:
        SecretFileError: group or others have access (the message gives the ``chmod`` to run).
        NotFoundError / InputError: as :func:`read_input`.
    """
    name = str(path)
    fd, st = open_regular(path, file=name, what=what)
    try:
        data = read_bounded(fd, limit, source=name, what=what)
        if not (public_ok and b"PUBLIC KEY-----" in data and b"PRIVATE KEY" not in data):
            check_private(st, name, what=what)
        return data
    except OSError as exc:
        raise InputError(f"{name}: cannot read {what}: {exc.strerror}", file=name) from None
    finally:
        os.close(fd)


def read_private_config(path: Path | str, *, limit: int, what: str) -> tuple[bytes, os.stat_result]:
    """A configuration file that may hold secrets (the Docker config's ``auths``): its bytes
    and its ``stat``, for the caller to :func:`check_private` once it knows whether it holds a
    secret. Refused at once when group or others may *write* it: its settings (which helper
    runs, which credentials go where) would be theirs.

    Raises:
        SecretFileError: group- or world-writable. NotFoundError / InputError: as :func:`read_input`.
    """
    name = str(path)
    fd, st = open_regular(path, file=name, what=what)
    try:
        data = read_bounded(fd, limit, source=name, what=what)
    except OSError as exc:
        raise InputError(f"{name}: cannot read {what}: {exc.strerror}", file=name) from None
    finally:
        os.close(fd)
    check_private(st, name, what=what, mask=0o022)
    return data, st


def check_private(st: os.stat_result, name: str, *, what: str, mask: int = 0o077) -> None:
    """ssh's rule for a file holding a secret: neither group nor others have access (the bits
    of ``mask``). The message names the ``chmod`` to run.

    Raises:
        SecretFileError: a bit of ``mask`` is set in the file's mode.
    """
    mode = stat.S_IMODE(st.st_mode)
    if mode & mask:
        import shlex

        who = "accessible" if mask == 0o077 else "writable"
        raise SecretFileError(
            f"permissions {mode:04o} are too open: a {what} must be {who} by its owner only "
            f"(as ssh requires of a private key); run: chmod 600 {shlex.quote(display_path(name))}",
            file=name,
            expected="mode 0600 or 0400",
            actual=f"mode {mode:04o}",
        )


class TomlError(InputError):
    """A TOML input is not UTF-8, not TOML, or nested deeper than :data:`MAX_TOML_DEPTH`."""

    code = "toml"


# Deepest nesting of tables and arrays accepted in a TOML input. Ours need 4; tomllib parses
# inline tables and arrays recursively with no limit of its own (a few KB of "[[[[" exhaust
# Python's stack), so the text is measured before it is parsed.
MAX_TOML_DEPTH = 32
# Comments and strings (whose brackets do not nest), and the brackets that do.
_TOML_TOKEN = re.compile(
    r"#[^\n]*"
    r'|"""(?:\\.|[^\\])*?"""(?:"{1,2}(?!"))?'
    r"|'''.*?'''(?:'{1,2}(?!'))?"
    r'|"(?:\\.|[^"\\\n])*"'
    r"|'[^'\n]*'"
    r"|[\[\]{}]",
    re.S,
)


def read_toml(
    path: Path | str,
    *,
    limit: int,
    what: str,
    source: str | None = None,
    error: type[InputError] = TomlError,
) -> dict[str, Any]:
    """The one TOML reader: a local file read by :func:`read_input` (at most ``limit`` bytes),
    UTF-8, nested at most :data:`MAX_TOML_DEPTH` deep (checked before ``tomllib`` parses it,
    and again on the result, which dotted keys can nest without brackets).

    Raises:
        ``error`` (an :class:`InputError`, exit 3; :class:`TomlError` by default): not UTF-8,
            not TOML (with its line), too deep.
        NotFoundError / InputError: as :func:`read_input`.
    """
    import tomllib

    name = source or str(path)
    data = read_input(path, limit=limit, what=what, source=name)
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise error(f"{what} is not UTF-8 text ({exc.reason} at byte {exc.start})", file=name) from None
    depth, line = _toml_nesting(text)
    if depth > MAX_TOML_DEPTH:
        raise _too_deep(error, what, name, line)
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        found = re.search(r"at line (\d+)", str(exc))
        raise error(
            f"{what} is not valid TOML: {exc}", file=name, line=int(found.group(1)) if found else None
        ) from None
    if _depth(doc) > MAX_TOML_DEPTH:
        raise _too_deep(error, what, name, None)
    return doc


def _too_deep(error: type[InputError], what: str, name: str, line: int | None) -> InputError:
    return error(f"{what} nests tables or arrays more than {MAX_TOML_DEPTH} levels deep", file=name, line=line)


def _toml_nesting(text: str) -> tuple[int, int | None]:
    """The deepest bracket nesting of a TOML text outside strings and comments, and the line
    where it first goes past :data:`MAX_TOML_DEPTH` (None when it does not)."""
    depth = deepest = 0
    for m in _TOML_TOKEN.finditer(text):
        token = m.group()
        if token in "[{":
            depth += 1
            if depth > deepest:
                deepest = depth
                if depth > MAX_TOML_DEPTH:
                    return depth, text.count("\n", 0, m.start()) + 1
        elif token in "]}":
            depth -= 1
    return deepest, None


def _depth(value: object) -> int:
    """How deep tables and arrays nest in a parsed document (iteratively: no recursion)."""
    deepest = 0
    stack: list[tuple[object, int]] = [(value, 0)]  # the document itself is no nesting
    while stack:
        item, level = stack.pop()
        children = item.values() if isinstance(item, dict) else item if isinstance(item, list) else None
        if children is None:
            continue
        deepest = max(deepest, level)
        if deepest > MAX_TOML_DEPTH:
            return deepest
        stack.extend((child, level + 1) for child in children)
    return deepest


def read_chunks(fd: int) -> Iterator[bytes]:
    """Yield a regular file's content from ``fd``; one read for small files."""
    size = os.fstat(fd).st_size
    if size <= SMALL_FILE:
        yield read_small(fd, size)
        return
    while data := os.read(fd, CHUNK):
        yield data


def absolute(path: str | os.PathLike[str]) -> str:
    """``path`` (as given on a command line) made absolute the way the kernel resolves it.

    ``os.path.abspath`` collapses ``link/..`` lexically, naming another file than the
    one the shell opens when ``link`` is a symlink: here everything up to the last
    ``..`` is resolved as the kernel does, and the rest is kept as written.
    """
    text = os.fspath(path)
    parts = text.split(os.sep)
    if ".." not in parts:
        return os.path.abspath(text)
    last = len(parts) - parts[::-1].index("..")
    head = os.path.realpath(os.sep.join(parts[:last]) or os.sep)
    return os.path.normpath(os.path.join(head, *parts[last:]))


# --- the one strict JSON reader ------------------------------------------------------

#: Deepest nesting of objects and lists any JSON we read may have (ours are 5 deep at most).
MAX_JSON_DEPTH = 64
#: A bound for small JSON answers (registry manifests, tokens, credential helpers).
MAX_JSON_BYTES = 4 << 20
_SURROGATE_ESCAPE = re.compile(r"\\u[dD][89a-fA-F]")  # the only way a lone surrogate gets into a str
_SURROGATE = re.compile("[\ud800-\udfff]")


class JsonError(InputError):
    """Bytes that are not one unambiguous JSON document: every JSON reader refuses them alike."""

    code = "malformed-json"


class JsonNumber(str):
    """A JSON number exactly as written (``1.0``, ``0.0450``, ``1e-3``): ``parse_json(exact=True)``."""

    __slots__ = ()


class _Duplicated(dict):  # type: ignore[type-arg]
    """An object that held a key twice (``key``): named with its JSON Pointer after parsing."""

    key: str


def parse_json(
    data: bytes,
    *,
    source: str,
    what: str = "document",
    limit: int,
    floats: bool = True,
    exact: bool = False,
    max_objects: int | None = None,
) -> Any:
    """``data`` as JSON, read so that every reader sees the same values as every other parser.

    Python's ``json`` keeps the last of two equal keys where other parsers keep the first
    (``"url"`` twice: one party checks one URL, another fetches the other), and accepts
    ``NaN``/``Infinity``, lone surrogates (``"\\ud800"``, which no UTF-8 encoder writes),
    UTF-16 input and nesting deep enough to exhaust the stack. All are refused here, with
    a JSON Pointer or line naming where; ``floats=False`` refuses non-integer numbers too.
    ``exact=True`` gives every number as its literal (a :class:`JsonNumber`, a str): HCDF's
    JSON form keeps ``1.0`` and ``0.0450`` as written. ``max_objects`` stops the parse at the
    first object over it: ~100 bytes of memory each, a 32 MiB flood of ``{}`` would be ~8M.

    Raises:
        JsonError: over ``limit`` bytes, not UTF-8, not JSON, or any ambiguity above.
    """
    import json

    if len(data) > limit:
        raise JsonError(f"{what} is over the {limit}-byte limit", file=source)
    try:
        text = data.decode("utf-8")  # never json's UTF-16/32 guess
    except UnicodeDecodeError as exc:
        raise JsonError(f"{what} is not UTF-8: {exc.reason} at byte {exc.start}", file=source) from None

    def bad_float(token: str) -> float:
        value = float(token)
        if not floats:
            raise JsonError(f"{what}: number {token[:40]} is not an integer", file=source)
        if value in (float("inf"), float("-inf")):
            raise JsonError(f"{what}: number {token[:40]} is out of range", file=source)
        return value

    def literal(token: str) -> Any:
        bad_float(token)  # still finite and in range
        return JsonNumber(token)

    def bad_constant(token: str) -> None:
        raise JsonError(f"{what}: {token} is not a JSON number", file=source)

    duplicated = False
    objects = 0

    def pairs(items: list[tuple[str, Any]]) -> dict[str, Any]:
        nonlocal duplicated, objects
        objects += 1
        if max_objects is not None and objects > max_objects:
            raise JsonError(
                f"{what} has more than {max_objects:,} objects: over the cap on elements",
                file=source,
                expected=f"at most {max_objects:,} objects",
            )
        out = dict(items)
        if len(out) == len(items):
            return out
        duplicated = True
        seen: set[str] = set()
        marked = _Duplicated(items)
        marked.key = next(k for k, _ in items if k in seen or seen.add(k))  # type: ignore[func-returns-value]
        return marked

    hooks: dict[str, Any] = {"parse_float": literal, "parse_int": JsonNumber} if exact else {"parse_float": bad_float}
    try:
        doc = json.loads(text, parse_constant=bad_constant, object_pairs_hook=pairs, **hooks)
    except json.JSONDecodeError as exc:
        raise JsonError(f"{what} is not JSON: {exc.msg} (column {exc.colno})", file=source, line=exc.lineno) from None
    except RecursionError:
        raise JsonError(
            f"{what} is nested too deeply", file=source, expected=f"at most {MAX_JSON_DEPTH} levels"
        ) from None
    except ValueError as exc:  # an integer of more than 4300 digits
        raise JsonError(f"{what} is not JSON: {exc}", file=source) from None
    strings = _SURROGATE_ESCAPE.search(text) is not None
    if duplicated or strings or not _shallow(doc):  # the walk that names where, only when needed
        _check_tree(doc, what=what, source=source, strings=strings)
    return doc


def _shallow(doc: Any) -> bool:
    """Is ``doc`` at most :data:`MAX_JSON_DEPTH` deep? One level at a time, in C-speed comprehensions."""
    level = [doc] if type(doc) is dict or type(doc) is list else []
    depth = 0
    while level:
        depth += 1
        if depth > MAX_JSON_DEPTH:
            return False
        level = [
            v
            for node in level
            for v in (node.values() if type(node) is dict else node)
            if type(v) is dict or type(v) is list
        ]
    return True


def _check_tree(doc: Any, *, what: str, source: str, strings: bool) -> None:
    """Depth, duplicate keys and (when ``strings``) lone surrogates, named by JSON Pointer."""

    def pointer(path: tuple[Any, ...] | None) -> str:
        parts: list[str] = []
        while path is not None:
            key, path = path
            parts.append(str(key).replace("~", "~0").replace("/", "~1"))
        return "/" + "/".join(reversed(parts)) if parts else "(the document)"

    if not isinstance(doc, (dict, list)):
        if strings and isinstance(doc, str) and _SURROGATE.search(doc):
            raise JsonError(f"{what}: the string holds a lone surrogate", file=source)
        return
    stack: list[tuple[Any, int, tuple[Any, ...] | None]] = [(doc, 1, None)]
    while stack:
        node, depth, path = stack.pop()
        if depth > MAX_JSON_DEPTH:
            raise JsonError(
                f"{what} is nested too deeply at {pointer(path)}",
                file=source,
                expected=f"at most {MAX_JSON_DEPTH} levels",
            )
        items: Any
        if isinstance(node, dict):
            if type(node) is _Duplicated:
                raise JsonError(
                    f"{what}: key {node.key!r} appears twice in the object at {pointer(path)} "
                    "(parsers disagree on which one counts)",
                    file=source,
                )
            items = node.items()
        else:
            items = enumerate(node)
        for key, value in items:
            if strings and isinstance(key, str) and _SURROGATE.search(key):
                raise JsonError(f"{what}: a key at {pointer(path)} holds a lone surrogate", file=source)
            if isinstance(value, (dict, list)):
                stack.append((value, depth + 1, (key, path)))
            elif strings and isinstance(value, str) and _SURROGATE.search(value):
                raise JsonError(f"{what}: the string at {pointer((key, path))} holds a lone surrogate", file=source)
