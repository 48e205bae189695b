"""Where a reference points: relative resolution, ``--base``, ``--mirror``, root confinement.

Pure functions over strings and paths: no file is opened and no socket used here.
A URL with credentials (``https://user:pass@host/``), in a document or a flag, is
refused, and messages show it redacted (:func:`redact`), so no secret reaches the
lock file, a flattened document, a message or ``--json``.
A :class:`Location` keeps the *logical* URL (what the document means, recorded in
the lock file, the same with or without a mirror) apart from where the bytes are
actually read (a local path confined to a root, or a remote URL).
"""

from __future__ import annotations

import functools
import os
import posixpath
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import quote, unquote, urljoin, urlsplit

from ..errors import CredentialsError, InputError, NotFoundError, PathEscapeError, userinfo_end
from ..errors import display_path as display_path  # re-exported: how messages name a local file
from ..errors import redact as redact  # re-exported: how messages show a URL with credentials
from ..localfile import absolute

REMOTE_SCHEMES = ("https", "http")
# Unreserved URL characters plus "/": text that means the same as a URL and as a path.
_PLAIN = re.compile(r"[A-Za-z0-9._~/-]+\Z")
# ...and already normal as a path: no empty, "." or ".." segment (none starts with ".").
_NORMAL_SEGMENT = r"[A-Za-z0-9_~-][A-Za-z0-9._~-]*"
_PLAIN_NORMAL = re.compile(rf"{_NORMAL_SEGMENT}(?:/{_NORMAL_SEGMENT})*\Z")


@dataclass(frozen=True, init=False)
class Location:
    url: str  # logical identity: file:///abs/path or https://…
    path: str | None = None  # read from here (local file or local mirror), normalised
    root: Path | None = None  # ...which must stay inside this folder
    remote: str | None = None  # or fetch from here (after mirror rewrite)

    def __init__(self, url: str, path: str | None = None, root: Path | None = None, remote: str | None = None) -> None:
        # Items of the instance dict, not the generated frozen __init__'s object.__setattr__
        # per field (one Location per reference: 10,000 a run on a large tree).
        d = self.__dict__
        d["url"] = url
        d["path"] = path
        d["root"] = root
        d["remote"] = remote

    @property
    def is_local(self) -> bool:
        return self.path is not None

    @property
    def scheme(self) -> str:
        return urlsplit(self.remote or self.url).scheme


def file_url(path: str | os.PathLike[str], *, directory: bool = False) -> str:
    """The ``file://`` URL of a local path.

    Raises:
        InputError: the path is not valid UTF-8 (the lock file and --json could not name it).
    """
    text = os.path.abspath(os.fspath(path))
    try:
        url = "file://" + quote(text)
    except UnicodeEncodeError:  # a name of undecodable bytes, held as surrogates (PEP 383)
        shown = display_path(text).encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")
        raise InputError(f"{shown}: the path is not valid UTF-8; rename it", file=shown) from None
    return url + "/" if directory and not url.endswith("/") else url


def _is_url(text: str) -> bool:
    return "://" in text


def _folder_of(base: str) -> str:
    """The normal folder (ending in "/") of the plain ``file:///`` URL ``base``."""
    folder = posixpath.normpath(base[7:] if base.endswith("/") else posixpath.dirname(base[7:]))
    return folder if folder.endswith("/") else folder + "/"


def refuse_credentials(url: str, *, what: str, file: str | None = None, line: int | None = None) -> None:
    """Refuse a URL that carries ``user:password@`` (``what`` names where it was given).

    Raises:
        CredentialsError: naming the URL redacted, never the secret.
    """
    if userinfo_end(url) >= 0:
        shown = redact(url)
        raise CredentialsError(
            f"{what} {shown} carries credentials (user:password@): refused, so that no secret "
            "reaches the lock file, the flattened output or any message; serve it without them",
            file=file,
            line=line,
            url=shown,
        )


def confinement_root(doc_path: str | os.PathLike[str], *, root: str | None, base: str | None) -> Path:
    """The folder local references may not leave: ``--root``, else a local ``--base``, else the
    document's folder (resolve's rule, for every verb that reads a tree)."""
    if root:
        return Path(absolute(root))
    if base and not _is_url(base):
        return Path(absolute(base))
    return Path(absolute(doc_path)).parent


@dataclass(frozen=True)
class Locator:
    """Turns the ``uri`` of a reference into a :class:`Location`.

    ``root`` confines local references; ``base`` (a folder or URL), when given,
    replaces the referencing document as the base of relative references;
    ``mirrors`` rewrite URL prefixes to a local folder or another URL.
    """

    root: Path
    base: str | None = None
    mirrors: tuple[tuple[str, str], ...] = ()

    @classmethod
    def create(
        cls,
        *,
        root: str | os.PathLike[str],
        base: str | None = None,
        mirrors: list[tuple[str, str]] | tuple[tuple[str, str], ...] = (),
    ) -> Locator:
        base_url = None
        if base is not None and _is_url(base):
            refuse_credentials(base, what="--base")
        for prefix, target in mirrors:
            refuse_credentials(prefix, what="--mirror prefix")
            if _is_url(target):
                refuse_credentials(target, what="--mirror target")
        if base is not None:
            base_url = base if _is_url(base) else file_url(absolute(base), directory=True)
            if not base_url.endswith("/"):
                base_url += "/"
        # Longest prefix first, so a specific mirror beats a general one.
        ordered = tuple(
            sorted(((p, t if _is_url(t) else absolute(t)) for p, t in mirrors), key=lambda m: len(m[0]), reverse=True)
        )
        return cls(root=Path(os.path.abspath(root)), base=base_url, mirrors=ordered)

    def for_document(self, path: str | os.PathLike[str]) -> Location:
        """The location of a root document given on the command line."""
        p = Path(os.path.abspath(path))
        return self._local(file_url(p), p, self.root, file=str(path), line=None)

    def locate(self, uri: str, referrer: Location, *, file: str, line: int | None) -> Location:
        """Resolve ``uri`` written in the document at ``referrer``.

        Raises:
            PathEscapeError: an absolute local path, or a path that leaves the root.
            CredentialsError: a URL with ``user:password@``.
            InputError: an empty or malformed uri, or an unsupported scheme.
        """
        text = uri.strip()
        if not text:
            raise InputError("empty uri", file=file, line=line)
        fast = self._plain_relative(text, referrer, file=file, line=line)
        if fast is not None:
            return fast
        if self._mirrors_files:  # the fast path is off under a file: mirror; this one routes through it
            fast = self._plain_mirrored(text, referrer, file=file, line=line, uri=uri)
            if fast is not None:
                return fast
        shown = redact(uri)
        try:
            scheme = urlsplit(text).scheme.lower()
            if scheme in REMOTE_SCHEMES:
                absolute = text
            elif scheme == "file" or text.startswith(("/", "\\")) or (len(scheme) == 1 and ":" in text):
                raise PathEscapeError(
                    f"absolute local path {shown!r} is refused: references must be relative "
                    "to their document (or --base) or https URLs",
                    file=file,
                    line=line,
                    expected="a relative path or an https URL",
                    actual=shown,
                )
            elif scheme:
                raise InputError(
                    f"unsupported URL scheme {scheme!r} in {shown!r}",
                    file=file,
                    line=line,
                    expected="a relative path or an https URL",
                    actual=shown,
                )
            else:
                absolute = urljoin(self.base or referrer.url, text)
            refuse_credentials(absolute, what="reference", file=file, line=line)
            return self._apply(absolute, file=file, line=line, uri=uri)
        except ValueError as exc:  # urlsplit: "Invalid IPv6 URL", a port out of range, ...
            raise InputError(f"malformed URL {shown!r}: {exc}", file=file, line=line, actual=shown) from None

    def plain_joiner(self, referrer: Location) -> Callable[[str], Location | None]:
        """For the references of one document: a function that gives :meth:`locate`'s result
        for a reference on its fast path (a plain normal relative path, joined to a folder
        inside the root), and None for any other, which :meth:`locate` must decide."""
        folder = self._plain_folder(self.base or referrer.url)
        if folder is None or not self._below_root(folder):
            return _never
        match, root, prefix = _PLAIN_NORMAL.match, self.root, "file://" + folder

        def join(text: str) -> Location | None:
            return Location(prefix + text, folder + text, root) if match(text) else None

        return join

    def _plain_relative(self, text: str, referrer: Location, *, file: str, line: int | None) -> Location | None:
        """The common case without URL parsing: a plain relative path from a local base.

        Only for text made of unreserved URL characters (no scheme, query, fragment or
        percent escapes) under a ``file://`` base that is itself plain, where the
        result is exactly what the general path (urljoin, normalise) gives. It saves
        most of the per-reference cost on trees with thousands of files.
        """
        folder = self._plain_folder(self.base or referrer.url)
        if folder is None:
            return None
        if _PLAIN_NORMAL.match(text):  # the join is already normal (folder is normal): no normpath
            path = f"{folder}{text}"
            if self._below_root(folder):  # then so is every normal path below it: _local's check, once
                return Location("file://" + path, path, self.root)
            return self._local("file://" + path, path, self.root, file=file, line=line, uri=text, is_normal=True)
        if text.startswith("/") or text.endswith("/") or not _PLAIN.match(text):
            return None
        path = posixpath.normpath(folder + text)
        return self._local("file://" + path, path, self.root, file=file, line=line, uri=text)

    @functools.cached_property
    def _folders_below_root(self) -> dict[str, bool]:
        return {}

    def _below_root(self, folder: str) -> bool:
        """Is the normal folder ``folder`` (ending in "/") the root or below it? Once per folder."""
        below = self._folders_below_root.get(folder)
        if below is None:
            below = self._folders_below_root[folder] = _lexically_inside(folder, os.fspath(self.root))
        return below

    def _plain_folder(self, base: str) -> str | None:
        """The folder (ending in "/") relative references of ``base`` join, when the fast
        path applies to it (a plain ``file://`` URL, no local mirror), normalised; else None."""
        return None if self._mirrors_files else self._base_folder(base)

    @functools.cached_property
    def _base_folders(self) -> dict[str, str | None]:
        return {}

    def _base_folder(self, base: str) -> str | None:
        """The normal folder (ending in "/") of ``base`` when it is a plain ``file:///`` URL,
        else None. Once per referring document."""
        folders = self._base_folders
        if base in folders:
            return folders[base]
        folder = folders[base] = _folder_of(base) if base.startswith("file:///") and _PLAIN.match(base, 7) else None
        return folder

    @functools.cached_property
    def _mirrors_files(self) -> bool:
        """Does a ``--mirror`` rewrite ``file:`` URLs (so that a local path may not be read as written)?"""
        return any(prefix.startswith("file:") for prefix, _ in self.mirrors)

    def _plain_mirrored(
        self, text: str, referrer: Location, *, file: str, line: int | None, uri: str
    ) -> Location | None:
        """:meth:`_plain_relative` under a ``file:`` mirror: the same plain relative path
        under the same plain ``file://`` base joins to the URL the general path builds
        (``urljoin`` then :func:`_normalise`), which is then routed through the mirrors
        as :meth:`_apply` routes it. A 2,000-model tree served from a mirror's cache
        pays ~10 µs per reference instead of ~50 (three URL parses and a join)."""
        folder = self._base_folder(self.base or referrer.url)
        if folder is None or text.startswith("/") or text.endswith("/") or not _PLAIN.match(text):
            return None
        path = f"{folder}{text}" if _PLAIN_NORMAL.match(text) else posixpath.normpath(folder + text)
        return self._route("file://" + path, file=file, line=line, uri=uri)

    def _apply(self, url: str, *, file: str, line: int | None, uri: str) -> Location:
        parts = urlsplit(url)
        if parts.scheme.lower() in REMOTE_SCHEMES and (not parts.hostname or "\\" in url):
            # Without a host, collapsing the path could make one of it (https:u:pw@host/x
            # -> https://u:pw@host/x), unseen by the credentials check; a backslash is read
            # as "/" by browsers and as a port or path character by others.
            shown = redact(uri)
            raise InputError(
                f"malformed URL {shown!r}: a remote reference is {parts.scheme}://host/path",
                file=file,
                line=line,
                expected=f"{parts.scheme}://host/path",
                actual=shown,
            )
        return self._route(_normalise(url), file=file, line=line, uri=uri)

    def _route(self, url: str, *, file: str, line: int | None, uri: str) -> Location:
        """Where the normal URL ``url`` is read from: the longest mirror prefix it starts
        with, else the local file it names, else the URL itself."""
        for prefix, target in self.mirrors:
            if url.startswith(prefix):
                rest = url[len(prefix) :]
                if _is_url(target):
                    return Location(url=url, remote=target.rstrip("/") + "/" + rest.lstrip("/"))
                mroot = Path(target)
                return self._local(url, mroot / unquote(rest.lstrip("/")), mroot, file=file, line=line, uri=uri)
        if url.startswith("file://"):
            # One file, one identity: quoted as file_url() quotes it, whether the reference
            # wrote a character such as ":" literally or escaped (the lock keys on it).
            path = Path(unquote(urlsplit(url).path))
            return self._local(file_url(path), path, self.root, file=file, line=line, uri=uri)
        return Location(url=url, remote=url)

    @staticmethod
    def _local(
        url: str,
        path: str | Path,
        root: Path,
        *,
        file: str,
        line: int | None,
        uri: str | None = None,
        is_normal: bool = False,
    ) -> Location:
        # Lexical check here; the symlink check happens on the opened descriptor (localfile.py).
        normal = path if is_normal and isinstance(path, str) else os.path.normpath(path)
        if not _lexically_inside(normal, os.fspath(root)):
            shown_root, shown = display_path(root), display_path(normal)
            about = f"{uri.strip()}: " if uri and uri.strip() != shown else ""
            raise PathEscapeError(
                f"{about}{shown} is outside the root {shown_root}",
                file=file,
                line=line,
                expected=f"a path inside {shown_root}",
                actual=display_path(normal),
            )
        return Location(url=url, path=normal, root=root)


def _never(text: str) -> Location | None:
    return None


def _lexically_inside(normal: str, root: str) -> bool:
    """Is the normal path ``normal`` the folder ``root`` or below it, by its text alone?"""
    return normal == root or normal.startswith(root.rstrip("/") + "/")


def _normalise(url: str) -> str:
    """Collapse ``.``/``..`` segments so one file has one identity."""
    parts = urlsplit(url)
    path = posixpath.normpath(parts.path) if parts.path else "/"
    if parts.path.endswith("/") and not path.endswith("/"):
        path += "/"
    if path.startswith("//"):
        path = "/" + path.lstrip("/")
    rebuilt = f"{parts.scheme}://{parts.netloc}{path}"
    if parts.query:
        rebuilt += "?" + parts.query
    return rebuilt


# How many folders above a document :func:`explain_missing` looks for a site root.
_SITE_ROOT_LEVELS = 16


def explain_missing(exc: NotFoundError, *, uri: str | None, referrer_url: str, base: str | None) -> NotFoundError:
    """``exc`` (a referenced local file is missing) naming the reference as written and,
    for a plain relative reference without ``--base``, hinting at ``--base``.

    Published fragments (hcdf_models) write ``href="models/…"`` relative to their site
    root, not to their own folder. When a folder above the referencing document holds
    the file, the hint names that folder; otherwise it only says what ``--base`` does.
    Looking costs a few ``stat`` calls, made only once the file is known to be missing.
    """
    text = (uri or "").strip()
    if not text or base is not None or not referrer_url.startswith("file://"):
        return exc
    hint = ""
    parts = urlsplit(text)
    if not (parts.scheme or parts.netloc or text.startswith(("/", "\\", "../", "./"))):
        relative = unquote(parts.path)
        folder = Path(unquote(urlsplit(referrer_url).path)).parent
        for above in list(folder.parents)[:_SITE_ROOT_LEVELS]:
            if (above / relative).is_file():
                shown = display_path(above)
                hint = (
                    f"; {relative} exists under {shown}: if the reference is relative to a site root "
                    f"(as published hcdf_models fragments write it), give --base {shown} "
                    "(every verb that reads a tree takes it)"
                )
                break
        else:
            hint = (
                "; relative references resolve against the referencing document: if it is relative "
                "to a site root (as published hcdf_models fragments write it), give --base DIR|URL"
            )
    message = exc.message if text in exc.message else f"{text}: {exc.message}"
    return NotFoundError(message + hint, file=exc.file, line=exc.line, url=exc.url)
