"""Errors that name the fix (issue 20 §4): each message says what to run, and where a test can,
it runs that command and checks that it is the fix."""

from __future__ import annotations

import hashlib
import shutil
import socket
from pathlib import Path

import pytest

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "robot"


@pytest.fixture
def robot(tmp_path):
    shutil.copytree(EXAMPLE, tmp_path / "robot")
    return tmp_path / "robot" / "robot.hcdf"


def test_a_changed_include_names_pin_update_and_nothing_still_referenced_is_called_unreferenced(cli, robot):
    arm = robot.parent / "assemblies" / "arm.hcdf"
    arm.write_bytes(arm.read_bytes() + b"<!-- edited -->\n")
    r = cli("verify", robot)
    assert r.exit_code == 1
    assert f"re-pin it with `hcdf-trust pin --write --update assemblies/arm.hcdf {robot}`" in r.stderr, r.stderr
    # gripper.glb and arm-link.glb are still referenced, from the include that failed its pin
    assert "no longer referenced" not in r.stderr
    assert cli("pin", "--write", "--update", "assemblies/arm.hcdf", robot).exit_code == 0  # the named fix
    assert cli("verify", robot).exit_code == 0


def test_an_include_removed_from_the_tree_is_still_no_longer_referenced(cli, robot):
    text = robot.read_text()
    kept = [line for line in text.splitlines(keepends=True) if "assemblies/sensor-head.hcdf" not in line]
    robot.write_text("".join(kept))
    r = cli("verify", robot, "--lock", robot.parent / "robot.hcdf.lock")
    assert r.exit_code == 1
    assert "assemblies/sensor-head.hcdf is in the lock file but no longer referenced" in r.stderr, r.stderr


def test_a_firmware_hash_that_is_not_the_built_image_names_update_hcdf(cli, robot, tmp_path):
    key = tmp_path / "k.pem"
    assert cli("ota", "keygen", "--type", "ecdsa-p256", "-o", key).exit_code == 0
    firmware = robot.parent / "firmware"
    (firmware / "arm-ctrl-1.4.2.bin").write_bytes((firmware / "arm-ctrl-1.4.2.bin").read_bytes() + b"\1")
    build = ("ota", "build", robot, "--firmware-dir", firmware, "--key", key)
    r = cli(*build, "--out", tmp_path / "rel")
    assert r.exit_code == 1 and "build again with --update-hcdf" in r.stderr, r.stderr
    assert "<software name='arm-ctrl'><hash> is not the MCUboot image hash" in r.stderr
    assert cli(*build, "--out", tmp_path / "rel2", "--update-hcdf").exit_code == 0  # the named fix


def test_a_malformed_hash_is_named_as_the_element_it_is(cli, tmp_path):
    doc = tmp_path / "r.hcdf"
    doc.write_text(
        '<?xml version="1.0"?>\n<hcdf version="1.0" name="r">\n<comp name="c">\n'
        '<software name="fw"><version>1.0.0</version><hash>not-hex</hash></software>\n</comp>\n</hcdf>\n'
    )
    r = cli("resolve", doc, "--no-lock", "--json")
    messages = [w["message"] for w in r.json["warnings"] if w["code"] == "bad-digest"]
    assert messages and "<hash>not-hex</hash> is not a hex SHA-256 digest" in messages[0], r.json
    assert not any('sha="not-hex"' in m for m in messages)


def test_strict_on_a_weak_pin_shows_the_full_digest_and_pin_write(cli, robot):
    r = cli("verify", robot, "--strict")
    assert r.exit_code == 1
    full = hashlib.sha256((robot.parent / "models" / "gripper.glb").read_bytes()).hexdigest()
    assert f"its full digest is sha256 {full}" in r.stderr and f"`hcdf-trust pin --write {robot}`" in r.stderr
    assert cli("pin", "--write", robot).exit_code == 0  # the named fix
    assert cli("verify", robot, "--strict").exit_code == 0


def test_update_given_before_doc_says_what_it_did(cli, robot):
    mesh = robot.parent / "meshes" / "chassis-hull.stl"
    old = hashlib.sha256(mesh.read_bytes()).hexdigest()
    mesh.write_bytes(mesh.read_bytes() + b"solid edited\n")
    new = hashlib.sha256(mesh.read_bytes()).hexdigest()
    r = cli("resolve", "--update", robot)
    assert r.exit_code == 0, r.stderr
    assert f"note: --update took no URI ({robot} is DOC)" in r.stderr
    assert f"updated meshes/chassis-hull.stl: sha256 {old} -> {new}" in r.stderr
    r = cli("resolve", "--update", "meshes/chassis-hull.stl", robot)
    assert r.exit_code == 0 and "--update: nothing to accept" in r.stderr and "took no URI" not in r.stderr


def test_an_unreachable_registry_names_the_flag_and_the_host(cli, robot, tmp_path):
    pw = tmp_path / "pass"
    pw.write_text("pw\n")
    pw.chmod(0o600)
    (tmp_path / "content").mkdir()
    reg = ("--keys", tmp_path / "keys", "--passphrase-file", pw)
    assert cli("registry", "init", tmp_path / "src", *reg).exit_code == 0
    r = cli("registry", "publish", tmp_path / "src", *reg, "--content", tmp_path / "content", "--out", tmp_path / "s")
    assert r.exit_code == 0, r.stderr
    with socket.socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    site = f"https://127.0.0.1:{port}/"
    root = tmp_path / "s" / "metadata" / "1.root.json"
    for argv, flag in (
        (("resolve", robot, "--no-lock", "--registry", site, "--trusted-root", root), "--registry"),
        (("registry", "verify", site, "--trusted-root", root, "--cache-dir", tmp_path / "c"), "SITE"),
    ):
        r = cli(*argv)
        assert r.exit_code == 3
        assert f"cannot reach the registry at 127.0.0.1:{port} (Connection refused)" in r.stderr, r.stderr
        assert f"check {flag} {site}" in r.stderr
        assert "HTTPSConnectionPool" not in r.stderr and "Max retries" not in r.stderr


@pytest.mark.parametrize("argv", [("resolve",), ("verify",), ("pin",), ("validate",), ("audit",), ("macsec", "plan")])
def test_a_missing_document_is_named_once(cli, tmp_path, monkeypatch, argv):
    monkeypatch.chdir(tmp_path)
    r = cli(*argv, "robto.hcdf")
    assert r.exit_code == 3
    assert r.stderr.count("robto.hcdf") == 1 and "robto.hcdf: no such file" in r.stderr, r.stderr
