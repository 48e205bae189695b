"""``ota build --update-hcdf``: the new hash lands as a minimal edit; includers and the lock follow."""

from __future__ import annotations

import difflib
import hashlib
import shutil

from tests._ota import tree
from tests.conftest import PROJECT

OLD = "45eb192b377bf5294c979182716b3461aa00034e5b4d2501eadf54456e9cc359"


def changed_lines(before: bytes, after: bytes) -> list[str]:
    diff = difflib.unified_diff(before.decode().splitlines(), after.decode().splitlines(), lineterm="", n=0)
    return [d for d in diff if d[:1] in "+-" and not d.startswith(("+++", "---"))]


def test_update_hcdf_edits_the_hash_and_repins_the_includers(cli, tmp_path):
    robot = tmp_path / "robot"
    shutil.copytree(PROJECT / "examples" / "robot", robot)
    arm = robot / "assemblies" / "arm.hcdf"
    real = arm.read_text().split("<hash>")[1].split("</hash>")[0]
    # an out-of-date hash (the raw file's SHA-256), with the tree re-pinned and re-locked around it
    arm.write_text(arm.read_text().replace(real, OLD))
    root = robot / "robot.hcdf"
    root.write_text(
        root.read_text().replace(
            hashlib.sha256(arm.read_bytes().replace(OLD.encode(), real.encode())).hexdigest(),
            hashlib.sha256(arm.read_bytes()).hexdigest(),
        )
    )
    assert cli("resolve", root).exit_code == 0
    key = tmp_path / "k.pem"
    cli("ota", "keygen", "-o", key)
    args = ["ota", "build", root, "--firmware-dir", robot / "firmware", "--key", key, "--out", tmp_path / "rel"]
    r = cli(*args)
    assert r.exit_code == 1 and OLD in r.stderr
    before = tree(robot)
    r = cli(*args, "--update-hcdf", "--json")
    assert r.exit_code == 0, r.stderr
    assert r.json["hcdf_changes"] == [
        {"file": r.json["hcdf_changes"][0]["file"], "line": 24, "comp": "shoulder", "old": OLD, "new": real}
    ]
    after = tree(robot)
    changed = {name for name in after if after[name] != before[name]}
    lock = next(n for n in changed if n.endswith(".lock"))
    assert changed == {"assemblies/arm.hcdf", "robot.hcdf", lock}
    assert changed_lines(before["assemblies/arm.hcdf"], after["assemblies/arm.hcdf"]) == [
        f"-      <hash>{OLD}</hash>",
        f"+      <hash>{real}</hash>",
    ]
    new_arm = hashlib.sha256(after["assemblies/arm.hcdf"]).hexdigest()
    root_diff = changed_lines(before["robot.hcdf"], after["robot.hcdf"])
    assert len(root_diff) == 4 and all(new_arm in line for line in root_diff if line.startswith("+"))
    # the edited tree verifies under its lock, and the release is bound to the new lock and root
    assert cli("verify", root).exit_code == 0
    assert cli("ota", "build", *args[2:], "--json").exit_code == 0
    rendering = __import__("json").loads((tmp_path / "rel" / "release.suit.json").read_text())
    assert rendering["hcdf"]["lock_sha256"] == hashlib.sha256(after[lock]).hexdigest()
    assert rendering["hcdf"]["root_sha256"] == hashlib.sha256(after["robot.hcdf"]).hexdigest()
