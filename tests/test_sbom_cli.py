"""`hcdf-trust sbom` fails closed: a tree that does not verify, a release of another tree or
signed by another key, an output that is an input; and it starts without the SBOM libraries."""

from __future__ import annotations

import shutil

import pytest

from tests.conftest import PROJECT
from tests.test_startup import _modules_after

ROBOT = PROJECT / "examples" / "robot"
SBOM_LIBS = {"cyclonedx", "spdx_python_model", "license_expression", "jsonschema", "hcdf_trust.sbom.model"}


@pytest.fixture
def robot(tmp_path):
    shutil.copytree(ROBOT, tmp_path / "robot")
    return tmp_path / "robot"


@pytest.fixture
def release(cli, robot, tmp_path):
    key = tmp_path / "k.pem"
    assert cli("ota", "keygen", "-o", key).exit_code == 0
    out = tmp_path / "release"
    r = cli("ota", "build", robot / "robot.hcdf", "--firmware-dir", robot / "firmware", "--key", key, "--out", out)
    assert r.exit_code == 0, r.stderr
    return out, tmp_path / "k.pub.pem"


def test_start_up_does_not_import_the_sbom_libraries():
    for args in (("--version",), ("sbom", "--help")):
        code, modules = _modules_after(*args)
        assert code == 0
        assert not {m.split(".")[0] for m in modules} & SBOM_LIBS, args
        assert "hcdf_trust.sbom.model" not in modules


def test_release_needs_its_key(cli, robot, release):
    out, _pub = release
    r = cli("sbom", robot / "robot.hcdf", "--format", "cyclonedx", "--release", out)
    assert r.exit_code == 2 and "--key" in r.stderr


def test_release_of_another_tree_is_refused(cli, robot, release):
    out, pub = release
    doc = robot / "robot.hcdf"
    # the root document is not in the lock: only the release's root digest tells the trees apart
    doc.write_text(doc.read_text().replace("hcdf-trust example robot", "another robot"))
    r = cli("sbom", doc, "--format", "cyclonedx", "--release", out, "--key", pub, "-o", robot / "bom.json")
    assert r.exit_code == 1, r.stderr
    assert "another root document" in r.stderr and "release.suit" in r.stderr
    assert not (robot / "bom.json").exists() and r.stdout == ""


def test_release_signed_by_another_key_is_refused(cli, robot, release, tmp_path):
    out, _pub = release
    assert cli("ota", "keygen", "-o", tmp_path / "other.pem").exit_code == 0
    r = cli("sbom", robot / "robot.hcdf", "--format", "spdx", "--release", out, "--key", tmp_path / "other.pub.pem")
    assert r.exit_code == 1 and "signed by another key" in r.stderr and r.stdout == ""


def test_tampered_release_image_is_refused(cli, robot, release):
    out, pub = release
    image = out / "scout2_arm" / "arm-ctrl" / "1.4.2.bin"
    data = bytearray(image.read_bytes())
    data[-1] ^= 1
    image.write_bytes(bytes(data))
    r = cli("sbom", robot / "robot.hcdf", "--format", "cyclonedx", "--release", out, "--key", pub)
    assert r.exit_code == 1 and "scout2_arm/arm-ctrl" in r.stderr and r.stdout == ""


def test_a_tree_that_does_not_verify_is_refused(cli, robot):
    (robot / "models" / "arm-link.glb").write_bytes(b"not the model")
    r = cli("sbom", robot / "robot.hcdf", "--format", "cyclonedx", "-o", robot / "bom.json")
    assert r.exit_code == 1 and "arm-link.glb" in r.stderr
    assert not (robot / "bom.json").exists()


def test_no_lock_is_refused(cli, robot):
    (robot / "robot.hcdf.lock").unlink()
    r = cli("sbom", robot / "robot.hcdf", "--format", "spdx")
    assert r.exit_code == 3 and "robot.hcdf.lock" in r.stderr and r.stdout == ""


@pytest.mark.parametrize(
    "target", ["robot.hcdf", "robot.hcdf.lock", "models/arm-link.glb", "assemblies/arm.hcdf", "release/release.suit"]
)
def test_output_onto_an_input_is_refused(cli, robot, release, target):
    out, pub = release
    path = out.parent / target if target.startswith("release/") else robot / target
    before = path.read_bytes()
    r = cli("sbom", robot / "robot.hcdf", "--format", "cyclonedx", "--release", out, "--key", pub, "-o", path)
    assert r.exit_code == 3, r.stderr
    assert "refusing" in r.stderr or "input" in r.stderr
    assert path.read_bytes() == before


def test_software_without_a_name_is_refused(cli, tmp_path):
    (tmp_path / "r.hcdf").write_text('<hcdf version="1.0" name="r"><comp name="c"><software/></comp></hcdf>')
    assert cli("resolve", tmp_path / "r.hcdf").exit_code == 0
    r = cli("sbom", tmp_path / "r.hcdf", "--format", "cyclonedx")
    assert r.exit_code == 3 and "r.hcdf:1" in r.stderr and "no name" in r.stderr


def test_a_tree_that_multiplies_past_the_limit_is_refused(cli, monkeypatch):
    from hcdf_trust.sbom import model

    monkeypatch.setattr(model, "MAX_COMPONENTS", 6)  # the robot: 8 comps in 3 sub-assemblies
    r = cli("sbom", ROBOT / "robot.hcdf", "--format", "cyclonedx")
    assert r.exit_code == 3 and "more than 6" in r.stderr and r.stdout == ""


def test_firmware_the_release_does_not_list_has_no_signer(cli, robot, tmp_path):
    import json

    config = tmp_path / "ota.toml"
    config.write_text((robot / "ota.toml").read_text().replace('type = "raw"', 'type = "raw"\nexclude = true'))
    assert cli("ota", "keygen", "-o", tmp_path / "k.pem").exit_code == 0
    out = tmp_path / "release"
    r = cli(
        "ota", "build", robot / "robot.hcdf", "--firmware-dir", robot / "firmware", "--key", tmp_path / "k.pem",
        "--out", out, "--config", config,
    )  # fmt: skip
    assert r.exit_code == 0, r.stderr
    r = cli("sbom", robot / "robot.hcdf", "--format", "cyclonedx", "--release", out, "--key", tmp_path / "k.pub.pem")
    assert r.exit_code == 0, r.stderr
    assert "compute/scout-os is not in the release" in r.stderr
    comps = {c["bom-ref"]: c for c in json.loads(r.stdout)["components"]}
    signed = {
        ref
        for ref, c in comps.items()
        if any(p["name"] == "hcdf:signature:key-sha256" for p in c.get("properties", []))
    }
    assert signed == {"firmware/scout2_arm/arm-ctrl@1.4.2"}


def test_names_that_could_collide_or_break_an_iri_give_distinct_valid_refs(cli, tmp_path):
    """Comps named alike, unnamed comps and includes, '/' '#' '%' and spaces in names: every
    comp and instance is listed once, under a ref that is also a valid IRI path."""
    import json
    import re

    from tests._sbom import spdx_graph, validate_cyclonedx, validate_spdx

    (tmp_path / "r.hcdf").write_text(
        '<hcdf version="1.0" name="r">'
        '<comp name="a b#c?d%e"><board>b/1</board><software name="fw 1"><version>1.0</version></software></comp>'
        '<comp name="b"><board>b</board><software name="1/fw 1"><version>1.0</version></software></comp>'
        '<comp/><comp/><comp name="x"/><comp name="x"/>'
        '<include uri="s.hcdf"/><include uri="s.hcdf" name="n"/><include uri="s.hcdf" name="n"/></hcdf>'
    )
    (tmp_path / "s.hcdf").write_text('<hcdf version="1.0" name="s"><comp name="c"/></hcdf>')
    assert cli("resolve", tmp_path / "r.hcdf").exit_code == 0
    r = cli("sbom", tmp_path / "r.hcdf", "--format", "cyclonedx")
    assert r.exit_code == 0, r.stderr
    validate_cyclonedx(r.stdout)
    components = json.loads(r.stdout)["components"]
    kinds = [c["type"] for c in components]
    # 6 comps of r, 3 instances of s with one comp each, 2 firmware (b/1 + "fw 1" is not b + "1/fw 1")
    assert (kinds.count("device"), kinds.count("firmware")) == (6 + 3 + 3, 2)
    assert len({c["bom-ref"] for c in components}) == len(components)
    data = cli("sbom", tmp_path / "r.hcdf", "--format", "spdx").stdout.encode()
    validate_spdx(data)
    elements, _ = spdx_graph(data)
    for element in elements.values():
        assert re.fullmatch(r"https://[A-Za-z0-9._~%/@:-]+", element["spdxId"]), element["spdxId"]
