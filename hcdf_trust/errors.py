"""One exception hierarchy; each class carries its exit code (DESIGN.md, "CLI contract").

Two roots, as in python-tuf: :class:`IntegrityError` (exit 1) when content is not what
was pinned or signed, :class:`InputError` (exit 3) when something could not be read,
parsed or fetched. Every error can name the file, line, expected and actual value.
"""

from __future__ import annotations

import os
import re
from typing import Any
from urllib.parse import unquote, urlsplit

# The public API (docs/api.md): the exception hierarchy and Notice. The helpers below are internal.
__all__ = [
    "HcdfTrustError",
    "IntegrityError",
    "DigestMismatchError",
    "LockDriftError",
    "UnpinnedError",
    "WeakPinError",
    "InputError",
    "MalformedDigestError",
    "XmlError",
    "NotHcdfError",
    "StreamSelectionError",
    "AmbiguousError",
    "AmbiguousReferenceError",
    "NotFoundError",
    "PathEscapeError",
    "CredentialsError",
    "SecretFileError",
    "FetchError",
    "OfflineError",
    "IncludeCycleError",
    "IncludeDepthError",
    "LockFileError",
    "FlattenError",
    "ErrorGroup",
    "Notice",
]


def counted(n: int, noun: str, plural: str | None = None) -> str:
    """``1 file``, ``2 files``: a count with its noun in the right number (``plural`` when not noun+s)."""
    return f"{n} {noun if n == 1 else plural or noun + 's'}"


def display_path(path: str | os.PathLike[str]) -> str:
    """How messages name a local file: relative to the working folder when inside it."""
    text = os.fspath(path)
    rel = os.path.relpath(text)
    return text if rel.startswith("..") else rel


def display_place(place: str) -> str:
    """A ``file`` or ``url`` as messages show it: absolute local paths and ``file:`` URLs
    by :func:`display_path`, relative paths and remote URLs as they are."""
    if place.startswith("file://"):
        return display_path(unquote(urlsplit(place).path))
    return display_path(place) if os.path.isabs(place) else place


# Where a URL's authority starts, as lenient (WHATWG) parsers read it: after the scheme
# and any run of slashes or backslashes ("https:u:pw@h", "https:\\\\u:pw@h", "https:///u:pw@h").
# file: URLs keep the strict "//" rule, so file:///u@x/ has no user.
_LAX_SCHEME = re.compile(r"(?![Ff][Ii][Ll][Ee]:)[A-Za-z][A-Za-z0-9+.-]*:[/\\]*")


def userinfo_end(text: str) -> int:
    """Where ``user:password@`` ends in a URL-like text (after the last ``@`` of the
    authority), or -1 when it has none. Textual, so it also works on malformed URLs
    (``https:u:pw@host``, which lenient parsers read as ``https://u:pw@host``)."""
    lax = _LAX_SCHEME.match(text)
    if lax is not None:
        start = lax.end()
    else:
        start = text.find("//")
        if start < 0:
            return -1
        start += 2
    end = len(text)
    for sep in "/?#\\":
        pos = text.find(sep, start)
        if pos >= 0:
            end = min(end, pos)
    at = text.rfind("@", start, end)
    return -1 if at < 0 else at + 1


def redact(text: str) -> str:
    """``text`` (a URL) as messages show it: its ``user:password@`` as ``***@`` and its query
    string as ``?***`` (``?token=…`` is a credential too). The fragment is kept.

    Only for what is printed: the lock file keeps URLs as the document writes them.
    """
    lax = _LAX_SCHEME.match(text)
    if lax is not None:
        start = lax.end()
    elif "//" in text:
        start = text.find("//") + 2
    else:
        return text
    end = userinfo_end(text)
    if end >= 0:
        text = text[:start] + "***@" + text[end:]
    query = text.find("?", start)
    if query >= 0:
        fragment = text.find("#", query)
        fragment = len(text) if fragment < 0 else fragment
        if fragment > query + 1:
            text = text[: query + 1] + "***" + text[fragment:]
    return text


class Pointer(int):
    """Where an element of a JSON document was written: prints as its JSON Pointer
    (``/hcdf/comp/3/visual/model``), compares and sorts as its place in document order.

    Every message names a location through ``line``; a ``Pointer`` there makes
    ``robot.json:/hcdf/comp/3: ...`` of what reads ``robot.hcdf:42: ...`` for XML, with no
    change to the code that reports it. ``--json`` output shows it as ``pointer`` (with
    ``line`` null): see :func:`json_locations`.
    """

    pointer: str

    def __new__(cls, index: int, pointer: str) -> Pointer:
        self = super().__new__(cls, index)
        self.pointer = pointer
        return self

    def __str__(self) -> str:
        return self.pointer

    def __format__(self, spec: str) -> str:
        return format(self.pointer, spec)

    def __repr__(self) -> str:
        return f"Pointer({int(self)}, {self.pointer!r})"


def at_line(line: int | None) -> str:
    """Where, inside a sentence: ``line 42`` for XML, the bare pointer (``/hcdf/comp/3``) for a
    JSON document, whose :class:`Pointer` would otherwise print as ``line /hcdf/comp/3``."""
    return str(line) if isinstance(line, Pointer) else f"line {line}"


def at_lines(lines: list[int | None], joiner: str = ", ") -> str:
    """:func:`at_line` of several places: ``lines 3, 7`` or ``/hcdf/comp/0, /hcdf/comp/1``."""
    if len(lines) == 1:
        return at_line(lines[0])
    shown = joiner.join(str(n) for n in lines)
    return shown if any(isinstance(n, Pointer) for n in lines) else f"lines {shown}"


def json_locations(value: Any) -> Any:
    """``value`` (a ``--json`` payload) with every ``"line": Pointer`` written as
    ``"line": null, "pointer": "/hcdf/..."`` (json's encoder would print the integer)."""
    if isinstance(value, dict):
        out = {k: json_locations(v) for k, v in value.items()}
        line = value.get("line")
        if isinstance(line, Pointer):
            out["line"] = None
            out["pointer"] = line.pointer
        return out
    if isinstance(value, list):
        return [json_locations(v) for v in value]
    if isinstance(value, Pointer):
        return value.pointer
    return value


class HcdfTrustError(Exception):
    """Base class of every error hcdf-trust reports. ``code`` is a stable, machine-readable
    identifier (``--json``'s ``code``), ``exit_code`` the CLI's exit status (1: integrity,
    3: input); ``file``, ``line``, ``expected``, ``actual`` and ``url`` say where and what,
    when known. Library functions collect these in lists (``Resolution.errors``) or raise them.

    Example:
        >>> from hcdf_trust.errors import DigestMismatchError, IntegrityError
        >>> e = DigestMismatchError("models/a.glb: digest mismatch", file="robot.hcdf", line=7,
        ...                         expected="sha256 00aa", actual="sha256 11bb")
        >>> isinstance(e, IntegrityError), e.exit_code, e.code
        (True, 1, 'digest-mismatch')
        >>> print(e)
        robot.hcdf:7: models/a.glb: digest mismatch
          expected: sha256 00aa
          actual:   sha256 11bb
        >>> e.to_dict()["line"]
        7
    """

    exit_code = 3
    code = "error"

    def __init__(
        self,
        message: str,
        *,
        file: str | None = None,
        line: int | None = None,
        expected: str | None = None,
        actual: str | None = None,
        url: str | None = None,
    ) -> None:
        super().__init__(message)
        self.message = message
        self.file = file
        self.line = line
        self.expected = expected
        self.actual = actual
        self.url = url

    def to_dict(self) -> dict[str, Any]:
        """``code``, ``message``, ``file``, ``line``; ``url``, ``expected``, ``actual`` when set.

        ``file`` and ``url`` are shown as messages show them (:func:`display_place`).
        """
        out: dict[str, Any] = {
            "code": self.code,
            "message": self.message,
            "file": display_place(self.file) if self.file else self.file,
            "line": self.line,
        }
        if self.url is not None:
            out["url"] = display_place(self.url)
        if self.expected is not None:
            out["expected"] = self.expected
        if self.actual is not None:
            out["actual"] = self.actual
        return out

    def lines(self) -> list[str]:
        """The message's lines: where and what, then ``expected`` and ``actual`` when set.

        The CLI prints each line through the secret filter, which escapes control characters
        in it: a newline inside a name or value cannot start a line of its own.
        """
        where = ""
        if self.file:
            shown = display_place(self.file)
            where = f"{shown}:{self.line}: " if self.line else f"{shown}: "
            if not self.line and self.message.startswith((where, f"{self.file}: ")):
                where = ""  # the message already starts with the file ("robot.hcdf: no such file")
        text = f"{where}{self.message}"
        if self.url:
            url = display_place(self.url)
            if url not in self.message and self.url not in self.message:
                text += f" [{url}]"
        out = [text]
        if self.expected is not None:
            out.append(f"  expected: {self.expected}")
        if self.actual is not None:
            out.append(f"  actual:   {self.actual}")
        return out

    def __str__(self) -> str:
        return "\n".join(self.lines())


# --- exit 1: the content is wrong -------------------------------------------------


class IntegrityError(HcdfTrustError):
    """Content is not what was pinned, locked or signed (exit 1): an attack or a mistake to
    look at, never to retry.

    Example:
        >>> from hcdf_trust.errors import IntegrityError, LockDriftError
        >>> issubclass(LockDriftError, IntegrityError), LockDriftError.exit_code
        (True, 1)
    """

    exit_code = 1
    code = "integrity"


class DigestMismatchError(IntegrityError):
    code = "digest-mismatch"


class LockDriftError(IntegrityError):
    """The document tree no longer matches its lock file (under ``--locked``)."""

    code = "lock-drift"


class UnpinnedError(IntegrityError):
    """A reference has no digest and the lock file does not pin it (under ``--locked``)."""

    code = "unpinned"


class WeakPinError(IntegrityError):
    """A short hex prefix was used as a pin under ``--strict``."""

    code = "weak-pin"


# --- exit 3: the input could not be used -------------------------------------------


class InputError(HcdfTrustError):
    """A file is missing, unreadable, malformed or hostile, or the network failed (exit 3).

    Example:
        >>> from hcdf_trust.include import resolve
        >>> from hcdf_trust.errors import InputError, NotFoundError
        >>> try:
        ...     resolve("examples/robot/no-such.hcdf")
        ... except InputError as e:
        ...     print(type(e).__name__, e.exit_code)
        NotFoundError 3
    """

    exit_code = 3
    code = "input"


class MalformedDigestError(InputError):
    code = "bad-digest"


class XmlError(InputError):
    code = "xml"


class NotHcdfError(XmlError):
    """The root element is not ``<hcdf>`` in no namespace (``<robot>``, ``<hcdf xmlns="urn:x">``)."""

    code = "not-hcdf"


class StreamSelectionError(InputError):
    """Which ``<stream-profile>`` a document selects cannot be read one way (a verb that must
    name it refuses; validate and audit report the same code as a finding)."""

    code = "stream-profile-selection"


class AmbiguousError(InputError):
    """An element the schema allows once (``maxOccurs="1"``), written twice where a verb reads it
    (``<software><hash>``, ``<version>``, ``<comp><board>``, a link's ``<macsec>``, a port's
    ``<speed>``...): one reader would take the first, another the last. Refused by every verb,
    naming both lines (:func:`hcdf_trust.document.single`)."""

    code = "ambiguous"


class AmbiguousReferenceError(AmbiguousError):
    """A reference that readers could read two ways (``uri`` and ``href`` that differ, a comment
    inside a text reference, a namespaced ``<x:include>``...): refused, never skipped."""

    code = "ambiguous-reference"


class NotFoundError(InputError):
    code = "not-found"


class PathEscapeError(InputError):
    """A local reference leaves its root (``..``, absolute path, symlink)."""

    code = "path-escape"


class CredentialsError(InputError):
    """A URL carries ``user:password@``: refused, so the secret reaches no lock, output or message."""

    code = "url-credentials"


class SecretFileError(InputError):
    """A key, passphrase or PIN cannot be used as given: its file is readable by others (ssh's
    rule), it is empty or holds several lines, or none was given."""

    code = "secret"


class FetchError(InputError):
    """Transport failure: TLS, timeout, too large, bad redirect, HTTP status."""

    code = "fetch"


class OfflineError(InputError):
    """The content is not available without the network and ``--offline`` forbids it."""

    code = "offline"


class IncludeCycleError(InputError):
    code = "include-cycle"


class IncludeDepthError(InputError):
    code = "include-depth"


class LockFileError(InputError):
    """The lock file is missing, unreadable or of an unknown format version."""

    code = "lock-file"


class FlattenError(InputError):
    """Includes cannot be merged: name collision, frame convention mismatch, bad pose."""

    code = "flatten"


class ErrorGroup(HcdfTrustError):
    """Several errors collected from one run; exit 1 if any is an integrity failure."""

    def __init__(self, errors: list[HcdfTrustError]) -> None:
        self.errors = errors
        first = errors[0]
        super().__init__(f"{counted(len(errors), 'error')}; first: {first}", file=first.file, line=first.line)
        self.exit_code = 1 if any(e.exit_code == 1 for e in errors) else 3
        self.code = "errors"


# --- warnings: reported, never fatal ---------------------------------------------------


class Notice:
    """A warning about a reference or file: reported (``--json`` as an object), never fatal.

    ``code`` is stable for machines (``unpinned``, ``weak-pin``, ``lock-pins``, ...) and is what a
    project's ``hcdf-trust.toml`` acknowledges; ``file``/``line`` name the place, as for errors.
    ``repeated``: a fact an earlier run already said when it wrote the lock that now covers it
    (listed by ``--json``, not said again to a person: see :func:`hcdf_trust.cli.warn`).

    Example:
        >>> from hcdf_trust.errors import Notice
        >>> n = Notice("weak-pin", "gripper.glb has a weak pin (32 bits)", file="arm.hcdf", line=38)
        >>> str(n), n.to_dict()["code"]
        ('arm.hcdf:38: gripper.glb has a weak pin (32 bits)', 'weak-pin')
    """

    __slots__ = ("code", "message", "file", "line", "url", "repeated")

    def __init__(
        self,
        code: str,
        message: str,
        *,
        file: str | None = None,
        line: int | None = None,
        url: str | None = None,
        repeated: bool = False,
    ) -> None:
        self.code = code
        self.message = message
        self.file = file
        self.line = line
        self.url = url
        self.repeated = repeated

    def to_dict(self) -> dict[str, Any]:
        file = display_place(self.file) if self.file else self.file
        out: dict[str, Any] = {"code": self.code, "message": self.message, "file": file, "line": self.line}
        if self.url is not None:
            out["url"] = display_place(self.url)
        if self.repeated:
            out["repeated"] = True
        return out

    def __str__(self) -> str:
        file = display_place(self.file) if self.file else None
        where = f"{file}:{self.line}: " if file and self.line else f"{file}: " if file else ""
        return f"{where}{self.message}"

    def __repr__(self) -> str:
        return f"Notice({self.code!r}, {str(self)!r})"


def relabel(item: HcdfTrustError | Notice, folder: str | os.PathLike[str], shown: str) -> None:
    """Make ``item`` (an error, each error of a group, or a notice) name ``shown`` wherever it
    names the private folder ``folder`` or a file in it, in place.

    A pull verifies what it fetched in a staging folder of its own (``.oci-pull-*``), which the
    user never named and which is gone once the command ends: its messages must name what the
    user asked for (``oci://HOST/REPO@sha256:…``) and the place inside it, as every other
    message names a file the user gave. The folder appears as its absolute path, its real
    path, as :func:`display_path` shows it or as a ``file:`` URL; each is replaced, in every
    text field.
    """
    from pathlib import Path

    paths = {os.path.abspath(folder), os.path.realpath(folder)}
    forms = {*paths, *(display_path(p) for p in paths), *(Path(p).as_uri() for p in paths)}  # a file: URL too
    ordered = sorted(forms, key=len, reverse=True)

    def fix(text: str | None) -> str | None:
        if text is None:
            return None
        for form in ordered:
            text = text.replace(form, shown)
        return text

    for name in ("message", "file", "url", "expected", "actual"):
        if hasattr(item, name):
            setattr(item, name, fix(getattr(item, name)))
    if isinstance(item, HcdfTrustError):
        item.args = tuple(fix(a) if isinstance(a, str) else a for a in item.args)
    if isinstance(item, ErrorGroup):
        for error in item.errors:
            relabel(error, folder, shown)
