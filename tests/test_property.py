"""Property-based hostile input (hypothesis): the tool never crashes with a traceback.

Corpus documents are mutated (elements dropped, duplicated, moved and reordered;
attribute values and text changed, including ``sha``, ``uri`` and ``href``; bytes
truncated, flipped or inserted) and fed to resolve, verify, pin and validate.
Every outcome must be a documented one: exit 0, 1 or 3 with an error message,
never an uncaught exception, never a write outside what a clean run may write.

The pure layers get the same treatment on their own: digest parsing, the safe
XML parser and the path locator.
"""

from __future__ import annotations

import copy
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st
from lxml import etree

from hcdf_trust.cli import main
from hcdf_trust.digest import FULL_HEX, MIN_WEAK_HEX, parse_pin
from hcdf_trust.errors import InputError, MalformedDigestError, PathEscapeError, XmlError
from hcdf_trust.include.locate import Locator, file_url
from hcdf_trust.xml import parse_bytes

from ._hostile import no_network, snapshot  # noqa: F401  (fixture used by name)
from .conftest import CORPUS, HCDFORMAT, MODELS

pytestmark = pytest.mark.usefixtures("no_network")

# CI runs 100 mutations per test; HCDF_FUZZ_EXAMPLES=1500 for a longer local soak
# (1,500 ran clean in ~30 s on 2 cores).
SETTINGS = settings(
    max_examples=int(os.environ.get("HCDF_FUZZ_EXAMPLES", "100")),
    deadline=None,
    database=None,  # nothing written into the project tree
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture, HealthCheck.data_too_large],
)


@dataclass(frozen=True)
class CorpusDoc:
    name: str
    path: Path
    base: Path  # where its relative references resolve (as the corpus README explains)


def _corpus_docs() -> list[CorpusDoc]:
    docs = []
    examples = HCDFORMAT / "examples"
    for name in ("test-minimal.hcdf", "drone-quadrotor.hcdf", "humanoid-mobile-base.hcdf"):
        docs.append(CorpusDoc(name, examples / name, examples))
    for name in ("all-joint-types.hcdf", "transmission-spring.hcdf", "power-solar-supercap.hcdf"):
        docs.append(CorpusDoc(name, HCDFORMAT / "tests" / "valid" / name, HCDFORMAT / "tests" / "valid"))
    for path in sorted(MODELS.glob("*/*/*-*.hcdf")):  # the real fragments, not the link stubs
        docs.append(CorpusDoc(path.name, path, MODELS))
    for name in ("navq95_system.hcdf", "optical-flow.hcdf"):
        docs.append(CorpusDoc(name, CORPUS / "dendrite" / name, CORPUS / "dendrite"))
    return [d for d in docs if d.path.is_file() and d.path.read_bytes().lstrip().startswith(b"<")]


DOCS = _corpus_docs()
if not DOCS:  # pragma: no cover
    pytest.skip(f"corpus not found at {CORPUS}", allow_module_level=True)

SCHEMA = HCDFORMAT / "hcdf.xsd"
_PLAIN = etree.XMLParser(remove_comments=False, resolve_entities=False, no_network=True)

INTERESTING = [
    "",
    " ",
    ".",
    "..",
    "../x.hcdf",
    "../../../../etc/passwd",
    "/etc/passwd",
    "file:///etc/passwd",
    "%2e%2e/%2e%2e/etc/passwd",
    "models/",
    "models/../models/x.glb",
    "C:\\x",
    "\\\\host\\share\\x",
    "https://127.0.0.1:9/x.glb",
    "http://example.invalid/x.glb",
    "ftp://x/y",
    "data:,x",
    "abc123",
    "abc123xyz",
    "sha256:",
    "0" * 64,
    "F" * 64,
    "0" * 65,
    "deadbeef",
    "DEADBEEF",
    "nan nan nan nan nan nan",
    "1e309 0 0 0 0 0",
    "0 0 0",
    "1 2 3 4 5 6 7",
    "true",
    "false",
    "2.0",
    "1.2",
    "-1",
    "99999999999999999999",
    "\u202e",
    "x" * 300,
]

# Real digests and references from the other corpus documents: well-formed, but wrong here.
REAL_VALUES = sorted(
    {
        v
        for d in DOCS
        for e in etree.fromstring(d.path.read_bytes(), etree.XMLParser()).iter()
        if isinstance(e.tag, str)
        for k, v in e.attrib.items()
        if k in ("sha", "uri", "href")
    }
)

_xml_char = st.characters(codec="utf-8", exclude_categories=("Cs", "Cc"))
VALUES = st.one_of(
    st.sampled_from(INTERESTING),
    st.sampled_from(REAL_VALUES or [""]),
    st.text(alphabet="0123456789abcdefABCDEF", max_size=70),
    st.text(alphabet=_xml_char, max_size=60),
)
REFERENCE_TAGS = {
    "include",
    "model",
    "mesh",
    "stream-profile",
    "software",
    "hash",
    "firmware-manifest-uri",
    "extension",
}
ATTRS = ["sha", "uri", "href", "name", "pose", "version", "active", "domain", "body-frame", "world-frame"]


def _elements(tree: etree._ElementTree) -> list[etree._Element]:
    return [e for e in tree.getroot().iter() if isinstance(e.tag, str)]


@st.composite
def mutated(draw) -> tuple[CorpusDoc, bytes, list[str]]:
    doc = draw(st.sampled_from(DOCS))
    tree = etree.fromstring(doc.path.read_bytes(), _PLAIN).getroottree()
    done: list[str] = []
    for op in draw(
        st.lists(
            st.sampled_from(["drop", "duplicate", "reorder", "move", "set-attr", "del-attr", "set-text"]),
            min_size=1,
            max_size=4,
        )
    ):
        els = _elements(tree)
        refs = [e for e in els if e.tag in REFERENCE_TAGS]
        if refs and draw(st.booleans()):  # half the time, aim at a reference
            els = refs
        el = els[draw(st.integers(0, len(els) - 1))]
        parent = el.getparent()
        if op == "drop" and parent is not None:
            parent.remove(el)
        elif op == "duplicate" and parent is not None:
            parent.insert(parent.index(el) + 1, copy.deepcopy(el))
        elif op == "reorder" and len(el) > 1:
            children = draw(st.permutations(list(el)))
            for child in children:
                el.append(child)  # append moves: the new order is the permutation
        elif op == "move" and parent is not None:
            target = els[draw(st.integers(0, len(els) - 1))]
            if target is not el and el not in target.iterancestors():
                target.append(el)
        elif op == "set-attr":
            name = draw(st.sampled_from(sorted(el.attrib) + ATTRS))
            el.set(name, draw(VALUES))
        elif op == "del-attr" and el.attrib:
            del el.attrib[draw(st.sampled_from(sorted(el.attrib)))]
        elif op == "set-text":
            el.text = draw(VALUES)
        done.append(f"{op} <{el.tag}>")
    data = etree.tostring(tree, xml_declaration=True, encoding="UTF-8")
    byte_op = draw(st.sampled_from(["none"] * 5 + ["truncate", "flip", "insert"]))
    if byte_op != "none" and data:
        at = draw(st.integers(0, len(data) - 1))
        if byte_op == "truncate":
            data = data[:at]
        elif byte_op == "flip":
            data = data[:at] + bytes([data[at] ^ draw(st.integers(1, 255))]) + data[at + 1 :]
        else:
            data = data[:at] + draw(st.binary(min_size=1, max_size=16)) + data[at:]
        done.append(f"{byte_op} at {at}")
    return doc, data, done


@pytest.fixture(scope="module")
def locks(tmp_path_factory) -> dict[str, Path]:
    """A lock for each unmutated corpus document (where it resolves), so that verify of a
    mutation gets past the lock and into drift, mismatch and parse errors."""
    folder = tmp_path_factory.mktemp("locks")
    runner = CliRunner()
    out = {}
    for doc in DOCS:
        copy_path = folder / doc.name
        copy_path.write_bytes(doc.path.read_bytes())
        lock = folder / f"{doc.name}.lock"
        runner.invoke(
            main,
            [
                "resolve",
                str(copy_path),
                "--offline",
                "--base",
                str(doc.base),
                "--lock",
                str(lock),
                "--cache-dir",
                str(folder / "cache"),
            ],
        )
        out[doc.name] = lock  # may not exist: verify must then say so, cleanly
    return out


def _args(command: str, doc: CorpusDoc, path: Path, work: Path, locks: dict[str, Path], schema: bool) -> list[str]:
    cache = str(work / "cache")
    base = ["--base", str(doc.base)]
    if command == "resolve":
        return [
            "resolve",
            str(path),
            "--offline",
            "--no-lock",
            "--out",
            str(work / "flat.hcdf"),
            "--cache-dir",
            cache,
            *base,
        ]
    if command == "verify":
        return ["verify", str(path), "--lock", str(locks[doc.name]), "--cache-dir", cache, *base]
    if command == "pin":  # never --write: base points into the corpus
        return ["pin", str(path), "--offline", "--cache-dir", cache, *base]
    return ["validate", str(path), *(["--schema", str(SCHEMA)] if schema else [])]


@pytest.fixture(scope="module")
def corpus_before():
    return snapshot(CORPUS)


@SETTINGS
@given(case=mutated(), schema=st.booleans(), as_json=st.booleans())
def test_mutated_corpus_documents_never_crash(locks, corpus_before, case, schema, as_json):
    doc, data, ops = case
    for command in ("resolve", "verify", "pin", "validate"):
        with tempfile.TemporaryDirectory() as tmp:
            work = Path(tmp)
            path = work / "doc.hcdf"
            path.write_bytes(data)
            args = _args(command, doc, path, work, locks, schema) + (["--json"] if as_json else [])
            before = snapshot(work)
            result = CliRunner().invoke(main, args, catch_exceptions=True)
            note = f"{command} on {doc.name} after {ops}:\n{result.stdout}\n{result.stderr}"
            event(f"{command} exit {result.exit_code}")
            assert result.exception is None or isinstance(result.exception, SystemExit), (
                f"uncaught {type(result.exception).__name__}: {result.exception}\n{note}"
            )
            assert result.exit_code in (0, 1, 3), note
            assert "Traceback" not in result.stderr, note
            if result.exit_code != 0:
                if as_json:
                    assert '"ok": false' in result.stdout, note
                else:
                    assert "error" in result.stderr, note
            after = snapshot(work)
            if command == "resolve" and result.exit_code == 0:
                after.pop(str(work / "flat.hcdf"), None)
            if command == "resolve" and result.exit_code != 0:
                assert not (work / "flat.hcdf").exists(), note
            created = set(after) - set(before)
            assert not {p for p in created if not p.startswith(str(work / "cache"))}, note


def test_corpus_untouched(corpus_before):
    """Runs last in this module: nothing above wrote into ../shared/corpus."""
    assert snapshot(CORPUS) == corpus_before


# --- the pure layers ----------------------------------------------------------------


@settings(max_examples=300, deadline=None, database=None)
@given(st.one_of(st.text(max_size=80), st.text(alphabet="0123456789abcdefABCDEF: \t", max_size=80)))
def test_parse_pin_is_total(text):
    """Any text: a lower-case hex pin of 8..64 digits, None (blank), or MalformedDigestError."""
    try:
        pin = parse_pin(text, file="f.hcdf", line=1)
    except MalformedDigestError as exc:
        assert exc.exit_code == 3 and exc.actual == text
        return
    if pin is None:
        assert not text.strip()
        return
    assert MIN_WEAK_HEX <= len(pin.hex) <= FULL_HEX
    assert pin.hex == pin.hex.lower() and set(pin.hex) <= set("0123456789abcdef")
    assert pin.hex in text.lower()


@settings(max_examples=300, deadline=None, database=None)
@given(
    st.one_of(
        st.binary(max_size=300),
        st.builds(
            lambda a, b: a + b,
            st.sampled_from(
                [b"<hcdf>", b'<?xml version="1.0"?><hcdf', b"<!DOCTYPE hcdf [", b"\xef\xbb\xbf<hcdf", b"\xff\xfe<\x00"]
            ),
            st.binary(max_size=200),
        ),
    )
)
def test_parse_bytes_is_total(data):
    """Any bytes: a tree without a DOCTYPE, or XmlError. Never another exception."""
    try:
        tree = parse_bytes(data, source="x.hcdf")
    except XmlError as exc:
        assert exc.exit_code == 3
        return
    assert tree.docinfo.doctype == ""


@settings(max_examples=300, deadline=None, database=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    uri=st.one_of(
        st.sampled_from(INTERESTING), st.text(alphabet="./%2e%2fEF\\:abc-_", max_size=40), st.text(max_size=40)
    )
)
def test_locator_never_leaves_the_root(tmp_path, uri):
    """Any uri: an InputError, a remote URL, or a local path inside the root (lexically)."""
    root = tmp_path / "root"
    doc = root / "sub" / "doc.hcdf"
    loc_doc = Locator.create(root=root).for_document(doc)
    try:
        loc = Locator.create(root=root).locate(uri, loc_doc, file="doc.hcdf", line=1)
    except (PathEscapeError, InputError):
        return
    if loc.is_local:
        real = os.path.normpath(loc.path)
        assert real == str(root) or real.startswith(str(root) + os.sep), (uri, loc)
        assert loc.url.startswith(file_url(root))
    else:
        assert loc.scheme in ("https", "http"), (uri, loc)
