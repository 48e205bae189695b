"""``hcdf-trust pin``: fill in and repair ``sha`` attributes across an include tree.

Each repair is a minimal text edit of one attribute in the document's raw bytes:
comments, formatting, attribute order and quoting stay as they were; the XML is
never re-serialized.

The rules (:func:`decide`, pure), for each reference and the file it names:

- A *missing* or *weak* pin is filled in with the full digest, provided the content
  agrees with the lock. A reference without a full pin is pinned by its lock entry
  (trust on first use), so content that differs from that entry is refused as
  tampered, never blessed.
- A pin (full or weak) that disagrees with the content, or content that differs
  from the lock entry of a reference without a full pin, is replaced only when the
  user names the file (``update``: the uri as written, its URL or its path) or asks
  for ``update_all``. Otherwise it is a digest-mismatch error (exit 1) and nothing
  is written.
- A correct pin of an include that this run edits is replaced by the digest of the
  edited bytes (reason ``include-edited``).

Every change reports its old and new digests and how the lock entry related to
them (:func:`lock_agreement`). The run has five steps:

1. Resolve the tree with ``accept_mismatch`` so that a disagreeing pin does not
   stop the walk, and with the ``update`` names, so that a named include's new
   content is read and walked (and a named remote file cached), as ``resolve --update``
   does. Whether content agrees with its pins and its lock entry is
   decided again here, by the rules above; every other error (missing file,
   malformed XML, transport, path escape, a bad ``sha`` text, an unreadable lock,
   ...) stops the run.
2. Settle documents bottom-up over the include tree: a document's own digest
   changes when it is edited, so each including document's pin of it is computed
   from the child's *edited* bytes. After ``pin --write`` a plain ``resolve`` passes.
3. Locate each reference's start tag in the raw bytes (by element order, checked
   against lxml's ``sourceline``) and its attributes within that tag only.
4. Check the new lock against the rule that a pin run changes only what it was told
   to accept (:func:`kept_violations`): only the entries of files named (``update``,
   ``update_all``), of documents this run edits and of files a full sha pins may change,
   and no include may be left unread (its references' entries would be dropped).
   Then plan the outputs with :class:`~hcdf_trust.outputs.OutputPlan`: the edited
   documents (in place, keeping their permission bits) and the lock file, rendered
   exactly as a following plain ``resolve`` writes it. Every other input (the
   tree's other documents, the verified artifacts, the cache) is protected, so the
   lock cannot land on one.
5. With ``write``, check that no edited document and not the lock changed since it
   was read, then commit: every file is written, or none.

Which references get a ``sha``: ``<include>``, ``<model uri|href>`` and
``<stream-profile>``. Not ``<geometry><mesh>`` (the schema has no ``sha`` there;
the lock file pins meshes), and not ``<software><hash>`` (firmware).

Remote documents (https, or served from a ``--mirror``) cannot be edited: a
missing or weak pin in one is skipped with a warning in :attr:`PinReport.warnings`;
a wrong pin in one stays a digest-mismatch error (exit 1), as it is for ``resolve``.
"""

from __future__ import annotations

import hashlib
import html
import os
import re
import stat
from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any
from urllib.parse import unquote, urlsplit

from lxml import etree

from ..digest import PREFIX, Pin, include_mismatch_hint, prefixed_style
from ..document import Document, Kind, Reference
from ..errors import (
    DigestMismatchError,
    HcdfTrustError,
    InputError,
    IntegrityError,
    LockFileError,
    Notice,
    WeakPinError,
)
from ..localfile import read_input
from ..outputs import OutputError, OutputPlan, protect_inputs
from ..xml import MAX_DOCUMENT_BYTES, sourceline
from . import lockfile
from .locate import Location, display_path, file_url
from .resolver import Artifact, Resolution, ResolveOptions, Use, display_url, resolve

PINNABLE = frozenset({Kind.INCLUDE, Kind.MODEL, Kind.STREAM_PROFILE})

# Why a sha is written.
MISSING = "missing"
WEAK = "weak"
OUTDATED = "outdated"  # the content disagreed with the pin or the lock; replaced because the user named it
INCLUDE_EDITED = "include-edited"  # the pin matched the include as read; this run edits the include

# Why a change is refused unless the user names the file.
PIN_DIFFERS = "pin-differs"
LOCK_DIFFERS = "lock-differs"

# How the lock entry related to a change.
AGREED_WITH_OLD = "agreed with old"
AGREED_WITH_NEW = "agreed with new"
NO_ENTRY = "no entry"
DISAGREED_WITH_BOTH = "disagreed with both"


@dataclass(frozen=True)
class PinChange:
    """One ``sha`` attribute that is (or would be) written."""

    file: str  # the referencing document, as errors name it
    line: int | None
    kind: str
    uri: str
    url: str  # what the uri resolves to
    reason: str  # missing | weak | outdated | include-edited
    old: str | None  # the sha text as written, None when absent
    new: str  # the full SHA-256 written
    lock: str  # agreed with old | agreed with new | no entry | disagreed with both
    lock_sha256: str | None  # the lock entry's digest, None when the lock has none

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
            "lock": self.lock,
            "lock_sha256": self.lock_sha256,
        }


@dataclass(frozen=True)
class LockChange:
    """One lock entry that is (or would be) added, changed or dropped."""

    url: str  # as the lock file writes it
    old: str | None  # None: a new entry
    new: str | None  # None: no longer referenced

    def to_dict(self) -> dict[str, Any]:
        return {"url": self.url, "old": self.old, "new": self.new}


@dataclass
class PinReport:
    changes: list[PinChange] = field(default_factory=list)
    lock_changes: list[LockChange] = field(default_factory=list)
    errors: list[HcdfTrustError] = field(default_factory=list)
    warnings: list[Notice] = field(default_factory=list)
    planned: list[str] = field(default_factory=list)  # the files ``write`` writes (or wrote)
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
    update: Iterable[str] = (),
    update_all: bool = False,
) -> PinReport:
    """Compute (and with ``write``, apply) every ``sha`` repair in ``doc_path``'s tree, and its lock.

    ``update`` names files whose disagreeing pins or lock entries may be replaced
    by their current content (the uri as written, the resolved URL or a path);
    ``update_all`` allows it for every file.

    Never raises for content errors: they are returned in :attr:`PinReport.errors`,
    and then no file is written. Without ``write`` nothing is written anywhere
    (not even the cache).
    """
    base = options or ResolveOptions()
    # The names go to resolve too: it reads a named include's new content (and walks what it
    # references), and caches a named file's new content, as `resolve --update` does.
    opts = replace(
        base,
        accept_mismatch=True,
        locked=False,
        write_cache=base.write_cache and write,
        update=tuple(update),
        update_all=update_all,
    )
    report = PinReport()
    try:
        res = resolve(doc_path, opts)
    except HcdfTrustError as exc:
        report.errors.append(exc)
        return report
    try:
        lock_raw, lock_entries = _read_lock(res.lock_path)
    except HcdfTrustError as exc:
        # resolve read it first and said what is wrong with it (a lock that is one of the
        # tree's inputs is named as such, not just as malformed)
        said = [e for e in res.errors if isinstance(e, LockFileError | OutputError)]
        report.errors.extend(said or [exc])
        return report

    # step 1: which errors pin decides again, and which stop it
    locations = _locations(res)
    editable = {url for url, loc in locations.items() if _is_editable(url, loc)}
    decided = {
        (use.doc, use.ref.line, url): use.ref.kind in PINNABLE and use.doc_url in editable
        for art in res.artifacts.values()
        if art.sha256 is not None
        for use in art.uses
        for url in (art.url, res.lock_url(art.url))  # lock drift names the lock's url
    }
    for err in res.errors:
        key = (err.file, err.line, err.url)
        if key in decided and isinstance(err, IntegrityError):
            if not isinstance(err, WeakPinError) or decided[key]:
                continue  # pins and lock versus content: decided by the rules above
        report.errors.append(err)
    if report.errors:
        return report
    lock = {url: entry.sha256 for url, entry in lock_entries.items()}

    # steps 2 and 3: settle documents bottom-up, editing their text
    planner = _Planner(res, editable, lock, res.updating)
    try:
        planner.settle(res.root_location.url)
    except HcdfTrustError as exc:
        planner.errors.append(exc)
    report.warnings.extend(planner.warnings)
    report.errors.extend(planner.errors)
    report.changes = sorted(planner.changes, key=lambda c: (c.file, c.line or 0, c.uri))
    if report.errors:
        return report

    # step 4: plan the edited documents and the lock, every other input protected
    entries = res.lock_entries(edited=planner.new_bytes)
    lock_new = lockfile.render(entries, root=res.lock_url(res.root_location.url))
    report.lock_changes = _lock_diff(lock, {e.url: e.sha256 for e in entries})
    report.errors.extend(_unread_includes(res))
    report.errors.extend(_check_kept(res, planner, lock_entries, entries))
    if report.errors:
        return report
    targets = _targets(res, planner, locations, report.errors)
    plan = OutputPlan()
    if not report.errors:
        protect_inputs(plan, res, doc=doc_path, options=base)
        try:
            for path, (url, _old, new) in targets.items():
                plan.add(path, new, flag="document", mode=stat.S_IMODE(os.stat(path).st_mode), edit=True)
                report.planned.append(display_url(url))
            if lock_new != lock_raw:
                plan.add(res.lock_path, lock_new, flag="--lock")
                report.planned.append(display_path(res.lock_path))
        except OutputError as exc:
            report.errors.append(exc)
        except OSError as exc:
            report.errors.append(InputError(f"cannot stat: {exc.strerror}", file=exc.filename))
    if report.errors or not write:
        return report

    # step 5: write everything or nothing, only if nothing changed since it was read
    report.errors.extend(_changed_since_read(targets, res.lock_path, lock_raw))
    if report.errors:
        return report
    try:
        plan.commit()
    except OutputError as exc:
        report.errors.append(exc)
        return report
    report.written = list(report.planned)
    return report


# -- the rules (pure) ----------------------------------------------------------------


def decide(
    pin: Pin | None, *, read: str, settled: str, locked: str | None, vouched: bool, named: bool
) -> tuple[str | None, str | None]:
    """``(reason, None)`` to write ``settled``, ``(None, refusal)``, or ``(None, None)``. Pure.

    ``read`` is the digest of the content as read, ``settled`` after this run's edits
    (they differ only for an include this run edits), ``locked`` the lock entry's
    digest, ``vouched`` whether some reference to the same file has a full pin equal
    to ``read``, ``named`` whether the user named the file for update.
    """
    if pin is not None and not pin.matches(read):
        return (OUTDATED, None) if named else (None, PIN_DIFFERS)
    if pin is None or not pin.is_full:
        if locked is not None and locked != read and not vouched:
            return (OUTDATED, None) if named else (None, LOCK_DIFFERS)
        return (MISSING if pin is None else WEAK), None
    return (INCLUDE_EDITED if settled != read else None), None


def lock_agreement(old: Pin | None, new: str, locked: str | None) -> str:
    """How the lock entry related to a change from ``old`` to ``new``. Pure.

    For a reference without a sha the lock entry was its pin, so a lock entry other
    than ``new`` counts as agreeing with the old state.
    """
    if locked is None:
        return NO_ENTRY
    if locked == new:
        return AGREED_WITH_NEW
    if old is None or old.matches(locked):
        return AGREED_WITH_OLD
    return DISAGREED_WITH_BOTH


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


def _read_lock(path: Path, *, parse: bool = True) -> tuple[bytes | None, dict[str, lockfile.LockEntry]]:
    """The lock file's bytes (None when there is none) and its entries by lock URL.

    Raises:
        HcdfTrustError: it cannot be read, or (with ``parse``) is not a valid lock file.
    """
    if not os.path.lexists(path):
        return None, {}
    entries = lockfile.load(path).entries if parse else {}  # refuses a FIFO, a device, a huge file...
    raw = read_input(path, limit=lockfile.MAX_LOCK_BYTES, what="lock file", source=display_path(path))
    return raw, entries


class _Planner:
    """Post-order over the include DAG (cycles are resolve errors, so none reach here)."""

    def __init__(self, res: Resolution, editable: set[str], lock: dict[str, str], named: set[str]) -> None:
        self.res = res
        self.editable = editable
        base = res.lock_path.parent  # the lock's URLs, absolute as the resolution's (no relpath per file)
        self.lock = {url if "://" in url else file_url(os.path.normpath(base / url)): sha for url, sha in lock.items()}
        self.named = named
        self.uses: dict[str, list[tuple[Use, Artifact]]] = {}
        self.vouched: set[str] = set()
        for art in res.artifacts.values():
            if art.sha256 is None:
                continue  # an error stopped the run before this is reached
            if any(u.pin is not None and u.pin.is_full and u.pin.hex == art.sha256 for u in art.uses):
                self.vouched.add(art.url)
            for use in art.uses:
                self.uses.setdefault(use.doc_url, []).append((use, art))
        self.digest: dict[str, str] = {}
        self.new_bytes: dict[str, bytes] = {}
        self.order: list[str] = []  # leaves first
        self.active: set[str] = set()
        self.changes: list[PinChange] = []
        self.warnings: list[Notice] = []
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
                read = art.sha256
                assert read is not None
                is_doc = use.ref.kind is Kind.INCLUDE and art.url in self.res.documents
                settled = self.digest[art.url] if is_doc else read
                sha = self._judge(url_now, use, art, read, settled)
                if sha is not None:
                    edits.append((use.ref, sha))
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

    def _judge(self, doc_url: str, use: Use, art: Artifact, read: str, settled: str) -> str | None:
        """Apply the rules to one reference: the digest to write into it, or None."""
        locked = self.lock.get(art.url)
        uri = use.ref.uri or ""
        editable = doc_url in self.editable and use.ref.kind in PINNABLE
        if not editable and use.pin is not None and not use.pin.matches(read):
            if use.ref.kind not in PINNABLE:
                why = f"a <{use.ref.kind.value}> sha is not one pin edits: fix or remove it by hand"
            else:
                why = "the referencing document is remote, and pin cannot edit it"
            self.errors.append(self._mismatch(f"{uri}: digest mismatch ({why})", use, art, use.pin.hex, read))
            return None
        reason, refused = decide(
            use.pin,
            read=read,
            settled=settled,
            locked=locked,
            vouched=art.url in self.vouched,
            named=art.url in self.named,
        )
        hint = f"if the new content is intended, run pin again with --update {uri} (or --all)"
        if refused == PIN_DIFFERS:
            assert use.pin is not None
            said = _lock_says(use.pin, read, locked)
            if art.kind is Kind.INCLUDE:
                said += f"; {include_mismatch_hint(uri, display_path(self.res.root.source))}"
            self.errors.append(
                self._mismatch(
                    f"{uri}: digest mismatch: the content is not what the sha pins ({said}); {hint}",
                    use,
                    art,
                    use.pin.hex,
                    read,
                )
            )
            return None
        if refused == LOCK_DIFFERS:
            assert locked is not None
            lock_name = display_path(self.res.lock_path)
            self.errors.append(
                self._mismatch(
                    f"{uri} changed since it was locked in {lock_name} (without a full sha, the lock entry is its "
                    f"pin); {hint}",
                    use,
                    art,
                    locked,
                    read,
                )
            )
            return None
        if reason is None or use.ref.kind not in PINNABLE:
            return None  # nothing to write, or a file that only the lock pins (a mesh)
        if not editable:
            self.warnings.append(
                Notice(
                    "pin-remote",
                    f"{uri} needs a pin ({reason}: sha256 {settled}) but {use.doc} is remote: pin cannot edit it",
                    file=use.doc,
                    line=use.ref.line,
                    url=display_url(art.url),
                )
            )
            return None
        self.changes.append(
            PinChange(
                file=use.doc,
                line=use.ref.line,
                kind=use.ref.kind.value,
                uri=uri,
                url=display_url(art.url),
                reason=reason,
                old=use.ref.sha,
                new=settled,
                lock=lock_agreement(use.pin, settled, locked),
                lock_sha256=locked,
            )
        )
        return settled

    @staticmethod
    def _mismatch(message: str, use: Use, art: Artifact, expected: str, actual: str) -> DigestMismatchError:
        return DigestMismatchError(
            message, file=use.doc, line=use.ref.line, url=art.url, expected=expected, actual=actual
        )


def _lock_says(pin: Pin, read: str, locked: str | None) -> str:
    if locked is None:
        return "the lock has no entry for it"
    if pin.matches(locked):
        return "the lock agrees with the sha: the file changed after it was pinned"
    if locked == read:
        return "the lock has the new content"
    return f"the lock has a third digest, {locked}"


# -- the lock keeps every pin it was not told to change ---------------------------------


class LockKeptError(IntegrityError):
    """This run would change or drop a lock entry that nothing it was told to accept changes."""

    code = "lock-kept"


def kept_violations(
    old: dict[str, lockfile.LockEntry], new: list[lockfile.LockEntry], *, may_change: set[str]
) -> list[tuple[str, lockfile.LockEntry, lockfile.LockEntry]]:
    """``(url, old entry, new entry)`` for each lock entry whose pin (digest and size) the
    new lock changes though its url is not in ``may_change``. Pure.

    The lock is the only pin of every reference without a full sha: an entry that changes
    without the user accepting that file's content would let tampered content through
    (trust on first use, taken again).
    """
    out = []
    for entry in new:
        before = old.get(entry.url)
        if before is None or entry.url in may_change:
            continue
        if (before.sha256, before.size) != (entry.sha256, entry.size):
            out.append((entry.url, before, entry))
    return out


def _check_kept(
    res: Resolution, planner: _Planner, old: dict[str, lockfile.LockEntry], new: list[lockfile.LockEntry]
) -> list[HcdfTrustError]:
    """An error for every lock entry this run would change without being told to (see
    :func:`kept_violations`). It may change: the files named with ``--update`` (all with
    ``--all``), the documents it edits, and files a full sha in the tree pins to their
    content (authoritative over the lock, as for ``resolve``)."""
    may_change = {res.lock_url(url) for url in res.updating | planner.vouched}
    may_change |= {res.lock_url(url) for url, data in planner.new_bytes.items() if data != res.documents[url].data}
    shown = display_path(res.lock_path)
    return [
        LockKeptError(
            f"{url}: this run would change its entry in {shown} though nothing it was told to accept changes "
            "it (name the file with --update to accept its content); nothing written",
            file=shown,
            url=url,
            expected=f"{before.sha256} ({before.size} bytes)",
            actual=f"{after.sha256} ({after.size} bytes)",
        )
        for url, before, after in kept_violations(old, new, may_change=may_change)
    ]


def _unread_includes(res: Resolution) -> list[HcdfTrustError]:
    """An error for every include whose content was hashed but not read as a document: the
    references in it would be missing, and their lock entries dropped."""
    return [
        PinEditError(
            f"{display_url(art.url)} was not read, so the files it references are unknown: refusing to "
            "write a lock that would drop their entries",
            file=art.uses[0].doc,
            line=art.uses[0].ref.line,
            url=art.url,
        )
        for art in res.artifacts.values()
        if art.kind is Kind.INCLUDE and art.sha256 is not None and art.error is None and art.url not in res.documents
    ]


# -- the outputs ---------------------------------------------------------------------


def _lock_diff(old: dict[str, str], new: dict[str, str]) -> list[LockChange]:
    return [
        LockChange(url, old.get(url), new.get(url))
        for url in sorted(set(old) | set(new))
        if old.get(url) != new.get(url)
    ]


def _targets(
    res: Resolution, planner: _Planner, locations: dict[str, Location], errors: list[HcdfTrustError]
) -> dict[str, tuple[str, bytes, bytes]]:
    """The edited documents by real path: (url, bytes as read, new bytes), leaves first."""
    targets: dict[str, tuple[str, bytes, bytes]] = {}
    for url in planner.order:
        new = planner.new_bytes[url]
        old = res.documents[url].data
        if new == old:
            continue
        local = locations[url].path
        assert local is not None  # only local documents are editable, so only they change
        path = os.path.realpath(local)
        seen = targets.get(path)
        if seen is not None and seen[2] != new:
            errors.append(
                PinEditError(
                    f"{path} is reached as two documents that need different edits (a symlink?): refusing to edit it",
                    file=display_url(url),
                )
            )
        targets[path] = (url, old, new)
    return targets


def _changed_since_read(
    targets: dict[str, tuple[str, bytes, bytes]], lock_path: Path, lock_raw: bytes | None
) -> list[HcdfTrustError]:
    """An error for each edited document, and the lock, whose bytes are no longer those read."""
    errors: list[HcdfTrustError] = []
    for path, (url, old, _new) in targets.items():
        try:
            current = read_input(path, limit=MAX_DOCUMENT_BYTES, source=display_url(url), what="document")
        except HcdfTrustError as exc:
            errors.append(InputError(f"cannot re-read: {exc.message}", file=display_url(url)))
            continue
        if current != old:
            errors.append(InputError("changed on disk while pinning: run pin again", file=display_url(url)))
    try:
        lock_now, _ = _read_lock(lock_path, parse=False)
    except HcdfTrustError as exc:
        errors.append(exc)
    else:
        if lock_now != lock_raw:
            shown = display_path(lock_path)
            errors.append(InputError("the lock file changed on disk while pinning: run pin again", file=shown))
    return errors


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


def json_not_edited(doc: Document, verb: str) -> str:
    """Why ``verb`` does not edit ``doc``, a document in HCDF's JSON form, and what to do instead.

    Edits here are minimal text edits of XML (comments and formatting kept); rewriting JSON
    through the converter would reorder and reformat the user's file. So a JSON document
    is converted, edited as XML, and converted back (docs/json-form.md).
    """
    xml = doc.source.rsplit("/", 1)[-1].removesuffix(".json") + ".hcdf"
    return (
        f"this document is in HCDF's JSON form, which {verb} does not edit in place: convert it "
        f"(hcdf-trust convert {doc.source} {xml}), {verb} the XML, and convert it back"
    )


def apply_pins(doc: Document, edits: list[tuple[Reference, str]]) -> bytes:
    """``doc``'s bytes with each reference's ``sha`` set to its full digest.

    An existing ``sha`` attribute has its value replaced (quotes and a ``sha256:``
    prefix kept); a missing one is inserted right after the ``uri``/``href``
    attribute, in the same quote style and in the document's pin style
    (:func:`~hcdf_trust.digest.prefixed_style`). Nothing else in the text changes.

    Raises:
        PinEditError: a reference cannot be located unambiguously in the text, or
        the document's encoding is not ASCII-compatible.
    """
    if doc.is_json:
        raise PinEditError(json_not_edited(doc, "pin"), file=doc.source)
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
    style = PREFIX.encode("ascii") if prefixed_style(r.sha for r in doc.references() if r.kind.fetchable) else b""
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
            splices.append((uri.end, uri.end, b" sha=" + q + style + sha.encode("ascii") + q))
    parts: list[bytes] = []
    pos = 0
    for start, end, new in sorted(splices):
        parts += (data[pos:start], new)
        pos = end
    parts.append(data[pos:])
    return b"".join(parts)
