"""The example robot's firmware stand-ins and ota.toml build a release that verifies (what ``make demo`` runs)."""

from __future__ import annotations

import json
import shutil

from tests.conftest import PROJECT


def test_example_robot_release_builds_and_verifies(cli, tmp_path):
    robot = tmp_path / "robot"
    shutil.copytree(PROJECT / "examples" / "robot", robot)
    key = tmp_path / "demo.pem"
    assert cli("ota", "keygen", "-o", key).exit_code == 0
    out = tmp_path / "release"
    r = cli(
        "ota",
        "build",
        robot / "robot.hcdf",
        "--firmware-dir",
        robot / "firmware",
        "--key",
        key,
        "--out",
        out,
        "--base-url",
        "https://firmware.example.com/scout2",
        "--json",
    )
    assert r.exit_code == 0, r.stderr
    images = {tuple(i["component_id"]): i for i in r.json["images"]}
    assert set(images) == {("scout2_arm", "arm-ctrl"), ("compute", "scout-os")}
    assert images[("compute", "scout-os")]["type"] == "raw"
    # the arm's <software><hash> is the MCUboot hash of the image built from its stand-in
    arm_hcdf = (robot / "assemblies" / "arm.hcdf").read_text()
    assert f"<hash>{images[('scout2_arm', 'arm-ctrl')]['mcuboot_hash']}</hash>" in arm_hcdf
    published = json.loads((robot / "firmware" / "arm-ctrl.latest.json").read_text())
    assert published["latest"]["mcuboot_hash"] == images[("scout2_arm", "arm-ctrl")]["mcuboot_hash"]
    r = cli("ota", "verify", out, "--key", tmp_path / "demo.pub.pem")
    assert r.exit_code == 0, r.stderr
