"""key-agreement eap-tls: a CA per network, a certificate per member, exported for wpa_supplicant."""

from __future__ import annotations

import json
import shutil
import subprocess

import pytest
from cryptography import x509
from cryptography.hazmat.primitives import serialization
from cryptography.x509.oid import NameOID

from hcdf_trust.macsec.backends import PassphraseWrapper
from hcdf_trust.macsec.store import KeyStore

from ._macsec import comp, hcdf, link, port, tree
from .test_macsec_export import _wpa_log, netns  # noqa: F401  (fixture)

PASS = b"eap passphrase"


@pytest.fixture
def eap(tmp_path, cli):
    caps = ("gcm-aes-128",)
    body = [comp("a", port("p0", *caps)), comp("b", port("p0", *caps), port("p1", *caps)), comp("c", port("p0", *caps))]
    body += ['<network name="n">', link("ab", "a/p0", "b/p0"), "</network>"]
    body += ['<network name="m">', link("bc", "b/p1", "c/p0", '<macsec policy="must-secure"/>'), "</network>"]
    body = [*body[:5], '<macsec policy="must-secure" key-agreement="eap-tls"/>', *body[5:]]
    doc = tree(tmp_path / "d", {"robot.hcdf": hcdf(*body)})
    pp = tmp_path / "pass"
    pp.write_bytes(PASS)
    base = ["--store", tmp_path / "keys", "--passphrase-file", pp]
    return doc, base


def _certs(store_dir):
    ks = KeyStore.open(store_dir, PassphraseWrapper(PASS))
    out = {}
    for entry_id, e in ks.entries.items():
        if e.kind.startswith("eap-tls"):
            secret = ks.key(e, e.generations[-1])
            out[entry_id] = secret
    return out


def test_generate_issues_a_network_ca_and_member_certificates(eap, cli, tmp_path):
    doc, base = eap
    r = cli("macsec", "generate", doc, *base, "--json")
    assert r.exit_code == 0, r.stderr
    assert set(r.json["created"]) == {"eap-ca:n", "eap-cert:n/a", "eap-cert:n/b", "link:m/bc"}
    assert cli("macsec", "generate", doc, *base, "--json").json["created"] == []
    certs = _certs(tmp_path / "keys")
    ca = x509.load_pem_x509_certificate(certs["eap-ca:n"].split(b"-----END PRIVATE KEY-----\n")[1])
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    for device in ("a", "b"):
        pem = certs[f"eap-cert:n/{device}"]
        cert = x509.load_pem_x509_certificate(pem[pem.index(b"-----BEGIN CERTIFICATE") :])
        cert.verify_directly_issued_by(ca)
        assert cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == device
    if shutil.which("openssl"):  # an independent verifier of the chain
        (tmp_path / "ca.pem").write_bytes(ca.public_bytes(serialization.Encoding.PEM))
        pem = certs["eap-cert:n/a"]
        (tmp_path / "a.pem").write_bytes(pem[pem.index(b"-----BEGIN CERTIFICATE") :])
        proc = subprocess.run(
            ["openssl", "verify", "-purpose", "sslclient", "-CAfile", tmp_path / "ca.pem", tmp_path / "a.pem"],
            capture_output=True,
            text=True,
        )
        assert proc.returncode == 0, proc.stdout + proc.stderr
    st = cli("macsec", "status", doc, *base, "--json").json
    assert st["missing"] == [] and st["orphaned"] == []


def test_eap_tls_export(eap, cli, tmp_path):
    doc, base = eap
    assert cli("macsec", "generate", doc, *base).exit_code == 0
    certs = _certs(tmp_path / "keys")
    r = cli("macsec", "export", doc, *base, "--device", "a", "--format", "json", "--out", tmp_path / "j")
    assert r.exit_code == 0, r.stderr
    text = (tmp_path / "j" / "a.macsec.json").read_text()
    bundle = json.loads(text)
    assert [x["id"] for x in bundle["associations"]] == ["link:n/ab"]
    b_key = certs["eap-cert:n/b"].split(b"-----BEGIN CERTIFICATE")[0].decode()
    ca_key = certs["eap-ca:n"].split(b"-----BEGIN CERTIFICATE")[0].decode()
    assert b_key not in text and ca_key not in text  # least privilege: never the CA's or a peer's key
    r = cli("macsec", "export", doc, *base, "--device", "a", "--format", "wpa_supplicant", "--out", tmp_path / "w")
    assert r.exit_code == 0, r.stderr
    names = sorted(p.name for p in (tmp_path / "w").iterdir())
    assert names == ["hcdf-n-a.key", "hcdf-n-a.pem", "hcdf-n-ca.pem", "wpa_supplicant-wired-p0.conf"]
    conf = (tmp_path / "w" / "wpa_supplicant-wired-p0.conf").read_text()
    assert "key_mgmt=IEEE8021X" in conf and "eap=TLS" in conf and "mka_cak" not in conf
    r = cli("macsec", "export", doc, *base, "--device", "a", "--format", "networkd", "--out", tmp_path / "nd")
    assert r.exit_code == 3 and "eap-tls needs MKA" in r.stderr


@pytest.mark.skipif(shutil.which("wpa_supplicant") is None, reason="wpa_supplicant not installed")
def test_wpa_supplicant_parses_the_eap_tls_block(eap, cli, tmp_path, netns):  # noqa: F811
    doc, base = eap
    assert cli("macsec", "generate", doc, *base).exit_code == 0
    out = tmp_path / "w"
    assert (
        cli("macsec", "export", doc, *base, "--device", "b", "--format", "wpa_supplicant", "--out", out).exit_code == 0
    )
    log = _wpa_log(netns, out / "wpa_supplicant-wired-p0.conf")
    assert "Failed to read or parse configuration" not in log and "unknown network field" not in log, log
    assert "macsec_linux: genl resolve failed" in log or "Failed to initialize driver" in log, log
