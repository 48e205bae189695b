"""A reference hidden in any way XML allows is reported or refused, never skipped (hypothesis).

Each example writes one intended reference (a location ``U`` and a digest ``S``, or a
firmware hash ``V``) in one of the ways XML offers: aliases (``uri``/``href``), whitespace,
character references, CDATA, comments, processing instructions, child elements,
namespaces, ``xml:base``, extensions. The walker must then either report exactly the
intended reference or refuse the document (exit 3, ``ambiguous-reference`` or
``not-hcdf``), and each way is pinned to the one of the two it must give, so refusing
everything would fail as surely as skipping.

The same documents go through ``resolve``: the intended file exists but does not match
the pin, while a decoy that matches it sits where a careless reader would look, so a
skipped reference would exit 0.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hcdf_trust.cli import main
from hcdf_trust.document import Document, Kind
from hcdf_trust.errors import ErrorGroup, HcdfTrustError

from ._hostile import no_network  # noqa: F401  (fixture used by name)

pytestmark = pytest.mark.usefixtures("no_network")

SETTINGS = settings(
    max_examples=int(os.environ.get("HCDF_FUZZ_EXAMPLES", "100")),
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)

REFUSALS = {"ambiguous-reference", "not-hcdf"}
DECOY = b"decoy content: matches the pin"
EVIL = b"intended content: does not match the pin"
S = hashlib.sha256(DECOY).hexdigest()
V = hashlib.sha256(b"firmware").hexdigest()
FILES = {
    "include": "evil.hcdf",
    "model": "models/evil.glb",
    "mesh": "meshes/evil.stl",
    "stream-profile": "profiles/evil.streams.xml",
    "firmware-manifest-uri": "firmware/evil.json",
}
DECOYS = {tag: name.replace("evil", "decoy") for tag, name in FILES.items()}
KIND = {
    "include": Kind.INCLUDE,
    "model": Kind.MODEL,
    "mesh": Kind.MESH,
    "stream-profile": Kind.STREAM_PROFILE,
    "firmware-manifest-uri": Kind.FIRMWARE_MANIFEST,
    "hash": Kind.FIRMWARE,
}
ATTRIBUTE_TAGS = ("include", "model", "mesh", "stream-profile")
TEXT_TAGS = ("firmware-manifest-uri", "hash")

# Where each kind of reference lives; {p} prefixes the parent's name, {pa} adds attributes
# to the parent, {ref} is the reference as written.
CONTEXT = {
    "include": '<{p}hcdf version="1.0" name="t"{pa}>\n  {ref}\n  <comp name="c"/>\n</{p}hcdf>\n',
    "model": '<hcdf version="1.0" name="t">\n  <comp name="c">\n    <{p}visual{pa}>{ref}</{p}visual>\n'
    "  </comp>\n</hcdf>\n",
    "mesh": '<hcdf version="1.0" name="t">\n  <comp name="c">\n    <collision><{p}geometry{pa}>{ref}</{p}geometry>'
    "</collision>\n  </comp>\n</hcdf>\n",
    "stream-profile": '<hcdf version="1.0" name="t">\n  <{p}network name="n"{pa}>{ref}</{p}network>\n</hcdf>\n',
    "firmware-manifest-uri": '<hcdf version="1.0" name="t">\n  <comp name="c">\n'
    '    <{p}software name="fw"{pa}><version>1.0</version>{ref}</{p}software>\n  </comp>\n</hcdf>\n',
}
CONTEXT["hash"] = CONTEXT["firmware-manifest-uri"]
NS = ' xmlns:x="urn:example:x"'
# name -> (Python codec, encoding declared in the document or None). UTF-16 with a BOM and
# no declaration is one lxml reports as UTF-8.
ENCODINGS = {
    "utf-8": ("utf-8", None),
    "utf-8 with BOM": ("utf-8-sig", None),
    "utf-8 declared": ("utf-8", "UTF-8"),
    "utf-16 with BOM": ("utf-16", None),
    "utf-16 declared": ("utf-16", "UTF-16"),
    "utf-32 with BOM": ("utf-32", None),
    "latin-1 declared": ("latin-1", "ISO-8859-1"),
}


@dataclass(frozen=True)
class Hidden:
    tag: str
    way: str
    xml: str
    refused: bool  # what the walker must do: refuse (exit 3), or report the intended reference
    encoding: str = "utf-8"

    @property
    def data(self) -> bytes:
        """The document as bytes in ``encoding``: the walker's shortcuts must hold in every one."""
        codec, declared = ENCODINGS[self.encoding]
        head = f'<?xml version="1.0" encoding="{declared}"?>\n' if declared else ""
        return (head + self.xml).encode(codec)

    @property
    def intended(self) -> str:
        return V if self.tag == "hash" else FILES[self.tag]


def _charrefs(draw: st.DrawFn, value: str) -> str:
    """``value`` with some characters written as character references (decimal or hex)."""
    flags = draw(st.lists(st.booleans(), min_size=len(value), max_size=len(value)))
    hexa = draw(st.booleans())
    written = [(f"&#x{ord(c):x};" if hexa else f"&#{ord(c)};") if f else c for c, f in zip(value, flags, strict=True)]
    return "".join(written)


def _split(draw: st.DrawFn, value: str) -> tuple[str, str]:
    at = draw(st.integers(0, len(value)))
    return value[:at], value[at:]


XML_SPACE = st.text(alphabet=" \t\n\r", min_size=1, max_size=4)
# Written inside a location: each makes readers disagree (XSD collapse, URL parsers, display).
INNER = st.sampled_from(["&#9;", "&#10;", "&#13;", "&#x200B;", "&#x202E;", "&#xFEFF;", "&#x7F;", "&#xA0;", "  "])
AROUND = st.sampled_from([" ", "&#9;", "&#10;", "&#13;", "\n", "\t", "&#xA0;", "&#x2003;"])


@st.composite
def hidden(draw: st.DrawFn) -> Hidden:
    tag = draw(st.sampled_from(ATTRIBUTE_TAGS + TEXT_TAGS))
    return draw(st.sampled_from(_ATTRIBUTE_WAYS if tag in ATTRIBUTE_TAGS else _TEXT_WAYS)).build(draw, tag)


@dataclass(frozen=True)
class Way:
    name: str
    refused: bool
    write: Callable[[st.DrawFn, str], tuple[str, str, str]]  # -> (reference, parent prefix, parent attributes)
    kinds: tuple[str, ...] = ATTRIBUTE_TAGS + TEXT_TAGS

    def build(self, draw: st.DrawFn, tag: str) -> Hidden:
        if tag not in self.kinds:
            tag = self.kinds[0]
        ref, prefix, parent_attrs = self.write(draw, tag)
        xml = CONTEXT[tag].format(p=prefix, pa=parent_attrs, ref=ref)
        return Hidden(tag, self.name, xml, self.refused, draw(st.sampled_from(sorted(ENCODINGS))))


def _attr(name: str, value: str) -> str:
    return f'{name}="{value}"'


def _el(tag: str, *attrs: str, body: str = "", prefix: str = "", ns: str = "") -> str:
    """An attribute reference element, always pinned with ``sha=S``."""
    inner = " ".join((*attrs, _attr("sha", S)))
    return f"<{prefix}{tag}{ns} {inner}>{body}</{prefix}{tag}>" if body else f"<{prefix}{tag}{ns} {inner}/>"


def _value(tag: str) -> str:
    return V if tag == "hash" else FILES[tag]


def _inside(draw: st.DrawFn, value: str, what: str) -> str:
    """``what`` written somewhere strictly inside ``value``."""
    at = draw(st.integers(1, len(value) - 1))
    return value[:at] + what + value[at:]


def _attribute_way(name: str, refused: bool, write: Callable[[st.DrawFn, str], str], **kw: object) -> Way:
    return Way(name, refused, lambda d, t: (write(d, t), "", ""), **kw)  # type: ignore[arg-type]


def _parent_way(name: str, refused: bool, prefix: str, attrs: str, kinds: tuple[str, ...]) -> Way:
    def write(d: st.DrawFn, t: str) -> tuple[str, str, str]:
        ref = _el(t, _attr("uri", FILES[t])) if t in ATTRIBUTE_TAGS else f"<{t}>{_value(t)}</{t}>"
        return ref, prefix, attrs

    return Way(name, refused, write, kinds=kinds)


def _uri_or_href(d: st.DrawFn) -> str:
    return d(st.sampled_from(["uri", "href"]))


def _xml_base_on_element(d: st.DrawFn, t: str) -> str:
    return _el(t, 'xml:base="https://elsewhere.example/"', _attr("uri", FILES[t]))


_ATTRIBUTE_WAYS = [
    _attribute_way("uri", False, lambda d, t: _el(t, _attr("uri", FILES[t]))),
    _attribute_way("href", False, lambda d, t: _el(t, _attr("href", FILES[t]))),
    _attribute_way("uri and href, equal", False, lambda d, t: _el(t, _attr("uri", FILES[t]), _attr("href", FILES[t]))),
    _attribute_way(
        "decoy uri, intended href", True, lambda d, t: _el(t, _attr("uri", DECOYS[t]), _attr("href", FILES[t]))
    ),
    _attribute_way(
        "intended uri, decoy href", True, lambda d, t: _el(t, _attr("href", DECOYS[t]), _attr("uri", FILES[t]))
    ),
    _attribute_way("character references", False, lambda d, t: _el(t, _attr(_uri_or_href(d), _charrefs(d, FILES[t])))),
    _attribute_way("whitespace before", True, lambda d, t: _el(t, _attr(_uri_or_href(d), d(AROUND) + FILES[t]))),
    _attribute_way("whitespace after", True, lambda d, t: _el(t, _attr(_uri_or_href(d), FILES[t] + d(AROUND)))),
    _attribute_way(
        "control or invisible character inside",
        True,
        lambda d, t: _el(t, _attr(_uri_or_href(d), _inside(d, FILES[t], d(INNER)))),
    ),
    _attribute_way(
        "comment inside the element", False, lambda d, t: _el(t, _attr("uri", FILES[t]), body="<!-- a note -->")
    ),
    _attribute_way("text instead of an attribute", True, lambda d, t: _el(t, body=FILES[t])),
    _attribute_way("text beside a decoy attribute", True, lambda d, t: _el(t, _attr("uri", DECOYS[t]), body=FILES[t])),
    _attribute_way(
        "text after a comment, beside a decoy attribute",
        True,
        lambda d, t: _el(t, _attr("uri", DECOYS[t]), body=f"<!-- -->{FILES[t]}"),
    ),
    _attribute_way(
        "child element instead of an attribute",
        True,
        lambda d, t: _el(t, body=(lambda n: f"<{n}>{FILES[t]}</{n}>")(_uri_or_href(d))),
    ),
    _attribute_way("prefixed element", True, lambda d, t: _el(t, _attr("uri", FILES[t]), prefix="x:", ns=NS)),
    _attribute_way(
        "default namespace on the element", True, lambda d, t: _el(t, _attr("uri", FILES[t]), ns=' xmlns="urn:x"')
    ),
    _parent_way("default namespace on the parent", True, "", ' xmlns="urn:example:x"', ATTRIBUTE_TAGS),
    _parent_way("prefixed parent", True, "x:", NS, ATTRIBUTE_TAGS),
    _attribute_way(
        "namespaced attribute",
        True,
        lambda d, t: _el(t, _attr("x:" + _uri_or_href(d), FILES[t]), _attr("uri", DECOYS[t]), ns=NS),
    ),
    _attribute_way(
        "xlink:href",
        True,
        lambda d, t: _el(t, _attr("xlink:href", FILES[t]), ns=' xmlns:xlink="http://www.w3.org/1999/xlink"'),
    ),
    _attribute_way("xml:base on the element", True, _xml_base_on_element),
    _parent_way("xml:base on the parent", True, "", ' xml:base="https://elsewhere.example/"', ATTRIBUTE_TAGS),
    _attribute_way(
        "inside an extension that is not a child of comp",
        False,
        lambda d, t: f'<extension domain="vendor">{_el(t, _attr("uri", FILES[t]))}</extension>',
    ),
    _attribute_way(
        "XInclude",
        True,
        lambda d, t: f'<xi:include xmlns:xi="http://www.w3.org/2001/XInclude" href="{FILES[t]}"/>',
        kinds=("include",),
    ),
]


def _text_way(name: str, refused: bool, body: Callable[[st.DrawFn, str], str], **kw: str) -> Way:
    prefix, ns, attrs = kw.get("prefix", ""), kw.get("ns", ""), kw.get("attrs", "")
    return Way(
        name, refused, lambda d, t: (f"<{prefix}{t}{ns}{attrs}>{body(d, _value(t))}</{prefix}{t}>", "", ""), TEXT_TAGS
    )


_TEXT_WAYS = [
    _text_way("plain text", False, lambda d, v: v),
    _text_way("whitespace around", False, lambda d, v: d(XML_SPACE) + v + d(st.sampled_from(["", "\n  "]))),
    _text_way("character references", False, _charrefs),
    _text_way("CDATA", False, lambda d, v: (lambda a, b: f"{a}<![CDATA[{b}]]>")(*_split(d, v))),
    _text_way("CDATA then text", False, lambda d, v: (lambda a, b: f"<![CDATA[{a}]]>{b}")(*_split(d, v))),
    _text_way("comment inside", True, lambda d, v: (lambda a, b: f"{a}<!-- -->{b}")(*_split(d, v))),
    _text_way("processing instruction inside", True, lambda d, v: (lambda a, b: f"{a}<?pi x?>{b}")(*_split(d, v))),
    _text_way("child element inside", True, lambda d, v: (lambda a, b: f"{a}<b>{b}</b>")(*_split(d, v))),
    _text_way("empty child element inside", True, lambda d, v: (lambda a, b: f"{a}<br/>{b}")(*_split(d, v))),
    _text_way("control or invisible character inside", True, lambda d, v: _inside(d, v, d(INNER))),
    _text_way("prefixed element", True, lambda d, v: v, prefix="x:", ns=NS),
    _text_way("default namespace on the element", True, lambda d, v: v, ns=' xmlns="urn:x"'),
    _text_way("uri attribute beside the text", True, lambda d, v: v, attrs=' uri="https://decoy.example/x.json"'),
    _parent_way("prefixed parent", True, "x:", NS, TEXT_TAGS),
    _parent_way("default namespace on the parent", True, "", ' xmlns="urn:example:x"', TEXT_TAGS),
    _parent_way("xml:base on the parent", True, "", ' xml:base="https://elsewhere.example/"', TEXT_TAGS),
    Way(
        "inside an extension that is not a child of comp",
        False,
        lambda d, t: (f'<extension domain="vendor"><{t}>{_value(t)}</{t}></extension>', "", ""),
        kinds=("firmware-manifest-uri",),
    ),
]


def _walk(h: Hidden) -> list[object] | HcdfTrustError:
    try:
        return list(Document.from_bytes(h.data, source="doc.hcdf").references())
    except HcdfTrustError as exc:
        return exc


def _codes(exc: HcdfTrustError) -> set[str]:
    return {e.code for e in exc.errors} if isinstance(exc, ErrorGroup) else {exc.code}


def _check_walk(h: Hidden) -> None:
    found = _walk(h)
    where = f"{h.tag} written as {h.way}, in {h.encoding}:\n{h.xml}"
    if isinstance(found, HcdfTrustError):
        assert found.exit_code == 3, where
        assert _codes(found) <= REFUSALS, (where, str(found))
        assert found.line is not None, where
        assert h.refused, f"refused, but should be reported: {where}\n{found}"
        return
    assert not h.refused, f"accepted, but should be refused: {where}\n{found}"
    if h.tag == "hash":
        assert any(r.kind is Kind.FIRMWARE and r.sha == V for r in found), where  # type: ignore[attr-defined]
    else:
        hits = [r for r in found if r.kind is KIND[h.tag] and r.uri == h.intended]  # type: ignore[attr-defined]
        assert hits, (where, found)
        if h.tag in ATTRIBUTE_TAGS:
            assert hits[0].sha == S, where  # type: ignore[attr-defined]


@SETTINGS
@given(hidden())
def test_a_hidden_reference_is_reported_or_the_document_refused(h: Hidden):
    _check_walk(h)


EVERY_WAY = [
    (w, t)
    for ways, tags in ((_ATTRIBUTE_WAYS, ATTRIBUTE_TAGS), (_TEXT_WAYS, TEXT_TAGS))
    for w in ways
    for t in tags
    if t in w.kinds
]


@pytest.mark.parametrize(("way", "tag"), EVERY_WAY, ids=[f"{t}-{w.name}" for w, t in EVERY_WAY])
@settings(SETTINGS, max_examples=max(3, SETTINGS.max_examples // 20))
@given(data=st.data())
def test_every_way_of_writing_every_kind(way: Way, tag: str, data: st.DataObject):
    """Each way, for each kind it applies to: the random test above need not draw them all."""
    _check_walk(way.build(data.draw, tag))


@pytest.fixture(scope="module")
def tree() -> Path:
    """A folder holding every intended file (content that does not match S) and every decoy (that does)."""
    with tempfile.TemporaryDirectory(prefix="walker-hidden-") as name:
        root = Path(name)
        for tag, rel in FILES.items():
            (root / rel).parent.mkdir(parents=True, exist_ok=True)
            evil = b'<hcdf version="1.0" name="evil"/>\n' if tag == "include" else EVIL
            (root / rel).write_bytes(evil)
            (root / DECOYS[tag]).write_bytes(DECOY)
        yield root


@settings(SETTINGS, max_examples=max(10, SETTINGS.max_examples // 2))
@given(h=hidden())
def test_resolve_never_exits_0_on_a_hidden_reference(tree: Path, h: Hidden):
    doc = tree / "doc.hcdf"
    doc.write_bytes(h.data)
    with tempfile.TemporaryDirectory(prefix="walker-run-") as run:
        args = ["resolve", str(doc), "--offline", "--json", "--lock", f"{run}/l.lock", "--cache-dir", f"{run}/cache"]
        result = CliRunner().invoke(main, args, catch_exceptions=False)
    where = f"{h.tag} written as {h.way}, in {h.encoding}:\n{h.xml}\n{result.stdout}{result.stderr}"
    out = json.loads(result.stdout)
    if result.exit_code == 3 and {e["code"] for e in out["errors"]} <= REFUSALS:
        assert h.refused, where
        return
    assert not h.refused, where
    if h.tag == "hash":
        assert any(f["hash"] == V for f in out["firmware"]), where
        return
    mine = [a for a in out["artifacts"] if a["uri"] == FILES[h.tag] and a["kind"] == KIND[h.tag].value]
    assert mine, where
    if h.tag in ATTRIBUTE_TAGS:  # the intended file was verified against the pin, and failed
        assert result.exit_code == 1, where
        assert any(e["code"] == "digest-mismatch" and FILES[h.tag] in e["message"] for e in out["errors"]), where
