"""``registry publish --oci`` and ``registry verify|fetch oci://…``: the TUF site through the real
registry; the TUF client's rules still decide, the OCI layer only transports (and hashes)."""

from __future__ import annotations

import json

import pytest

from tests._oci import registry  # noqa: F401 -- fixture
from tests._registry import PASSPHRASE, ROS2_XSD, build

pytestmark = pytest.mark.filterwarnings("ignore::ResourceWarning")
REPO = "hcdf/registry"


@pytest.fixture
def site(tmp_path, cli, monkeypatch, registry):  # noqa: F811
    monkeypatch.setenv("HCDF_TRUST_PASSPHRASE", PASSPHRASE)
    reg = build(tmp_path, cli)
    r = reg.publish("--oci", registry.ref(REPO, "v1"), "--json")
    assert r.exit_code == 0, r.stderr
    return reg, r.json["oci"]["digest"]


def test_publish_oci_then_verify_and_fetch_from_the_registry(cli, site, registry, tmp_path):  # noqa: F811
    reg, digest = site
    body, got = registry.manifest(REPO, "v1")
    assert got == digest
    doc = json.loads(body)
    assert doc["artifactType"] == "application/vnd.hcdf.registry.site.v1"
    titles = {x["annotations"]["org.opencontainers.image.title"] for x in doc["layers"]}
    assert titles == {str(p.relative_to(reg.site)) for p in reg.site.rglob("*") if p.is_file()}
    r = reg.verify(registry.ref(REPO, "v1"), cache="oci-client")
    assert r.exit_code == 0, r.stderr
    pinned = registry.ref(REPO, "x").replace(":x", "@" + digest)
    out = tmp_path / "ros2.xsd"
    r = reg.fetch("org.ros2", out=out, site=pinned, cache="oci-client2")
    assert r.exit_code == 0, r.stderr
    assert out.read_bytes() == ROS2_XSD.read_bytes()


def test_target_blob_edited_on_the_registry_disk(cli, site, registry, tmp_path):  # noqa: F811
    reg, _ = site
    doc = json.loads(registry.manifest(REPO, "v1")[0])
    layer = next(x for x in doc["layers"] if "org.ros2" in x["annotations"]["org.opencontainers.image.title"]
                 and x["mediaType"].endswith("target.v1"))  # fmt: skip
    path = registry.blob_path(layer["digest"])
    data = bytearray(path.read_bytes())
    data[10] ^= 1
    path.chmod(0o644)
    path.write_bytes(bytes(data))
    out = tmp_path / "ros2.xsd"
    r = reg.fetch("org.ros2", out=out, site=registry.ref(REPO, "v1"), cache="c3")
    assert r.exit_code != 0, r.stderr
    assert not out.exists()


def test_metadata_blob_edited_on_the_registry_disk(cli, site, registry):  # noqa: F811
    reg, _ = site
    doc = json.loads(registry.manifest(REPO, "v1")[0])
    layer = next(
        x for x in doc["layers"] if x["annotations"]["org.opencontainers.image.title"] == "metadata/timestamp.json"
    )
    path = registry.blob_path(layer["digest"])
    data = bytearray(path.read_bytes())
    at = data.index(b'"sig":"') + 8  # one hex digit of the signature: same size
    data[at] = ord("0") if data[at] != ord("0") else ord("1")
    path.chmod(0o644)
    path.write_bytes(bytes(data))
    r = reg.verify(registry.ref(REPO, "v1"), cache="c4")
    assert r.exit_code != 0
    assert "metadata/timestamp.json: the blob's SHA-256 is not its digest in the site manifest" in r.stderr, r.stderr


def test_site_layer_title_traversing(cli, site, registry):  # noqa: F811
    reg, _ = site
    doc = json.loads(registry.manifest(REPO, "v1")[0])
    doc["layers"][0]["annotations"]["org.opencontainers.image.title"] = "../../metadata/x"
    registry.put_manifest(REPO, "evil", json.dumps(doc).encode())
    r = reg.verify(registry.ref(REPO, "evil"), cache="c5")
    assert r.exit_code == 3 and "is not a plain relative path" in r.stderr, r.stderr


def test_release_is_not_a_site(cli, site, registry):  # noqa: F811
    reg, _ = site
    doc = json.loads(registry.manifest(REPO, "v1")[0])
    doc["artifactType"] = "application/vnd.hcdf.release.v1"
    registry.put_manifest(REPO, "release", json.dumps(doc).encode())
    r = reg.verify(registry.ref(REPO, "release"), cache="c6")
    assert r.exit_code == 3 and "not an hcdf-trust registry site" in r.stderr, r.stderr


def test_tls_registry_and_https_site_trust_the_ca_bundle_only(cli, tmp_path, monkeypatch, tls, serve, tmp_path_factory):
    """--ca-bundle on publish --oci, verify and fetch, over a TLS registry (distribution with a
    test CA's certificate) and over an https site: trusted through it, refused without it."""
    from tests._oci import running_registry

    monkeypatch.setenv("HCDF_TRUST_PASSPHRASE", PASSPHRASE)
    monkeypatch.delenv("HCDF_TRUST_CA_BUNDLE", raising=False)
    reg = build(tmp_path, cli)
    folder = tmp_path_factory.mktemp("registry-tls")
    cert = tls.ca.issue_cert("127.0.0.1")
    cert.cert_chain_pems[0].write_to_path(str(folder / "cert.pem"))
    cert.private_key_pem.write_to_path(str(folder / "key.pem"))
    other = tmp_path / "other-ca.pem"
    tls.other_ca.cert_pem.write_to_path(str(other))
    with running_registry(folder, tls=(folder / "cert.pem", folder / "key.pem")) as oci:
        ref = oci.ref(REPO, "v1")
        r = reg.publish("--oci", ref, "--ca-bundle", tls.ca_pem, "--json")
        assert r.exit_code == 0, r.stderr
        r = cli("registry", "verify", ref, "--trusted-root", reg.root_json, "--cache-dir", tmp_path / "c1",
                "--ca-bundle", tls.ca_pem)  # fmt: skip
        assert r.exit_code == 0, r.stderr
        out = tmp_path / "ros2.xsd"
        r = cli("registry", "fetch", "org.ros2", "--from", ref, "--trusted-root", reg.root_json,
                "--cache-dir", tmp_path / "c2", "-o", out, "--ca-bundle", tls.ca_pem)  # fmt: skip
        assert r.exit_code == 0, r.stderr
        assert out.read_bytes() == ROS2_XSD.read_bytes()
        # the same through the environment variable (the flag's fallback)
        monkeypatch.setenv("HCDF_TRUST_CA_BUNDLE", str(tls.ca_pem))
        r = cli("registry", "verify", ref, "--trusted-root", reg.root_json, "--cache-dir", tmp_path / "c3")
        assert r.exit_code == 0, r.stderr
        monkeypatch.delenv("HCDF_TRUST_CA_BUNDLE")
        r = cli("registry", "verify", ref, "--trusted-root", reg.root_json, "--cache-dir", tmp_path / "c4",
                "--ca-bundle", other)  # fmt: skip
        assert r.exit_code == 3 and "CERTIFICATE_VERIFY_FAILED" in r.stderr, r.stderr
    # an https site (python-tuf's urllib3 fetcher) trusts the same bundle
    site = serve("good", root=reg.site)
    r = cli("registry", "verify", site.url("/"), "--trusted-root", reg.root_json, "--cache-dir", tmp_path / "c5",
            "--ca-bundle", tls.ca_pem)  # fmt: skip
    assert r.exit_code == 0, r.stderr
    r = cli("registry", "verify", site.url("/"), "--trusted-root", reg.root_json, "--cache-dir", tmp_path / "c6")
    assert r.exit_code == 3, r.stderr


def test_ca_bundle_and_insecure_registry_mean_the_same_in_every_verb():
    """One option object per flag: same help, type and environment variable everywhere."""
    from tests.test_flags_uniform import VERBS, _option

    tls_verbs = ["ota build", "ota verify", "ota push", "ota pull", "registry publish", "registry verify",
                 "registry fetch", "resolve", "pin", "validate", "audit", "bundle write", "bundle push",
                 "bundle pull"]  # fmt: skip
    for verb in tls_verbs:
        opt = _option(VERBS[verb], "--ca-bundle")
        assert opt is not None, verb
        assert (opt.help, opt.envvar) == (_option(VERBS["ota pull"], "--ca-bundle").help, "HCDF_TRUST_CA_BUNDLE")
    oci_verbs = ("ota push", "ota pull", "registry publish", "registry verify", "registry fetch", "validate", "audit",
                 "bundle push", "bundle pull")  # fmt: skip
    for verb in oci_verbs:
        opt = _option(VERBS[verb], "--insecure-registry")
        assert opt is not None and opt.multiple, verb
        assert opt.help == _option(VERBS["ota pull"], "--insecure-registry").help, verb
    helps = {v: _option(c, "--ca-bundle").help for v, c in VERBS.items() if _option(c, "--ca-bundle") is not None}
    assert len(set(helps.values())) == 1, helps
