"""``validate --registry`` and ``audit --registry`` over https and oci:// with a private CA
(``--ca-bundle``, its environment fallback) and ``--insecure-registry``, with the meaning the
other verbs give them (issue 22's leftovers).

Real servers on 127.0.0.1: the loopback https server (a test CA's certificate) serving the
published TUF site, and the CNCF distribution registry with TLS holding the same site as an
OCI artifact (``registry publish --oci``). The oracle is the verdict the same document gets
against the site as a folder: the same findings, trusted through the CA and refused without it.
"""

from __future__ import annotations

import pytest

from tests._oci import running_registry
from tests._registry import PASSPHRASE, build

pytestmark = pytest.mark.filterwarnings("ignore::ResourceWarning")
BODY = (
    '<comp name="c">\n<extension domain="com.example.unknown" version="1.0"><x/></extension>\n'
    '<extension domain="org.ros2" version="1.0"><not-ros/></extension>\n</comp>'
)


@pytest.fixture
def site(cli, tmp_path, monkeypatch):
    monkeypatch.setenv("HCDF_TRUST_PASSPHRASE", PASSPHRASE)
    monkeypatch.delenv("HCDF_TRUST_CA_BUNDLE", raising=False)
    reg = build(tmp_path / "reg", cli)
    doc = tmp_path / "robot.hcdf"
    doc.write_text(f'<hcdf version="1.0">\n{BODY}\n</hcdf>\n')
    return reg, doc


def _codes(r, key):
    return sorted((f["code"], f["line"]) for f in r.json[key] if f["code"].startswith("extension"))


def _run(cli, reg, verb, doc, where, *extra):
    online = ("--online",) if verb == "audit" and "://" in str(where) else ()
    return cli(verb, doc, "--registry", where, "--trusted-root", reg.root_json, "--json", *online, *extra)


@pytest.mark.parametrize("verb", ["validate", "audit"])
def test_an_https_registry_is_trusted_through_the_ca_bundle_only(cli, site, serve, tls, tmp_path, monkeypatch, verb):
    reg, doc = site
    key = "findings"
    local = _run(cli, reg, verb, doc, reg.site)
    want = _codes(local, key)
    assert ("extension-content", 4) in want, local.stdout  # the oracle: the site as a folder
    srv = serve("good", root=reg.site)
    r = _run(cli, reg, verb, doc, srv.base, "--ca-bundle", tls.ca_pem)
    assert r.exit_code == local.exit_code and _codes(r, key) == want, (r.stdout, r.stderr)
    # the environment variable is the flag's fallback
    monkeypatch.setenv("HCDF_TRUST_CA_BUNDLE", str(tls.ca_pem))
    r = _run(cli, reg, verb, doc, srv.base)
    assert r.exit_code == local.exit_code and _codes(r, key) == want, (r.stdout, r.stderr)
    monkeypatch.delenv("HCDF_TRUST_CA_BUNDLE")
    # without it, or with another CA: refused (exit 3), nothing checked against an untrusted site
    other = tmp_path / "other-ca.pem"
    tls.other_ca.cert_pem.write_to_path(str(other))
    for extra in ([], ["--ca-bundle", other]):
        r = _run(cli, reg, verb, doc, srv.base, *extra)
        assert r.exit_code == 3, (extra, r.stdout, r.stderr)
        assert "CERTIFICATE_VERIFY_FAILED" in r.stdout + r.stderr or "certificate" in (r.stdout + r.stderr).lower()


@pytest.mark.parametrize("verb", ["validate", "audit"])
def test_an_oci_registry_with_tls_and_insecure_registry(cli, site, tls, tmp_path_factory, tmp_path, verb):
    """The site as an OCI artifact on a TLS registry (--ca-bundle), and on a plain-http one
    that a --ca-bundle would otherwise make us talk https to (--insecure-registry)."""
    reg, doc = site
    want = _codes(_run(cli, reg, verb, doc, reg.site), "findings")
    folder = tmp_path_factory.mktemp("registry-tls")
    cert = tls.ca.issue_cert("127.0.0.1")
    cert.cert_chain_pems[0].write_to_path(str(folder / "cert.pem"))
    cert.private_key_pem.write_to_path(str(folder / "key.pem"))
    with running_registry(folder, tls=(folder / "cert.pem", folder / "key.pem")) as oci:
        ref = oci.ref("hcdf/registry", "v1")
        assert reg.publish("--oci", ref, "--ca-bundle", tls.ca_pem).exit_code == 0
        r = _run(cli, reg, verb, doc, ref, "--ca-bundle", tls.ca_pem)
        assert _codes(r, "findings") == want, (r.stdout, r.stderr)
        r = _run(cli, reg, verb, doc, ref)  # loopback without a CA bundle: plain http to a TLS server
        assert r.exit_code == 3, (r.stdout, r.stderr)
    with running_registry(tmp_path_factory.mktemp("registry-plain")) as plain:
        ref = plain.ref("hcdf/registry", "v1")
        assert reg.publish("--oci", ref).exit_code == 0
        r = _run(cli, reg, verb, doc, ref, "--ca-bundle", tls.ca_pem)  # https to a plain server
        assert r.exit_code == 3, (r.stdout, r.stderr)
        r = _run(cli, reg, verb, doc, ref, "--ca-bundle", tls.ca_pem, "--insecure-registry", plain.netloc)
        assert _codes(r, "findings") == want, (r.stdout, r.stderr)


def test_audit_online_fetches_a_remote_file_through_the_ca_bundle(cli, https_server, tls, tmp_path, monkeypatch):
    """--ca-bundle also covers audit --online's fetches, as bundle's and ota build's."""
    import hashlib

    monkeypatch.delenv("HCDF_TRUST_CA_BUNDLE", raising=False)
    data = b"glTF" + bytes(range(200))
    digest = hashlib.sha256(data).hexdigest()
    url = https_server.add("/models/wheel.glb", data)
    doc = tmp_path / "r.hcdf"
    doc.write_text(
        f'<?xml version="1.0"?>\n<hcdf version="1.0" name="r"><comp name="c"><visual name="v">'
        f'<model uri="{url}" sha="{digest}"/></visual></comp></hcdf>\n'
    )
    cache = tmp_path / "cache"
    r = cli("audit", doc, "--online", "--cache-dir", cache, "--json")  # the server's CA is not trusted
    assert r.exit_code != 0 and "wheel.glb" in r.stdout + r.stderr, (r.stdout, r.stderr)
    r = cli("audit", doc, "--online", "--cache-dir", cache, "--ca-bundle", tls.ca_pem, "--json")
    fetch_errors = [f for f in r.json["findings"] if f["severity"] == "error"]
    assert fetch_errors == [], r.stdout
