"""``audit`` on the corpus humanoid and on examples/robot: what we expect, written down from
reading the files before the command was ever run on them.

Humanoid (corpus, read-only; audit writes nothing, so it runs on the file in place):
- references: two ``<stream-profile uri="profiles/operational.streams.xml">`` without sha (lines
  1946 and 2015, one per arm network), and no lock file next to it; nothing remote.
- no ``<software>``, no ``<extension>``: no firmware or extension findings.
- MACsec: every network with links or chains is ``must-secure`` (backbone 256, arm chains and
  base 128), no ``type="file"`` key store (tpm, secure-element): no control-traffic, key-store or
  (at the default minimum gcm-aes-128) cipher finding. Endpoints lacking the cipher: agx-thor
  mgbe0/mgbe1 declare nothing on the gcm-aes-256 backbone; the four base peripheral links inherit
  the base network's gcm-aes-128 and none of their eight ports declares MACsec; in each arm chain
  the camera spur (mcn3 eth2 via, cam eth0) declares nothing: 14 in all.
- With ``minimum-cipher = "gcm-aes-256"``: every gcm-aes-128 association is weak: the two arm
  chains (key-ref), the four n79->j100 links (key-ref) and the four peripheral links: 10.

examples/robot (locked and verified by `make demo`):
- references: the gripper model's ``sha="adaa3b07"`` is a 32-bit weak pin (assemblies/arm.hcdf,
  one document however often included); the unpinned mesh and firmware manifest are pinned by
  the lock, which matches the tree: no unpinned, lock or http finding.
- firmware: ``scout-os`` has no ``<hash>`` and version ``2026.11`` (not MAJOR.MINOR.PATCH);
  ``arm-ctrl`` 1.4.2 has a full hash.
- MACsec: all must-secure, ciphers declared by every endpoint; ``<key-store type="file">``
  at robot.hcdf:84.
"""

from __future__ import annotations

from pathlib import Path

from lxml import etree

from .conftest import HCDFORMAT, PROJECT

HUMANOID = HCDFORMAT / "examples" / "humanoid-mobile-base.hcdf"
ROBOT = PROJECT / "examples" / "robot" / "robot.hcdf"


def _found(result) -> set[tuple[str, str, int | None]]:
    return {(f["code"], Path(f["file"]).name, f["line"]) for f in result.json["findings"]}


def _port_line(tree, comp: str, port: str) -> int:
    (el,) = tree.xpath(f"//comp[@name='{comp}']//port[@name='{port}']")
    return el.sourceline


def test_humanoid_findings(cli):
    r = cli("audit", HUMANOID, "--json")
    assert r.exit_code == 1, r.stderr  # the unpinned profiles are errors under the default policy
    name = HUMANOID.name
    tree = etree.parse(str(HUMANOID))
    lacking = [
        ("agx-thor", "mgbe0"), ("agx-thor", "mgbe1"),
        ("s32j100", "eth_head"), ("s32j100", "eth_lidar_front"), ("s32j100", "eth_lidar_rear"),
        ("s32j100", "eth_radar"), ("head", "eth0"), ("lidar-front", "eth0"), ("lidar-rear", "eth0"),
        ("radar-4d", "eth0"), ("mcn3-l", "eth2"), ("cam-l", "eth0"), ("mcn3-r", "eth2"), ("cam-r", "eth0"),
    ]  # fmt: skip
    expected = {("unpinned", name, 1946), ("unpinned", name, 2015), ("not-locked", name, None)}
    expected |= {("macsec-capability", name, _port_line(tree, c, p)) for c, p in lacking}
    assert _found(r) == expected
    assert len(r.json["findings"]) == len(expected)
    assert {f["code"] for f in r.json["errors"]} == {"unpinned"}
    assert r.json["checked"] == ["references", "stream-profiles", "firmware", "macsec"]


def test_humanoid_minimum_cipher(cli, tmp_path):
    policy = tmp_path / "policy.toml"
    policy.write_text('[macsec]\nminimum-cipher = "gcm-aes-256"\n')
    r = cli("audit", HUMANOID, "--policy", policy, "--json")
    tree = etree.parse(str(HUMANOID))
    lines = [tree.xpath(f"//chain[@name='{c}']")[0].sourceline for c in ("left-arm-chain", "right-arm-chain")]
    links = [f"n79_to_j100_p{i}" for i in range(4)] + ["j100_to_head", "j100_to_lidar_f", "j100_to_lidar_r"]
    links.append("j100_to_radar")
    lines += [tree.xpath(f"//link[@name='{n}']")[0].sourceline for n in links]
    weak = [f for f in r.json["findings"] if f["code"] == "macsec-weak-cipher"]
    assert sorted(f["line"] for f in weak) == sorted(lines)
    assert all("gcm-aes-128" in f["message"] for f in weak)


def test_example_robot_findings(cli):
    r = cli("audit", ROBOT, "--json")
    assert r.exit_code == 1, r.stderr  # scout-os has no hash
    arm = etree.parse(str(ROBOT.parent / "assemblies" / "arm.hcdf"))
    gripper = arm.xpath("//model[@sha='adaa3b07']")[0].sourceline
    robot = etree.parse(str(ROBOT))
    scout = robot.xpath("//software[@name='scout-os']")[0]
    assert _found(r) == {
        ("weak-pin", "arm.hcdf", gripper),
        ("firmware-no-hash", "robot.hcdf", scout.sourceline),
        ("firmware-version", "robot.hcdf", scout.find("version").sourceline),
        ("macsec-file-key-store", "robot.hcdf", 84),
    }
    assert len(r.json["findings"]) == 4
    assert [f["code"] for f in r.json["errors"]] == ["firmware-no-hash"]


def test_human_output_names_file_line_severity_code(cli):
    r = cli("audit", ROBOT)
    assert r.exit_code == 1
    assert "robot.hcdf:84: warning[macsec-file-key-store]:" in r.stderr
    assert "audit: 1 error, 3 warnings" in r.stderr
