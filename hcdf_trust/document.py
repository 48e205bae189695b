"""An HCDF document and the one walker that yields every reference it makes.

Every place that knows where references live in HCDF is here: resolve, pin,
flatten, validate, ota and macsec all consume :meth:`Document.references`.
Unknown elements and attributes are ignored (the HCDF versioning rules), so
later dialects (``version="1.2"``, ``"2.0"``, ``<mcu>``, ``<model href>``) walk too.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from enum import Enum
from typing import Any

from lxml import etree

from .errors import XmlError
from .xml import parse_bytes, sourceline


class Kind(str, Enum):
    INCLUDE = "include"
    MODEL = "model"
    MESH = "mesh"
    STREAM_PROFILE = "stream-profile"
    FIRMWARE = "firmware"  # <software><hash>: a digest with no file to fetch
    FIRMWARE_MANIFEST = "firmware-manifest"
    EXTENSION = "extension"  # <extension domain version>: resolved by a registry, not fetched

    @property
    def fetchable(self) -> bool:
        return self not in (Kind.FIRMWARE, Kind.EXTENSION)


@dataclass(frozen=True)
class Reference:
    """One reference found in a document, with where it was written."""

    kind: Kind
    line: int | None
    uri: str | None = None
    sha: str | None = None  # the digest text exactly as written
    uri_attr: str | None = None  # "uri" or "href"; None when the uri is element text
    name: str | None = None  # include name prefix, software name
    pose: str | None = None  # include pose "x y z roll pitch yaw"
    active: bool = True  # stream-profile
    domain: str | None = None  # extension
    version: str | None = None  # extension / software version
    element: Any = field(default=None, compare=False, repr=False, hash=False)


def _text(el: etree._Element | None) -> str | None:
    if el is None or el.text is None:
        return None
    return el.text.strip() or None


def _bool(value: str | None, default: bool = True) -> bool:
    if value is None:
        return default
    return value.strip().lower() in ("true", "1")


@dataclass
class Document:
    """A parsed HCDF document. ``source`` is how errors name it (a path or URL)."""

    source: str
    tree: etree._ElementTree
    data: bytes = field(repr=False)

    @classmethod
    def from_bytes(cls, data: bytes, *, source: str) -> Document:
        """Parse and check that the root is ``<hcdf>``.

        Raises:
            XmlError: malformed or hostile XML, or not an HCDF document.
        """
        tree = parse_bytes(data, source=source)
        root = tree.getroot()
        if not isinstance(root.tag, str) or etree.QName(root).localname != "hcdf":
            raise XmlError(
                f"not an HCDF document: root element is <{root.tag}>, expected <hcdf>",
                file=source,
                line=sourceline(root),
            )
        return cls(source=source, tree=tree, data=data)

    @property
    def root(self) -> etree._Element:
        return self.tree.getroot()

    @property
    def version(self) -> str:
        return self.root.get("version", "1.0")

    @property
    def body_frame(self) -> str | None:
        return self.root.get("body-frame")

    @property
    def world_frame(self) -> str | None:
        return self.root.get("world-frame")

    def references(self) -> list[Reference]:
        """Every reference in document order. Extension content is opaque and not walked."""
        return list(_walk(self.root))


# Elements that can carry a reference; lxml finds them in C, in document order.
_REFERENCE_TAGS = ("include", "model", "mesh", "stream-profile", "hash", "firmware-manifest-uri", "extension")


def _walk(root: etree._Element) -> Iterator[Reference]:
    for el in root.iter(*_REFERENCE_TAGS):
        if el.tag != "extension" and any(True for _ in el.iterancestors("extension")):
            continue  # vendor content: may contain anything, never fetched by us
        ref = _reference(el, el.tag)
        if ref is not None:
            yield ref


def _reference(el: etree._Element, tag: str) -> Reference | None:
    line = sourceline(el)
    if tag == "include":
        return Reference(
            Kind.INCLUDE,
            line,
            uri=el.get("uri"),
            sha=el.get("sha"),
            uri_attr="uri",
            name=el.get("name"),
            pose=el.get("pose"),
            element=el,
        )
    if tag == "model":
        # The schema says uri; the published model repository writes href.
        attr = "uri" if el.get("uri") is not None else "href" if el.get("href") is not None else None
        if attr is None:
            return None
        return Reference(Kind.MODEL, line, uri=el.get(attr), sha=el.get("sha"), uri_attr=attr, element=el)
    if tag == "mesh":
        parent = el.getparent()
        if parent is None or parent.tag != "geometry" or el.get("uri") is None:
            return None  # <network><mesh> is a wireless topology, not a file
        return Reference(Kind.MESH, line, uri=el.get("uri"), sha=el.get("sha"), uri_attr="uri", element=el)
    if tag == "stream-profile" and el.get("uri") is not None:
        return Reference(
            Kind.STREAM_PROFILE,
            line,
            uri=el.get("uri"),
            sha=el.get("sha"),
            uri_attr="uri",
            active=_bool(el.get("active")),
            element=el,
        )
    if tag == "hash" and (sw := el.getparent()) is not None and sw.tag == "software":
        return Reference(
            Kind.FIRMWARE,
            line,
            sha=_text(el),
            name=sw.get("name"),
            version=_text(sw.find("version")),
            element=el,
        )
    if tag == "firmware-manifest-uri" and _text(el):
        sw = el.getparent()
        return Reference(
            Kind.FIRMWARE_MANIFEST,
            line,
            uri=_text(el),
            name=sw.get("name") if sw is not None else None,
            element=el,
        )
    if tag == "extension":
        return Reference(Kind.EXTENSION, line, domain=el.get("domain"), version=el.get("version"), element=el)
    return None


def software_elements(doc: Document) -> list[etree._Element]:
    """Every ``<software>`` entry outside extension content, in document order (the ota
    verbs read them whole: name, version, hash, and the enclosing ``<comp>``'s board)."""
    return [el for el in doc.root.iter("software") if not any(True for _ in el.iterancestors("extension"))]
