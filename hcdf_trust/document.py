"""An HCDF document and the one walker that yields every reference it makes.

Every place that knows where references live in HCDF is here: resolve, pin,
flatten, validate, ota and macsec all consume :meth:`Document.references`.
Unknown elements and attributes are ignored (the HCDF versioning rules), so
later dialects (``version="1.2"``, ``"2.0"``, ``<mcu>``, ``<model href>``) walk too.

Every reference is seen, or the document is refused (:class:`AmbiguousReferenceError`,
exit 3); nothing that another XML reader would take for a reference is skipped:

- The root is ``<hcdf>`` in no namespace (:class:`NotHcdfError` otherwise).
- ``<include>``, ``<model>``, ``<mesh>`` (in ``<geometry>``, or with a uri) and
  ``<stream-profile>`` (in ``<network>``, or with a uri) take their location from
  ``uri`` or ``href``; both are accepted, and both at once only with equal values.
  Text inside such an element, or a ``<uri>``/``<href>``/``<sha>`` child, is refused.
- ``<software><hash>`` and ``<firmware-manifest-uri>`` are read as the element's whole
  string value (CDATA and character references are ordinary text, surrounding XML
  whitespace is dropped as the schema's ``collapse`` drops it); one that holds a
  comment, a processing instruction or a child element, or carries a ``uri``/``href``
  attribute, is refused.
- A location is refused when readers could disagree on it: whitespace around an
  attribute value, a tab, newline or run of spaces inside, control or invisible
  formatting characters (U+200B, bidi overrides).
- HCDF has no namespace: outside extension content, an element in a namespace
  (``<x:include>``, XInclude's ``<xi:include href>``, ``<x:software><hash>``,
  ``<comp xmlns="urn:x">``), a namespaced ``uri``, ``href`` or ``sha`` attribute
  (``xlink:href``) and ``xml:base`` (which moves every relative reference) are refused.
- An element the schema allows once and a verb reads (``<software>``'s ``<version>``,
  ``<hash>`` and ``<firmware-manifest-uri>``, ``<comp>``'s ``<board>`` and ``<software>``)
  written twice is refused (:class:`AmbiguousError`, naming both lines): one reader would
  take the first, another the last. Every verb reads such elements through :func:`single`
  and :func:`single_text`, so they cannot disagree (the MACsec planner checks its own:
  ``<macsec>``, ``<key-store>``, ``<speed>``... as it reads them).
- Extension content is opaque: what is inside an ``<extension>`` child of ``<comp>``
  (HCDF's one extension point) is vendor data, never walked. An ``<extension>``
  anywhere else is reported and its content walked like the rest of the document,
  so an extension cannot be used to hide the document's own references.
"""

from __future__ import annotations

import unicodedata
from collections.abc import Iterable
from dataclasses import dataclass, field
from enum import Enum
from typing import Any, cast

from lxml import etree

from .errors import AmbiguousError, AmbiguousReferenceError, NotHcdfError, Notice, at_lines, counted, redact
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


@dataclass(frozen=True, init=False)
class Reference:
    """One reference found in a document, with where it was written."""

    kind: Kind
    line: int | None
    uri: str | None = None
    sha: str | None = None  # the digest text exactly as written
    uri_attr: str | None = None  # "uri" or "href" ("uri" when both, equal, are written); None for text
    name: str | None = None  # include name prefix, software name
    pose: str | None = None  # include pose "x y z roll pitch yaw"
    selected: bool | None = None  # stream-profile: marked selected / not (see stream_profile_selection)
    domain: str | None = None  # extension
    version: str | None = None  # extension / software version
    element: Any = field(default=None, compare=False, repr=False, hash=False)

    def __init__(
        self,
        kind: Kind,
        line: int | None,
        uri: str | None = None,
        sha: str | None = None,
        uri_attr: str | None = None,
        name: str | None = None,
        pose: str | None = None,
        selected: bool | None = None,
        domain: str | None = None,
        version: str | None = None,
        element: Any = None,
    ) -> None:
        # The generated frozen __init__ makes one object.__setattr__ call per field (3.8 µs
        # a reference, a third of the walk); items of the instance dict cost a quarter of
        # that, and the dict keeps sharing its keys with the class's (in field order).
        d = self.__dict__
        d["kind"] = kind
        d["line"] = line
        d["uri"] = uri
        d["sha"] = sha
        d["uri_attr"] = uri_attr
        d["name"] = name
        d["pose"] = pose
        d["selected"] = selected
        d["domain"] = domain
        d["version"] = version
        d["element"] = element


_XS_BOOLEAN = {"true": True, "1": True, "false": False, "0": False}  # xs:boolean, whitespace collapsed
SELECTION_ROLES = ("default",)  # upstream's StreamProfileSelectionRole (hcdformat-rs, 05d27b58)


def _marked(el: etree._Element) -> bool | None:
    """How a ``<stream-profile>`` marks itself: True (``selection-role="default"``, upstream's
    newer form, or 1.0's ``active="true"``), False (``active="false"``), None (neither, or a
    value that is not understood: :func:`stream_profile_selection` reports those)."""
    role = el.get("selection-role")
    if role is not None and role.strip() in SELECTION_ROLES:
        return True
    active = el.get("active")
    return None if active is None else _XS_BOOLEAN.get(active.strip())


ROOT = "hcdf"


def require_root(root: etree._Element, *, source: str, names: tuple[str, ...] = (ROOT,)) -> str:
    """The root's name, when it is one of ``names`` in no namespace.

    Raises:
        NotHcdfError: anything else, naming what the root is.
    """
    if isinstance(root.tag, str) and root.tag in names:
        return root.tag
    wanted = " or ".join(f"<{n}>" for n in names)
    what = "an HCDF document" if names == (ROOT,) else "an HCDF document or stream profile"
    raise NotHcdfError(
        f"not {what}: root element is {_describe(root)}, expected {wanted} in no namespace",
        file=source,
        line=sourceline(root),
        expected=wanted,
        actual=_describe(root),
    )


def _describe(el: etree._Element) -> str:
    if not isinstance(el.tag, str):
        return "not an element"
    q = etree.QName(el)
    if q.namespace is None:
        return f"<{q.localname}>"
    written = f"{el.prefix}:{q.localname}" if el.prefix else q.localname
    return f"<{written}> in namespace {q.namespace!r}"


def is_json_form(data: bytes) -> bool:
    """Whether ``data`` is (meant as) HCDF's JSON form: its first byte after whitespace (and a
    UTF-8 byte order mark) is ``{``, which never starts an XML document."""
    return data.lstrip(b" \t\r\n\xef\xbb\xbf")[:1] == b"{"


@dataclass
class Document:
    """A parsed HCDF document. ``source`` is how errors name it (a path or URL)."""

    source: str
    tree: etree._ElementTree
    data: bytes = field(repr=False)
    #: For a document written in HCDF's JSON form: where each element was written (its
    #: JSON Pointer, see :func:`where`); None for XML.
    json: Any = field(default=None, repr=False, compare=False)
    _references: list[Reference] | None = field(default=None, init=False, repr=False, compare=False)

    @classmethod
    def from_bytes(cls, data: bytes, *, source: str) -> Document:
        """Parse (XML, or HCDF's JSON form: :mod:`hcdf_trust.jsonform`), check that the root
        is ``<hcdf>``, and find every reference.

        Raises:
            XmlError: malformed or hostile XML.
            JsonError, JsonFormError: malformed or hostile JSON, or JSON that the converter
                would have to drop or guess (see :mod:`hcdf_trust.jsonform`).
            NotHcdfError: the root is not ``<hcdf>`` in no namespace.
            AmbiguousReferenceError: a reference written so that readers could disagree
                on it (see the module docstring); the first, naming the lines of any others.
        """
        doc = cls.parse(data, source=source)
        require_root(doc.root, source=source)
        doc.references()
        return doc

    @classmethod
    def parse(cls, data: bytes, *, source: str) -> Document:
        """The one way a document's bytes become a tree: XML, or the JSON form (whose first
        byte is ``{``, never XML's), read through the HCDF schema; no other check."""
        if is_json_form(data):
            from . import jsonform

            form = jsonform.read(data, source=source)
            return cls(source=source, tree=form.tree, data=data, json=form)
        return cls(source=source, tree=parse_bytes(data, source=source), data=data)

    @property
    def is_json(self) -> bool:
        return self.json is not None

    def where(self, el: etree._Element) -> int | None:
        """Where ``el`` was written: its line (XML) or a :class:`~hcdf_trust.errors.Pointer`
        (JSON: an int that prints as ``/hcdf/comp/3/visual/model``). Messages name it as
        ``file:where``."""
        return sourceline(el)

    @property
    def root(self) -> etree._Element:
        return self.tree.getroot()

    @property
    def version(self) -> str:
        return self.root.get("version", "1.0")

    @property
    def foreign_major(self) -> bool:
        """Whether ``version`` names a major other than 1 (``"2.0"``, as hcdf_models writes).

        Upstream keeps ``version="1.0"`` and its own reader (hcdformat-rs ``version.rs``)
        refuses any other major; this walker reads such a document as it reads 1.0.
        """
        return self.version.strip().split(".")[0] != "1"

    @property
    def body_frame(self) -> str | None:
        return self.root.get("body-frame")

    @property
    def world_frame(self) -> str | None:
        return self.root.get("world-frame")

    def references(self) -> list[Reference]:
        """Every reference in document order. Extension content is opaque and not walked.

        Raises:
            AmbiguousReferenceError: see the module docstring.
        """
        if self._references is None:
            refs: list[Reference] = []
            problems: list[AmbiguousError] = []
            _walk(self.root, self.source, refs, problems, namespaces=_may_use_namespaces(self))
            if problems:
                problems.sort(key=lambda e: e.line or 0)
                first = problems[0]
                if len(problems) > 1:  # one error per document: every consumer reports it the same way
                    lines = at_lines([e.line for e in problems[1:11]]) + (", ..." if len(problems) > 11 else "")
                    first.message += f" (and {len(problems) - 1} more at {lines})"
                    first.args = (first.message,)
                raise first
            self._references = refs
        return list(self._references)


URI_ATTRS = ("uri", "href")  # where an attribute reference element writes its location
_ATTRIBUTE_REFERENCES = ("include", "model", "mesh", "stream-profile")
_TEXT_REFERENCES = ("hash", "firmware-manifest-uri")
_REFERENCE_TAGS = (*_ATTRIBUTE_REFERENCES, *_TEXT_REFERENCES, "extension")
_REFERENCE_ATTR_NAMES = frozenset((*URI_ATTRS, "sha"))
# Children that hcdf.xsd allows once (maxOccurs="1") and that a verb reads, checked from the
# <software> they belong to (or sit in): a second one is refused, and every verb reads them
# through single() / single_text(). (Walking <software>, not <version>, keeps root.iter() free
# on documents without firmware: lxml skips a walk for names the document never uses, and
# "version" is the root's attribute in every document.)
_ONCE_IN_SOFTWARE = ("version", "hash", "firmware-manifest-uri")
_WALK_TAGS = (*_REFERENCE_TAGS, "software")
_XML_BASE = "{http://www.w3.org/XML/1998/namespace}base"
_XML_SPACE = " \t\r\n"
_NAMESPACED_ELEMENTS = etree.XPath("//*[namespace-uri()]")
_NAMESPACED_ATTRIBUTES = etree.XPath("//@*[namespace-uri()]")
# Encodings in which "xmlns" and "xml:" are the same bytes as in ASCII.
_ASCII_COMPATIBLE = frozenset(("UTF-8", "ASCII", "US-ASCII"))


def _may_use_namespaces(doc: Document) -> bool:
    """False when no element or attribute of ``doc`` can be in a namespace: its text declares
    none (no ``xmlns``) and uses no ``xml:`` attribute. Saves two tree scans on plain HCDF.

    Only for bytes where ASCII reads as ASCII: lxml reports a UTF-16 document without a
    declaration as UTF-8, but its '<' (3C 00) always holds a NUL byte.
    """
    data = doc.data
    ascii_like = (doc.tree.docinfo.encoding or "").upper() in _ASCII_COMPATIBLE and b"\x00" not in data
    return not ascii_like or b"xmlns" in data or b"xml:" in data


def _opaque(el: etree._Element) -> bool:
    """Inside the content of an ``<extension>`` child of ``<comp>`` (vendor data)."""
    for ext in el.iterancestors("extension"):
        parent = ext.getparent()
        if parent is not None and parent.tag == "comp":
            return True
    return False


def _walk(
    root: etree._Element,
    source: str,
    refs: list[Reference],
    problems: list[AmbiguousError],
    *,
    namespaces: bool = True,
) -> None:
    """Append every reference under ``root`` to ``refs`` and every refusal to ``problems``."""

    def refuse(el: etree._Element, message: str) -> None:
        problems.append(AmbiguousReferenceError(message, file=source, line=sourceline(el)))

    namespaced = cast("list[etree._Element]", _NAMESPACED_ELEMENTS(root)) if namespaces else []
    attributes = cast("list[Any]", _NAMESPACED_ATTRIBUTES(root)) if namespaces else []  # _ElementUnicodeResult
    for el in namespaced:
        parent = el.getparent()
        if parent is not None and etree.QName(parent).namespace is not None:
            continue  # inside a namespaced element already refused (or opaque): one error per subtree
        if not _opaque(el):
            refuse(
                el,
                f"{_describe(el)}: HCDF elements have no namespace, and a reader that ignores "
                "namespaces could take this one for HCDF's (a reference, or what makes one)",
            )
    for attr in attributes:
        el = attr.getparent()
        name = str(attr.attrname)
        local = etree.QName(name).localname
        if (name == _XML_BASE or local in _REFERENCE_ATTR_NAMES) and not _opaque(el):
            shown = (
                "an xml:base attribute"
                if name == _XML_BASE
                else f"an attribute {local} in namespace {etree.QName(name).namespace!r}"
            )
            refuse(
                el,
                f"<{etree.QName(el).localname}> has {shown} ({str(attr)!r}): refused, "
                "it changes or hides where a reference points",
            )
    # Most documents have no <comp><extension>: then nothing is opaque (one scan in C).
    opaque = any(getattr(ext.getparent(), "tag", None) == "comp" for ext in root.iter("extension"))
    add = refs.append
    for el in root.iter(*_WALK_TAGS):
        if opaque and _opaque(el):
            continue  # vendor content: may contain anything, never fetched by us
        tag = el.tag
        if tag == "software":
            _check_software(el, source, problems)
            continue
        try:
            ref = (tag == "model" and _plain_model(el)) or _reference(el, tag, source)
        except AmbiguousError as exc:
            problems.append(exc)
            continue
        if ref is not None:
            add(ref)


def _check_software(sw: etree._Element, source: str, problems: list[AmbiguousError]) -> None:
    """Refuse what the verbs read of a ``<software>`` written so that two readers could
    differ: its ``<version>``, ``<hash>``, ``<firmware-manifest-uri>`` twice, a second
    ``<software>`` in its ``<comp>``, the comp's ``<board>`` twice, and a ``<version>`` or
    ``<board>`` that is not plain text."""
    tags = [child.tag for child in sw]
    if len(set(tags)) < len(tags):  # some child twice (the common case, all distinct, stops here)
        for tag in _ONCE_IN_SOFTWARE:
            if tags.count(tag) > 1:
                problems.append(_twice(sw, list(sw.iterchildren(tag)), source))
    texts = [el for el in sw.iterchildren("version") if len(el)][:1]
    comp = sw.getparent()
    if comp is not None and comp.tag == "comp":
        first = next(sw.itersiblings("software", preceding=True), None)
        if first is not None:
            problems.append(_twice(comp, [first, sw], source))
        else:  # (the comp's board checked once, from its first <software>)
            boards = list(comp.iterchildren("board"))
            if len(boards) > 1:
                problems.append(_twice(comp, boards, source))
            texts += [el for el in boards[:1] if len(el)]
    problems.extend(_not_plain_text(el, source) for el in texts)


def _plain_model(el: etree._Element) -> Reference | None:
    """``_reference`` of a ``<model>`` in the form nearly every one is written: one of uri
    or href, a location of printable ASCII with no space at either end or run of spaces,
    no text and no child. None for anything else, which ``_reference`` checks in full."""
    uri, href = el.get("uri"), el.get("href")
    if href is None:
        value, attr = uri, "uri"
    elif uri is None:
        value, attr = href, "href"
    else:
        return None
    if value is None or el.text is not None or len(el) or not _plain_text(value):
        return None
    line = el.sourceline or sourceline(el)  # (the call only for a JSON document's elements)
    return Reference(Kind.MODEL, line, value, el.get("sha"), attr, element=el)  # type: ignore[arg-type]


def _plain_text(value: str) -> bool:
    """Printable ASCII with no space at either end and no run of spaces: a location every
    reader reads alike (the common case, which :func:`_unclear` passes at once)."""
    return value.isascii() and value.isprintable() and value[:1] != " " and value[-1:] != " " and "  " not in value


def _unclear(value: str, *, what: str) -> str | None:
    """Why readers could read ``value`` (a location) differently, or None."""
    if _plain_text(value):
        return None
    if value != value.strip(_XML_SPACE):
        return f"{what} {redact(value)!r} has whitespace around it"
    # Printable ASCII holds no control, format, separator or space character but " "
    # (the per-character scan below costs more than the rest of the reference).
    if not (value.isascii() and value.isprintable()):
        return _unclear_character(value, what=what)
    if "  " in value:
        return f"{what} {redact(value)!r} has a run of spaces (a schema-aware reader collapses it)"
    return None


def _unclear_character(value: str, *, what: str) -> str | None:
    for ch in value:
        if ch == " ":
            continue
        if ch.isspace() or unicodedata.category(ch) in ("Cc", "Cf", "Zl", "Zp", "Zs"):
            return f"{what} {redact(value)!r} contains U+{ord(ch):04X} ({unicodedata.name(ch, 'a control character')})"
    if "  " in value:
        return f"{what} {redact(value)!r} has a run of spaces (a schema-aware reader collapses it)"
    return None


def _location(el: etree._Element, tag: str, source: str) -> tuple[str | None, str | None]:
    """(uri, the attribute it came from) of an attribute reference element."""
    uri, href = el.get("uri"), el.get("href")
    if uri is not None and href is not None and uri != href:
        raise AmbiguousReferenceError(
            f"<{tag}> has uri={redact(uri)!r} and href={redact(href)!r}: one element, two different references",
            file=source,
            line=sourceline(el),
        )
    attr = "uri" if uri is not None else "href" if href is not None else None
    value = uri if uri is not None else href
    if value is not None and (why := _unclear(value, what=f"<{tag}> {attr}")):
        raise AmbiguousReferenceError(why, file=source, line=sourceline(el))
    # its own text nodes: before the first child and after each (a comment's tail is text too)
    text = el.text
    children = len(el) > 0
    if children:
        text = (text or "") + "".join(child.tail or "" for child in el)
    if text and (text := text.strip(_XML_SPACE)):
        raise AmbiguousReferenceError(
            f"<{tag}> holds text {redact(text)!r}: its reference is its uri or href attribute, never its text",
            file=source,
            line=sourceline(el),
        )
    for child in el if children else ():
        if isinstance(child.tag, str) and etree.QName(child).localname in _REFERENCE_ATTR_NAMES:
            raise AmbiguousReferenceError(
                f"<{tag}> has a <{etree.QName(child).localname}> child: write the reference as an attribute",
                file=source,
                line=sourceline(child),
            )
    return value, attr


def _string_value(el: etree._Element, tag: str, source: str) -> str | None:
    """A text reference's whole string value (stripped of XML whitespace), None when empty.

    Raises:
        AmbiguousReferenceError: a comment, PI or element inside, a uri/href attribute,
            or a value readers could disagree on.
    """
    for child in el:
        raise AmbiguousReferenceError(
            f"<{tag}> contains {_what(child)}: its text could be read in more than one way",
            file=source,
            line=sourceline(child) or sourceline(el),
        )
    for attr in URI_ATTRS:
        if el.get(attr) is not None:
            raise AmbiguousReferenceError(
                f"<{tag}> has a {attr} attribute ({redact(el.get(attr) or '')!r}): its reference is its text",
                file=source,
                line=sourceline(el),
            )
    value = (el.text or "").strip(_XML_SPACE)
    if not value:
        return None
    if why := _unclear(value, what=f"<{tag}>"):
        raise AmbiguousReferenceError(why, file=source, line=sourceline(el))
    return value


def _reference(el: etree._Element, tag: str, source: str) -> Reference | None:
    line = sourceline(el)
    if tag == "model":
        # The schema says uri; the published model repository writes href.
        uri, attr = _location(el, tag, source)
        return Reference(Kind.MODEL, line, uri=uri, sha=el.get("sha"), uri_attr=attr, element=el)
    parent = el.getparent()
    if tag == "include":
        uri, attr = _location(el, tag, source)
        return Reference(
            Kind.INCLUDE,
            line,
            uri=uri,
            sha=el.get("sha"),
            uri_attr=attr,
            name=el.get("name"),
            pose=el.get("pose"),
            element=el,
        )
    if tag == "mesh":
        # <network><mesh> is a wireless topology, not a file; any mesh with a location is one.
        if not _has_location(el) and (parent is None or parent.tag != "geometry"):
            return None
        uri, attr = _location(el, tag, source)
        return Reference(Kind.MESH, line, uri=uri, sha=el.get("sha"), uri_attr=attr, element=el)
    if tag == "stream-profile":
        if not _has_location(el) and (parent is None or parent.tag != "network"):
            return None
        uri, attr = _location(el, tag, source)
        return Reference(
            Kind.STREAM_PROFILE,
            line,
            uri=uri,
            sha=el.get("sha"),
            uri_attr=attr,
            selected=_marked(el),
            element=el,
        )
    if tag == "hash":
        if parent is None or parent.tag != "software":
            return None
        return Reference(
            Kind.FIRMWARE,
            line,
            sha=_string_value(el, tag, source),
            name=parent.get("name"),
            version=single_text(parent, "version", source=source),
            element=el,
        )
    if tag == "firmware-manifest-uri":
        uri = _string_value(el, tag, source)
        if uri is None:
            return None
        return Reference(
            Kind.FIRMWARE_MANIFEST, line, uri=uri, name=parent.get("name") if parent is not None else None, element=el
        )
    if tag == "extension":
        return Reference(Kind.EXTENSION, line, domain=el.get("domain"), version=el.get("version"), element=el)
    return None


def _has_location(el: etree._Element) -> bool:
    return any(el.get(a) is not None for a in URI_ATTRS)


STREAM_SELECTION = "stream-profile-selection"


@dataclass(frozen=True)
class StreamSelection:
    """Which of a document's ``<stream-profile>`` references are the ones a robot runs.

    Both dialects are read, with one meaning: 1.0's ``active`` (an ``xs:boolean``, default
    true: "one is active at a time", per ``<network>``) and upstream's ``selection-role="default"``
    (05d27b58, top-level profiles: "the root document may identify one profile as the default
    selection"). One selection per scope (a 1.0 ``<network>``, or the document's top level): in
    a scope where no profile carries ``selection-role`` an unmarked profile is selected (1.0's
    default); once one does, only marked profiles are. ``problems`` (message, line) are what
    cannot be read one way: a value neither dialect defines, ``selection-role="default"`` with
    ``active="false"``, or more than one profile selected in one scope.
    """

    profiles: tuple[Reference, ...]
    selected: tuple[Reference, ...]
    problems: tuple[tuple[str, int | None], ...]


def stream_profile_selection(doc: Document) -> StreamSelection:
    """The :class:`StreamSelection` of one document (validate, audit and sbom read it)."""
    profiles = tuple(r for r in doc.references() if r.kind is Kind.STREAM_PROFILE)
    problems: list[tuple[str, int | None]] = []
    for r in profiles:
        role, active = r.element.get("selection-role"), r.element.get("active")
        what = f"<stream-profile uri={redact(r.uri or '')!r}>"
        if role is not None and role.strip() not in SELECTION_ROLES:
            problems.append((f'{what}: selection-role="{redact(role)}" is not one HCDF defines ("default")', r.line))
        if active is not None and active.strip() not in _XS_BOOLEAN:
            problems.append((f'{what}: active="{redact(active)}" is not a boolean (true, false, 1, 0)', r.line))
        elif role is not None and r.selected and active is not None and not _XS_BOOLEAN[active.strip()]:
            problems.append((f'{what}: selection-role="default" and active="{active}" say opposite things', r.line))
    # One selection per scope: a 1.0 <network> holds its own profiles; upstream's newer model
    # lists them at the top level. 1.0's default applies to a profile that writes neither
    # attribute, in a scope where no profile uses selection-role.
    scopes: dict[Any, list[Reference]] = {}  # keyed by the parent element (lxml keeps one proxy while held)
    for r in profiles:
        scopes.setdefault(r.element.getparent(), []).append(r)
    selected: list[Reference] = []
    for group in scopes.values():
        newer = any(r.element.get("selection-role") is not None for r in group)
        chosen = [r for r in group if r.selected or (not newer and r.element.get("active") is None)]
        selected += chosen
        if len(chosen) > 1:
            lines = at_lines([r.line for r in chosen])
            parent = chosen[0].element.getparent()
            where = f"<{parent.tag} name={parent.get('name')!r}>" if parent.tag == "network" else "this document"
            problems.append(
                (
                    f"{len(chosen)} stream profiles are selected in {where} ({lines}): a robot runs one at a "
                    'time; mark one selection-role="default" (or active="true"), the others active="false"',
                    chosen[1].line,
                )
            )
    return StreamSelection(profiles, tuple(selected), tuple(problems))


FOREIGN_MAJOR = "foreign-major-version"


def foreign_major_notice(docs: Iterable[Document]) -> Notice | None:
    """One notice for every document of a run whose version has a major other than 1.

    Said once per run, at the first such document, naming the others: a tree of
    hcdf_models boards is one fact to know, not one warning per file.
    """
    foreign = [d for d in docs if d.foreign_major]
    if not foreign:
        return None
    first = foreign[0]
    others = f" (and {counted(len(foreign) - 1, 'more document')} of this tree)" if len(foreign) > 1 else ""
    return Notice(
        FOREIGN_MAJOR,
        f'version="{first.version}"{others}: read here as HCDF 1.0, but upstream\'s own reader '
        '(hcdformat-rs) accepts only 1.x and refuses this document; upstream keeps version="1.0"',
        file=first.source,
        line=sourceline(first.root),
    )


def software_elements(doc: Document) -> list[etree._Element]:
    """Every ``<software>`` entry outside extension content, in document order (the ota
    verbs read them whole: name, version, hash, and the enclosing ``<comp>``'s board)."""
    return [el for el in doc.root.iter("software") if not any(True for _ in el.iterancestors("extension"))]


# --- the one reading of an element the schema allows once ------------------------------


def single(parent: etree._Element, tag: str, *, source: str) -> etree._Element | None:
    """The one ``<tag>`` child of ``parent`` (None when there is none), for a child that
    hcdf.xsd allows once. Every verb reads such children through this function (or
    :func:`only`), so no two verbs can take different ones.

    Raises:
        AmbiguousError: two or more, naming the lines of the first two.
    """
    return only(list(parent.iterchildren(tag)), source=source)


def only(found: list[etree._Element], *, source: str) -> etree._Element | None:
    """The one element of ``found`` (same-named children of one parent, as a caller that
    groups children in one pass collected them), None when empty.

    Raises:
        AmbiguousError: two or more, naming the lines of the first two.
    """
    if len(found) > 1:
        parent = found[0].getparent()
        raise _twice(parent if parent is not None else found[0], found, source)
    return found[0] if found else None


def single_text(parent: etree._Element, tag: str, *, source: str) -> str | None:
    """The text of the one ``<tag>`` child of ``parent``, without the XML whitespace
    around it; None when the child is missing or empty.

    Raises:
        AmbiguousError: the child is written twice, or holds a comment, processing
            instruction or element (``.text`` and the string value then differ).
    """
    el = single(parent, tag, source=source)
    if el is None:
        return None
    if len(el):
        raise _not_plain_text(el, source)
    return (el.text or "").strip(_XML_SPACE) or None


def _not_plain_text(el: etree._Element, source: str) -> AmbiguousError:
    child = el[0]
    return AmbiguousError(
        f"<{_local(el)}> contains {_what(child)}: its text could be read in more than one way",
        file=source,
        line=sourceline(child) or sourceline(el),
    )


def _local(el: etree._Element) -> str:
    return etree.QName(el).localname if isinstance(el.tag, str) else "?"


def _what(child: etree._Element) -> str:
    if isinstance(child, etree._Comment):
        return "a comment"
    if isinstance(child, etree._ProcessingInstruction):
        return "a processing instruction"
    return f"a {_describe(child)} element"


def _twice(parent: etree._Element, found: list[etree._Element], source: str) -> AmbiguousError:
    tag = _local(found[0])
    lines = [sourceline(e) for e in found]
    shown = at_lines(lines[:2], " and ") + (f" (and {len(lines) - 2} more)" if len(lines) > 2 else "")
    return AmbiguousError(
        f"<{_local(parent)}> has {len(found)} <{tag}> elements, at {shown}: the schema allows one, "
        "and one reader would take the first, another the last",
        file=source,
        line=lines[1],
        expected=f"one <{tag}>",
        actual=f"{len(found)} <{tag}> elements ({shown})",
    )
