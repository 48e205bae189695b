"""``validate`` names the schema it used by path *and* SHA-256, as upstream binds tooling to a
schema by digest (hcdformat ``versions/HASHES``: three different 1.0 ``hcdf.xsd`` byte strings
exist; the corpus holds two of them). ``--schema`` is repeatable.

Oracle: hashlib over the XSD files on disk.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

from tests.conftest import HCDFORMAT

XSD = HCDFORMAT / "hcdf.xsd"
OLDER = HCDFORMAT / "versions" / "1.0" / "hcdf.xsd"  # the copy upstream calls drifted
PROFILE_XSD = HCDFORMAT / "hcdf-stream-profile.xsd"
DRONE = HCDFORMAT / "examples" / "drone-quadrotor.hcdf"
PROFILE = HCDFORMAT / "examples" / "profiles" / "operational.streams.xml"


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_report_names_path_and_digest(cli):
    r = cli("validate", DRONE, "--schema", XSD, "--json")
    assert r.exit_code == 0, r.stdout
    assert r.json["schema"].endswith("hcdformat/hcdf.xsd")
    assert r.json["schema_sha256"] == sha(XSD)
    r = cli("validate", DRONE, "--schema", XSD)
    assert f"validated against {XSD} (sha256 {sha(XSD)})" in r.stderr
    # the drifted copy validates the same document, and the report says which one it was
    r = cli("validate", DRONE, "--schema", OLDER, "--json")
    assert r.json["schema_sha256"] == sha(OLDER) != sha(XSD)


def test_no_schema_no_digest(cli):
    r = cli("validate", DRONE, "--json")
    assert r.json["schema"] is None and r.json["schema_sha256"] is None


def test_several_schemas_the_one_that_declares_the_root(cli):
    for doc, used in ((DRONE, XSD), (PROFILE, PROFILE_XSD)):
        r = cli("validate", doc, "--schema", PROFILE_XSD, "--schema", XSD, "--json")
        assert r.exit_code == 0, r.stdout
        assert r.json["schema_sha256"] == sha(used), doc.name
        assert r.json["schema"].endswith(used.name)
    # the same file twice is one schema
    r = cli("validate", DRONE, "--schema", XSD, "--schema", XSD, "--json")
    assert r.exit_code == 0 and r.json["schema_sha256"] == sha(XSD)


def test_several_schemas_by_the_documents_major_version(cli, tmp_path):
    two = tmp_path / "v2" / "hcdf.xsd"
    two.parent.mkdir()
    text = XSD.read_text()
    head = text.index("<xs:schema")
    assert 'version="1.0"' in text[head : text.index(">", head)]
    two.write_text(text[:head] + text[head:].replace('version="1.0"', 'version="2.0"', 1))
    doc2 = tmp_path / "two.hcdf"
    doc2.write_text('<hcdf version="2.0" name="x"><comp name="a"/></hcdf>\n')
    doc1 = tmp_path / "one.hcdf"
    doc1.write_text('<hcdf version="1.0" name="x"><comp name="a"/></hcdf>\n')
    for doc, used in ((doc2, two), (doc1, XSD)):
        r = cli("validate", doc, "--schema", XSD, "--schema", two, "--json")
        assert r.json["schema_sha256"] == sha(used), (doc.name, r.stdout)


def test_two_schemas_that_both_fit_are_refused(cli):
    """Which of two 1.0 hcdf.xsd validates the document is the user's choice, not argument order."""
    r = cli("validate", DRONE, "--schema", XSD, "--schema", OLDER)
    assert r.exit_code == 2, r.stdout + r.stderr
    assert sha(XSD) in r.stderr and sha(OLDER) in r.stderr
