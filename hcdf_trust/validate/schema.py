"""Where the XSD comes from, and XSD validation with lxml.

A :class:`SchemaSource` answers one question: which schema applies to a document
with this root element and ``version``. :class:`FileSchemaSource` serves
``--schema FILE``; a signed registry will serve the schema published for a
version. Sources build schemas with :func:`compile_schema`, which caches them.

Why lxml and not xmlschema: on this machine, for the real 308 KB ``hcdf.xsd``,
lxml builds the schema in ~5 ms and validates the 85 KB humanoid example in
~0.6 ms; xmlschema takes ~240 ms and ~50 ms, plus ~150 ms to import. lxml's
errors already carry a line and an XPath, and its (libxml2) wording is the one
the upstream test suite's ``.expected`` files are written against. The HCDF
schemas are XSD 1.0, so nothing needs xmlschema's XSD 1.1 support.
"""

from __future__ import annotations

import hashlib
import os
import threading
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any, Protocol, cast, runtime_checkable
from urllib.parse import unquote, urlsplit

from lxml import etree

from ..errors import InputError
from ..include.locate import display_path
from ..localfile import absolute, open_local, read_bounded
from ..xml import parse_bytes, sourceline
from .findings import Finding, Severity

XS = "http://www.w3.org/2001/XMLSchema"
MAX_SCHEMA_BYTES = 16 << 20
MAX_SCHEMA_FINDINGS = 1000  # a hostile document could produce millions
_CACHE_SIZE = 8
_LINE_CAP = 65535  # libxml2 reports larger line numbers as this


@dataclass(eq=False)
class Schema:
    """A built XSD, ready to validate parsed trees. Safe to share between threads."""

    name: str  # how reports name it: a path, or a registry target
    sha256: str  # of the top-level XSD bytes
    version: str | None  # the xs:schema version attribute
    elements: frozenset[str]  # global element names, Clark notation
    xsd: etree.XMLSchema = field(repr=False)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def declares(self, tag: str) -> bool:
        """Whether a document whose root has this (Clark) tag can validate against it."""
        return tag in self.elements

    def validate(self, tree: etree._ElementTree, *, source: str) -> list[Finding]:
        """Every XSD violation in ``tree`` as a finding with file, line and XPath.

        The message is libxml2's own text, unchanged.
        """
        with self._lock:  # the error log belongs to the schema object
            if self.xsd.validate(tree):
                return []
            entries = list(self.xsd.error_log)  # type: ignore[call-overload]  # lxml-stubs: _ErrorLog is iterable
        findings = []
        for entry in entries[:MAX_SCHEMA_FINDINGS]:
            severity: Severity = "error" if entry.level >= etree.ErrorLevels.ERROR else "warning"
            line = _line_of(tree, entry)
            findings.append(Finding("xsd", severity, entry.message, file=source, line=line, path=entry.path or None))
        if len(entries) > MAX_SCHEMA_FINDINGS:
            findings.append(
                Finding(
                    "xsd",
                    "error",
                    f"{len(entries) - MAX_SCHEMA_FINDINGS} more XSD errors not listed",
                    file=source,
                )
            )
        return findings


def _line_of(tree: etree._ElementTree, entry: etree._LogEntry) -> int | None:
    line = entry.line or None
    if (line is None or line == _LINE_CAP) and entry.path:  # (a tree built from JSON has no lines)
        try:
            found = cast("list[object]", tree.xpath(entry.path))  # a location path selects a node-set
        except etree.XPathError:
            found = []
        if found and isinstance(found[0], etree._Element) and sourceline(found[0]):
            line = sourceline(found[0])
    return line


@runtime_checkable
class SchemaSource(Protocol):
    """Supplies the schema for a document. The one seam a signed registry plugs into."""

    def schema_for(self, *, root: str, version: str | None) -> Schema | None:
        """The schema for a document with this root tag (Clark notation) and version.

        Returns None when the source has no schema for it (nothing is validated).

        Raises:
            InputError: the schema exists but cannot be read or built.
        """
        ...


class FileSchemaSource:
    """``--schema FILE`` (repeatable): the schema a document is validated against, by content.

    Upstream binds tooling to a schema by its SHA-256 (``versions/HASHES``): several 1.0
    ``hcdf.xsd`` byte strings exist, so the report names the file *and* its digest
    (:attr:`Schema.sha256`). With several files the one used is the one that declares the
    document's root element and whose ``version`` has the document's major (a file without
    a ``version`` matches any). Two different files that both fit are refused
    (:class:`SchemaChoiceError`; ``validate`` exits 2): the report would depend on their order. When no
    file declares the root (a stream profile checked with ``--schema hcdf.xsd``), the
    conventional sibling of each file is tried (``hcdf-stream-profile.xsd``); otherwise
    the first file is used and the XSD reports the root it does not know.
    """

    SIBLINGS = {"hcdf": "hcdf.xsd", "stream-profile": "hcdf-stream-profile.xsd"}

    def __init__(self, path: str | os.PathLike[str], *more: str | os.PathLike[str]) -> None:
        self.paths = [Path(p) for p in (path, *more)]

    @property
    def path(self) -> Path:
        return self.paths[0]

    def schema_for(self, *, root: str, version: str | None) -> Schema:
        given = [load_schema_file(p) for p in self.paths]
        fits = [s for s in given if s.declares(root)]
        if not fits:
            sibling_name = self.SIBLINGS.get(etree.QName(root).localname)
            for path in self.paths if sibling_name else ():
                sibling = path.parent / str(sibling_name)
                if sibling.name != path.name and sibling.is_file():
                    other = load_schema_file(sibling)
                    if other.declares(root):
                        fits.append(other)
        if not fits:
            return given[0]
        major = (version or "1").strip().split(".")[0]
        same = [s for s in fits if s.version is None or s.version.strip().split(".")[0] == major] or fits
        distinct = {s.sha256: s for s in same}
        if len(distinct) > 1:
            names = ", ".join(f"{s.name} (sha256 {s.sha256})" for s in distinct.values())
            raise SchemaChoiceError(
                f"{len(distinct)} of the --schema files fit a <{etree.QName(root).localname}> document of "
                f"version {version}: {names}; give the one to validate against"
            )
        return same[0]

    def __repr__(self) -> str:
        return f"FileSchemaSource({', '.join(repr(str(p)) for p in self.paths)})"


class SchemaChoiceError(InputError):
    """Several ``--schema`` files fit one document: which one validates it is the user's choice
    (the CLI reports it as a usage error, exit 2)."""

    code = "schema-choice"


def load_schema_file(path: str | os.PathLike[str]) -> Schema:
    """Read and build the XSD at ``path`` (cached by content).

    Raises:
        NotFoundError, InputError: unreadable, too large, not XML, not a usable XSD.
    """
    p = Path(absolute(path))
    shown = display_path(p)
    with open_local(p, p.parent, file=shown) as fd:
        data = read_bounded(fd, MAX_SCHEMA_BYTES, source=shown, what="schema")
    return compile_schema(data, name=shown, base=p.parent)


_cache: OrderedDict[tuple[str, str | None, str], Schema] = OrderedDict()
_cache_lock = threading.Lock()


def compile_schema(data: bytes, *, name: str, base: Path | None = None) -> Schema:
    """Build a schema from XSD bytes, or return the one already built from the same bytes.

    ``base`` is the folder that ``xs:include``/``xs:import``/``xs:redefine``
    locations are relative to. They must be relative paths that stay inside it
    (never URLs); each file is read here, checked with the safe parser and
    handed to libxml2 from memory, so libxml2 opens no file and no socket
    itself. Without ``base`` they are refused.

    Raises:
        InputError (XmlError, PathEscapeError, NotFoundError): not well-formed,
        has a DTD, a remote, absolute or escaping import, or not a valid XSD.
    """
    digest = hashlib.sha256(data).hexdigest()
    key = (digest, str(base) if base is not None else None, name)  # the name is part of the report
    with _cache_lock:
        cached = _cache.get(key)
        if cached is not None:
            _cache.move_to_end(key)
            return cached
    tree = parse_bytes(data, source=name)
    root = tree.getroot()
    if root.tag != f"{{{XS}}}schema":
        raise InputError(f"not an XSD: root element is <{root.tag}>", file=name, line=sourceline(root))
    files: dict[Path, bytes] = {}
    _collect_imports(tree, base=base, root=base, name=name, files=files)
    if files:
        assert base is not None
        # parse again with a parser whose only resolver serves the checked files
        parser = etree.XMLParser(
            resolve_entities=False, no_network=True, load_dtd=False, huge_tree=False, collect_ids=False
        )
        parser.resolvers.add(_ServeChecked(files))
        tree = etree.fromstring(data, parser, base_url=(base / "schema.xsd").as_uri()).getroottree()
    try:
        xsd = etree.XMLSchema(tree)
    except etree.XMLSchemaParseError as exc:
        raise InputError(f"not a usable XSD: {exc}", file=name) from None
    tns = root.get("targetNamespace")
    elements = frozenset(
        f"{{{tns}}}{el.get('name')}" if tns else el.get("name", "") for el in root.iterchildren(f"{{{XS}}}element")
    )
    schema = Schema(name=name, sha256=digest, version=root.get("version"), elements=elements, xsd=xsd)
    with _cache_lock:
        _cache[key] = schema
        while len(_cache) > _CACHE_SIZE:
            _cache.popitem(last=False)
    return schema


_IMPORTS = tuple(f"{{{XS}}}{t}" for t in ("include", "import", "redefine", "override"))


class _ServeChecked(etree.Resolver):
    """Give libxml2 the schema files we read and checked; refuse any other load."""

    def __init__(self, files: dict[Path, bytes]) -> None:
        self.files = files

    # lxml calls resolve(system_url, public_id, context); lxml-stubs omits ``context``.
    def resolve(self, system_url: str, public_id: str | None, context: object) -> Any:  # type: ignore[override]
        url = str(system_url)
        path = Path(unquote(urlsplit(url).path)) if url.startswith("file:") else Path(url)
        data = self.files.get(Path(os.path.normpath(path)))
        if data is None:
            raise InputError(f"schema load of {url!r} refused")
        return self.resolve_string(data, context, base_url=url)


def _collect_imports(
    tree: etree._ElementTree, *, base: Path | None, root: Path | None, name: str, files: dict[Path, bytes]
) -> None:
    for el in tree.getroot().iterchildren(*_IMPORTS):
        location = el.get("schemaLocation")
        if location is None:
            continue  # xs:import by namespace only: libxml2 loads nothing
        line = sourceline(el)
        if base is None or root is None or urlsplit(location).scheme or PurePosixPath(location).is_absolute():
            raise InputError(
                f"schema import {location!r} refused: imports must be relative paths next to the schema",
                file=name,
                line=line,
            )
        target = Path(os.path.normpath(base / unquote(location)))
        if target in files:
            continue
        shown = display_path(target)
        with open_local(target, root, file=name, line=line) as fd:
            data = read_bounded(fd, MAX_SCHEMA_BYTES, source=shown, what="schema")
        files[target] = data
        sub = parse_bytes(data, source=shown)
        _collect_imports(sub, base=target.parent, root=root, name=shown, files=files)
