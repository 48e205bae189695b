"""The lock file: every artifact of one root document's tree, its digest and size.

Format (``lock_version`` 2): one JSON object with sorted keys ``artifacts``,
``lock_version`` and ``root``. ``artifacts`` holds one object per distinct file,
sorted by URL, one per line (diff-friendly, and rendered with the C JSON encoder).
Each has ``kind``, ``uri`` (as first written), ``url``, ``sha256``, ``size`` and
``referenced_from`` (the documents that reference it, without line numbers, so
moving a reference is not a change). Local URLs, ``root`` and ``referenced_from``
are relative to the lock file's folder, so the lock survives moving the checkout.

The loader accepts exactly what :func:`render` writes: anything else (wrong types,
missing or extra keys, duplicate URLs or keys, floats, NaN, deep nesting, over
:data:`MAX_LOCK_BYTES`) is a :class:`LockFileError` (exit 3).
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import operator
import os
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from json.encoder import encode_basestring  # the C escaper json itself uses
from pathlib import Path
from typing import Any, NamedTuple, NoReturn

from ..errors import InputError, LockDriftError, LockFileError, NotFoundError, display_path
from ..localfile import JsonError, parse_json, read_input

LOCK_VERSION = 2
SUFFIX = ".lock"
# ~300 bytes per artifact: room for ~100,000 files. A larger file is refused unread.
MAX_LOCK_BYTES = 32 << 20
KINDS = frozenset({"include", "model", "mesh", "stream-profile", "firmware-manifest"})
_KEYS = frozenset({"kind", "uri", "url", "sha256", "size", "referenced_from"})
_TOP = frozenset({"artifacts", "lock_version", "root"})
itemgetter = operator.itemgetter("kind", "uri", "url", "sha256", "size", "referenced_from")
_BY_URL = operator.attrgetter("url", "kind")  # render's order (in C: 10,000 entries)
_URL = operator.attrgetter("url")


def default_path(doc: str | os.PathLike[str]) -> Path:
    """``<DOC filename>.lock`` beside DOC: two roots in one folder never share a lock."""
    p = Path(doc)
    return p.with_name(p.name + SUFFIX)


class LockEntry(NamedTuple):
    """One artifact of the lock (a named tuple: 10,000 of them are built per run)."""

    kind: str
    uri: str
    url: str
    sha256: str
    size: int
    referenced_from: tuple[str, ...] = ()

    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "uri": self.uri,
            "url": self.url,
            "sha256": self.sha256,
            "size": self.size,
            "referenced_from": list(self.referenced_from),
        }


@dataclass(frozen=True)
class Lock:
    """A loaded lock file: the root document it belongs to and its entries by URL.

    ``rendered`` is the file's bytes when they are exactly what :func:`render` writes for
    ``entries`` and ``root`` (else None): a run whose entries are unchanged reuses them
    (:func:`render_unchanged`) instead of rendering 10,000 lines again.
    """

    root: str
    entries: dict[str, LockEntry]
    rendered: bytes | None = field(default=None, repr=False, compare=False)
    # SHA-256 of the file's bytes as read (load sets it): what a verification was made against.
    sha256: str = field(default="", repr=False, compare=False)


def render(entries: list[LockEntry], *, root: str) -> bytes:
    """The lock file's bytes: deterministic, valid JSON, one artifact per line.

    Each artifact line is exactly ``json.dumps(entry.to_dict(), sort_keys=True,
    ensure_ascii=False)``, built from json's own C string escaper (the indenting
    encoder is pure Python: 10,000 entries cost more than resolving them).
    """
    lines = [_entry_json(e) for e in sorted(entries, key=_BY_URL)]
    body = ",\n".join(lines)
    artifacts = f"[\n{body}\n]" if lines else "[]"
    text = f'{{"artifacts": {artifacts},\n"lock_version": {LOCK_VERSION},\n"root": {encode_basestring(root)}}}\n'
    return text.encode()


def render_unchanged(entries: list[LockEntry], *, root: str, before: Lock | None) -> bytes:
    """``render(entries, root=root)``, taken from ``before`` (the lock as read) when that
    is the same lock: same root, same entries (render sorts them), bytes as render writes."""
    if before is not None and before.rendered is not None and before.root == root:
        by_url = dict(zip(map(_URL, entries), entries, strict=True))
        if len(entries) == len(before.entries) and by_url == before.entries:
            return before.rendered
    return render(entries, root=root)


def _entry_json(e: LockEntry) -> str:
    esc = encode_basestring
    refs = ", ".join(map(esc, e.referenced_from))
    return (
        f'{{"kind": {esc(e.kind)}, "referenced_from": [{refs}], "sha256": {esc(e.sha256)}, '
        f'"size": {int(e.size)}, "uri": {esc(e.uri)}, "url": {esc(e.url)}}}'
    )


# The characters of a rendered line outside its six values (a size of "0" is one digit).
_LINE_FIXED = len(_entry_json(LockEntry("", "", "", "", 0, ()))) - 1


def load(path: str | os.PathLike[str]) -> Lock:
    """Read and check a lock file.

    Raises:
        LockFileError: missing, not a regular file, over :data:`MAX_LOCK_BYTES`,
            not JSON, an unknown ``lock_version``, or any shape :func:`render` does not write.
    """
    name = display_path(path)  # as messages show it: relative to the working folder when inside it
    try:
        raw = read_input(os.fspath(path), limit=MAX_LOCK_BYTES, what="lock file", source=name)
    except NotFoundError:
        if os.path.islink(path):  # fail closed, but say what is there
            target = os.readlink(path)
            raise LockFileError(
                f"lock file {name} is a symlink to {target!r}, which does not exist", file=name
            ) from None
        hint = "run resolve without --locked first"
        raise LockFileError(f"lock file {name} does not exist ({hint})", file=name) from None
    except InputError as exc:  # FIFO, device, directory, too large, unreadable
        raise LockFileError(f"cannot read lock file: {exc.message}", file=name) from None
    digest = hashlib.sha256(raw).hexdigest()
    try:
        lock = _canonical(raw.decode(), raw)
    except UnicodeDecodeError as exc:
        _bad(name, f"not UTF-8: {exc.reason} at byte {exc.start}")
    if lock is not None:
        return dataclasses.replace(lock, sha256=digest)
    try:  # any other form: the one strict reader (duplicate keys, NaN, surrogates, depth), integers only
        doc = parse_json(raw, source=name, what="lock file", limit=MAX_LOCK_BYTES, floats=False)
    except JsonError as exc:
        conflict = merge_conflict(raw.decode(errors="replace"), name)
        if conflict is not None:
            raise conflict from None
        _bad(name, exc.message.removeprefix("lock file: ").removeprefix("lock file "))
    return dataclasses.replace(_check(doc, name), sha256=digest)


# The lines render() writes, read without json: its decoder refuses duplicate keys only
# through a Python hook called for every object (2 µs each, more than the rest of
# loading 10,000 artifacts). These strings hold no quote, backslash or control
# character, so each one's JSON value is its text; a lock in any other form (an escape,
# an upper-case digest, other spacing or key order) is read by json and _check.
_STRING = r'"([^"\\\x00-\x1f]*)"'
_NAMES = r'\[((?:"[^"\\\x00-\x1f]*"(?:, "[^"\\\x00-\x1f]*")*)?)\]'
_ENTRY = (
    rf'\{{"kind": {_STRING}, "referenced_from": {_NAMES}, "sha256": "([0-9a-f]{{64}})", '
    rf'"size": (0|[1-9][0-9]{{0,17}}), "uri": {_STRING}, "url": {_STRING}\}}'
)
_LINES = re.compile(_ENTRY + r"(?:,\n|\Z)")  # a line and its separator (none after the last)
_HEAD = '{"artifacts": [\n'
#: ``LockEntry(*fields)`` from a tuple of its six fields, built in C (``tuple.__new__``, what
#: ``LockEntry._make`` calls), not by the named tuple's Python ``__new__``.
new_entry = functools.partial(tuple.__new__, LockEntry)
_TAIL = re.compile(rf'\n\],\n"lock_version": {LOCK_VERSION},\n"root": {_STRING}\}}\n')


def _canonical(text: str, raw: bytes) -> Lock | None:
    """The lock, when ``text`` (decoded from ``raw``) is in the form :func:`render` writes
    and every value is valid; otherwise None, and the general path reads it and names
    what is wrong. When its artifacts are also in render's order, ``raw`` is render's
    output for them (each line is render's line for the values it holds): ``rendered``.

    One regex scan finds every line; the matches cover the body exactly (no text
    between, before or after them) when their lengths add up to the body's. The
    checks then run over whole columns, in C: ~1 µs an artifact, not ~4 in a loop.
    """
    end = text.rfind("\n],\n")
    tail = _TAIL.fullmatch(text, end) if text.startswith(_HEAD) and end > len(_HEAD) else None
    if tail is None or not tail.group(1):
        return None
    rows = _LINES.findall(text, len(_HEAD), end)  # the body, read in place (as if text ended at end)
    count = len(rows)
    if not count:
        return None
    columns = tuple(zip(*rows, strict=True))
    kinds, refs, shas, sizes, uris, urls = columns
    values = sum(len("".join(column)) for column in columns)
    if count * _LINE_FIXED + 2 * (count - 1) + values != end - len(_HEAD):
        return None  # text the matches skipped: not render's lines
    if not KINDS.issuperset(kinds) or "" in uris or "" in urls or len(set(urls)) != count:
        return None
    names_of = {r: tuple(r[1:-1].split('", "')) if r else () for r in set(refs)}  # a few distinct lists
    if any("" in names for names in names_of.values()):
        return None
    # LockEntry(...) runs the named tuple's Python __new__; tuple.__new__ (what its _make
    # calls) builds the same six-field tuple in C.
    fields = zip(kinds, uris, urls, shas, map(int, sizes), map(names_of.__getitem__, refs), strict=True)
    entries = dict(zip(urls, map(new_entry, fields), strict=True))
    ordered = all(map(operator.lt, urls, urls[1:]))  # render's order: by url (each url once)
    return Lock(root=tail.group(1), entries=entries, rendered=raw if ordered else None)


# git's conflict markers: "<<<<<<< ours", "||||||| base" (diff3), "=======", ">>>>>>> theirs".
_MARKER = re.compile(r"^(?:(<{7}|\|{7}|>{7})(?: .*)?|(={7}))$", re.M)
_URL_SHA = re.compile(r'"sha256": "([0-9a-fA-F]{64})".*"url": "([^"\\]*)"')


def merge_conflict(text: str, name: str) -> LockFileError | None:
    """The error for a lock holding git merge-conflict markers (None if it holds none). Pure.

    It names the entries the two sides disagree on (a url with another digest on each
    side, or on one side only) and says how to recover without losing the first-use
    pins: every entry is the only pin of a reference without a full sha, so deleting
    the lock, or re-locking from the files as they are now, would trust them anew.
    """
    starts = [m for m in _MARKER.finditer(text) if m.group(1) == "<" * 7]
    if not starts:
        return None
    sides: dict[str, dict[str, str]] = {"ours": {}, "theirs": {}}
    side: str | None = None
    for row in text.splitlines():
        marker = _MARKER.fullmatch(row)
        if marker is not None:
            tag = marker.group(1) or marker.group(2)
            side = {"<" * 7: "ours", "|" * 7: None, "=" * 7: "theirs", ">" * 7: None}[tag]
            continue
        entry = _URL_SHA.search(row) if side is not None else None
        if side is not None and entry is not None:
            sides[side][entry.group(2)] = entry.group(1).lower()
    ours, theirs = sides["ours"], sides["theirs"]
    differ = sorted(url for url in ours.keys() | theirs.keys() if ours.get(url) != theirs.get(url))
    shown = ", ".join(
        f"{url} ({(ours.get(url) or 'absent')[:12]} | {(theirs.get(url) or 'absent')[:12]})" for url in differ[:8]
    ) + (f" and {len(differ) - 8} more" if len(differ) > 8 else "")
    line = text.count("\n", 0, starts[0].start()) + 1
    return LockFileError(
        f"lock file {name} has unresolved merge-conflict markers (git's <<<<<<< at line {line}, "
        f"{len(starts)} conflict(s)); the entries the two sides pin differently (ours | theirs): "
        f"{shown or 'none'}. Do not delete it: it is the only pin of every reference without a full sha. "
        "Keep one side of each conflict (or every line of both, once per url), or take one side whole "
        f"(git checkout --ours {name}), then run resolve: an entry whose file differs from the side kept "
        "fails as lock-drift until you have checked it and run resolve --update URI for it",
        file=name,
        line=line,
        expected="a lock file without merge-conflict markers",
        actual=starts[0].group(0)[:60],
    )


def _check(doc: object, name: str) -> Lock:
    if not isinstance(doc, dict):
        _bad(name, f"expected a JSON object, found {_type(doc)}")
    version = doc.get("lock_version")
    if version != LOCK_VERSION or type(version) is not int:
        hint = f"delete {name} and run `hcdf-trust resolve` to lock the tree again (trust on first use)"
        raise LockFileError(
            f"unsupported lock_version {json.dumps(version)} (this version reads and writes {LOCK_VERSION}): {hint}",
            file=name,
            expected=str(LOCK_VERSION),
            actual=json.dumps(version),
        )
    if doc.keys() != _TOP:
        _bad(name, f"top-level keys must be {sorted(_TOP)}, found {sorted(doc)}")
    root, items = doc["root"], doc["artifacts"]
    if type(root) is not str or not root:
        _bad(name, f"root must be a non-empty string, found {_type(root)}")
    if type(items) is not list:
        _bad(name, f"artifacts must be a list, found {_type(items)}")
    entries: dict[str, LockEntry] = {}
    for i, item in enumerate(items):
        try:
            if type(item) is not dict or len(item) != len(_KEYS):
                raise KeyError
            kind, uri, url, sha, size, refs = itemgetter(item)  # six keys, all present: exactly _KEYS
        except KeyError:
            keys = sorted(item) if type(item) is dict else _type(item)
            _bad(name, f"artifact {i}: expected an object with keys {sorted(_KEYS)}, found {keys}")
        if type(url) is not str or not url:
            _bad(name, f"artifact {i}: url must be a non-empty string")
        if type(kind) is not str or kind not in KINDS:
            _bad(name, f"artifact {url}: kind must be one of {sorted(KINDS)}, found {kind!r}")
        if type(uri) is not str or not uri:
            _bad(name, f"artifact {url}: uri must be a non-empty string")
        if type(sha) is not str or not _is_hex64(sha):
            _bad(name, f"artifact {url}: sha256 is not a full digest (64 hex digits), found {sha!r}")
        if type(size) is not int or size < 0:
            _bad(name, f"artifact {url}: size must be a non-negative integer, found {size!r}")
        if not _is_names(refs):
            _bad(name, f"artifact {url}: referenced_from must be a list of document paths")
        if url in entries:
            _bad(name, f"artifact {url} is listed twice")
        entries[url] = LockEntry(kind, uri, url, sha.lower(), size, tuple(refs))
    return Lock(root=root, entries=entries)


def _is_hex64(text: str) -> bool:
    """64 hex digits, either case. ``bytes.fromhex`` (C) skips whitespace only between
    digit pairs, so 64 characters that decode to 32 bytes are 64 digits."""
    try:
        return len(text) == 64 and len(bytes.fromhex(text)) == 32
    except ValueError:
        return False


def _is_names(refs: object) -> bool:
    """A list of non-empty strings (``str.join`` refuses anything but strings, in C)."""
    if type(refs) is not list or "" in refs:
        return False
    try:
        "".join(refs)
    except TypeError:
        return False
    return True


def _type(value: object) -> str:
    return {dict: "an object", list: "a list", str: "a string", bool: "a boolean", int: "an integer"}.get(
        type(value), "null" if value is None else type(value).__name__
    )


def _bad(name: str, why: str) -> NoReturn:
    raise LockFileError(f"malformed lock file: {why}", file=name)


Where = Mapping[str, tuple[str | None, int | None]]


def compare(
    locked: dict[str, LockEntry], actual: dict[str, LockEntry], *, lock_path: str, where: Where
) -> list[LockDriftError]:
    """Every difference between the lock and what the tree resolves to now. Pure.

    Digest and size are compared; ``uri`` and ``referenced_from`` are not (moving or
    respelling a reference is not drift). ``where`` maps a URL to the file and line
    of its first reference in the current parse, for the messages.
    """
    errors: list[LockDriftError] = []
    for url, now in sorted(actual.items()):
        before = locked.get(url)
        file, line = where.get(url, (None, None))
        if before is None:
            errors.append(
                LockDriftError(f"{now.uri} is not in the lock file {lock_path}", file=file, line=line, url=url)
            )
        else:
            drift = drift_error(before, now.sha256, now.size, uri=now.uri, url=url, file=file, line=line)
            if drift is not None:
                errors.append(drift)
    for url in sorted(set(locked) - set(actual)):
        errors.append(LockDriftError(f"{url} is in the lock file but no longer referenced", file=lock_path, url=url))
    return errors


def drift_error(
    before: LockEntry,
    sha256: str,
    size: int,
    *,
    uri: str,
    url: str,
    file: str | None,
    line: int | None,
    hint: str = "",
) -> LockDriftError | None:
    """The error for content that differs from its lock entry (digest or size), or None. Pure."""
    if before.sha256 != sha256:
        return LockDriftError(
            f"{uri} changed since it was locked{hint}",
            file=file,
            line=line,
            url=url,
            expected=before.sha256,
            actual=sha256,
        )
    if before.size != size:
        return LockDriftError(
            f"{uri} changed since it was locked (its size differs){hint}",
            file=file,
            line=line,
            url=url,
            expected=f"{before.size} bytes",
            actual=f"{size} bytes",
        )
    return None
