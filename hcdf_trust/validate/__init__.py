"""``hcdf-trust validate``: XSD validation plus the HCDF rules the XSD cannot express.

>>> from hcdf_trust.validate import validate_document
>>> report = validate_document("robot.hcdf", schema="hcdf.xsd")   # doctest: +SKIP
>>> report.ok, [str(f) for f in report.findings]                   # doctest: +SKIP

Two steps, both always run and both collect every finding:

1. XSD (only when a schema is given): lxml's ``XMLSchema``, built once per
   process and content (see :mod:`.schema` for the numbers behind the choice).
   The schema comes from a :class:`SchemaSource`; ``--schema FILE`` is a
   :class:`FileSchemaSource`, which also picks ``hcdf-stream-profile.xsd`` next
   to ``hcdf.xsd`` for a ``<stream-profile>`` document.
2. Semantic rules (``<hcdf>`` documents only): :mod:`.semantic`, pure functions
   over the parsed tree. The local include chain is read (never fetched:
   :mod:`.includes`) so that names included files define resolve, under the
   prefixes flattening gives them, and so that frame conventions can be compared.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

from lxml import etree

from ..document import (
    ROOT,
    STREAM_SELECTION,
    Document,
    foreign_major_notice,
    require_root,
    stream_profile_selection,
)
from ..errors import at_line
from ..include.locate import display_path
from ..include.resolver import TreeOptions, link_stub_target
from ..localfile import absolute
from ..xml import sourceline
from . import semantic
from .findings import Finding, Severity, ValidationReport
from .includes import local_include_edges, read_local
from .schema import FileSchemaSource, Schema, SchemaChoiceError, SchemaSource, compile_schema, load_schema_file

__all__ = [
    "FileSchemaSource",
    "Finding",
    "Schema",
    "SchemaChoiceError",
    "SchemaSource",
    "Severity",
    "ValidationReport",
    "compile_schema",
    "load_schema_file",
    "validate_document",
]

_ROOTS = (ROOT, "stream-profile")
SchemaArg = str | os.PathLike[str] | Sequence[str | os.PathLike[str]] | SchemaSource | None


def validate_document(
    doc: str | os.PathLike[str] | Document,
    *,
    schema: SchemaArg = None,
    tree_options: TreeOptions | None = None,
) -> ValidationReport:
    """Validate one document; every problem found is a finding in the report.

    ``doc`` is a path (an ``<hcdf>`` document or a ``<stream-profile>``) or an
    already parsed :class:`Document` (its includes are then not read).
    ``schema`` is an XSD path, several (:class:`FileSchemaSource` picks the one that fits),
    any :class:`SchemaSource`, or None for the semantic rules only (``report.schema`` is
    then None; otherwise ``report.schema`` and ``report.schema_sha256`` name the XSD used).
    ``tree_options`` holds resolve's ``--base``, ``--mirror`` and ``--root``, for finding
    the local includes.

    Raises:
        InputError (NotFoundError, XmlError, ...): the document or the schema
        cannot be read, is malformed or hostile, or hides a reference
        (AmbiguousReferenceError).
        NotHcdfError: the root is neither ``<hcdf>`` nor ``<stream-profile>`` in no namespace.
    """
    path: Path | None = None
    if isinstance(doc, Document):
        tree, source = doc.tree, doc.source
    else:
        path = Path(absolute(doc))
        from ..bundle import is_bundle, read_root_entry

        if is_bundle(path):  # its root entry, read from the checked archive; a bundle has no includes
            source, data = read_root_entry(path)
            path = None
        else:
            data = read_local(path, path.parent, source=display_path(path))
            stub = link_stub_target(path, data)  # a symlink checked out as a plain file
            if stub is not None:
                path = stub
                data = read_local(path, path.parent, source=display_path(path))
            source = display_path(path)
        doc = Document.parse(data, source=source)  # XML or the JSON form
        tree = doc.tree
    root = tree.getroot()
    kind = require_root(root, source=source, names=_ROOTS)  # <hcdf xmlns="urn:x"> is not HCDF
    if kind == ROOT:
        doc.references()  # every reference is seen, or the document is refused (exit 3)
    report = ValidationReport(source=source)
    findings: list[Finding] = []
    if kind == ROOT:
        if (notice := foreign_major_notice([doc])) is not None:
            findings.append(Finding(notice.code, "warning", notice.message, file=source, line=notice.line))
        streams = stream_profile_selection(doc)
        for text, line in streams.problems:
            findings.append(Finding(STREAM_SELECTION, "error", text, file=source, line=line))
        if len(streams.selected) == 1:
            chosen = streams.selected[0]
            report.notes.append(f"selected stream profile: {chosen.uri} ({at_line(chosen.line)})")

    source_of_schema = _schema_source(schema)
    if source_of_schema is not None:
        found = source_of_schema.schema_for(root=root.tag, version=root.get("version"))
        if found is None:
            report.notes.append(f"no schema is known for <{kind}> version {root.get('version')}")
        else:
            report.schema = found.name
            report.schema_sha256 = found.sha256
            report.checked.append("xsd")
            findings.extend(found.validate(tree, source=source))
            findings.extend(_version_mismatch(root, found, source))

    if kind == "hcdf":
        edges = local_include_edges(doc, path, source=source, tree=tree_options) if path is not None else []
        result = semantic.check(root, source=source, includes=edges)
        report.checked.append("semantic")
        findings.extend(result.findings)
        report.notes.extend(result.notes)
    else:
        report.notes.append("a stream profile has no semantic rules here: only its XSD is checked")

    order = {source: 0}
    findings.sort(key=lambda f: (order.get(f.file or "", 1), f.file or "", f.line or 0))
    report.findings = findings
    return report


def _schema_source(schema: SchemaArg) -> SchemaSource | None:
    if schema is None:
        return None
    if isinstance(schema, SchemaSource):
        return schema
    if isinstance(schema, str | os.PathLike):
        return FileSchemaSource(schema)
    return FileSchemaSource(*schema) if schema else None


def _version_mismatch(root: etree._Element, schema: Schema, source: str) -> list[Finding]:
    doc_version, schema_version = root.get("version"), schema.version
    if not doc_version or not schema_version:
        return []
    if doc_version.split(".")[0] == schema_version.split(".")[0]:
        return []
    return [
        Finding(
            "schema-version",
            "warning",
            f"document version {doc_version} but schema {schema.name} is version {schema_version}: "
            "the major versions differ",
            file=source,
            line=sourceline(root),
        )
    ]
