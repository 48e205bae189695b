"""`hcdf-trust sbom` on the example robot and the corpus drone: the expectations below were
written by reading the HCDF files (examples/robot, ../shared/corpus/hcdformat/examples),
then checked against each format's own validator."""

from __future__ import annotations

import hashlib
import json
import shutil

import pytest

from tests._sbom import (
    cdx_components,
    cdx_graph,
    cdx_props,
    cdx_sha256,
    spdx_graph,
    spdx_props,
    validate_cyclonedx,
    validate_spdx,
)
from tests.conftest import HCDFORMAT, PROJECT

ROBOT = PROJECT / "examples" / "robot"
DRONE = HCDFORMAT / "examples" / "drone-quadrotor.hcdf"

# from examples/robot: the include pins and the lock file's entries
ARM_SHA = "3bb8be3b7a2a83776bbc5187189b1900c12f18f82aa666f4f471940a152c0693"
HEAD_SHA = "05127d6d18e18a2514b1bb778c784a9d21efe77aceb93cc3b7c6deb78ab51d37"
FILES = {
    "file/models/chassis.glb": "14662db9eb3db5be8bc90a5a14deb58563ef31e605e14dd598b5a6341163f22f",
    "file/meshes/chassis-hull.stl": "6ac1a9aa6a7ccf8c5f72269e697d7721f7e1914243d220a91cb3ceb016b3bc4d",
    "file/models/arm-link.glb": "8b2f0ebf68f1d46ea7ae6dc4384080ef0cf5de2828bc7396265e0c34111a2ac7",
    # written as the weak pin adaa3b07 in arm.hcdf; the lock holds the full digest
    "file/models/gripper.glb": "adaa3b076b88becda44d529ac2c0d1f1fa34a31b80ccdb5ea12dcea241c668b1",
    "file/models/camera-head.glb": "5f3fa4f7649dbf775c2faa6c68bcc5cb5fa9cc88f18ed275a82363f9b7a5c7b7",
    "file/profiles/operational.streams.xml": "03afc225badfc099817aa1a31bdc719a761d211f23f35f178da6583b2e514039",
    "file/firmware/arm-ctrl.latest.json": "83663e8b3d733668f11bbffc86b1e54a785ae9442b436a1fbf0027dff8b89fd5",
}
ARM_HASH = "856a8b3415ed27a14eadd2e320ad44797baa05efe4f89ee008e22a24eb81f75a"  # arm.hcdf <software><hash>
ARM_FW = "firmware/scout2_arm/arm-ctrl@1.4.2"
OS_FW = "firmware/compute/scout-os@2026.11"  # compute has no <board>: keyed by its name, as ota build does
GRAPH = {
    "robot": {"assembly/left_arm", "assembly/right_arm", "assembly/head", "comp/compute",
              "file/profiles/operational.streams.xml"},
    "comp/compute": {"file/models/chassis.glb", "file/meshes/chassis-hull.stl", OS_FW},
    "assembly/head": {"comp/head/camera"},
    "comp/head/camera": {"file/models/camera-head.glb"},
    ARM_FW: {"file/firmware/arm-ctrl.latest.json"},
    OS_FW: set(),
    **{ref: set() for ref in FILES},
}  # fmt: skip
for side in ("left_arm", "right_arm"):
    GRAPH[f"assembly/{side}"] = {f"comp/{side}/shoulder", f"comp/{side}/forearm", f"comp/{side}/gripper"}
    GRAPH[f"comp/{side}/shoulder"] = {"file/models/arm-link.glb", ARM_FW}
    GRAPH[f"comp/{side}/forearm"] = {"file/models/arm-link.glb"}
    GRAPH[f"comp/{side}/gripper"] = {"file/models/gripper.glb"}


def sbom(cli, doc, fmt: str, *extra) -> bytes:
    r = cli("sbom", doc, "--format", fmt, *extra)
    assert r.exit_code == 0, r.stderr
    return r.stdout.encode()


def test_example_robot_cyclonedx(cli):
    text = sbom(cli, ROBOT / "robot.hcdf", "cyclonedx")
    validate_cyclonedx(text.decode())
    bom = json.loads(text)
    assert bom["specVersion"] == "1.6"
    comps = cdx_components(bom)
    assert cdx_graph(bom) == GRAPH
    assert set(comps) == set(GRAPH)
    robot = bom["metadata"]["component"]
    assert (robot["type"], robot["name"], robot["description"]) == ("device", "scout2", "hcdf-trust example robot")
    assert robot["licenses"] == [{"license": {"id": "Apache-2.0"}}] and "authors" not in robot
    assert cdx_sha256(robot) == hashlib.sha256((ROBOT / "robot.hcdf").read_bytes()).hexdigest()
    # the arm is included twice: two sub-assemblies, one file digest, neither with author or license
    for ref, sha, name, instance in (
        ("assembly/left_arm", ARM_SHA, "scout2-arm", "left_arm"),
        ("assembly/right_arm", ARM_SHA, "scout2-arm", "right_arm"),
        ("assembly/head", HEAD_SHA, "scout2-head", "head"),
    ):
        c = comps[ref]
        assert (c["type"], c["name"], cdx_sha256(c), cdx_props(c)["hcdf:instance"]) == ("device", name, sha, instance)
        assert "licenses" not in c and "authors" not in c
    # comps are devices named as the flattened document names them, with their board
    for side in ("left_arm", "right_arm"):
        shoulder = comps[f"comp/{side}/shoulder"]
        assert (shoulder["type"], shoulder["name"]) == ("device", f"{side}_shoulder")
        assert cdx_props(shoulder)["hcdf:board"] == "scout2_arm"
        assert cdx_props(shoulder)["hcdf:file"] == "assemblies/arm.hcdf:6"
        assert "hcdf:board" not in cdx_props(comps[f"comp/{side}/forearm"])
    assert comps["comp/head/camera"]["name"] == "head_camera"
    assert "hcdf:board" not in cdx_props(comps["comp/compute"])
    # firmware: once per (board, name, version), the MCUboot hash as written; no release, no signer
    arm = comps[ARM_FW]
    assert (arm["type"], arm["name"], arm["version"]) == ("firmware", "arm-ctrl", "1.4.2")
    assert cdx_props(arm) == {"hcdf:board": "scout2_arm", "hcdf:mcuboot-hash": ARM_HASH}
    assert "hashes" not in arm  # the MCUboot hash is not the file's SHA-256
    scout_os = comps[OS_FW]
    assert (scout_os["name"], scout_os["version"], cdx_props(scout_os)) == (
        "scout-os",
        "2026.11",
        {"hcdf:board": "compute"},
    )
    for ref, sha in FILES.items():
        assert (comps[ref]["type"], cdx_sha256(comps[ref])) == ("file", sha)
    assert not [c for c in comps.values() if c["type"] == "device-driver"]  # the example has no <driver>
    assert (
        cdx_props({"properties": bom["metadata"]["properties"]})["hcdf:lock-sha256"]
        == hashlib.sha256((ROBOT / "robot.hcdf.lock").read_bytes()).hexdigest()
    )


def test_example_robot_spdx(cli):
    data = sbom(cli, ROBOT / "robot.hcdf", "spdx")
    validate_spdx(data)
    doc = json.loads(data)
    assert doc["@context"] == "https://spdx.org/rdf/3.0.1/spdx-context.jsonld"
    elements, rels = spdx_graph(data)
    contains = {src: to for (src, kind), to in rels.items() if kind == "contains"}
    assert contains == {ref: deps for ref, deps in GRAPH.items() if deps}
    packages = {k: v for k, v in elements.items() if v["type"] in ("software_Package", "software_File")}
    assert set(packages) == set(GRAPH)
    purposes = {k: v["software_primaryPurpose"] for k, v in packages.items()}
    assert {k for k, v in purposes.items() if v == "firmware"} == {ARM_FW, OS_FW}
    devices = {r for r in GRAPH if r.split("/")[0] in ("robot", "assembly", "comp")}
    assert {k for k, v in purposes.items() if v == "device"} == devices
    for ref, sha in FILES.items():
        assert packages[ref]["type"] == "software_File"
        assert packages[ref]["verifiedUsing"] == [{"type": "Hash", "algorithm": "sha256", "hashValue": sha}]
    assert packages["assembly/left_arm"]["verifiedUsing"][0]["hashValue"] == ARM_SHA
    assert packages[ARM_FW]["software_packageVersion"] == "1.4.2"
    assert spdx_props(packages[ARM_FW])["hcdf:mcuboot-hash"] == ARM_HASH
    assert spdx_props(packages["comp/left_arm/shoulder"])["hcdf:board"] == "scout2_arm"
    # the robot's <license>, declared; no sub-assembly has one
    licensed = {src for (src, kind) in rels if kind == "hasDeclaredLicense"}
    assert licensed == {"robot"}
    (lic,) = rels[("robot", "hasDeclaredLicense")]
    assert elements[lic]["simplelicensing_licenseExpression"] == "Apache-2.0"
    sbom_el = next(v for v in elements.values() if v["type"] == "software_Sbom")
    assert sbom_el["rootElement"][0].endswith("/robot")


def test_corpus_drone(cli, tmp_path):
    """The drone has no references but <author>, <license>, one <software> and six sensor drivers."""
    lock = tmp_path / "drone.lock"
    assert cli("resolve", DRONE, "--lock", lock).exit_code == 0
    text = sbom(cli, DRONE, "cyclonedx", "--lock", lock)
    validate_cyclonedx(text.decode())
    bom = json.loads(text)
    comps = cdx_components(bom)
    robot = bom["metadata"]["component"]
    assert (robot["name"], robot["authors"], robot["licenses"]) == (
        "cogni-quadrotor",
        [{"name": "CogniPilot Foundation"}],
        [{"license": {"id": "Apache-2.0"}}],
    )
    names = ["frame", "navq95", "mcxn_rtk_gnss", "mcxn_optical_flow", "battery", "pdb"]
    names += [f"{kind}_{pos}" for kind in ("esc", "motor") for pos in ("fl", "fr", "rl", "rr")]
    assert {c["name"] for c in comps.values() if c["bom-ref"].startswith("comp/")} == set(names)
    boards = {c["name"]: cdx_props(c).get("hcdf:board") for c in comps.values() if c["bom-ref"].startswith("comp/")}
    assert {k: v for k, v in boards.items() if v} == {
        "navq95": "navq95",
        **{f"esc_{p}": "am32-esc-35a" for p in ("fl", "fr", "rl", "rr")},
        "mcxn_rtk_gnss": "mr-mcxn-t1",
        "mcxn_optical_flow": "mr-mcxn-t1",
    }
    drivers = {c["name"] for c in comps.values() if c["type"] == "device-driver"}
    assert drivers == {"imx219", "ubx-f9p", "paa3905", "icm45686", "bmm350", "bmp581"}
    fw = [c for c in comps.values() if c["type"] == "firmware"]
    assert [(c["name"], c["version"], cdx_props(c)) for c in fw] == [("cerebri", "1.0.0", {"hcdf:board": "navq95"})]
    graph = cdx_graph(bom)
    assert graph["comp/navq95"] == {"firmware/navq95/cerebri@1.0.0", "driver/imx219"}
    assert graph["comp/mcxn_rtk_gnss"] == {"driver/ubx-f9p"}
    assert graph["comp/mcxn_optical_flow"] == {f"driver/{d}" for d in ("paa3905", "icm45686", "bmm350", "bmp581")}
    assert graph["robot"] == {f"comp/{n}" for n in names}
    assert not [c for c in comps.values() if c["type"] == "file"]
    data = sbom(cli, DRONE, "spdx", "--lock", lock)
    validate_spdx(data)
    elements, _ = spdx_graph(data)
    assert {v["name"] for v in elements.values() if v.get("software_primaryPurpose") == "deviceDriver"} == drivers
    by_id = {v["spdxId"]: v for v in elements.values()}
    assert [by_id[a]["name"] for a in elements["robot"]["originatedBy"]] == ["CogniPilot Foundation"]


def _tree(tmp_path, cli, sub_author: str, sub_license: str):
    """A robot with one sub-assembly whose own root names another author and license."""
    (tmp_path / "robot.hcdf").write_text(
        '<hcdf version="1.0" name="r"><author>Root Robotics</author><license>MIT</license>'
        '<comp name="base"><board>b1</board></comp>'
        '<include uri="sub.hcdf" name="wheel"/></hcdf>'
    )
    (tmp_path / "sub.hcdf").write_text(
        f'<hcdf version="1.0" name="wheel-module"><author>{sub_author}</author><license>{sub_license}</license>'
        '<comp name="hub"><sensor name="enc"><inertial><driver name="as5600"/></inertial></sensor></comp></hcdf>'
    )
    assert cli("resolve", tmp_path / "robot.hcdf").exit_code == 0
    return tmp_path / "robot.hcdf"


def test_sub_assembly_author_and_license_come_from_its_own_root(cli, tmp_path):
    doc = _tree(tmp_path, cli, "Wheel Works GmbH", "Apache-2.0 OR MIT")
    bom = json.loads(sbom(cli, doc, "cyclonedx"))
    validate_cyclonedx(json.dumps(bom))
    comps = cdx_components(bom)
    assert comps["robot"]["authors"] == [{"name": "Root Robotics"}]
    assert comps["robot"]["licenses"] == [{"license": {"id": "MIT"}}]
    wheel = comps["assembly/wheel"]
    assert (wheel["name"], wheel["authors"]) == ("wheel-module", [{"name": "Wheel Works GmbH"}])
    assert wheel["licenses"] == [{"expression": "Apache-2.0 OR MIT"}]
    assert cdx_sha256(wheel) == hashlib.sha256((tmp_path / "sub.hcdf").read_bytes()).hexdigest()
    assert cdx_graph(bom)["comp/wheel/hub"] == {"driver/as5600"}
    assert comps["comp/wheel/hub"]["name"] == "wheel_hub"
    data = sbom(cli, doc, "spdx")
    validate_spdx(data)
    elements, rels = spdx_graph(data)
    exprs = {
        src: [elements[t]["simplelicensing_licenseExpression"] for t in to]
        for (src, kind), to in rels.items()
        if kind == "hasDeclaredLicense"
    }
    assert exprs == {"robot": ["MIT"], "assembly/wheel": ["Apache-2.0 OR MIT"]}
    by_id = {v["spdxId"]: v for v in elements.values()}
    assert [by_id[a]["name"] for a in elements["assembly/wheel"]["originatedBy"]] == ["Wheel Works GmbH"]


def test_a_license_that_is_not_an_spdx_expression(cli, tmp_path):
    doc = _tree(tmp_path, cli, "A", "Proprietary, see LICENSE.txt")
    bom = json.loads(sbom(cli, doc, "cyclonedx"))
    validate_cyclonedx(json.dumps(bom))
    assert cdx_components(bom)["assembly/wheel"]["licenses"] == [{"license": {"name": "Proprietary, see LICENSE.txt"}}]
    data = sbom(cli, doc, "spdx")
    validate_spdx(data)
    elements, rels = spdx_graph(data)
    (lic,) = rels[("assembly/wheel", "hasDeclaredLicense")]
    assert elements[lic]["simplelicensing_licenseExpression"] == "LicenseRef-Proprietary-see-LICENSE.txt"
    assert "Proprietary, see LICENSE.txt" in elements[lic]["comment"]


@pytest.mark.parametrize("fmt", ["cyclonedx", "spdx"])
def test_release_adds_the_signer(cli, tmp_path, fmt):
    robot = tmp_path / "robot"
    shutil.copytree(ROBOT, robot)
    key = tmp_path / "k.pem"
    assert cli("ota", "keygen", "-o", key).exit_code == 0
    out = tmp_path / "release"
    r = cli("ota", "build", robot / "robot.hcdf", "--firmware-dir", robot / "firmware", "--key", key, "--out", out)
    assert r.exit_code == 0, r.stderr
    from cryptography.hazmat.primitives import serialization

    public = serialization.load_pem_public_key((tmp_path / "k.pub.pem").read_bytes())
    spki = public.public_bytes(serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo)
    key_sha = hashlib.sha256(spki).hexdigest()
    arm_file = hashlib.sha256((out / "scout2_arm" / "arm-ctrl" / "1.4.2.bin").read_bytes()).hexdigest()
    os_file = hashlib.sha256((out / "compute" / "scout-os" / "2026.11.bin").read_bytes()).hexdigest()
    plain = sbom(cli, robot / "robot.hcdf", fmt)
    data = sbom(cli, robot / "robot.hcdf", fmt, "--release", out, "--key", tmp_path / "k.pub.pem")
    assert data != plain
    if fmt == "cyclonedx":
        validate_cyclonedx(data.decode())
        comps = cdx_components(json.loads(data))
        arm, scout_os = comps[ARM_FW], comps[OS_FW]
        props, sha = cdx_props, cdx_sha256
    else:
        validate_spdx(data)
        elements, _ = spdx_graph(data)
        arm, scout_os = elements[ARM_FW], elements[OS_FW]
        props = spdx_props

        def sha(el):
            return el["verifiedUsing"][0]["hashValue"]

    for fw, file_sha in ((arm, arm_file), (scout_os, os_file)):
        p = props(fw)
        assert p["hcdf:signature:key-sha256"] == key_sha
        assert (p["hcdf:signature:alg"], p["hcdf:signature:key-type"]) == ("ES256", "ecdsa-p256")
        assert p["hcdf:release:sequence-number"] == "1"
        assert sha(fw) == file_sha
    assert props(arm)["hcdf:mcuboot-hash"] == ARM_HASH
    assert "hcdf:mcuboot-hash" not in props(scout_os)  # a raw image has none


def test_same_inputs_give_the_same_bytes_across_processes(tmp_path):
    """Two processes with different hash seeds: byte-identical output (sets never leak order)."""
    import os
    import subprocess
    import sys

    outputs = []
    for seed in ("1", "2"):
        for fmt in ("cyclonedx", "spdx"):
            env = {**os.environ, "PYTHONHASHSEED": seed, "XDG_CACHE_HOME": str(tmp_path / "cache")}
            env.pop("SOURCE_DATE_EPOCH", None)
            proc = subprocess.run(
                [sys.executable, "-m", "hcdf_trust.cli", "sbom", str(ROBOT / "robot.hcdf"), "--format", fmt],
                capture_output=True,
                env=env,
                cwd=tmp_path,
                timeout=120,
            )
            assert proc.returncode == 0, proc.stderr
            outputs.append(proc.stdout)
    assert outputs[0] == outputs[2] and outputs[1] == outputs[3]
    assert json.loads(outputs[0])["metadata"]["timestamp"] == "1970-01-01T00:00:00+00:00"


def test_a_changed_model_changes_the_sbom(cli, tmp_path):
    robot = tmp_path / "robot"
    shutil.copytree(ROBOT, robot)
    doc = robot / "robot.hcdf"
    before = {fmt: sbom(cli, doc, fmt) for fmt in ("cyclonedx", "spdx")}
    assert sbom(cli, doc, "cyclonedx", "-o", tmp_path / "a.json") == b""
    assert (tmp_path / "a.json").read_bytes() == before["cyclonedx"]  # -o writes what stdout prints
    stl = robot / "meshes" / "chassis-hull.stl"  # unpinned in robot.hcdf: the lock pins it
    stl.write_bytes(stl.read_bytes() + b"\n")
    r = cli("sbom", doc, "--format", "cyclonedx")
    assert r.exit_code == 1 and r.stdout == "" and "chassis-hull.stl" in r.stderr  # drift: refused
    assert cli("resolve", doc, "--update", "meshes/chassis-hull.stl").exit_code == 0
    new_sha = hashlib.sha256(stl.read_bytes()).hexdigest()
    for fmt, old in before.items():
        new = sbom(cli, doc, fmt)
        assert new != old
    bom, old_bom = json.loads(new := sbom(cli, doc, "cyclonedx")), json.loads(before["cyclonedx"])
    assert cdx_sha256(cdx_components(bom)["file/meshes/chassis-hull.stl"]) == new_sha
    assert bom["serialNumber"] != old_bom["serialNumber"]
    assert new == sbom(cli, doc, "cyclonedx")
    elements_new, _ = spdx_graph(sbom(cli, doc, "spdx"))
    elements_old, _ = spdx_graph(before["spdx"])
    assert next(iter(elements_new.values()))["spdxId"] != next(iter(elements_old.values()))["spdxId"]


def test_source_date_epoch_sets_the_time(cli, monkeypatch):
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1764547200")
    bom = json.loads(sbom(cli, ROBOT / "robot.hcdf", "cyclonedx"))
    assert bom["metadata"]["timestamp"] == "2025-12-01T00:00:00+00:00"
    data = sbom(cli, ROBOT / "robot.hcdf", "spdx")
    info = next(o for o in json.loads(data)["@graph"] if o["type"] == "CreationInfo")
    assert info["created"] == "2025-12-01T00:00:00Z"
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "yesterday")
    r = cli("sbom", ROBOT / "robot.hcdf", "--format", "spdx")
    assert r.exit_code == 2 and "SOURCE_DATE_EPOCH" in r.stderr and r.stdout == ""  # a usage error, as ota build's


@pytest.mark.parametrize("fmt", ["cyclonedx", "spdx"])
def test_a_release_provenance_is_an_external_reference(cli, tmp_path, fmt):
    # the oracle: the file on disk, hashed here, and the --base-url given to ota build
    robot = tmp_path / "robot"
    shutil.copytree(ROBOT, robot)
    key = tmp_path / "k.pem"
    assert cli("ota", "keygen", "-o", key).exit_code == 0
    out = tmp_path / "release"
    build = ["ota", "build", robot / "robot.hcdf", "--firmware-dir", robot / "firmware", "--key", key, "--out", out]
    assert cli(*build, "--base-url", "https://fw.example.com/scout2/").exit_code == 0
    release = ("--release", out, "--key", tmp_path / "k.pub.pem")
    without = sbom(cli, robot / "robot.hcdf", fmt, *release)
    assert b"provenance.intoto.json" not in without  # no provenance, no reference
    assert cli(*build, "--base-url", "https://fw.example.com/scout2/", "--provenance").exit_code == 0
    data = sbom(cli, robot / "robot.hcdf", fmt, *release)
    url = "https://fw.example.com/scout2/provenance.intoto.json"
    file_sha = hashlib.sha256((out / "provenance.intoto.json").read_bytes()).hexdigest()
    if fmt == "cyclonedx":
        validate_cyclonedx(data.decode())
        bom = json.loads(data)
        comps = cdx_components(bom)
        holders = [bom, comps[ARM_FW], comps[OS_FW]]
        for holder in holders:
            (ref,) = holder["externalReferences"]
            assert (ref["type"], ref["url"]) == ("attestation", url)
            assert ref["hashes"] == [{"alg": "SHA-256", "content": file_sha}]
        assert "externalReferences" not in comps["robot"]
    else:
        validate_spdx(data)
        elements, _ = spdx_graph(data)
        for ref in ("sbom", ARM_FW, OS_FW):
            (ext,) = elements[ref]["externalRef"]
            assert (ext["externalRefType"], ext["locator"]) == ("buildMeta", [url])
            assert file_sha in ext["comment"]
    # a provenance signed by another key is not listed: the run fails, nothing written
    import base64

    from hcdf_trust.ota.keys import generate
    from hcdf_trust.ota.signer import FileSigner
    from hcdf_trust.provenance import dsse

    statement = base64.b64decode(json.loads((out / "provenance.intoto.json").read_bytes())["payload"])
    (out / "provenance.intoto.json").write_bytes(dsse.sign(statement, [FileSigner(generate("ed25519"))]))
    r = cli("sbom", robot / "robot.hcdf", "--format", fmt, *release, "-o", tmp_path / "bom.json")
    assert r.exit_code == 1 and "provenance.intoto.json" in r.stderr and not (tmp_path / "bom.json").exists()
