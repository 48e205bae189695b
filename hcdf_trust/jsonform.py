"""HCDF's JSON form <-> XML, driven by the HCDF schema (xmlschema), located by JSON Pointer.

The shape is upstream's (``examples/drone-quadrotor.json``, ``tests/golden/*/model.json``):
the root key ``hcdf``; an element is an object whose keys are its attributes and its child
elements (the schema says which is which: the JSON does not); a child written once is a
value, a repeated one a list; text beside attributes is ``$text``; numbers and booleans
where the schema types them so; the root's ``version`` a number.

Why a schema: ``{"uri": "a.glb"}`` is an attribute in one element and a child element in
another, and xmlschema's own encoder with ``attr_prefix=''`` takes every key for an element
(measured). Here every key is looked up in the element type's attribute declarations, then
its content model; a key that is neither is **refused**, never dropped: a dropped key could
be a reference no verb would then see. Inside vendor content (what ``<extension>``'s wildcard
admits, which no schema declares) a key whose value is a string, number or boolean is an
attribute, an object or list a child element, as upstream's drone writes them; the direct
children of ``<extension>`` are elements.

What the JSON form cannot say, and what is done about it (docs/json-form.md):

- numbers keep their literal here (``1.0`` stays ``1.0``, ``0.0450`` stays ``0.0450``): the
  strict reader hands over the text of each number, never a float. Other JSON readers lose
  trailing zeros and ``1.0`` vs ``1``; so where the schema wants a string (a version, a name)
  a number is accepted only when every reader writes it back the same (``1.0``, ``2``), the
  root's ``version`` (which selects the schema) included, and
  a ``uri``, ``href``, ``sha``, ``<hash>`` or ``<firmware-manifest-uri>`` must be a string;
- comments, processing instructions and whitespace between elements are dropped (XML -> JSON);
- the order between differently named siblings (``<a/><b/><a/>`` becomes ``a: [..], b: ..``):
  a conversion that would change any reference (kind, location, pin, order) is refused.

xmlschema is imported here only, and this module only when a JSON document is read.
"""

from __future__ import annotations

import hashlib
import re
import threading
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lxml import etree

from .errors import InputError, Pointer
from .localfile import JsonNumber as Number
from .localfile import absolute, open_local, parse_json, read_bounded
from .xml import MAX_DOCUMENT_BYTES, MAX_ELEMENTS, LocationTable

TEXT = "$text"
ROOT = "hcdf"
SCHEMA_ENV = "HCDF_TRUST_SCHEMA"
#: The keys whose value is a reference or its pin: only a JSON string is read there.
REFERENCE_ATTRIBUTES = frozenset(("uri", "href", "sha"))
REFERENCE_TEXTS = frozenset(("hash", "firmware-manifest-uri"))
_JSON_NUMBER = re.compile(r"-?(?:0|[1-9][0-9]*)(?:\.[0-9]+)?(?:[eE][+-]?[0-9]+)?")
# An XML name without a colon that is not reserved (xmlns, xml:..., anything starting "xml"
# is the XML specification's): a key that is not one cannot be an element or attribute.
_NCNAME = re.compile(r"(?![Xx][Mm][Ll])[A-Za-z_][A-Za-z0-9_.\-]*")
_NUMERIC = frozenset(("decimal", "double", "float"))
_XML_SPACE = " \t\r\n"


class JsonFormError(InputError):
    """A JSON document the converter cannot read as HCDF without guessing (exit 3)."""

    code = "json-form"


def pointer_join(base: str, key: str | int) -> str:
    """``base`` + one JSON Pointer step (``~`` and ``/`` escaped, RFC 6901)."""
    return f"{base}/{str(key).replace('~', '~0').replace('/', '~1')}"


# --- which schema ------------------------------------------------------------------------

#: Another source of the schema's bytes (``validate --registry``: the registry's core schema
#: for a version): version -> (name, XSD bytes), None when it has none for that version.
SchemaProvider = Callable[[str | None], tuple[str, bytes] | None]
_schema_paths: tuple[str, ...] = ()
_provider: SchemaProvider | None = None


def use_schemas(paths: Sequence[str]) -> None:
    """The ``--schema`` files (or ``$HCDF_TRUST_SCHEMA``) JSON documents of this run are read
    with: the one whose ``version`` fits the document's is chosen, as ``validate`` chooses."""
    global _schema_paths, _provider
    _schema_paths = tuple(str(p) for p in paths)
    _provider = None


def use_schema_provider(provider: SchemaProvider) -> None:
    """Where the schema comes from when no ``--schema`` is given (a signed registry)."""
    global _provider
    _provider = provider


@dataclass(eq=False)
class Form:
    """A built HCDF schema, as the converter reads it."""

    name: str
    sha256: str
    xsd: Any = field(repr=False)  # xmlschema.XMLSchema10
    _types: dict[int, _Content] = field(default_factory=dict, repr=False)

    def content(self, decl: Any) -> _Content | None:
        """What an element declaration allows (None: undeclared, wildcard content)."""
        if decl is None:
            return None
        t = decl.type
        found = self._types.get(id(t))
        if found is None:
            found = self._types[id(t)] = _Content.of(t)
        return found


@dataclass
class _Content:
    attributes: dict[str, str]  # name -> "number" | "boolean" | "string"
    elements: dict[str, Any]  # name -> XsdElement
    wildcard: bool
    text: str | None  # the kind of its text ("number" ...), None for element-only content

    @classmethod
    def of(cls, t: Any) -> _Content:
        from xmlschema.validators import XsdAnyElement, XsdElement

        if t.is_simple():
            return cls({}, {}, False, _kind(t))
        attributes = {str(name): _kind(a.type) for name, a in t.attributes.items() if name}
        if None in t.attributes:  # xs:anyAttribute: a key could be either; none in hcdf.xsd
            raise InputError("the schema declares xs:anyAttribute: the JSON form cannot tell attributes there")
        if t.has_simple_content():
            return cls(attributes, {}, False, _kind(t.content))
        elements: dict[str, Any] = {}
        wildcard = False
        if t.content is not None and not t.is_empty():
            for c in t.content.iter_elements():
                if isinstance(c, XsdElement):
                    elements.setdefault(c.local_name, c)
                elif isinstance(c, XsdAnyElement):
                    wildcard = True
        clash = set(attributes) & set(elements)
        if clash:
            raise InputError(f"the schema's type {t.name} has attributes and elements named {sorted(clash)}")
        return cls(attributes, elements, wildcard, "string" if t.mixed else None)


def _kind(st: Any) -> str:
    """How the JSON form writes a value of simple type ``st``."""
    if st is None or not st.is_simple() or st.is_list() or st.is_union():
        return "string"
    primitive = getattr(st, "primitive_type", None)
    name = getattr(primitive, "local_name", None)
    if name in _NUMERIC:
        return "number"
    return "boolean" if name == "boolean" else "string"


_forms: OrderedDict[str, Form] = OrderedDict()
_forms_lock = threading.Lock()


def form_for(version: str | None, *, source: str) -> Form:
    """The converter for a document of this ``version``: built once per schema content.

    Raises:
        JsonFormError: no schema was given (``--schema`` / ``$HCDF_TRUST_SCHEMA``).
        InputError: the schema cannot be read or built.
    """
    from .validate.schema import FileSchemaSource, SchemaChoiceError

    if not _schema_paths and _provider is not None:
        found = _provider(version)
        if found is None:
            raise JsonFormError(f"the registry has no HCDF schema for version {version}", file=source)
        name, data = found
        return _build(name, hashlib.sha256(data).hexdigest(), data, None)
    if not _schema_paths:
        raise JsonFormError(
            "HCDF's JSON form is read through the HCDF schema, and none was given: "
            f"pass --schema hcdf.xsd (or set {SCHEMA_ENV}); the official schema is not shipped",
            file=source,
        )
    try:
        chosen = FileSchemaSource(*_schema_paths).schema_for(root=ROOT, version=version)
    except SchemaChoiceError as exc:
        raise JsonFormError(exc.message, file=source) from None
    with _forms_lock:
        cached = _forms.get(chosen.sha256)
    if cached is not None:
        return cached
    path, data = _schema_bytes(chosen.name, chosen.sha256)
    return _build(chosen.name, chosen.sha256, data, path.parent)


def _build(name: str, sha256: str, data: bytes, base: Path | None) -> Form:
    """xmlschema's model of an XSD (cached by content). Its imports and includes, if any, are
    read only from inside ``base`` (none at all without one); nothing from the network."""
    with _forms_lock:
        cached = _forms.get(sha256)
    if cached is not None:
        return cached
    import xmlschema

    try:
        xsd = xmlschema.XMLSchema10(
            data.decode("utf-8"),
            base_url=str(base) if base is not None else None,
            allow="sandbox" if base is not None else "none",
            defuse="always",
        )
    except (xmlschema.XMLSchemaException, UnicodeDecodeError, ValueError) as exc:
        raise InputError(f"xmlschema cannot build {name}: {exc}", file=name) from None
    form = Form(name=name, sha256=sha256, xsd=xsd)
    with _forms_lock:
        _forms[sha256] = form
        while len(_forms) > 4:
            _forms.popitem(last=False)
    return form


def _schema_bytes(name: str, sha256: str) -> tuple[Path, bytes]:
    """The bytes of the chosen schema file (the one ``validate`` picked, by name and digest)."""
    from .include.locate import display_path

    candidates = [Path(absolute(p)) for p in _schema_paths]
    candidates += [p.parent / "hcdf.xsd" for p in candidates]
    for path in candidates:
        if display_path(path) != name:
            continue
        with open_local(path, path.parent, file=name) as fd:
            data = read_bounded(fd, 16 << 20, source=name, what="schema")
        if hashlib.sha256(data).hexdigest() == sha256:
            return path, data
        raise InputError("the schema changed while it was read", file=name, expected=sha256)
    raise InputError(f"schema {name} not found among --schema files", file=name)


# --- JSON -> XML ---------------------------------------------------------------------------


@dataclass
class JsonDocument:
    """A JSON document read as XML: its tree, and where each element was written."""

    tree: etree._ElementTree
    locations: LocationTable
    form: Form


def read(data: bytes, *, source: str) -> JsonDocument:
    """Parse HCDF's JSON form (the strict reader: size, depth, duplicate keys, non-finite
    numbers) and build the XML tree the walker reads, every element located by JSON Pointer.

    Raises:
        JsonError: not one unambiguous JSON document.
        JsonFormError: not HCDF's shape, or a key or value the converter would have to drop
            or guess (named by JSON Pointer).
    """
    doc = parse_json(  # every element but a scalar one is an object: a flood of {} stops mid-parse
        data, source=source, what="HCDF JSON document", limit=MAX_DOCUMENT_BYTES, exact=True, max_objects=MAX_ELEMENTS
    )
    if not isinstance(doc, dict) or list(doc) != [ROOT]:
        keys = sorted(doc) if isinstance(doc, dict) else type(doc).__name__
        raise JsonFormError(
            f'not HCDF\'s JSON form: expected one key "{ROOT}" at the top, found {keys}',
            file=source,
            expected=f'{{"{ROOT}": {{...}}}}',
        )
    if _elements_at_least(doc) > MAX_ELEMENTS:  # a flood of "" in a list, before any is built
        raise JsonFormError(
            f"more than {MAX_ELEMENTS:,} elements: over the cap on a JSON document's elements",
            file=source,
            expected=f"at most {MAX_ELEMENTS:,} elements",
        )
    body = doc[ROOT]
    version = body.get("version") if isinstance(body, dict) else None
    if isinstance(version, Number) and not _canonical_number(version):  # it picks the schema: read it alike
        raise JsonFormError(
            f"the root's version is the number {version}, which JSON readers read differently "
            f"(as {_float_text(version)}), and it selects the schema: write it as a string",
            file=source,
            line=Pointer(1, f"/{ROOT}/version"),
            expected=f'"{version}"',
            actual=str(version),
        )
    form = form_for(str(version) if isinstance(version, (str, Number)) else None, source=source)
    builder = _Builder(form, source)
    root = builder.element(None, ROOT, body, form.xsd.elements.get(ROOT), "/" + ROOT, root=True)
    return JsonDocument(root.getroottree(), builder.table, form)


def _elements_at_least(doc: Any) -> int:
    """How many elements ``doc`` builds at least: every list item, every object not in a list.

    One level at a time in C-speed comprehensions, as localfile's depth check walks.
    """
    count = 0
    level = [doc]
    while level:
        lists = [v for node in level if type(node) is dict for v in node.values() if type(v) is list]
        objects = [v for node in level if type(node) is dict for v in node.values() if type(v) is dict]
        count += len(objects) + sum(map(len, lists))
        level = objects + [v for items in lists for v in items if type(v) is dict or type(v) is list]
    return count


class _Builder:
    def __init__(self, form: Form, source: str) -> None:
        self.form = form
        self.source = source
        self.table = LocationTable()
        self.count = 0

    def fail(self, pointer: str, message: str, **kw: Any) -> JsonFormError:
        return JsonFormError(message, file=self.source, line=Pointer(self.count or 1, pointer), **kw)

    def element(
        self, parent: etree._Element | None, name: str, value: Any, decl: Any, pointer: str, *, root: bool = False
    ) -> etree._Element:
        if not _NCNAME.fullmatch(name):
            raise self.fail(pointer, f"key {name!r} cannot be an XML element name")
        self.count += 1
        if self.count > MAX_ELEMENTS:  # scalar elements too (a list of strings)
            raise self.fail(
                pointer,
                f"more than {MAX_ELEMENTS:,} elements: over the cap on a JSON document's elements",
                expected=f"at most {MAX_ELEMENTS:,} elements",
            )
        el = etree.Element(name) if parent is None else etree.SubElement(parent, name)
        self.table.add(el, Pointer(self.count, pointer))
        content = self.form.content(decl)
        if isinstance(value, dict):
            if content is not None and content.text is not None and not content.attributes and decl.type.is_simple():
                raise self.fail(pointer, f"<{name}> holds a value, not an object", expected="a string or number")
            for key, item in value.items():
                self.member(el, name, key, item, content, pointer, root=root)
        elif isinstance(value, list):
            raise self.fail(pointer, f"<{name}>: a list inside a list has no XML meaning")
        else:
            if content is not None and content.text is None:
                raise self.fail(pointer, f"<{name}> holds elements, not a value: write an object", actual=repr(value))
            kind = content.text if content is not None and content.text else "string"
            el.text = self.scalar(value, kind, pointer, name, name in REFERENCE_TEXTS)
        return el

    def member(
        self, el: etree._Element, name: str, key: str, item: Any, content: _Content | None, pointer: str, *, root: bool
    ) -> None:
        try:
            self._member(el, name, key, item, content, pointer, root=root)
        except ValueError as exc:  # lxml: a character XML does not allow (U+0000, U+FFFE, lone controls)
            raise self.fail(pointer_join(pointer, key), f"{key!r}: {exc}") from None

    def _member(
        self, el: etree._Element, name: str, key: str, item: Any, content: _Content | None, pointer: str, *, root: bool
    ) -> None:
        if type(item) is str and content is not None and key in content.attributes:
            el.set(key, item)  # the common case: an attribute written as a string (no Pointer needed)
            return
        here = pointer_join(pointer, key)
        if key == TEXT:
            if content is not None and content.text is None:
                raise self.fail(here, f"<{name}> holds elements, not text: {TEXT} has no place here")
            kind = content.text if content is not None else "string"
            el.text = self.scalar(item, kind or "string", here, name, name in REFERENCE_TEXTS)
            return
        if content is not None and key in content.attributes:
            kind = "number" if (root and key == "version") else content.attributes[key]
            el.set(key, self.scalar(item, kind, here, f"{name} {key}", key in REFERENCE_ATTRIBUTES))
            return
        if content is None and not isinstance(item, (dict, list)):  # vendor content: a value is an attribute
            if not _NCNAME.fullmatch(key):
                raise self.fail(here, f"key {key!r} cannot be an XML attribute name")
            el.set(key, self.scalar(item, "string", here, f"{name} {key}", key in REFERENCE_ATTRIBUTES))
            return
        decl = content.elements.get(key) if content is not None else None
        if decl is None and content is not None and not content.wildcard:
            raise self.fail(
                here,
                f"<{name}> has no attribute or element {key!r} in {self.form.name}: refused, not dropped "
                "(it could hold a reference no verb would see)",
                expected=f"one of {sorted([*content.attributes, *content.elements])}",
                actual=key,
            )
        if isinstance(item, list):
            if not item:
                raise self.fail(here, f"{key!r} is an empty list: leave the key out")
            for i, one in enumerate(item):
                self.element(el, key, one, decl, pointer_join(here, i))
        else:
            self.element(el, key, item, decl, here)

    def scalar(self, value: Any, kind: str, pointer: str, what: str, reference: bool) -> str:
        """The XML text of a JSON value: a string as is, a number's literal, true/false."""
        if isinstance(value, Number):
            if reference:
                raise self.fail(
                    pointer,
                    f"{what} is the number {value}: a reference or its pin is a string",
                    expected="a JSON string",
                    actual=str(value),
                )
            if kind != "number" and not _canonical_number(value):
                raise self.fail(
                    pointer,
                    f"{what} is the number {value}, which JSON readers write back differently "
                    f"(as {_float_text(value)}): write it as a string",
                    expected=f'"{value}"',
                    actual=str(value),
                )
            return str(value)
        if isinstance(value, str):
            return value
        if isinstance(value, bool) and not reference:
            return "true" if value else "false"
        shown = "null" if value is None else type(value).__name__
        raise self.fail(
            pointer,
            f"{what} is {shown}" + (": a reference or its pin is a string" if reference else ": expected a value"),
            expected="a JSON string" if reference else "a string, number or boolean",
            actual=shown,
        )


def _float_text(literal: str) -> str:
    value = float(literal)
    return repr(int(value)) if value.is_integer() and "." not in literal and "e" not in literal.lower() else repr(value)


def _canonical_number(literal: str) -> bool:
    """Whether float-based JSON readers write ``literal`` back as written (``1.0``, ``2``)."""
    try:
        return _float_text(literal) == literal
    except (ValueError, OverflowError):
        return False


# --- XML -> JSON ---------------------------------------------------------------------------


@dataclass
class Converted:
    """An XML document in the JSON form, and what the JSON form could not keep."""

    value: dict[str, Any]
    losses: list[str]


def to_json(root: etree._Element, *, source: str, form: Form) -> Converted:
    """The JSON form of an ``<hcdf>`` tree.

    Raises:
        JsonFormError: something the JSON form cannot say (an undeclared attribute, text
            beside child elements, an attribute in vendor content), named by line.
    """
    losses: list[str] = []
    out = _Writer(form, source, losses)
    return Converted({ROOT: out.value(root, form.xsd.elements.get(ROOT), root=True)}, losses)


class _Writer:
    def __init__(self, form: Form, source: str, losses: list[str]) -> None:
        self.form = form
        self.source = source
        self.losses = losses
        self.dropped: set[str] = set()

    def lose(self, what: str) -> None:
        if what not in self.dropped:
            self.dropped.add(what)
            self.losses.append(what)

    def fail(self, el: etree._Element, message: str) -> JsonFormError:
        from .xml import sourceline

        return JsonFormError(message, file=self.source, line=sourceline(el))

    def value(self, el: etree._Element, decl: Any, *, root: bool = False, vendor: bool = False) -> Any:
        """``el`` in the JSON form. ``vendor``: its parent is undeclared vendor content, where a
        value key is an attribute, so a text-only child is written ``{"$text": ...}``."""
        content = self.form.content(decl)
        name = str(el.tag)
        out: dict[str, Any] = {}
        for key, text in el.attrib.items():
            key = str(key)
            if key.startswith("{"):
                raise self.fail(el, f"<{name}> has a namespaced attribute {key}: the JSON form has no namespaces")
            if content is None:  # vendor content: a value key is an attribute
                out[key] = str(text)
                continue
            if key not in content.attributes:
                raise self.fail(
                    el,
                    f"<{name}> attribute {key!r} is not declared in {self.form.name}: "
                    "the JSON form could not say it is an attribute",
                )
            kind = "number" if (root and key == "version") else content.attributes[key]
            out[key] = _typed(str(text), kind, canonical=root and key == "version")
        children: dict[str, list[etree._Element]] = {}
        order: list[str] = []
        text = el.text or ""
        for child in el:
            text += child.tail or ""
            if not isinstance(child.tag, str):
                self.lose("comments and processing instructions")
                continue
            tag = str(child.tag)
            if tag.startswith("{"):
                raise self.fail(child, f"<{tag}> is in a namespace: the JSON form has none")
            if order and order[-1] != tag and tag in children:
                self.lose("the order between differently named sibling elements")
            if tag not in children:
                order.append(tag)
                children[tag] = []
            children[tag].append(child)
        if children and text.strip(_XML_SPACE):
            raise self.fail(el, f"<{name}> holds text beside child elements: the JSON form cannot keep both")
        if not children and text and (content is None or content.text is not None):
            kind = content.text if content is not None and content.text else "string"
            if not out and not vendor and (content is None or not content.attributes or decl.type.is_simple()):
                return _typed(text, kind)
            out[TEXT] = _typed(text, kind)
        elif text and not text.strip(_XML_SPACE):
            self.lose("whitespace between elements")
        elif text:
            raise self.fail(el, f"<{name}> holds text where the schema allows only elements")
        if not children and not out and content is not None and content.text is not None:
            return ""  # an empty value element
        for tag in order:
            sub = content.elements.get(tag) if content is not None else None
            if content is not None and sub is None and not content.wildcard:
                raise self.fail(children[tag][0], f"<{tag}> is not declared in <{name}>: the JSON form cannot place it")
            if tag in out:
                raise self.fail(children[tag][0], f"<{name}> has an attribute and an element named {tag!r}")
            values = [self.value(c, sub, vendor=content is None) for c in children[tag]]
            out[tag] = values[0] if len(values) == 1 else values
        return out


def _typed(text: str, kind: str, *, canonical: bool = False) -> Any:
    if kind == "number" and _JSON_NUMBER.fullmatch(text) and (not canonical or _canonical_number(text)):
        return Number(text)
    if kind == "boolean" and text in ("true", "false"):
        return text == "true"
    return text


def dumps(value: Any) -> str:
    """JSON text with every number written as its literal (json.dumps would write floats)."""
    import json

    parts: list[str] = []

    def walk(v: Any, indent: str) -> None:
        if isinstance(v, dict):
            if not v:
                parts.append("{}")
                return
            inner = indent + "  "
            parts.append("{\n")
            for i, (k, item) in enumerate(v.items()):
                parts.append(f"{inner}{json.dumps(k, ensure_ascii=False)}: ")
                walk(item, inner)
                parts.append(",\n" if i < len(v) - 1 else "\n")
            parts.append(indent + "}")
        elif isinstance(v, list):
            inner = indent + "  "
            parts.append("[\n")
            for i, item in enumerate(v):
                parts.append(inner)
                walk(item, inner)
                parts.append(",\n" if i < len(v) - 1 else "\n")
            parts.append(indent + "]")
        elif isinstance(v, Number):
            parts.append(str(v))
        else:
            parts.append(json.dumps(v, ensure_ascii=False))

    walk(value, "")
    parts.append("\n")
    return "".join(parts)


__all__ = [
    "Converted",
    "Form",
    "JsonDocument",
    "JsonFormError",
    "Number",
    "dumps",
    "form_for",
    "read",
    "to_json",
    "use_schemas",
]


# --- convert: one document, both ways -------------------------------------------------------


@dataclass
class Conversion:
    """``convert``'s result: the output bytes and what the report says about them."""

    data: bytes
    to: str  # "json" or "xml"
    schema: str
    schema_sha256: str
    references: int
    losses: list[str]


def _reference_key(ref: Any) -> tuple[Any, ...]:
    return (ref.kind, ref.uri, ref.sha, ref.uri_attr, ref.name, ref.pose, ref.selected, ref.domain, ref.version)


def convert(data: bytes, *, source: str) -> Conversion:
    """``data`` (an HCDF document, XML or the JSON form) in the other form.

    Both sides are read as every verb reads them (:class:`~hcdf_trust.document.Document`:
    every reference seen, or the document refused), and the output is read back: a
    conversion that would change any reference (kind, location, pin, name, order) or that
    the strict JSON reader would not read back is refused.

    Raises:
        JsonFormError: the forms disagree on a reference, or the output would not read back.
        InputError (XmlError, JsonError, AmbiguousReferenceError, NotHcdfError): the input.
    """
    from .document import Document

    doc = Document.from_bytes(data, source=source)
    if doc.is_json:
        form: Form = doc.json.form
        out = etree.tostring(doc.tree, xml_declaration=True, encoding="UTF-8", pretty_print=True)
        to, losses = "xml", []
    else:
        form = form_for(doc.version, source=source)
        converted = to_json(doc.root, source=source, form=form)
        out = dumps(converted.value).encode("utf-8")
        to, losses = "json", converted.losses
    try:
        back = Document.from_bytes(out, source=f"{source} (converted)")
    except InputError as exc:
        raise JsonFormError(f"the {to.upper()} form would not read back: {exc.message}", file=source) from None
    before = [_reference_key(r) for r in doc.references()]
    after = [_reference_key(r) for r in back.references()]
    if before != after:
        pairs = enumerate(zip(before, after, strict=False))
        at = next((i for i, (a, b) in pairs if a != b), min(len(before), len(after)))
        shown = doc.references()[at] if at < len(before) else None
        raise JsonFormError(
            f"converting would change reference {at + 1} of {len(before)}: refused (the JSON form cannot keep "
            "what tells them apart, e.g. the order of differently named elements)",
            file=source,
            line=shown.line if shown is not None else None,
            expected=repr(before[at][1:3]) if at < len(before) else "no reference",
            actual=repr(after[at][1:3]) if at < len(after) else "no reference",
        )
    return Conversion(out, to, form.name, form.sha256, len(before), losses)
