"""Read the local include chain of a document, for the frame-convention rule.

The includes are those the document walker finds (:meth:`Document.references`, the
same ones resolve follows: ``uri`` or ``href``, at any depth). Only local files are
read, through the include package's locator (relative to
the including document, confined to the root document's folder) and its safe
opener (no symlink escape, regular files only); every file is parsed by
:func:`hcdf_trust.xml.parse_bytes`. Nothing is fetched, hashed or cached: that
is ``resolve``'s job. An include that cannot be read becomes an edge with a
reason, never an exception.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, TypedDict

from ..document import Document, Kind, Reference
from ..errors import HcdfTrustError, NotFoundError
from ..include.flatten import SEPARATOR
from ..include.locate import Location, Locator, confinement_root, display_path, file_url, redact
from ..localfile import open_local, read_bounded
from ..xml import MAX_DOCUMENT_BYTES
from .semantic import IncludeEdge

if TYPE_CHECKING:
    from ..include.resolver import TreeOptions

MAX_INCLUDE_DEPTH = 16
MAX_INCLUDE_EDGES = 1000


# One file of the walk: its location, its includes still to visit, its name, its prefix,
# and the chain of files from the root down to it.
_Frame = tuple[Location, Iterator[Reference], str, str, tuple[str, ...]]


class _EdgeFields(TypedDict):
    """What every :class:`IncludeEdge` of one ``<include>`` shares."""

    parent: str
    line: int | None
    uri: str
    prefix: str


def read_local(path: Path | str, root: Path | str, *, source: str, line: int | None = None) -> bytes:
    """A local document's bytes, confined to ``root`` and bounded in size.

    Raises:
        NotFoundError, PathEscapeError, InputError.
    """
    with open_local(path, root, file=source, line=line) as fd:
        return read_bounded(fd, MAX_DOCUMENT_BYTES, source=source)


def _includes(doc: Document) -> Iterator[Reference]:
    return (ref for ref in doc.references() if ref.kind is Kind.INCLUDE)


def local_include_edges(
    document: Document, path: Path, *, source: str, tree: TreeOptions | None = None
) -> list[IncludeEdge]:
    """Every ``<include>`` reachable through local files, depth first in document order
    (the order flattening uses).

    Each edge carries the prefix flattening gives the included file's names
    (the include ``name`` chain joined with ``_``) and, when the file could be
    read, its parsed root and frames. A file included twice under two names is
    visited twice but read once. ``tree`` gives resolve's ``--base``, ``--mirror`` and ``--root``.
    """
    path = Path(os.path.abspath(path))
    base, mirrors, root = (tree.base, tree.mirrors, tree.root) if tree is not None else (None, (), None)
    root_dir = confinement_root(path, root=root, base=base)
    locator = Locator.create(root=root_dir, base=base, mirrors=mirrors)
    start = Location(url=file_url(path), path=str(path), root=root_dir)
    read: dict[str, tuple[str, Document] | HcdfTrustError] = {}  # url -> (display, document) or why not
    edges: list[IncludeEdge] = []

    # Depth first with an explicit stack of (location, its remaining includes, name, prefix,
    # the chain of files above it): no recursion, however long the chain.
    frames: list[_Frame] = [(start, _includes(document), source, "", (start.url,))]
    while frames:
        loc, includes, shown, prefix, stack = frames[-1]
        for inc in includes:
            uri, line = inc.uri, inc.line
            if not uri:
                continue  # the XSD reports the missing attribute
            name = (inc.name or "").strip()
            edge = _EdgeFields(  # uri is only shown, never the secret of a user:password@ URL
                parent=shown, line=line, uri=redact(uri), prefix=f"{prefix}{name}{SEPARATOR}" if name else prefix
            )
            try:
                child = locator.locate(uri, loc, file=shown, line=line)
            except HcdfTrustError as exc:
                edges.append(IncludeEdge(**edge, skipped=exc.message, refused=_refused(exc)))
                continue
            if not child.is_local or child.path is None:
                edges.append(IncludeEdge(**edge, skipped="not a local file; validate does not fetch"))
                continue
            if child.url in stack:
                edges.append(IncludeEdge(**edge, skipped="include cycle"))
                continue
            if len(stack) > MAX_INCLUDE_DEPTH or len(edges) >= MAX_INCLUDE_EDGES:
                edges.append(IncludeEdge(**edge, skipped="include tree too deep or too large"))
                continue
            if child.url not in read:
                child_name = display_path(child.path)
                try:
                    data = read_local(child.path, child.root or path.parent, source=shown, line=line)
                    read[child.url] = (child_name, Document.from_bytes(data, source=child_name))
                except HcdfTrustError as exc:
                    read[child.url] = exc
            found = read[child.url]
            if isinstance(found, HcdfTrustError):
                edges.append(IncludeEdge(**edge, skipped=found.message, refused=_refused(found)))
                continue
            child_name, doc = found
            edges.append(
                IncludeEdge(
                    **edge,
                    child=child_name,
                    body_frame=doc.body_frame,
                    world_frame=doc.world_frame,
                    document=doc.root,
                )
            )
            below = (*stack, child.url)
            frames.append((child, _includes(doc), child_name, edge["prefix"], below))
            break  # walk the included file's includes first: depth first, document order
        else:
            frames.pop()
    return edges


def _refused(exc: HcdfTrustError) -> bool:
    """A missing include is only unchecked; one that escapes its root, is not a
    regular file or is hostile XML is refused, as resolve would refuse it."""
    return not isinstance(exc, NotFoundError)
