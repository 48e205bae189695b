"""``ota build --update-hcdf``: write the built images' hashes into ``<software><hash>``.

Minimal text edits, as ``pin`` makes them: the hash element's text is replaced in the
document's raw bytes (located with :func:`hcdf_trust.include.pin.scan_start_tags`,
checked against lxml's tree), nothing else changes. An edited document's own digest
changes, so every including document's ``sha`` pin of it is rewritten with
:func:`hcdf_trust.include.pin.apply_pins`, up to the root, and the lock file's entries
for those documents are updated. The caller writes everything in one output plan.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from typing import Any

from lxml import etree

from ..document import Document
from ..errors import HcdfTrustError, InputError
from ..include.pin import apply_pins, json_not_edited, scan_start_tags
from ..localfile import read_input
from ..xml import MAX_DOCUMENT_BYTES, sourceline


@dataclass(frozen=True)
class HashEdit:
    doc_url: str
    element: Any  # the <hash> element in the resolved document
    old: str
    new: str


@dataclass
class EditResult:
    documents: dict[str, bytes]  # url -> new bytes, for every document that changes
    lock: bytes


def _elements(doc: Document) -> list[etree._Element]:
    return [el for el in doc.root.getroottree().iter() if isinstance(el.tag, str)]


def replace_text(doc: Document, element: etree._Element, new: str) -> bytes:
    """``doc``'s bytes with the text of ``element`` (a leaf holding only text) set to ``new``.

    Raises:
        InputError: the element has children, comments or PIs, or cannot be located.
    """
    if len(element) or element.text is None:
        raise InputError(
            f"<{element.tag}> holds more than text: edit it by hand", file=doc.source, line=sourceline(element)
        )
    if doc.is_json:
        raise InputError(json_not_edited(doc, "ota build --update-hcdf"), file=doc.source, line=sourceline(element))
    data = doc.data
    tags = scan_start_tags(data)
    elements = _elements(doc)
    if len(tags) != len(elements):
        raise InputError("the document's text and tree disagree: edit it by hand", file=doc.source)
    i = elements.index(element)
    start = tags[i].end
    end = data.find(b"<", start)
    raw = data[start:end]
    text = raw.decode(doc.tree.docinfo.encoding or "utf-8")
    if text != element.text:  # an entity or character reference: not a plain edit
        raise InputError(
            f"<{element.tag}> text is not plain: edit it by hand", file=doc.source, line=sourceline(element)
        )
    lead = len(raw) - len(raw.lstrip())
    trail = len(raw.rstrip())
    return data[: start + lead] + new.encode("ascii") + data[start + trail :]


def update_tree(res: Any, edits: list[HashEdit]) -> EditResult:
    """New bytes for the edited documents and their includers, and the new lock file.

    Raises:
        InputError: a document to edit is remote, or an edit cannot be made safely.
    """

    by_doc: dict[str, list[HashEdit]] = {}
    for e in edits:
        by_doc.setdefault(e.doc_url, []).append(e)
    parents: dict[str, list[tuple[Any, str]]] = {}  # child url -> [(include ref, parent url)]
    for parent, children in res.includes.items():
        for ref, child in children:
            parents.setdefault(child, []).append((ref, parent))
    new_bytes: dict[str, bytes] = {}
    # documents to settle: the edited ones and every ancestor, children before parents
    order: list[str] = []
    seen: set[str] = set()

    def visit(url: str) -> None:
        if url in seen:
            return
        seen.add(url)
        order.append(url)
        for _ref, parent in parents.get(url, []):
            visit(parent)

    for url in by_doc:
        visit(url)
    depth: dict[str, int] = {}

    def level(url: str) -> int:  # distance from the root, so deeper documents settle first
        if url not in depth:
            depth[url] = 0  # a cycle is a resolve error; never recurse forever
            ups = [level(p) for _r, p in parents.get(url, [])]
            depth[url] = 1 + max(ups) if ups else 0
        return depth[url]

    order.sort(key=level, reverse=True)
    for url in order:
        if not url.startswith("file://"):
            raise InputError(f"cannot update the remote document {url}", url=url)
        doc = res.documents[url]
        pin_edits = []
        for ref, child in res.includes.get(url, []):
            if child in new_bytes and ref.sha:
                pin_edits.append((ref, hashlib.sha256(new_bytes[child]).hexdigest()))
        data = apply_pins(doc, pin_edits) if pin_edits else doc.data
        if url in by_doc:
            index = {el: i for i, el in enumerate(_elements(doc))}
            for e in by_doc[url]:
                current = Document.from_bytes(data, source=doc.source)  # the bytes edited so far
                target = _elements(current)[index[e.element]]
                data = replace_text(current, target, e.new)
        new_bytes[url] = data
    lock = res.render_lock(edited=new_bytes)
    return EditResult(documents=new_bytes, lock=lock)


def check_unchanged(res: Any, urls: list[str]) -> list[HcdfTrustError]:
    """Every document about to be edited is still what was resolved (no concurrent edit)."""
    from urllib.parse import unquote, urlsplit

    errors: list[HcdfTrustError] = []
    for url in urls:
        path = unquote(urlsplit(url).path)
        try:
            current = read_input(path, limit=MAX_DOCUMENT_BYTES, what="document")
        except HcdfTrustError as exc:
            errors.append(exc)
            continue
        if current != res.documents[url].data:
            errors.append(InputError("changed on disk during the build: run it again", file=path))
    return errors
