"""PKCS#11 keys: SoftHSM2 started in a temporary SOFTHSM2_CONF; the private key is made in
the token and never leaves it. imgtool's CLI and ``ota verify`` check the result."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import cbor2
import pkcs11
import pytest
from cryptography.hazmat.primitives import serialization
from pkcs11 import Attribute, KeyType
from pkcs11.util.ec import encode_ec_public_key, encode_named_curve_parameters
from pycose.keys import CoseKey
from pycose.messages import CoseMessage

from hcdf_trust.ota.hsm import DEFAULT_MODULES
from tests._ota import make_robot, tree
from tests._suit import zcbor_validate

IMGTOOL = str(Path(sys.executable).with_name("imgtool"))
MODULE = next((m for m in DEFAULT_MODULES if os.path.exists(m)), DEFAULT_MODULES[0])
PIN = "4321"


@pytest.fixture
def token(tmp_path, monkeypatch):
    """A fresh SoftHSM2 token "release" with an ECDSA P-256 and an Ed25519 key pair made inside it."""
    conf = tmp_path / "softhsm2.conf"
    (tmp_path / "tokens").mkdir()
    conf.write_text(f"directories.tokendir = {tmp_path / 'tokens'}\nobjectstore.backend = file\nlog.level = ERROR\n")
    monkeypatch.setenv("SOFTHSM2_CONF", str(conf))
    subprocess.run(
        [
            shutil.which("softhsm2-util") or "softhsm2-util",
            "--init-token",
            "--free",
            "--label",
            "release",
            "--pin",
            PIN,
            "--so-pin",
            "87654321",
        ],
        check=True,
        capture_output=True,
    )
    lib = pkcs11.lib(MODULE)
    lib.reinitialize()
    pubs = {}
    with lib.get_token(token_label="release").open(user_pin=PIN, rw=True) as session:
        ec = session.create_domain_parameters(
            KeyType.EC, {Attribute.EC_PARAMS: encode_named_curve_parameters("secp256r1")}, local=True
        )
        pub, _ = ec.generate_keypair(store=True, label="fw-signing")
        pubs["ecdsa-p256"] = serialization.load_der_public_key(encode_ec_public_key(pub))
        ed = session.create_domain_parameters(
            KeyType.EC_EDWARDS, {Attribute.EC_PARAMS: encode_named_curve_parameters("1.3.101.112")}, local=True
        )
        pub, _ = ed.generate_keypair(store=True, label="ed-signing")
        point = bytes(pub[Attribute.EC_POINT])[2:]
        pubs["ed25519"] = serialization.load_der_public_key(bytes.fromhex("302a300506032b6570032100") + point)
    files = {}
    for kind, key in pubs.items():
        path = tmp_path / f"{kind}.pub.pem"
        path.write_bytes(key.public_bytes(serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo))
        files[kind] = path
    pin_file = tmp_path / "pin"
    pin_file.write_text(PIN + "\n")
    return files, pin_file


@pytest.mark.parametrize(("kind", "label"), [("ecdsa-p256", "fw-signing"), ("ed25519", "ed-signing")])
def test_images_and_manifest_signed_in_the_token_verify(tmp_path, cli, token, kind, label):
    pubs, pin_file = token
    robot = make_robot(tmp_path, cli)
    robot.key = f"pkcs11:token=release;object={label}?module-path={MODULE}"
    robot.pub = pubs[kind]
    out = tmp_path / "rel"
    r = robot.build(cli, out, "--pin-file", pin_file, "--json")
    assert r.exit_code == 0, r.stderr
    for app in ("flex-io", "rtk-gnss"):
        latest = json.loads((out / "mr_mcxn_t1" / app / "latest.json").read_text())
        image = out / "mr_mcxn_t1" / app / f"{latest['latest']['version']}.bin"
        proc = subprocess.run([IMGTOOL, "verify", "-k", robot.pub, image], capture_output=True, text=True)
        assert proc.returncode == 0 and "correctly validated" in proc.stdout, proc.stdout + proc.stderr
    r = cli("ota", "verify", out, "--key", robot.pub)
    assert r.exit_code == 0, r.stderr
    # the token-made COSE_Sign1 verifies with pycose too (a second, independent implementation)
    auth = cbor2.loads(cbor2.loads((out / "release.suit").read_bytes()).value[2])
    msg = CoseMessage.decode(auth[1])
    msg.payload = auth[0]
    msg.key = CoseKey.from_pem_public_key(robot.pub.read_text())
    assert msg.verify_signature() is True
    # and the envelope is the draft's: zcbor with the draft's CDDL (issue 17)
    proc = zcbor_validate((out / "release.suit").read_bytes(), tmp_path)
    assert proc.returncode == 0, proc.stdout + proc.stderr


def test_pin_from_the_environment(tmp_path, cli, token, monkeypatch):
    pubs, _ = token
    robot = make_robot(tmp_path, cli)
    robot.key = "pkcs11:token=release;object=fw-signing"
    monkeypatch.setenv("HCDF_TRUST_PKCS11_PIN", PIN)
    monkeypatch.setenv("HCDF_TRUST_PKCS11_MODULE", MODULE)
    out = tmp_path / "rel"
    assert robot.build(cli, out).exit_code == 0
    assert cli("ota", "verify", out, "--key", pubs["ecdsa-p256"]).exit_code == 0


def test_wrong_or_missing_pin_exits_3_and_writes_nothing(tmp_path, cli, token, monkeypatch):
    _pubs, _ = token
    robot = make_robot(tmp_path, cli)
    monkeypatch.setenv("HCDF_TRUST_PKCS11_MODULE", MODULE)
    monkeypatch.delenv("HCDF_TRUST_PKCS11_PIN", raising=False)
    robot.key = "pkcs11:token=release;object=fw-signing"
    out = tmp_path / "rel"
    out.mkdir()
    (out / "keep").write_text("as it was")
    before = tree(out)
    bad = tmp_path / "bad-pin"
    bad.write_text("0000\n")
    r = robot.build(cli, out, "--pin-file", bad)
    assert r.exit_code == 3 and "wrong PIN" in r.stderr
    r = robot.build(cli, out)
    assert r.exit_code == 3 and "--pin-file" in r.stderr
    robot.key = "pkcs11:token=release;object=fw-signing?pin-value=" + PIN
    r = robot.build(cli, out)
    assert r.exit_code == 3 and "PIN on the command line is refused" in r.stderr
    robot.key = "pkcs11:token=release;object=no-such-key"
    r = robot.build(cli, out, "--pin-file", tmp_path / "pin")
    assert r.exit_code == 3 and "no key pair 'no-such-key'" in r.stderr
    assert tree(out) == before
