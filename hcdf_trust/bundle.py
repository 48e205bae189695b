"""``.hcdfz`` bundles: upstream's format, written from a verified tree and read without extracting.

The format is upstream's (CogniPilot/hcdformat ``docs/design/bundling-and-remote-assets.md`` and
``rust/hcdformat-rs/src/{bundle,zip_store}.rs`` at 05d27b58): a ZIP whose first entry is the root
``.hcdf``, every entry ``ZIP_STORED``, includes flattened into that one document, every referenced
file under ``assets/`` as ``<stem>_<sha>.<ext>`` with document-relative URIs and ``sha256:<hex>``
pins. Upstream's bundle verifier is lenient (it walks local headers and ignores the central
directory); this reader accepts exactly the archives the writer writes and refuses the rest:

- :func:`read_archive` checks the ZIP structure (exit 3, :class:`BundleFormatError`);
- :class:`BundleFiles` is the resolver's seam: the same walker reads the entries instead of files,
  so a bundle gets the same verdicts as a tree (``include/resolver.py``);
- :func:`check_contents` adds the bundle's own rules once the tree is walked (exit 1,
  :class:`BundleIntegrityError`): no unused entry, content-addressed names that match their bytes;
- :func:`build` writes one from a verified :class:`~hcdf_trust.include.resolver.Resolution`.
"""

from __future__ import annotations

import hashlib
import os
import re
import stat
import struct
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from .digest import Hashed
from .errors import InputError, IntegrityError, UnpinnedError, display_path

if TYPE_CHECKING:
    from .include.resolver import Resolution

_Bad = Callable[..., "BundleFormatError"]

SUFFIX = ".hcdfz"
ASSETS = "assets"
SHORT_SHA = 12  # hex digits of the content hash in an asset's name (upstream's SHORT_SHA)
# Caps, checked before any entry is read. Without ZIP64 (which neither upstream nor we write) an
# archive holds at most 65,535 entries and 4 GiB; our resolver's trees top out near 10,000 files.
# A bundle is read whole into memory, once (not mapped: a file truncated under a mapping kills the
# reader with SIGBUS, and the digest recorded must be of the very bytes checked), so the byte cap
# is a memory cap, as it is for the writer, which builds the archive in memory.
MAX_ENTRIES = 20_000
MAX_BYTES = 2 << 30

# Record layouts (APPNOTE.TXT 4.3.7, 4.3.12, 4.3.16), little-endian.
_LOCAL = struct.Struct("<IHHHHHIIIHH")  # 30 bytes
_CENTRAL = struct.Struct("<IHHHHHHIIIHHHHHII")  # 46 bytes
_EOCD = struct.Struct("<IHHHHIIH")  # 22 bytes
_SIG_LOCAL, _SIG_CENTRAL, _SIG_EOCD = 0x04034B50, 0x02014B50, 0x06054B50
_VERSION = 20  # 2.0: what upstream writes as "version made by" (MS-DOS host) and "needed"
_MODE_REFUSED = 0o7022  # setuid, setgid, sticky, group- or world-writable: never on a verified file
_UTF8_FLAG = 0x800  # general purpose bit 11: the name is UTF-8 (other writers set it)
_DRIVE = re.compile(r"[A-Za-z]:")
_ADDRESSED = re.compile(r"_([0-9a-f]{12,64})(?:\.[^./]*)?\Z")  # <stem>_<hex>[.<ext>]
_UNSAFE_STEM = re.compile(r"[^0-9A-Za-z._-]")
# Every name the writer writes: the root at the top, every other file one level under assets/,
# in safe_stem's ASCII alphabet. Anything else (a subfolder, ':' an NTFS stream, a fullwidth dot
# that Windows' best-fit maps to '.', names equal but for Unicode normalization) is refused.
_WRITTEN_NAME = re.compile(r"(?:assets/)?[0-9A-Za-z._-]+")


class BundleFormatError(InputError):
    """The archive is not a ``.hcdfz`` this reader accepts (exit 3): its structure, not its content."""

    code = "bundle-format"


class BundleIntegrityError(IntegrityError):
    """The bundle's content breaks its own contract (exit 1): an unused entry, a name whose
    hash is not its bytes', a reference to something the bundle does not hold."""

    code = "bundle-integrity"


class BundleMissingError(BundleIntegrityError):
    code = "bundle-missing"


def is_bundle(path: str | os.PathLike[str]) -> bool:
    """Is ``path`` named as a bundle (``*.hcdfz``, any case)? The name decides, as upstream's does."""
    return os.fspath(path).lower().endswith(SUFFIX)


# --- reading --------------------------------------------------------------------------------


@dataclass(frozen=True)
class Entry:
    name: str
    offset: int  # of the data, in the archive
    size: int
    crc: int


class Archive:
    """A checked archive, held in memory: entries in archive order, their data by name."""

    def __init__(self, path: str, entries: list[Entry], view: memoryview, sha256: str) -> None:
        self.path = path
        self.entries = entries
        self.by_name = {e.name: e for e in entries}
        self.sha256 = sha256  # of the whole archive: what ota build and the SBOM record
        self.size = len(view)
        self._view = view

    @property
    def root(self) -> Entry:
        return self.entries[0]

    def data(self, entry: Entry) -> memoryview:
        return self._view[entry.offset : entry.offset + entry.size]

    def close(self) -> None:
        self._view.release()


def read_archive(
    path: str | os.PathLike[str], *, max_entries: int | None = None, max_bytes: int | None = None
) -> Archive:
    """Read and check ``path``: a regular file, read whole (bounded), every rule of :func:`check_structure`.

    Raises:
        NotFoundError, InputError: it cannot be opened or is not a regular file.
        BundleFormatError: the archive breaks a rule (named, with the entry and expected/actual).
    """
    from .localfile import open_regular, read_whole

    shown = display_path(path)
    fd, st = open_regular(os.fspath(path), what="bundle")
    try:
        limit = MAX_BYTES if max_bytes is None else max_bytes
        if st.st_size > limit:
            raise BundleFormatError(
                f"{shown}: {st.st_size} bytes, more than the cap of {limit} for a bundle",
                file=shown,
                expected=f"at most {limit} bytes",
                actual=str(st.st_size),
            )
        view = memoryview(read_whole(fd, limit, source=shown, what="bundle"))
    finally:
        os.close(fd)
    try:
        entries = check_structure(view, shown=shown, max_entries=MAX_ENTRIES if max_entries is None else max_entries)
    except BaseException:
        view.release()
        raise
    return Archive(shown, entries, view, hashlib.sha256(view).hexdigest())


def read_root_entry(path: str | os.PathLike[str]) -> tuple[str, bytes]:
    """``(display name, bytes)`` of a bundle's root document (``X.hcdfz/robot.hcdf``), from an
    archive checked by :func:`read_archive`: what ``validate`` reads of a bundle.

    Raises:
        BundleFormatError, InputError: as :func:`read_archive`; the root is over the document cap.
    """
    from .xml import MAX_DOCUMENT_BYTES

    archive = read_archive(path)
    try:
        root = archive.root
        source = f"{archive.path}/{root.name}"
        if root.size > MAX_DOCUMENT_BYTES:
            raise InputError(f"{source}: {root.size} bytes, more than the {MAX_DOCUMENT_BYTES}-byte limit", file=source)
        return source, bytes(archive.data(root))
    finally:
        archive.close()


def check_structure(data: memoryview | bytes, *, shown: str, max_entries: int = MAX_ENTRIES) -> list[Entry]:
    """The entries of a ``.hcdfz`` image, in archive order, after checking every structural rule.

    Hand-rolled rather than :mod:`zipfile`, which is lenient where a bundle must not be: it reads
    the central directory alone and accepts data before the first entry (it shifts every offset
    by it, for self-extracting archives), data between and after entries and an archive comment
    (where a second document can hide), entries that overlap or share bytes (the classic zip bomb),
    duplicate names (a warning at most: which copy an extractor keeps differs by tool), local
    headers whose method, sizes or CRC disagree with the central directory (it trusts the central
    one; other tools read the local one, so two tools would see two different files), and names
    that are absolute or climb out (``extract`` rewrites them; a foreign extractor may not). Here:

    1. the end record is the last 22 bytes (no comment), one disk, no ZIP64;
    2. the central directory ends where the end record starts, and holds at most ``max_entries``;
    3. each entry is a regular file (no directory, symlink or device in its external attributes),
       stored (method 0), unencrypted, sizes equal, no extra field or comment, a name the writer
       writes (``<root>.hcdf`` or ``assets/<[0-9A-Za-z._-]+>``) that is not a duplicate (also
       ignoring case: one file on a case-insensitive disk);
    4. entries lie back to back from byte 0 to the central directory, in central-directory order:
       nothing before, between, after or shared, so the bytes read are exactly the file's bytes;
    5. each local header repeats its central record (name, method, flags, CRC, sizes, time);
    6. each entry's CRC-32 matches its data.

    Raises:
        BundleFormatError: the first rule broken, naming the entry and expected/actual.
    """

    def bad(
        message: str, *, entry: str | None = None, expected: object = None, actual: object = None
    ) -> BundleFormatError:
        where = f"{shown}: entry {entry!r}: " if entry is not None else f"{shown}: "
        return BundleFormatError(
            where + message,
            file=shown,
            expected=None if expected is None else str(expected),
            actual=None if actual is None else str(actual),
        )

    size = len(data)
    if size < _EOCD.size:
        raise bad("not a ZIP archive (shorter than an end-of-central-directory record)", actual=f"{size} bytes")
    sig, disk, cd_disk, count_disk, count, cd_size, cd_offset, comment = _EOCD.unpack_from(data, size - _EOCD.size)
    if sig != _SIG_EOCD:
        raise bad(
            "the last 22 bytes are not the end-of-central-directory record "
            "(not a ZIP archive, or data or a comment after it)",
            expected=hex(_SIG_EOCD),
            actual=hex(sig),
        )
    if comment:
        raise bad(
            "the archive has a comment (data after the last entry)", expected="0 bytes", actual=f"{comment} bytes"
        )
    if disk or cd_disk or count_disk != count:
        raise bad("a multi-disk archive", expected="one disk", actual=f"disk {disk}, central directory on {cd_disk}")
    if count == 0xFFFF or cd_size == 0xFFFFFFFF or cd_offset == 0xFFFFFFFF:
        raise bad("a ZIP64 archive (a bundle is not: at most 65,535 entries and 4 GiB)")
    if count > max_entries:
        raise bad(
            f"{count} entries, more than the cap of {max_entries}", expected=f"at most {max_entries}", actual=count
        )
    if count == 0:
        raise bad("the archive has no entries (a bundle's first entry is its root .hcdf)")
    if cd_offset + cd_size != size - _EOCD.size:
        raise bad(
            "the central directory does not end where the end record starts (data between them, or wrong offsets)",
            expected=size - _EOCD.size,
            actual=cd_offset + cd_size,
        )

    entries: list[Entry] = []
    seen: dict[str, str] = {}  # casefolded name -> name
    pos = cd_offset
    expected_offset = 0  # rule 4: the next entry starts where the previous one ended
    for index in range(count):
        if pos + _CENTRAL.size > cd_offset + cd_size:
            raise bad(f"the central directory is truncated at entry {index + 1} of {count}")
        (
            sig,
            made_by,
            needed,
            flags,
            method,
            mtime,
            mdate,
            crc,
            csize,
            usize,
            name_len,
            extra_len,
            comment_len,
            disk_start,
            _internal,
            external,
            offset,
        ) = _CENTRAL.unpack_from(data, pos)
        if sig != _SIG_CENTRAL:
            raise bad(
                f"central directory record {index + 1} has a wrong signature",
                expected=hex(_SIG_CENTRAL),
                actual=hex(sig),
            )
        raw_name = bytes(data[pos + _CENTRAL.size : pos + _CENTRAL.size + name_len])
        name = _decode_name(raw_name, flags, bad)
        pos += _CENTRAL.size + name_len + extra_len + comment_len
        if pos > cd_offset + cd_size:
            raise bad(f"central directory record {index + 1} runs past the central directory", entry=name)
        _check_name(name, bad)
        if not _WRITTEN_NAME.fullmatch(name):
            raise bad(
                "is not a name the writer writes (ASCII only: names equal but for case or Unicode"
                " normalization, a subfolder, an NTFS stream or a Windows device would alias or extract elsewhere)",
                entry=name,
                expected=f"<root>.hcdf or {ASSETS}/<[0-9A-Za-z._-]+>",
                actual=name,
            )
        folded = name.casefold()
        if folded in seen:
            what = "a duplicate name" if seen[folded] == name else f"the same name as {seen[folded]!r} but for case"
            raise bad(what, entry=name)
        seen[folded] = name
        kind = _special(made_by, external)
        if kind is not None:
            raise bad(f"is {kind}, not a regular file (external attributes {external:#010x})", entry=name)
        if needed > _VERSION:
            raise bad(
                f"needs ZIP version {needed // 10}.{needed % 10} to extract (a reader older than that skips it)",
                entry=name,
                expected=f"at most {_VERSION // 10}.{_VERSION % 10}",
                actual=f"{needed // 10}.{needed % 10}",
            )
        mode = _unix_mode(made_by, external)
        if mode & _MODE_REFUSED:
            raise bad(
                f"has Unix mode {mode:04o}: setuid, setgid, sticky or writable by group or others"
                " (unzip restores it on the verified file)",
                entry=name,
                expected="no mode, or one without 7022 (as 0644 or 0755)",
                actual=f"{mode:04o}",
            )
        if method != 0:
            raise bad(
                "is compressed: every bundle entry is ZIP_STORED",
                entry=name,
                expected="method 0 (stored)",
                actual=f"method {method}",
            )
        if flags & ~_UTF8_FLAG:
            raise bad(
                "has general purpose flags set (encryption or a data descriptor)",
                entry=name,
                expected="0",
                actual=hex(flags),
            )
        if csize != usize:
            raise bad("stored sizes differ", entry=name, expected=f"compressed size = size {usize}", actual=csize)
        if extra_len or comment_len or disk_start:
            raise bad("has an extra field, a comment or another disk", entry=name)
        # Rule 4 and 5: the local header sits exactly where the previous entry ended and repeats this record.
        if offset != expected_offset:
            what = "data before the first entry" if index == 0 else "a gap or an overlap with the previous entry"
            raise bad(f"starts at byte {offset}: {what}", entry=name, expected=expected_offset, actual=offset)
        if offset + _LOCAL.size > cd_offset:
            raise bad("its local header runs into the central directory", entry=name)
        lsig, lneeded, lflags, lmethod, ltime, ldate, lcrc, lcsize, lusize, lname_len, lextra_len = _LOCAL.unpack_from(
            data, offset
        )
        local_name = bytes(data[offset + _LOCAL.size : offset + _LOCAL.size + lname_len])
        central = (_SIG_LOCAL, needed, flags, method, mtime, mdate, crc, csize, usize, raw_name, 0)
        local = (lsig, lneeded, lflags, lmethod, ltime, ldate, lcrc, lcsize, lusize, local_name, lextra_len)
        if local != central:
            fields = (
                "signature",
                "version",
                "flags",
                "method",
                "time",
                "date",
                "CRC-32",
                "compressed size",
                "size",
                "name",
                "extra field length",
            )
            which = [f for f, a, b in zip(fields, central, local, strict=True) if a != b]
            diff = {f: (a, b) for f, a, b in zip(fields, central, local, strict=True) if a != b}
            raise bad(
                "its local header disagrees with the central directory on " + ", ".join(which),
                entry=name,
                expected="; ".join(f"{f} {a!r}" for f, (a, _) in diff.items()),
                actual="; ".join(f"{f} {b!r}" for f, (_, b) in diff.items()),
            )
        start = offset + _LOCAL.size + lname_len
        end = start + usize
        if end > cd_offset:
            raise bad(
                "its data runs past the start of the central directory (its size disagrees with the archive)",
                entry=name,
                expected=f"at most {cd_offset - start} bytes",
                actual=usize,
            )
        actual_crc = zlib.crc32(data[start:end])
        if actual_crc != crc:
            raise bad(
                "its data does not match its CRC-32", entry=name, expected=f"{crc:#010x}", actual=f"{actual_crc:#010x}"
            )
        entries.append(Entry(name, start, usize, crc))
        expected_offset = end
    if pos != cd_offset + cd_size:
        raise bad("the central directory holds more than its records", expected=cd_size, actual=pos - cd_offset)
    if expected_offset != cd_offset:
        raise bad(
            f"{cd_offset - expected_offset} bytes between the last entry and the central directory"
            " (data after the last entry)",
            expected=expected_offset,
            actual=cd_offset,
        )
    root = entries[0].name
    if "/" in root or not root.endswith(".hcdf"):
        roots = [e.name for e in entries if "/" not in e.name and e.name.endswith(".hcdf")]
        raise bad(
            "the root .hcdf is not the first entry",
            expected="a top-level *.hcdf first",
            actual=f"{root!r} first"
            + (f", {roots[0]!r} at entry {[e.name for e in entries].index(roots[0]) + 1}" if roots else ""),
        )
    return entries


def _decode_name(raw: bytes, flags: int, bad: _Bad) -> str:
    """The name as UTF-8. Without the UTF-8 flag (bit 11) other tools read a non-ASCII name as
    CP437: two readings of one name, so only ASCII is accepted there (both writers write ASCII)."""
    if not flags & _UTF8_FLAG and not raw.isascii():
        raise bad("an entry name is not ASCII and not flagged UTF-8 (tools read it two ways)", actual=repr(raw))
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError:
        raise bad("an entry name is not UTF-8", actual=repr(raw)) from None


def _check_name(name: str, bad: _Bad) -> None:
    """An entry name that extracts to the same place everywhere: relative, forward slashes, no
    ``.``/``..``/empty segment, no drive letter, no control character."""
    if not name:
        raise bad("an entry has an empty name")
    if name.startswith("/"):
        raise bad("is an absolute path", entry=name)
    if "\\" in name:
        raise bad("holds a backslash (a separator on Windows)", entry=name)
    if _DRIVE.match(name):
        raise bad("starts with a drive letter", entry=name)
    if any(ord(c) < 0x20 or ord(c) == 0x7F for c in name):
        raise bad("holds a control character", entry=name)
    if name.endswith("/"):
        raise bad("is a directory entry", entry=name)
    if any(part in ("", ".", "..") for part in name.split("/")):
        raise bad("has an empty, '.' or '..' segment (it escapes or aliases another path)", entry=name)


def _unix_mode(made_by: int, external: int) -> int:
    """The permission bits an extractor restores (Unix host only; the writer records none)."""
    return (external >> 16) & 0o7777 if made_by >> 8 == 3 else 0


def _special(made_by: int, external: int) -> str | None:
    """What a non-regular entry is, from its external attributes (None for a regular file)."""
    host = made_by >> 8
    if external & 0x10:  # MS-DOS directory attribute, set by every host
        return "a directory"
    if host == 3:  # Unix: st_mode in the high 16 bits
        mode = external >> 16
        if mode and not stat.S_ISREG(mode):
            if stat.S_ISLNK(mode):
                return "a symlink"
            if stat.S_ISDIR(mode):
                return "a directory"
            return "a special file (FIFO, socket or device)"
    return None


# --- the resolver's seam --------------------------------------------------------------------


class BundleFiles:
    """:class:`~hcdf_trust.localfile.ConfinedFolders`' interface over a checked archive.

    The resolver reads a bundle through the same walker and the same verdicts as a tree: the
    root document is ``<bundle path>/<root name>``, so a reference ``assets/x.glb`` locates to
    ``<bundle path>/assets/x.glb`` (``..`` out of it is refused by the locator, as out of any
    root), and this class serves those paths from the archive instead of the filesystem.
    """

    def __init__(self, archive: Archive, folder: str) -> None:
        self.archive = archive
        self.folder = folder.rstrip("/") + "/"

    @property
    def root_path(self) -> str:
        return self.folder + self.archive.root.name

    def entry(self, path: str, *, file: str | None = None, line: int | None = None) -> Entry:
        name = path[len(self.folder) :] if path.startswith(self.folder) else None
        entry = self.archive.by_name.get(name) if name else None
        if entry is None:
            shown = name if name else display_path(path)
            raise BundleMissingError(
                f"{shown} is not in the bundle {self.archive.path}",
                file=file,
                line=line,
                expected=f"an entry of {self.archive.path}",
                actual=shown,
            )
        return entry

    def size(self, path: str) -> int:
        """An entry's size, -1 if there is none (the resolver's hint for hashing on a thread)."""
        entry = self.archive.by_name.get(path[len(self.folder) :]) if path.startswith(self.folder) else None
        return entry.size if entry is not None else -1

    def read(
        self,
        path: str,
        root: object = None,
        *,
        file: str | None = None,
        line: int | None = None,
        limit: int,
        source: str,
    ) -> bytes:
        entry = self.entry(path, file=file, line=line)
        if entry.size > limit:
            raise InputError(f"{source}: {entry.size} bytes, more than the {limit}-byte limit", file=file, line=line)
        return bytes(self.archive.data(entry))

    def hash(self, path: str, root: object = None, *, file: str | None = None, line: int | None = None) -> Hashed:
        entry = self.entry(path, file=file, line=line)
        return Hashed(hashlib.sha256(self.archive.data(entry)).hexdigest(), entry.size)

    def hash_entry(self, path: str, root: object = None) -> tuple[str, int, tuple[int, int]] | None:
        return None  # hash() names a missing entry; there is no faster path to take

    def name_pin(self, path: str | None) -> str | None:
        """The full SHA-256 an entry's name carries (``<stem>_<64 hex>.<ext>``), or None: the
        pin of a reference that has no ``sha`` site (``<firmware-manifest-uri>``)."""
        if path is None or not path.startswith(self.folder):
            return None
        m = _ADDRESSED.search(path)
        return m.group(1) if m and len(m.group(1)) == 64 else None

    def close(self) -> None:
        """Nothing: the archive's bytes stay with the :class:`Resolution` (``res.bundle``), which
        may read an entry again after the run (the registry's stream-profile check)."""


def check_contents(res: Resolution, files: BundleFiles) -> list[BundleIntegrityError]:
    """The bundle's own rules, once the walker has read what the document references (pure).

    Every entry but the root is referenced, lies under ``assets/`` and is content-addressed
    (``<stem>_<hex>.<ext>``, the hex a prefix of its SHA-256), every pin is full (there is no
    lock to complete a prefix), and the document has no
    ``<include>`` (a bundle is flat). The pins themselves are the walker's (a digest mismatch).
    """
    errors: list[BundleIntegrityError] = []
    archive = files.archive
    used: dict[str, str] = {}
    for doc_url, edges in res.includes.items():
        for ref, _child in edges:
            errors.append(
                BundleIntegrityError(
                    f"<include uri={ref.uri!r}> in a bundle: a bundle holds one flattened document",
                    file=res.documents[doc_url].source,
                    line=ref.line,
                    expected="no <include>",
                    actual=ref.uri,
                )
            )
    for art in res.artifacts.values():
        path = art.location.path
        if path is None or not path.startswith(files.folder) or art.sha256 is None:
            continue
        name = path[len(files.folder) :]
        used[name] = art.uri
        m = _ADDRESSED.search(name)
        use = art.uses[0]
        if not name.startswith(ASSETS + "/") or m is None:
            errors.append(
                BundleIntegrityError(
                    f"{archive.path}: entry {name!r} is not a content-addressed asset",
                    file=use.doc,
                    line=use.ref.line,
                    expected=f"{ASSETS}/<name>_<sha256 prefix>.<ext>",
                    actual=name,
                )
            )
        elif art.pin_status == "weak":  # no lock completes it: the writer writes full pins only
            pin = next(u.pin for u in art.uses if u.pin is not None)
            errors.append(
                BundleIntegrityError(
                    f"{archive.path}: entry {name!r} is pinned by {len(pin.hex)} hex digits: a bundle has no lock,"
                    " every pin in it is a full sha256",
                    file=use.doc,
                    line=use.ref.line,
                    expected="sha256:<64 hex digits>",
                    actual=f"sha256:{pin.hex}",
                )
            )
        elif not art.sha256.startswith(m.group(1)):
            errors.append(
                BundleIntegrityError(
                    f"{archive.path}: entry {name!r}: the hash in its name is not its content's",
                    file=use.doc,
                    line=use.ref.line,
                    expected=m.group(1),
                    actual=art.sha256,
                )
            )
    for entry in archive.entries[1:]:
        if entry.name not in used:
            errors.append(
                BundleIntegrityError(
                    f"{archive.path}: entry {entry.name!r} is not referenced by the root document",
                    file=archive.path,
                    expected="every entry referenced",
                    actual=entry.name,
                )
            )
    return errors


# --- writing --------------------------------------------------------------------------------


def unpinned(res: Resolution) -> list[UnpinnedError]:
    """What a bundle cannot carry: a reference that neither a full ``sha`` nor the lock pins
    (a bundle pins every file it holds; it would otherwise pin what happened to be there)."""

    locked = res.locked.entries if res.locked is not None else {}
    errors = []
    for art in res.artifacts.values():
        if art.pin_status == "full" or res.lock_url(art.url) in locked:
            continue
        use = art.uses[0]
        errors.append(
            UnpinnedError(
                f"{art.uri} is not pinned: a bundle carries only files pinned by a full sha256 or the lock"
                " (`hcdf-trust resolve` writes the lock, `pin --write` the sha)",
                file=use.doc,
                line=use.ref.line,
                url=art.url,
                expected="a full sha256 or a lock entry",
                actual=art.sha256,
            )
        )
    return errors


def encode(entries: list[tuple[str, bytes | memoryview]]) -> bytes:
    """A ``ZIP_STORED`` archive of ``entries`` in the given order, byte for byte what upstream's
    ``zip_store::write_stored`` writes for them.

    Hand-rolled rather than :mod:`zipfile`: zipfile is deterministic with fixed ``ZipInfo``s, but
    it cannot write upstream's bytes (it refuses DOS date 0, records a Unix host, permissions and
    ``version made by`` 20/3.x), and upstream's are the reference: same entries, same archive, so
    a bundle can be compared with upstream's ``hcdf bundle`` by its digest. Time and date 0, no
    permissions (external attributes 0: extracted with the umask), no extra fields.
    """
    out: list[bytes | memoryview] = []
    central: list[bytes] = []
    offset = 0
    for name, data in entries:
        raw = name.encode("utf-8")
        crc = zlib.crc32(data)
        size = len(data)
        header = _LOCAL.pack(_SIG_LOCAL, _VERSION, 0, 0, 0, 0, crc, size, size, len(raw), 0) + raw
        out += [header, data]
        central.append(
            _CENTRAL.pack(
                _SIG_CENTRAL, _VERSION, _VERSION, 0, 0, 0, 0, crc, size, size, len(raw), 0, 0, 0, 0, 0, offset
            )
            + raw
        )
        offset += len(header) + size
    cd = b"".join(central)
    end = _EOCD.pack(_SIG_EOCD, 0, 0, len(entries), len(entries), len(cd), offset, 0)
    return b"".join([*out, cd, end])


def safe_stem(name: str, fallback: str) -> str:
    """Upstream's ``safe_stem``/``safe_root_stem``: every character outside ``[0-9A-Za-z._-]``
    becomes ``_``; empty or dots only is ``fallback``."""
    stem = _UNSAFE_STEM.sub("_", name)
    return fallback if not stem.strip(".") else stem


def asset_name(source: str, sha256: str, *, full: bool, default_ext: str = "") -> str:
    """``assets/<stem>_<hex>.<ext>`` for content ``sha256`` read from ``source`` (a path or URL
    path): the hex is upstream's 12 digits, or all 64 when the reference has no ``sha`` site and
    the name is its pin. The extension keeps its case, as upstream's does."""
    base = source.rstrip("/").rsplit("/", 1)[-1]
    stem, dot, ext = base.rpartition(".")
    if not dot or not stem:
        stem, ext = base, default_ext
    hexpart = sha256 if full else sha256[:SHORT_SHA]
    name = f"{safe_stem(stem, 'file')}_{hexpart}"
    ext = _UNSAFE_STEM.sub("_", ext)  # the reader accepts only safe_stem's alphabet (_WRITTEN_NAME)
    return f"{ASSETS}/{name}.{ext}" if ext else f"{ASSETS}/{name}"


def root_name(doc_name: str | None, doc_path: str) -> str:
    """The root entry's name: the document's ``name``, else the file's stem (upstream's rule)."""
    stem = doc_name or Path(doc_path).stem
    return safe_stem(stem, "root") + ".hcdf"


def build(
    res: Resolution,
    *,
    root: str | None = None,
    base: str | None = None,
    mirrors: tuple[tuple[str, str], ...] = (),
    cache_dir: str | None = None,
    max_elements: int | None = None,
) -> bytes:
    """The ``.hcdfz`` of a tree that resolved cleanly: one flattened document, first, then every
    file it references under ``assets/``, each read again and checked against the digest the
    run verified (a file swapped since is refused, not bundled). Deterministic: the same tree
    gives the same bytes.

    ``root``/``base``/``mirrors``/``cache_dir`` are the run's: the flattened document's
    references are located again with them, to find each one's verified artifact.

    Raises:
        FlattenError: the tree did not resolve cleanly, or cannot be flattened.
        BundleIntegrityError: a file changed since it was verified, or a reference has no
            verified artifact.
        InputError: a file cannot be read.
    """
    from .digest import PREFIX
    from .document import URI_ATTRS, Document, Kind
    from .include.flatten import DEFAULT_MAX_ELEMENTS, flatten
    from .include.locate import Locator, confinement_root
    from .include.resolver import display_url
    from .localfile import open_local, read_bounded
    from .store import ContentStore, default_cache_dir

    flat = flatten(res, root=root, base=base, max_elements=max_elements or DEFAULT_MAX_ELEMENTS)
    root_loc = res.root_location
    source = display_url(root_loc.url)
    doc = Document.from_bytes(flat, source=source)
    assert root_loc.path is not None
    locator = Locator.create(root=confinement_root(root_loc.path, root=root, base=base), base=base, mirrors=mirrors)
    store = ContentStore(cache_dir or default_cache_dir())
    assets: dict[str, bytes] = {}
    for ref in doc.references():
        if not ref.kind.fetchable:
            continue  # <software><hash>, <extension>: nothing to carry
        line = ref.line
        art = res.artifacts.get(locator.locate(ref.uri or "", root_loc, file=source, line=ref.line).url)
        if ref.kind is Kind.INCLUDE or art is None or art.sha256 is None:
            raise BundleIntegrityError(
                f"{ref.uri}: no verified file for this reference of the flattened document", file=source, line=line
            )
        loc = art.location
        if loc.path is not None:
            with open_local(loc.path, loc.root or os.path.dirname(loc.path), file=source, line=ref.line) as fd:
                data = read_bounded(fd, MAX_BYTES, source=display_path(loc.path), what="file")
        else:
            cached = store.verified_path(art.sha256, repair=False)
            if cached is None:
                raise BundleIntegrityError(
                    f"{ref.uri}: its verified copy is no longer in the cache", file=source, line=line
                )
            with open_local(cached, cached.parent, file=source, line=ref.line) as fd:
                data = read_bounded(fd, MAX_BYTES, source=str(cached), what="file")
        actual = hashlib.sha256(data).hexdigest()
        if actual != art.sha256:
            raise BundleIntegrityError(
                f"{ref.uri}: changed since it was verified; nothing written",
                expected=art.sha256,
                actual=actual,
                file=source,
                line=line,
            )
        # No sha site (<firmware-manifest-uri>): the name carries the full digest and is the pin.
        full = ref.uri_attr is None
        name = asset_name(
            loc.path or art.url.split("?", 1)[0], actual, full=full, default_ext="stl" if ref.kind is Kind.MESH else ""
        )
        assets[name] = data
        el = ref.element
        if full:
            el.text = name
        else:
            for attr in URI_ATTRS:
                if el.get(attr) is not None:
                    el.set(attr, name)
            el.set("sha", PREFIX + actual)
    from lxml import etree

    # flatten's comment naming the expanded includes shows their paths as seen from the working
    # folder: the same tree bundled from another folder would differ. The bundle drops it.
    for node in doc.root.iterchildren(etree.Comment):
        if (node.text or "").startswith(" Flattened by hcdf-trust from "):
            doc.root.remove(node)
    xml = etree.tostring(doc.root.getroottree(), xml_declaration=True, encoding="UTF-8") + b"\n"
    entries: list[tuple[str, bytes | memoryview]] = [(root_name(doc.root.get("name"), root_loc.path), xml)]
    entries += sorted(assets.items())
    total = sum(len(data) + 76 + 2 * len(name) for name, data in entries) + _EOCD.size  # headers: 30 + 46
    if len(entries) > MAX_ENTRIES or total > MAX_BYTES:
        raise BundleFormatError(
            f"{source}: {len(entries)} entries, {total} bytes: more than a bundle holds",
            file=source,
            expected=f"at most {MAX_ENTRIES} entries and {MAX_BYTES} bytes",
            actual=f"{len(entries)} entries, {total} bytes",
        )
    longest = max((name for name, _ in entries), key=lambda n: len(n.encode("utf-8")))
    if len(longest.encode("utf-8")) > 0xFFFF:  # a ZIP header holds a name's length in 16 bits
        raise BundleFormatError(
            f"{source}: entry name {longest[:40]!r}... is {len(longest.encode('utf-8'))} bytes: more than a ZIP holds",
            file=source,
            expected="at most 65535 bytes",
            actual=str(len(longest.encode("utf-8"))),
        )
    return encode(entries)
