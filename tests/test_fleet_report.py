"""``fleet status --out`` (a version report signed by the host, host-attested) and
``audit --fleet-report``, against the in-process SMP devices of test_fleet_status.py."""

from __future__ import annotations

import base64
import json

import pytest
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec

from hcdf_trust.ota.keys import generate, private_pem, public_pem

from ._fleet import run, set_running, status

POLICY = """[checks.firmware-no-hash]
enabled = false
"""


@pytest.fixture
def host(tmp_path):
    key = generate("ecdsa-p256")
    (tmp_path / "host.pem").write_bytes(private_pem(key, None))
    (tmp_path / "host.pub.pem").write_bytes(public_pem(key))
    (tmp_path / "policy.toml").write_text(POLICY)
    return tmp_path


def dsse_verify(envelope: dict, public_pem_bytes: bytes) -> dict:
    """Independent oracle: DSSE v1's PAE and an ECDSA P-256/SHA-256 check with cryptography alone."""
    body = base64.b64decode(envelope["payload"])
    ptype = envelope["payloadType"].encode()
    pae = b"DSSEv1 %d %s %d %s" % (len(ptype), ptype, len(body), body)
    key = serialization.load_pem_public_key(public_pem_bytes)
    [sig] = envelope["signatures"]
    key.verify(base64.b64decode(sig["sig"]), pae, ec.ECDSA(hashes.SHA256()))
    return json.loads(body)


def audit(world, host, report, key=None):
    return run(
        "audit",
        world["robot"].doc,
        "--release",
        world["new_dir"],
        "--key",
        world["robot"].pub,
        "--fleet-report",
        report,
        "--fleet-key",
        key or host / "host.pub.pem",
        "--policy",
        host / "policy.toml",
        "--json",
    )


def fleet_findings(r) -> list[tuple[str, str]]:
    return [
        (f["code"], f["message"])
        for f in r.json["findings"]
        if f["check"].startswith("fleet") or f["code"].startswith("fleet")
    ]


def test_signed_report_of_a_current_fleet(fleet, host):
    out = host / "fleet-report.json"
    r = status(fleet, "--json", "-o", out, "--host-key", host / "host.pem")
    assert r.exit_code == 0, r.stdout
    assert r.json["wrote"] == [str(out)] or r.json["wrote"][0].endswith("fleet-report.json")
    statement = dsse_verify(json.loads(out.read_text()), (host / "host.pub.pem").read_bytes())
    assert "host-attested" in statement["statement"] and "not device attestation" in statement["statement"]
    assert statement["description"]["sha256"] == fleet["doc_sha"]
    assert {d["comp"]: d["verdict"] for d in statement["devices"]} == dict.fromkeys(("left", "right", "imu"), "current")
    r = audit(fleet, host, out)
    assert r.exit_code == 0, r.stdout
    assert "fleet" in r.json["checked"] and fleet_findings(r) == []


def test_audit_flags_devices_not_running_the_release(fleet, host):
    set_running(fleet, "right", "old")
    out = host / "r.json"
    r = status(fleet, "-o", out, "--host-key", host / "host.pem", "--previous", fleet["old_dir"])
    assert r.exit_code == 1  # the status exit code is the verdicts', report or not
    r = audit(fleet, host, out)
    assert r.exit_code == 1
    [(code, message)] = fleet_findings(r)
    assert code == "fleet-device" and "'right'" in message and "outdated" in message


def test_tampered_or_foreign_reports_are_refused(fleet, host):
    out = host / "r.json"
    assert status(fleet, "-o", out, "--host-key", host / "host.pem").exit_code == 0
    env = json.loads(out.read_text())
    body = json.loads(base64.b64decode(env["payload"]))
    body["devices"] = body["devices"][:1]
    env["payload"] = base64.b64encode(json.dumps(body).encode()).decode()
    (host / "tampered.json").write_text(json.dumps(env))
    with pytest.raises(InvalidSignature):
        dsse_verify(env, (host / "host.pub.pem").read_bytes())
    r = audit(fleet, host, host / "tampered.json")
    assert r.exit_code == 1
    assert any(code == "fleet-report" for code, _ in fleet_findings(r))
    other = generate("ecdsa-p256")
    (host / "other.pub.pem").write_bytes(public_pem(other))
    r = audit(fleet, host, out, key=host / "other.pub.pem")
    assert r.exit_code == 1 and any(code == "fleet-report" for code, _ in fleet_findings(r))
    (host / "junk.json").write_text('{"payloadType": 1, "payloadType": 2}')
    assert audit(fleet, host, host / "junk.json").exit_code == 3


def test_report_needs_the_host_key_and_never_lands_on_an_input(fleet, host):
    assert status(fleet, "-o", host / "r.json").exit_code == 2
    key_before = (host / "host.pem").read_bytes()
    r = status(fleet, "-o", host / "host.pem", "--host-key", host / "host.pem")
    assert r.exit_code == 3 and (host / "host.pem").read_bytes() == key_before
    r = status(fleet, "-o", fleet["robot"].doc, "--host-key", host / "host.pem")
    assert r.exit_code == 3


def test_report_signed_in_a_pkcs11_token(fleet, tmp_path):
    """The host key in SoftHSM2 (made inside the token, never leaving it). The token is used
    from child processes only: python-pkcs11 loads a module once per process, and another
    test's token folder would not be seen after this one's."""
    import os
    import shutil
    import subprocess
    import sys

    from hcdf_trust.ota.hsm import DEFAULT_MODULES

    module = next((m for m in DEFAULT_MODULES if os.path.exists(m)), None)
    if module is None or shutil.which("softhsm2-util") is None:
        pytest.skip("SoftHSM2 is not installed (.ci/apt-packages lists softhsm2)")
    conf = tmp_path / "softhsm2.conf"
    (tmp_path / "tokens").mkdir()
    conf.write_text(f"directories.tokendir = {tmp_path / 'tokens'}\nobjectstore.backend = file\nlog.level = ERROR\n")
    env = dict(os.environ, SOFTHSM2_CONF=str(conf))
    subprocess.run(
        ["softhsm2-util", "--init-token", "--free", "--label", "host", "--pin", "4321", "--so-pin", "87654321"],
        check=True,
        capture_output=True,
        env=env,
    )
    keygen = f"""
import pkcs11, sys
from pkcs11 import Attribute, KeyType
from pkcs11.util.ec import encode_ec_public_key, encode_named_curve_parameters
from cryptography.hazmat.primitives import serialization
with pkcs11.lib({module!r}).get_token(token_label="host").open(user_pin="4321", rw=True) as s:
    params = s.create_domain_parameters(
        KeyType.EC, {{Attribute.EC_PARAMS: encode_named_curve_parameters("secp256r1")}}, local=True
    )
    pub, _ = params.generate_keypair(store=True, label="fleet-host")
    key = serialization.load_der_public_key(encode_ec_public_key(pub))
sys.stdout.buffer.write(key.public_bytes(serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo))
"""
    pem = subprocess.run([sys.executable, "-c", keygen], check=True, capture_output=True, env=env).stdout
    (tmp_path / "host.pub.pem").write_bytes(pem)
    (tmp_path / "pin").write_text("4321\n")
    (tmp_path / "pin").chmod(0o600)
    (tmp_path / "bad-pin").write_text("0000\n")
    (tmp_path / "bad-pin").chmod(0o600)
    (tmp_path / "policy.toml").write_text(POLICY)
    uri = f"pkcs11:token=host;object=fleet-host?module-path={module}"

    def status_in_child(out, pin):
        argv = [sys.executable, "-m", "hcdf_trust.cli", "fleet", "status", fleet["robot"].doc,
                "--release", fleet["new_dir"], "--key", fleet["robot"].pub, "-o", out, "--host-key", uri,
                "--pin-file", pin]  # fmt: skip
        for name, device in fleet["uris"].items():
            argv += ["--device", f"{name}={device}"]
        return subprocess.run([str(a) for a in argv], capture_output=True, text=True, env=env, timeout=120)

    out = tmp_path / "r.json"
    p = status_in_child(out, tmp_path / "pin")
    assert p.returncode == 0, p.stderr
    statement = dsse_verify(json.loads(out.read_text()), pem)
    assert "not device attestation" in statement["statement"]
    r = audit(fleet, tmp_path, out)
    assert r.exit_code == 0 and fleet_findings(r) == [], r.stdout
    p = status_in_child(tmp_path / "r2.json", tmp_path / "bad-pin")
    assert p.returncode == 3, p.stderr
    assert not (tmp_path / "r2.json").exists()
