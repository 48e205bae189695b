"""validate --registry: schemas per version from the registry, extension and stream-profile checks."""

from __future__ import annotations

import shutil

import pytest

from tests._registry import PASSPHRASE, PROFILE, serve_corpus_registry
from tests.conftest import HCDFORMAT


@pytest.fixture(autouse=True)
def _passphrase(monkeypatch):
    monkeypatch.setenv("HCDF_TRUST_PASSPHRASE", PASSPHRASE)


@pytest.fixture(scope="module")
def published(tmp_path_factory):
    """A registry with the corpus's domains, profile and core schemas, served on 127.0.0.1."""
    with serve_corpus_registry(tmp_path_factory.mktemp("reg"), core_schemas=True) as served:
        yield served


def _validate(cli, published, doc, *extra):
    reg, srv = published
    return cli("validate", doc, "--registry", srv.base, "--trusted-root", reg.root_json, "--json", *extra)


def test_upstream_valid_files_validate_against_the_registered_schema(cli, published):
    for doc in sorted((HCDFORMAT / "tests" / "valid").glob("*.hcdf")):
        res = _validate(cli, published, doc)
        assert res.exit_code == 0, (doc.name, res.stdout)
        assert res.json["schema"] == "registry:schemas/hcdf/1.0.xsd"
        assert "registry" in res.json["checked"]


def test_upstream_invalid_files_fail_with_their_expected_message(cli, published):
    for doc in sorted((HCDFORMAT / "tests" / "invalid").glob("*.hcdf")):
        expected = doc.with_suffix(".expected").read_text().strip()
        res = _validate(cli, published, doc)
        assert res.exit_code in (1, 3), doc.name  # 3: not well-formed (wrong-version-type.hcdf)
        assert any(expected in f["message"] for f in res.json["errors"]), (doc.name, expected)


def test_a_version_with_no_registered_schema_is_noted(cli, published, tmp_path):
    doc = tmp_path / "v9.hcdf"
    doc.write_text('<hcdf version="9.9"><comp name="a"/></hcdf>')
    res = _validate(cli, published, doc)
    assert res.json["schema"] is None
    assert any("no schema is known for <hcdf> version 9.9" in n for n in res.json["notes"])


def test_stream_profile_validates_against_the_registered_profile_schema(cli, published):
    res = _validate(cli, published, PROFILE)
    assert res.exit_code == 0, res.stdout
    assert res.json["schema"] == "registry:schemas/hcdf-stream-profile/1.0.xsd"


def test_unregistered_extension_domain_is_a_warning_and_an_error_with_strict(cli, published):
    doc = HCDFORMAT / "tests" / "valid" / "extension-only.hcdf"  # domain="gazebo"
    res = _validate(cli, published, doc)
    assert res.exit_code == 0
    (warning,) = [f for f in res.json["findings"] if f["code"] == "extension-unregistered"]
    assert warning["severity"] == "warning" and "'gazebo' is not registered" in warning["message"]
    assert warning["line"] == 4
    res = _validate(cli, published, doc, "--strict")
    assert res.exit_code == 1
    assert [f["code"] for f in res.json["errors"]] == ["extension-unregistered"]


def test_unregistered_extension_version(cli, published, tmp_path):
    doc = tmp_path / "x.hcdf"
    doc.write_text('<hcdf version="1.0" name="x"><comp name="a">\n'
                   '<extension domain="org.ros2" version="7.0"><topic-map/></extension></comp></hcdf>')  # fmt: skip
    res = _validate(cli, published, doc, "--strict")
    assert res.exit_code == 1
    (err,) = res.json["errors"]
    assert "org.ros2 version '7.0' is not registered (registered: 1.0)" in err["message"] and err["line"] == 2


def test_extension_content_is_validated_against_the_registered_schema(cli, published, tmp_path):
    good = '<topic sensor="imu0" name="/imu" type="sensor_msgs/msg/Imu" qos="sensor_data"/>'
    bad = '<topic sensor="imu0" name="/imu" type="sensor_msgs/msg/Imu" qos="warp_speed"/>'
    for topic, ok in ((good, True), (bad, False)):
        doc = tmp_path / "x.hcdf"
        doc.write_text(f'<hcdf version="1.0" name="x"><comp name="a">\n<extension domain="org.ros2" version="1.0">'
                       f"<topic-map>\n{topic}</topic-map></extension></comp></hcdf>")  # fmt: skip
        res = _validate(cli, published, doc)
        assert (res.exit_code == 0) is ok, res.stdout
        if not ok:
            (err,) = res.json["errors"]
            assert err["code"] == "extension-content" and "warp_speed" in err["message"] and err["line"] == 3


def test_corpus_drone_gazebo_extension_does_not_match_its_schema(cli, published):
    """A real finding: the drone example writes <physics>/<plugin>, the gazebo schema's root is <gazebo-sim>."""
    res = _validate(cli, published, HCDFORMAT / "examples" / "drone-quadrotor.hcdf")
    content = [f for f in res.json["errors"] if f["code"] == "extension-content"]
    assert {f["message"] for f in content} == {
        "<physics> is not an element of the org.gazebosim 1.0 schema",
        "<plugin> is not an element of the org.gazebosim 1.0 schema",
    }
    assert not [f for f in res.json["findings"] if f["code"] == "extension-unregistered"]


def test_registered_stream_profile_digest_is_enforced(cli, published, tmp_path):
    robot = tmp_path / "robot"
    (robot / "profiles").mkdir(parents=True)
    shutil.copy(HCDFORMAT / "examples" / "humanoid-mobile-base.hcdf", robot)
    shutil.copy(PROFILE, robot / "profiles")
    doc = robot / "humanoid-mobile-base.hcdf"
    res = _validate(cli, published, doc)
    assert not [f for f in res.json["findings"] if f["code"].startswith("stream-profile")]
    profile = robot / "profiles" / PROFILE.name
    profile.write_bytes(profile.read_bytes().replace(b'max-latency-us="200"', b'max-latency-us="900"', 1))
    res = _validate(cli, published, doc)
    assert res.exit_code == 1
    errors = [f for f in res.json["errors"] if f["code"] == "stream-profile-digest"]
    assert len(errors) == 2  # the profile is referenced from two networks
    assert "(operational 1.0) differs from the registered one" in errors[0]["message"]


def test_registry_needs_a_trusted_root(cli, published):
    reg, srv = published
    res = cli("validate", PROFILE, "--registry", srv.base)
    assert res.exit_code == 2 and "--trusted-root" in res.stderr


def test_a_json_document_is_read_through_the_registered_core_schema(cli, published, monkeypatch):
    """No --schema: the registry's hcdf 1.0 schema reads the drone's JSON form too; its findings
    are located by JSON Pointer (the JSON revision lacks the root's required name)."""
    monkeypatch.delenv("HCDF_TRUST_SCHEMA", raising=False)
    res = _validate(cli, published, HCDFORMAT / "examples" / "drone-quadrotor.json")
    assert res.json["schema"] == "registry:schemas/hcdf/1.0.xsd", res.stdout
    xsd = [f for f in res.json["errors"] if f["code"] == "xsd"]
    assert [(f["pointer"], f["line"]) for f in xsd] == [("/hcdf", None)] and "'name' is required" in xsd[0]["message"]
    content = [f for f in res.json["errors"] if f["code"] == "extension-content"]
    assert content and all(f["pointer"].startswith("/hcdf/comp/1/extension/1") for f in content)
