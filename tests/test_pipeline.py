"""The whole chain `make demo` runs (its own recipe, read from the Makefile), then one tampered
artifact per stage, each caught by the next verification with exit 1."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys

from .conftest import CORPUS, PROJECT
from .test_flatten_root import demo_lines


def _flip(path, offset: int | None = None) -> None:
    """Flip one bit of one byte of ``path`` (the middle one unless ``offset``), keeping its mode."""
    data = bytearray(path.read_bytes())
    data[len(data) // 2 if offset is None else offset] ^= 0x01
    mode = path.stat().st_mode
    path.chmod(0o600)
    path.write_bytes(bytes(data))
    path.chmod(mode & 0o777)


def test_demo_chain_then_one_tampered_artifact_per_stage(cli, tmp_path, monkeypatch):
    shutil.copytree(PROJECT / "examples", tmp_path / "examples", ignore=shutil.ignore_patterns("out"))
    monkeypatch.chdir(tmp_path)
    for extra in ("pkcs11", "tpm2_pytss", "sigstore"):  # `make demo` installs no extras: none is imported
        monkeypatch.setitem(sys.modules, extra, None)
    verbs = []
    for line in demo_lines(CORPUS):
        if isinstance(line, str):  # a shell line (the throwaway passphrases)
            subprocess.run(line, shell=True, check=True, cwd=tmp_path)
            continue
        r = cli(*line)
        assert r.exit_code == 0, (line, r.stderr)
        verbs.append(" ".join(line[:2]) if line[0] in ("ota", "registry", "macsec") else line[0])
    assert {"registry publish", "registry verify", "ota verify", "macsec export", "audit", "sbom"} <= set(verbs)
    out = tmp_path / "examples" / "out"
    for name in ("registry.pass", "macsec.pass"):
        assert (out / name).stat().st_mode & 0o777 == 0o600
    bom = json.loads((out / "scout2.cdx.json").read_text())
    assert bom["bomFormat"] == "CycloneDX"

    pub = out / "ota-demo-key.pub.pem"
    store = ["--store", out / "macsec", "--passphrase-file", out / "macsec.pass"]
    client = ["--trusted-root", out / "registry-site" / "metadata" / "1.root.json"]

    # a GLB of the robot: verify against the lock
    _flip(tmp_path / "examples" / "robot" / "models" / "chassis.glb")
    assert cli("verify", "examples/robot/robot.hcdf").exit_code == 1
    _flip(tmp_path / "examples" / "robot" / "models" / "chassis.glb")
    assert cli("verify", "examples/robot/robot.hcdf").exit_code == 0

    # a firmware image in the release: ota verify
    (image,) = (out / "release").glob("scout2_arm/arm-ctrl/*.bin")
    _flip(image)
    r = cli("ota", "verify", out / "release", "--key", pub)
    assert r.exit_code == 1, r.stderr
    _flip(image)
    assert cli("ota", "verify", out / "release", "--key", pub).exit_code == 0

    # a target file of the published registry: registry verify (a fresh client cache)
    (target,) = (out / "registry-site" / "targets" / "extensions" / "com.example.scout2").glob("*.1.0.xsd")
    _flip(target)
    r = cli("registry", "verify", out / "registry-site", *client, "--cache-dir", tmp_path / "client2")
    assert r.exit_code == 1, r.stderr
    _flip(target)
    r = cli("registry", "verify", out / "registry-site", *client, "--cache-dir", tmp_path / "client3")
    assert r.exit_code == 0, r.stderr

    # one byte of the MACsec key store: status and export
    keys = out / "macsec" / "macsec-keys.json"
    text = keys.read_text()
    value = [json.loads(line) for line in text.splitlines()[1:]]  # JSON Lines: a header, then the associations
    ciphertext = _first_ciphertext(value)
    at = text.index(ciphertext) + len(ciphertext) // 2
    _flip(keys, at)
    assert len(keys.read_bytes()) == len(text.encode())
    r = cli("macsec", "status", "examples/robot/robot.hcdf", *store)
    assert r.exit_code == 1, r.stderr
    export = ["--device", "compute", "--format", "iproute2", "--out", tmp_path / "export2"]
    r = cli("macsec", "export", "examples/robot/robot.hcdf", *store, *export)
    assert r.exit_code == 1, r.stderr
    assert not (tmp_path / "export2").exists() or not os.listdir(tmp_path / "export2")


def _first_ciphertext(value) -> str:
    """The first long base64/hex string in the store (an encrypted key), found by walking the JSON."""
    if isinstance(value, dict):
        for v in value.values():
            found = _first_ciphertext(v)
            if found:
                return found
    elif isinstance(value, list):
        for v in value:
            found = _first_ciphertext(v)
            if found:
                return found
    elif isinstance(value, str) and len(value) >= 40:
        return value
    return ""


def test_a_relative_root_is_resolved_again_after_a_chdir(tmp_path, monkeypatch):
    """In one process (a library caller, the tests), the same relative root in another folder is that folder's."""
    from hcdf_trust.localfile import hash_local

    for name in ("a", "b"):
        (tmp_path / name / "root").mkdir(parents=True)
        (tmp_path / name / "root" / "f").write_bytes(name.encode())
    for name in ("a", "b"):
        monkeypatch.chdir(tmp_path / name)
        assert hash_local("root/f", "root").sha256 == hashlib.sha256(name.encode()).hexdigest()
