"""The offline run of the official SPDX 3 validator is a real oracle: it refuses what
spdx.org's 3.0.1 schema or shapes refuse, and it never reaches the network."""

from __future__ import annotations

import json

import pytest

from tests._spdx3 import SERVED, _offline, spdx3_validate
from tests.conftest import PROJECT


@pytest.fixture(scope="module")
def robot_spdx() -> dict:
    from click.testing import CliRunner

    from hcdf_trust.cli import main

    r = CliRunner().invoke(main, ["sbom", str(PROJECT / "examples/robot/robot.hcdf"), "--format", "spdx"])
    assert r.exit_code == 0, r.stderr
    return json.loads(r.stdout)


def _doc(data: dict) -> dict:
    return next(o for o in data["@graph"] if o["type"] == "SpdxDocument")


def test_extension_profile_is_refused_by_the_shacl_stage(robot_spdx):
    """What `sbom --format spdx` wrote before: "extension" expands to the Core `extension`
    property (a term of the 3.0.1 context), not to the profile."""
    assert spdx3_validate(json.dumps(robot_spdx).encode()) == []
    data = json.loads(json.dumps(robot_spdx))
    _doc(data)["profileConformance"].append("extension")
    errors = spdx3_validate(json.dumps(data).encode())
    assert errors and all(e.startswith("[shacl]") for e in errors), errors
    assert "Core/profileConformance" in errors[0]
    assert "Value Node: <https://spdx.org/rdf/3.0.1/terms/Core/extension>" in errors[0]


def test_the_compact_profile_iri_is_refused_by_the_json_schema(robot_spdx):
    """The IRI that would expand to the Extension profile is not a value the schema allows:
    no spelling of the profile passes both stages, so it is left out."""
    data = json.loads(json.dumps(robot_spdx))
    _doc(data)["profileConformance"].append("spdx:Core/ProfileIdentifierType/extension")
    errors = spdx3_validate(json.dumps(data).encode())
    assert errors and all(e.startswith("[schema]") for e in errors), errors


def test_a_missing_required_property_is_refused(robot_spdx):
    data = json.loads(json.dumps(robot_spdx))
    package = next(o for o in data["@graph"] if o["type"] == "software_Package")
    del package["creationInfo"]
    assert spdx3_validate(json.dumps(data).encode())


def test_only_the_three_spec_urls_are_answered():
    import urllib.error
    import urllib.request

    with _offline():
        for url in SERVED:
            with urllib.request.urlopen(url) as f:
                assert f.read(1)
        with pytest.raises(urllib.error.URLError, match="refusing"):
            urllib.request.urlopen("https://spdx.org/rdf/3.0.1/terms/Core/Element")
        with pytest.raises(urllib.error.URLError, match="refusing"):
            urllib.request.urlopen("file:///etc/passwd")
