"""An independent oracle for the reference walker (hcdf_trust/document.py).

For every HCDF document of the corpus and of the example robot, the references
``Document.references()`` yields must be exactly those a plain XPath 1.0 query,
written here without any of document.py's helpers, selects: same kind, line,
location and digest, in document order. The query states the walker's contract
in one expression, so a reference the walker skipped (or invented) shows up as a
difference on real files.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from lxml import etree

from hcdf_trust.document import Document
from hcdf_trust.errors import XmlError

from .conftest import CORPUS, PROJECT

ROBOT = PROJECT / "examples" / "robot"

# Vendor content: the inside of an <extension> child of <comp>. Unprefixed names in
# XPath 1.0 select elements in no namespace only, as HCDF elements are.
OPAQUE = "ancestor::extension[parent::comp]"
REFERENCES = etree.XPath(
    " | ".join(
        [
            f"//include[not({OPAQUE})]",
            f"//model[not({OPAQUE})]",
            f"//mesh[(@uri or @href or parent::geometry) and not({OPAQUE})]",
            f"//stream-profile[(@uri or @href or parent::network) and not({OPAQUE})]",
            f"//software/hash[not({OPAQUE})]",
            f"//firmware-manifest-uri[normalize-space(.) != '' and not({OPAQUE})]",
            f"//extension[not({OPAQUE})]",
        ]
    )
)
KIND = {
    "include": "include",
    "model": "model",
    "mesh": "mesh",
    "stream-profile": "stream-profile",
    "hash": "firmware",
    "firmware-manifest-uri": "firmware-manifest",
    "extension": "extension",
}
# Anything that looks like a reference, in any namespace and anywhere (extensions too).
LOOKALIKES = etree.XPath(
    "//*[local-name()='include' or local-name()='model' or local-name()='mesh' or local-name()='stream-profile' "
    "or local-name()='hash' or local-name()='firmware-manifest-uri'] | //@*[local-name()='uri' or local-name()='href']"
)


def _documents() -> list[Path]:
    paths = sorted(CORPUS.rglob("*.hcdf")) + sorted(ROBOT.rglob("*.hcdf"))
    # {device}.hcdf pointers (a symlink or a stub naming a sibling) are not documents of their own
    return [p for p in paths if not p.is_symlink() and p.read_bytes().lstrip().startswith(b"<")]


DOCUMENTS = _documents()


def _oracle(path: Path) -> list[tuple[str, int, str | None, str | None]]:
    tree = etree.parse(str(path), etree.XMLParser(resolve_entities=False, no_network=True))
    out = []
    for el in REFERENCES(tree):
        tag = el.tag
        if tag in ("hash", "firmware-manifest-uri"):
            value = el.xpath("normalize-space(.)") or None
            uri, sha = (None, value) if tag == "hash" else (value, None)
        elif tag == "extension":
            uri, sha = None, None
        else:
            uri = el.get("uri") if el.get("uri") is not None else el.get("href")
            sha = el.get("sha")
        out.append((KIND[tag], el.sourceline, uri, sha))
    return out


def _well_formed(path: Path) -> bool:
    try:
        etree.parse(str(path), etree.XMLParser(resolve_entities=False, no_network=True))
    except etree.XMLSyntaxError:
        return False
    return True


def test_the_corpus_and_the_robot_are_there():
    names = {p.name for p in DOCUMENTS}
    assert {"humanoid-mobile-base.hcdf", "drone-quadrotor.hcdf", "navq95_system.hcdf", "robot.hcdf"} <= names
    assert sum(1 for p in DOCUMENTS if "hcdf_models" in p.parts) >= 5


@pytest.mark.parametrize("path", DOCUMENTS, ids=lambda p: str(p.relative_to(p.parents[2])))
def test_walker_finds_exactly_what_the_xpath_oracle_finds(path):
    if not _well_formed(path):
        with pytest.raises(XmlError):
            Document.from_bytes(path.read_bytes(), source=path.name)
        return
    doc = Document.from_bytes(path.read_bytes(), source=path.name)  # no real file is refused
    got = [(r.kind.value, r.line, r.uri, r.sha) for r in doc.references()]
    assert got == _oracle(path)


def test_the_oracle_sees_every_kind_and_every_lookalike_on_real_files():
    """The comparison above means something: the real files hold every kind of reference,
    and no reference-like element or attribute of theirs lies outside what the query selects."""
    kinds: set[str] = set()
    total = 0
    for path in DOCUMENTS:
        if not _well_formed(path):
            continue
        found = _oracle(path)
        kinds |= {kind for kind, *_ in found}
        total += len(found)
        tree = etree.parse(str(path))
        selected = set(REFERENCES(tree))
        for item in LOOKALIKES(tree):
            el = item if isinstance(item, etree._Element) else item.getparent()
            if el.tag == "stream-profile" and el.getparent() is None:
                continue  # a stream-profile document's root is not a reference
            inside_vendor_content = bool(el.xpath(OPAQUE))
            assert el in selected or inside_vendor_content, f"{path}:{el.sourceline}: <{el.tag}> not selected"
    assert kinds == set(KIND.values())
    assert total >= 40
