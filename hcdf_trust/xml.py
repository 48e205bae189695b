"""The only XML parser factory: no DTD, no entities, no network, bounded depth and size.

Every XML read in hcdf-trust goes through :func:`parse_bytes`. libxml2 already
caps depth (256 without XML_PARSE_HUGE) and text node size (10 MB); we add a
byte limit before parsing and refuse any document that carries a DOCTYPE, so
entity tricks (external, parameter, billion-laughs) never reach the tree.
"""

from __future__ import annotations

import weakref
from collections.abc import Iterator
from typing import NoReturn, cast

from lxml import etree

from .errors import Pointer, XmlError

# An HCDF document is text; the humanoid example is ~100 KB. 32 MiB is generous
# and keeps lxml's ~13x memory blow-up (notes/env.md §3) under half a gigabyte.
MAX_DOCUMENT_BYTES = 32 << 20
MAX_DEPTH = 200
#: The most elements a flattened tree (``flatten``/``bundle``, unless ``--max-elements``
#: raises it) or one JSON-form document may have: the JSON form costs ~15x its XML per
#: element while it is built, so it is capped while read (docs/json-form.md).
MAX_ELEMENTS = 250_000
#: The most elements one XML document may have (~130 bytes each in lxml, so ~130 MB):
#: 32 MiB of ``<a/>`` would otherwise be 8 million elements and 1.2 GB.
MAX_DOCUMENT_ELEMENTS = 1_000_000


class _ExternalLoadRefused(Exception):
    def __init__(self, url: str) -> None:
        super().__init__(url)
        self.url = url


class _RefuseExternal(etree.Resolver):
    """Refuse every external load before any I/O.

    Even with ``load_dtd=False`` libxml2 opens an external DTD subset and external
    parameter entities named in a DOCTYPE: a local file would be read (an existence
    and content oracle) and a FIFO would hang the parser for ever.
    """

    # lxml calls resolve(system_url, public_id, context); lxml-stubs omits ``context``.
    def resolve(self, system_url: str, public_id: str | None, context: object) -> NoReturn:  # type: ignore[override]
        raise _ExternalLoadRefused(str(system_url))


def _parser(target: object = None) -> etree.XMLParser:
    """The one parser configuration; ``target`` (an lxml parser target) builds no tree."""
    parser = etree.XMLParser(
        # lxml calls only the callbacks a target has; the stubs' protocol wants all five.
        target=cast("etree.ParserTarget | None", target),
        resolve_entities=False,
        no_network=True,
        load_dtd=False,
        dtd_validation=False,
        huge_tree=False,
        remove_blank_text=False,
        collect_ids=False,
    )
    parser.resolvers.add(_RefuseExternal())
    return parser


def parse_bytes(data: bytes, *, source: str) -> etree._ElementTree:
    """Parse an XML document safely.

    Raises:
        XmlError: empty, too large, not well-formed, not UTF-8, has a DTD, too deep.
    """
    if not data.strip():
        raise XmlError("empty document", file=source)
    if len(data) > MAX_DOCUMENT_BYTES:
        raise XmlError(
            f"document is {len(data)} bytes, over the {MAX_DOCUMENT_BYTES}-byte limit",
            file=source,
        )
    if data.count(b"<") > MAX_DOCUMENT_ELEMENTS:  # every element needs one: most documents stop here
        _check_element_count(data, source)
    try:
        tree = etree.fromstring(data, _parser()).getroottree()
    except _ExternalLoadRefused as exc:
        raise XmlError(
            f"a DOCTYPE that loads {exc.url!r} is refused (external DTDs and entities are never loaded)",
            file=source,
        ) from None
    except etree.XMLSyntaxError as exc:
        line = exc.lineno if getattr(exc, "lineno", None) else None
        raise XmlError(f"malformed XML: {exc.msg}", file=source, line=line) from None
    except ValueError as exc:  # e.g. an encoding declaration lxml cannot honour
        raise XmlError(f"malformed XML: {exc}", file=source) from None
    docinfo = tree.docinfo
    # lxml-stubs' DocInfo lacks ``doctype`` (a str, "" without a DOCTYPE).
    if docinfo.doctype or docinfo.internalDTD is not None or docinfo.externalDTD is not None:  # type: ignore[union-attr]
        raise XmlError("a DOCTYPE is not allowed in HCDF (entities and DTDs are refused)", file=source, line=1)
    _check_depth(tree, source)
    return tree


class _TooManyElements(Exception):
    pass


class _ElementCounter:
    """An lxml parser target that builds nothing and stops one element past the cap."""

    def __init__(self) -> None:
        self.count = 0

    def start(self, tag: str, attrib: dict[str, str]) -> None:
        self.count += 1
        if self.count > MAX_DOCUMENT_ELEMENTS:
            raise _TooManyElements

    def close(self) -> None:
        return None


def _check_element_count(data: bytes, source: str) -> None:
    """Refuse a flood of elements before lxml builds a tree of them.

    Counting costs one Python call per element, so it runs only when the text has more
    ``<`` than the cap allows elements. Any other fault is left to the real parse.
    """
    try:
        etree.fromstring(data, _parser(_ElementCounter()))
    except _TooManyElements:
        raise XmlError(
            f"more than {MAX_DOCUMENT_ELEMENTS:,} elements: over the cap on one XML document's elements",
            file=source,
            expected=f"at most {MAX_DOCUMENT_ELEMENTS:,} elements",
        ) from None
    except (etree.XMLSyntaxError, ValueError, _ExternalLoadRefused):
        return


# Any element MAX_DEPTH + 1 levels down; evaluated by libxml2, not a Python walk.
_TOO_DEEP = etree.XPath("/" + "/".join(["*"] * (MAX_DEPTH + 1)))


def _check_depth(tree: etree._ElementTree, source: str) -> None:
    # libxml2 alone stops at 256 levels (without huge_tree); we want a lower bound.
    deep = cast("list[etree._Element]", _TOO_DEEP(tree))  # a location path selects elements
    if deep:
        raise XmlError(f"elements nested deeper than {MAX_DEPTH} levels", file=source, line=sourceline(deep[0]))


class LocationTable:
    """Where each element of a tree built from a JSON document was written.

    Holding the element proxies keeps them (lxml hands out the same proxy while one is
    alive), so an element is found by identity. Registered while the table lives.
    """

    __slots__ = ("__weakref__", "_where")

    def __init__(self) -> None:
        self._where: dict[etree._Element, Pointer] = {}
        _TABLES.add(self)

    def add(self, el: etree._Element, where: Pointer) -> None:
        self._where[el] = where

    def get(self, el: etree._Element) -> Pointer | None:
        return self._where.get(el)

    def items(self) -> Iterator[tuple[etree._Element, Pointer]]:
        return iter(self._where.items())


_TABLES: weakref.WeakSet[LocationTable] = weakref.WeakSet()


def sourceline(el: etree._Element) -> int | None:
    """Where ``el`` was written: the line it starts on (XML), a :class:`Pointer` (an element
    of a JSON document: prints as ``/hcdf/comp/3``), None when unknown.

    Every message names a location through here. lxml-stubs declares the attribute as
    ``sourceline = ...`` (an Ellipsis), so read it through here wherever its type matters.
    """
    line: int | None = el.sourceline  # type: ignore[assignment]  # lxml-stubs: `sourceline = ...`
    if line is None and _TABLES:  # parsed XML always has a line: only built trees get here
        for table in list(_TABLES):
            found = table.get(el)
            if found is not None:
                return found
    return line
