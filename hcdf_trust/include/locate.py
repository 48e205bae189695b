"""Where a reference points: relative resolution, ``--base``, ``--mirror``, root confinement.

Pure functions over strings and paths: no file is opened and no socket used here.
A :class:`Location` keeps the *logical* URL (what the document means, recorded in
the lock file, the same with or without a mirror) apart from where the bytes are
actually read (a local path confined to a root, or a remote URL).
"""

from __future__ import annotations

import os
import posixpath
import re
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import quote, unquote, urljoin, urlsplit

from ..errors import InputError, PathEscapeError

REMOTE_SCHEMES = ("https", "http")
# Unreserved URL characters plus "/": text that means the same as a URL and as a path.
_PLAIN = re.compile(r"[A-Za-z0-9._~/-]+\Z")


@dataclass(frozen=True)
class Location:
    url: str  # logical identity: file:///abs/path or https://…
    path: str | None = None  # read from here (local file or local mirror), normalised
    root: Path | None = None  # ...which must stay inside this folder
    remote: str | None = None  # or fetch from here (after mirror rewrite)

    @property
    def is_local(self) -> bool:
        return self.path is not None

    @property
    def scheme(self) -> str:
        return urlsplit(self.remote or self.url).scheme


def file_url(path: str | os.PathLike[str], *, directory: bool = False) -> str:
    text = os.path.abspath(os.fspath(path))
    url = "file://" + quote(text)
    return url + "/" if directory and not url.endswith("/") else url


def display_path(path: str | os.PathLike[str]) -> str:
    """How messages name a local file: relative to the working folder when inside it."""
    text = os.fspath(path)
    rel = os.path.relpath(text)
    return text if rel.startswith("..") else rel


def _is_url(text: str) -> bool:
    return "://" in text


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
        if base is not None:
            base_url = base if _is_url(base) else file_url(base, directory=True)
            if not base_url.endswith("/"):
                base_url += "/"
        # Longest prefix first, so a specific mirror beats a general one.
        ordered = tuple(sorted(mirrors, key=lambda m: len(m[0]), reverse=True))
        return cls(root=Path(os.path.abspath(root)), base=base_url, mirrors=ordered)

    def for_document(self, path: str | os.PathLike[str]) -> Location:
        """The location of a root document given on the command line."""
        p = Path(os.path.abspath(path))
        return self._local(file_url(p), p, self.root, file=str(path), line=None)

    def locate(self, uri: str, referrer: Location, *, file: str, line: int | None) -> Location:
        """Resolve ``uri`` written in the document at ``referrer``.

        Raises:
            PathEscapeError: an absolute local path, or a path that leaves the root.
            InputError: an empty uri or an unsupported scheme.
        """
        text = uri.strip()
        if not text:
            raise InputError("empty uri", file=file, line=line)
        fast = self._plain_relative(text, referrer, file=file, line=line)
        if fast is not None:
            return fast
        parts = urlsplit(text)
        scheme = parts.scheme.lower()
        if scheme in REMOTE_SCHEMES:
            absolute = text
        elif scheme == "file" or text.startswith(("/", "\\")) or (len(scheme) == 1 and ":" in text):
            raise PathEscapeError(
                f"absolute local path {uri!r} is refused: references must be relative "
                "to their document (or --base) or https URLs",
                file=file,
                line=line,
                actual=uri,
            )
        elif scheme:
            raise InputError(f"unsupported URL scheme {scheme!r} in {uri!r}", file=file, line=line, actual=uri)
        else:
            absolute = urljoin(self.base or referrer.url, text)
        return self._apply(absolute, file=file, line=line, uri=uri)

    def _plain_relative(self, text: str, referrer: Location, *, file: str, line: int | None) -> Location | None:
        """The common case without URL parsing: a plain relative path from a local base.

        Only for text made of unreserved URL characters (no scheme, query, fragment or
        percent escapes) under a ``file://`` base that is itself plain, where the
        result is exactly what the general path (urljoin, normalise) gives. It saves
        most of the per-reference cost on trees with thousands of files.
        """
        base = self.base or referrer.url
        if (
            not base.startswith("file:///")
            or self._file_mirrors
            or text.startswith("/")
            or text.endswith("/")
            or not _PLAIN.match(text)
            or not _PLAIN.match(base, 7)
        ):
            return None
        folder = base[7:] if base.endswith("/") else posixpath.dirname(base[7:])
        path = posixpath.normpath(posixpath.join(folder, text))
        return self._local("file://" + path, path, self.root, file=file, line=line)

    @property
    def _file_mirrors(self) -> bool:
        return any(prefix.startswith("file:") for prefix, _ in self.mirrors)

    def _apply(self, url: str, *, file: str, line: int | None, uri: str) -> Location:
        url = _normalise(url)
        for prefix, target in self.mirrors:
            if url.startswith(prefix):
                rest = url[len(prefix) :]
                if _is_url(target):
                    return Location(url=url, remote=target.rstrip("/") + "/" + rest.lstrip("/"))
                mroot = Path(os.path.abspath(target))
                return self._local(url, mroot / unquote(rest.lstrip("/")), mroot, file=file, line=line)
        if url.startswith("file://"):
            # One file, one identity: quoted as file_url() quotes it, whether the reference
            # wrote a character such as ":" literally or escaped (the lock keys on it).
            path = Path(unquote(urlsplit(url).path))
            return self._local(file_url(path), path, self.root, file=file, line=line)
        return Location(url=url, remote=url)

    @staticmethod
    def _local(url: str, path: str | Path, root: Path, *, file: str, line: int | None) -> Location:
        # Lexical check here; the symlink check happens on the opened descriptor (fetch.py).
        normal = os.path.normpath(path)
        root_text = os.fspath(root)
        if normal != root_text and not normal.startswith(root_text.rstrip("/") + "/"):
            raise PathEscapeError(
                f"{path} is outside the root {root}",
                file=file,
                line=line,
                expected=f"a path inside {root}",
                actual=str(normal),
            )
        return Location(url=url, path=normal, root=root)


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
