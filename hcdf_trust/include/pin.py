"""``hcdf-trust pin``: fill in and repair ``sha`` attributes across an include tree.

Each repair is a minimal text edit of one attribute in the document's raw bytes:
comments, formatting, attribute order and quoting stay as they were; the XML is
never re-serialized. The run has four steps:

1. Resolve the tree with ``accept_mismatch`` so that an outdated include pin does
   not stop the walk. Digest mismatches and weak pins on references pin can edit
   are what it repairs; every other error (missing file, malformed XML, transport,
   path escape, a bad ``sha`` text, ...) stops the run and nothing is written.
2. Settle documents bottom-up over the include tree: a document's own digest
   changes when it is edited, so each including document's pin of it is computed
   from the child's *edited* bytes. After ``pin --write`` a plain ``resolve`` passes.
3. Locate each reference's start tag in the raw bytes (by element order, checked
   against lxml's ``sourceline``) and its attributes within that tag only.
4. With ``write``, check that no file changed since it was read, then replace each
   edited file atomically, leaves first, keeping its permission bits.

Which references get a ``sha``: ``<include>``, ``<model uri|href>`` and
``<stream-profile>``. Not ``<geometry><mesh>`` (the schema has no ``sha`` there;
the lock file pins meshes), and not ``<software><hash>`` (firmware).

Remote documents (https, or served from a ``--mirror``) cannot be edited: a
missing or weak pin in one is skipped with a warning in :attr:`PinReport.warnings`;
a wrong pin in one stays a digest-mismatch error (exit 1), as it is for ``resolve``.
The lock file is not touched: run ``hcdf-trust resolve`` afterwards to refresh it.
"""

from __future__ import annotations

import hashlib
import html
import os
import re
import stat
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any
from urllib.parse import unquote, urlsplit

from lxml import etree

from ..digest import Pin
from ..document import Document, Kind, Reference
from ..errors import (
    DigestMismatchError,
    HcdfTrustError,
    InputError,
    WeakPinError,
)
from ..store import atomic_write
from ..xml import sourceline
from .locate import Location, file_url
from .resolver import Artifact, Resolution, ResolveOptions, Use, display_url, resolve

PINNABLE = frozenset({Kind.INCLUDE, Kind.MODEL, Kind.STREAM_PROFILE})

MISSING = "missing"
WEAK = "weak"
OUTDATED = "outdated"


@dataclass(frozen=True)
class PinChange:
    """One ``sha`` attribute that is (or would be) written."""

    file: str  # the referencing document, as errors name it
    line: int | None
    kind: str
    uri: str
    url: str  # what the uri resolves to
    reason: str  # missing | weak | outdated
    old: str | None  # the sha text as written, None when absent
    new: str  # the full SHA-256 written

    def to_dict(self) -> dict[str, Any]:
        return {
            "file": self.file,
            "line": self.line,
            "kind": self.kind,
            "uri": self.uri,
            "url": self.url,
            "reason": self.reason,
            "old": self.old,
            "new": self.new,
        }


@dataclass
class PinReport:
    changes: list[PinChange] = field(default_factory=list)
    errors: list[HcdfTrustError] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    written: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.errors


class PinEditError(InputError):
    """A reference could not be located in the document's text for a safe edit."""

    code = "pin-edit"


def pin_tree(
    doc_path: str | os.PathLike[str],
    options: ResolveOptions | None = None,
    *,
    write: bool = False,
) -> PinReport:
    """Compute (and with ``write``, apply) every ``sha`` repair in ``doc_path``'s tree.

    Never raises for content errors: they are returned in :attr:`PinReport.errors`,
    and then no file is written. Without ``write`` nothing is written anywhere
    (not even the cache).
    """
    base = options or ResolveOptions()
    opts = replace(base, accept_mismatch=True, locked=False, write_cache=base.write_cache and write)
    report = PinReport()
    try:
        res = resolve(doc_path, opts)
    except HcdfTrustError as exc:
        report.errors.append(exc)
        return report

    # step 1: which errors pin repairs, and which stop it
    locations = _locations(res)
    editable = {url for url, loc in locations.items() if _is_editable(url, loc)}
    repairable = {
        (use.doc, use.ref.line, art.url)
        for art in res.artifacts.values()
        for use in art.uses
        if use.ref.kind in PINNABLE and use.doc_url in editable
    }
    for err in res.errors:
        if isinstance(err, DigestMismatchError | WeakPinError):
            if (err.file, err.line, err.url) in repairable:
                continue
            if isinstance(err, DigestMismatchError):
                err = _explain_unrepairable(err, res)
        report.errors.append(err)
    if report.errors:
        return report

    # step 2: settle documents bottom-up
    planner = _Planner(res, editable)
    try:
        planner.settle(res.root_location.url)
    except HcdfTrustError as exc:
        planner.errors.append(exc)
    report.warnings.extend(planner.warnings)
    report.errors.extend(planner.errors)
    report.changes = sorted(planner.changes, key=lambda c: (c.file, c.line or 0, c.uri))
    if report.errors or not write:
        return report

    # step 4: write, leaves first, only if every file is still what was read
    targets: dict[Path, tuple[str, bytes, bytes]] = {}
    for url in planner.order:
        new = planner.new_bytes[url]
        old = res.documents[url].data
        if new == old:
            continue
        local = locations[url].path
        assert local is not None  # only local documents are editable, so only they change
        path = Path(os.path.realpath(local))
        seen = targets.get(path)
        if seen is not None and seen[2] != new:
            report.errors.append(
                PinEditError(
                    f"{path} is reached as two documents that need different edits (a symlink?): refusing to edit it",
                    file=display_url(url),
                )
            )
        targets[path] = (url, old, new)
    for path, (url, old, _new) in targets.items():
        try:
            current = path.read_bytes()
        except OSError as exc:
            report.errors.append(InputError(f"cannot re-read: {exc}", file=display_url(url)))
            continue
        if current != old:
            report.errors.append(InputError("changed on disk while pinning: run pin again", file=display_url(url)))
    if report.errors:
        return report
    for path, (url, _old, new) in targets.items():
        try:
            mode = stat.S_IMODE(os.stat(path).st_mode)
            atomic_write(path, new, mode=mode)
        except OSError as exc:
            report.errors.append(InputError(f"cannot write: {exc}", file=display_url(url)))
            return report
        report.written.append(display_url(url))
    return report


# -- the tree ------------------------------------------------------------------------


def _locations(res: Resolution) -> dict[str, Location]:
    out = {url: art.location for url, art in res.artifacts.items()}
    out[res.root_location.url] = res.root_location
    return out


def _is_editable(url: str, loc: Location) -> bool:
    """A local file whose identity is its own path (not a mirror copy of a remote URL)."""
    if not url.startswith("file://") or loc.path is None:
        return False
    return file_url(loc.path) == url or Path(unquote(urlsplit(url).path)) == Path(loc.path)


def _explain_unrepairable(err: DigestMismatchError, res: Resolution) -> DigestMismatchError:
    why = None
    for art in res.artifacts.values():
        for use in art.uses:
            if (use.doc, use.ref.line, art.url) != (err.file, err.line, err.url):
                continue
            if use.ref.kind not in PINNABLE:
                why = f"a <{use.ref.kind.value}> sha is not one pin edits: fix or remove it by hand"
            else:
                why = "the referencing document is remote, and pin cannot edit it"
    if why is None:
        return err
    return DigestMismatchError(
        f"{err.message} ({why})",
        file=err.file,
        line=err.line,
        url=err.url,
        expected=err.expected,
        actual=err.actual,
    )


def reason_for(pin: Pin | None, actual: str) -> str | None:
    """Why a pin needs rewriting to ``actual``, or None if it is already a full match. Pure."""
    if pin is None:
        return MISSING
    if not pin.matches(actual):
        return OUTDATED
    if not pin.is_full:
        return WEAK
    return None


class _Planner:
    """Post-order over the include DAG (cycles are resolve errors, so none reach here)."""

    def __init__(self, res: Resolution, editable: set[str]) -> None:
        self.res = res
        self.editable = editable
        self.uses: dict[str, list[tuple[Use, Artifact]]] = {}
        for art in res.artifacts.values():
            for use in art.uses:
                if use.ref.kind in PINNABLE:
                    self.uses.setdefault(use.doc_url, []).append((use, art))
        self.digest: dict[str, str] = {}
        self.new_bytes: dict[str, bytes] = {}
        self.order: list[str] = []  # leaves first
        self.active: set[str] = set()
        self.changes: list[PinChange] = []
        self.warnings: list[str] = []
        self.errors: list[HcdfTrustError] = []

    def settle(self, url: str) -> str:
        """The digest of document ``url`` after its edits (and its includes' edits).

        Depth first, leaves first, with an explicit stack: a 1,000-file chain needs no recursion.
        """
        pending = [(url, False)]
        while pending:
            url_now, children_done = pending.pop()
            if url_now in self.digest:
                continue
            if not children_done:
                if url_now in self.active:  # resolve reports cycles; never loop on one regardless
                    raise PinEditError(f"include cycle through {display_url(url_now)}")
                self.active.add(url_now)
                pending.append((url_now, True))
                for use, art in reversed(self.uses.get(url_now, [])):
                    if use.ref.kind is Kind.INCLUDE and art.url in self.res.documents:
                        pending.append((art.url, False))
                continue
            doc = self.res.documents[url_now]
            edits: list[tuple[Reference, str]] = []
            for use, art in self.uses.get(url_now, []):
                actual: str | None
                if use.ref.kind is Kind.INCLUDE and art.url in self.res.documents:
                    actual = self.digest[art.url]
                else:
                    actual = art.sha256
                if actual is None:  # cannot happen in a clean resolution
                    continue
                reason = reason_for(use.pin, actual)
                if reason is None:
                    continue
                change = PinChange(
                    file=use.doc,
                    line=use.ref.line,
                    kind=use.ref.kind.value,
                    uri=use.ref.uri or "",
                    url=display_url(art.url),
                    reason=reason,
                    old=use.ref.sha,
                    new=actual,
                )
                if url_now in self.editable:
                    edits.append((use.ref, actual))
                    self.changes.append(change)
                else:
                    self.warnings.append(
                        f"{use.doc}:{use.ref.line}: {change.uri} needs a pin ({reason}: sha256 "
                        f"{actual}) but {use.doc} is remote: pin cannot edit it"
                    )
            data = doc.data
            if edits:
                try:
                    data = apply_pins(doc, edits)
                except HcdfTrustError as exc:
                    self.errors.append(exc)
            self.new_bytes[url_now] = data
            self.order.append(url_now)
            self.digest[url_now] = hashlib.sha256(data).hexdigest()
        return self.digest[url]


# -- the text edit -------------------------------------------------------------------

# Markup that starts with "<" in a well-formed document. A DOCTYPE never reaches
# here (xml.py refuses it) but is skipped correctly anyway.
_MARKUP = re.compile(
    rb"""
      (?P<comment><!--.*?-->)
    | (?P<cdata><!\[CDATA\[.*?\]\]>)
    | (?P<pi><\?.*?\?>)
    | (?P<decl><!(?:[^>"'\[]|"[^"]*"|'[^']*'|\[.*?\])*>)
    | (?P<end></[^>]*>)
    | (?P<start><(?P<name>[^\s/>]+)(?P<attrs>(?:[^>"']|"[^"]*"|'[^']*')*)>)
    """,
    re.S | re.X,
)
_ATTR = re.compile(rb"""(?P<ws>\s+)(?P<name>[^\s=/>]+)\s*=\s*(?P<q>["'])(?P<value>.*?)(?P=q)""", re.S)
_TAG_TAIL = re.compile(rb"\s*/?\s*")


@dataclass(frozen=True)
class Attr:
    name: bytes
    quote: bytes
    value_start: int
    value_end: int
    end: int  # offset just after the closing quote


@dataclass(frozen=True)
class StartTag:
    name: bytes
    start: int  # offset of "<"
    end: int  # offset just after ">"
    first_line: int
    last_line: int
    attrs: tuple[Attr, ...]

    def attr(self, name: str) -> Attr | None:
        key = name.encode("ascii")
        for a in self.attrs:
            if a.name == key:
                return a
        return None


def scan_start_tags(data: bytes) -> list[StartTag]:
    """Every start tag of a well-formed document, in document order, with its attributes.

    Raises:
        PinEditError: the text does not scan as XML markup.
    """
    tags: list[StartTag] = []
    pos = 0
    line = 1
    counted = 0
    while True:
        lt = data.find(b"<", pos)
        if lt < 0:
            return tags
        m = _MARKUP.match(data, lt)
        if m is None:
            line += data.count(b"\n", counted, lt)
            raise PinEditError(f"cannot scan the markup at line {line}")
        if m.group("start") is not None:
            line += data.count(b"\n", counted, lt)
            counted = lt
            last = line + data.count(b"\n", lt, m.end())
            attrs = _scan_attrs(data, m.start("attrs"), m.end("attrs"), line)
            tags.append(StartTag(m.group("name"), lt, m.end(), line, last, attrs))
        pos = m.end()


def _scan_attrs(data: bytes, start: int, end: int, line: int) -> tuple[Attr, ...]:
    attrs = []
    pos = start
    while True:
        m = _ATTR.match(data, pos, end)
        if m is None:
            break
        attrs.append(Attr(m.group("name"), m.group("q"), m.start("value"), m.end("value"), m.end()))
        pos = m.end()
    tail = _TAG_TAIL.match(data, pos, end)
    if tail is None or tail.end() != end:
        raise PinEditError(f"cannot scan the attributes of the start tag at line {line}")
    return tuple(attrs)


def _attr_text(raw: bytes, encoding: str) -> str:
    """An attribute value as the parser reports it: whitespace normalized, references expanded."""
    text = raw.decode(encoding)
    text = text.replace("\r\n", " ").replace("\r", " ").replace("\n", " ").replace("\t", " ")
    return html.unescape(text)


def apply_pins(doc: Document, edits: list[tuple[Reference, str]]) -> bytes:
    """``doc``'s bytes with each reference's ``sha`` set to its full digest.

    An existing ``sha`` attribute has its value replaced (quotes and a ``sha256:``
    prefix kept); a missing one is inserted right after the ``uri``/``href``
    attribute, in the same quote style. Nothing else in the text changes.

    Raises:
        PinEditError: a reference cannot be located unambiguously in the text, or
        the document's encoding is not ASCII-compatible.
    """
    data = doc.data
    encoding = doc.tree.docinfo.encoding or "utf-8"
    try:
        ascii_compatible = "<hcdf sha='0'>".encode(encoding) == b"<hcdf sha='0'>"
    except LookupError:
        ascii_compatible = False
    if not ascii_compatible or data.startswith((b"\xff\xfe", b"\xfe\xff")):
        raise PinEditError(f"cannot edit a document encoded as {encoding}", file=doc.source)
    tags = scan_start_tags(data)
    elements = [el for el in doc.root.getroottree().iter() if isinstance(el.tag, str)]
    if len(elements) != len(tags):
        raise PinEditError(
            f"found {len(tags)} start tags in the text but {len(elements)} elements in the tree",
            file=doc.source,
        )
    index = {el: i for i, el in enumerate(elements)}
    splices: list[tuple[int, int, bytes]] = []
    for ref, sha in edits:
        i = index.get(ref.element)
        if i is None or ref.uri_attr is None:
            raise PinEditError(f"cannot locate <{ref.kind.value}> in the text", file=doc.source, line=ref.line)
        tag, el = tags[i], elements[i]
        name = tag.name.decode(encoding).rpartition(":")[2]
        el_line = sourceline(el)
        if name != etree.QName(el).localname or not (el_line is None or tag.first_line <= el_line <= tag.last_line):
            raise PinEditError(
                f"the text at line {tag.first_line} does not match <{ref.kind.value}>",
                file=doc.source,
                line=ref.line,
            )
        uri = tag.attr(ref.uri_attr)
        if uri is None or _attr_text(data[uri.value_start : uri.value_end], encoding) != ref.uri:
            raise PinEditError(
                f"cannot locate the {ref.uri_attr} attribute of {ref.uri}", file=doc.source, line=ref.line
            )
        old = tag.attr("sha")
        if old is not None:
            text = data[old.value_start : old.value_end]
            prefix = b"sha256:" if text.strip().lower().startswith(b"sha256:") else b""
            splices.append((old.value_start, old.value_end, prefix + sha.encode("ascii")))
        else:
            q = uri.quote
            splices.append((uri.end, uri.end, b" sha=" + q + sha.encode("ascii") + q))
    out = data
    for start, end, new in sorted(splices, reverse=True):
        out = out[:start] + new + out[end:]
    return out
