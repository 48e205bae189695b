"""``bundle push`` / ``bundle pull`` against a real registry (CNCF distribution on 127.0.0.1).

The oracles are independent of the code under test: the pulled file's bytes against the file
pushed, ``zipfile`` for the root entry's digest, the registry's own storage for what was sent;
each attack of issue 22 is played on the registry's disk or through its API (an endless blob
through the loopback test server), and a refused pull must leave ``--out`` as it was.
"""

from __future__ import annotations

import base64
import hashlib
import json
import shutil
import zipfile
from pathlib import Path

import pytest

from tests._oci import MANIFEST_TYPE, PASSWORD, USER, auth_registry, module_cli, registry, running_registry  # noqa: F401 -- fixtures
from tests.test_bundle import _entries, _hostile_cases, _zip

PROJECT = Path(__file__).resolve().parent.parent
REPO = "robots/bundle"
BUNDLE_TYPE = "application/vnd.hcdf.bundle.v1"
LAYER_TYPE = "application/vnd.hcdf.bundle.v1+zip"
pytestmark = pytest.mark.filterwarnings("ignore::ResourceWarning")


@pytest.fixture(scope="module")
def bundles(tmp_path_factory, registry):  # noqa: F811
    """The example robot bundled (pushed as b1), and a second revision of it (pushed as b2)."""
    cli = module_cli()
    tmp = tmp_path_factory.mktemp("bundles")
    shutil.copytree(PROJECT / "examples", tmp / "examples", ignore=shutil.ignore_patterns("out"))
    doc = tmp / "examples" / "robot" / "robot.hcdf"
    one = tmp / "scout2.hcdfz"
    assert cli("bundle", doc, one).exit_code == 0
    two = tmp / "scout2-b.hcdfz"
    doc.write_text(doc.read_text().replace('name="scout2"', 'name="scout3"', 1))
    r = cli("bundle", doc, two)
    assert r.exit_code == 0, r.stderr
    assert one.read_bytes() != two.read_bytes()
    for tag, path in (("b1", one), ("b2", two)):
        r = cli("bundle", "push", path, registry.ref(REPO, tag), "--json")
        assert r.exit_code == 0, r.stderr
    return one, two


def _doc(registry, tag="b1"):  # noqa: F811
    return json.loads(registry.manifest(REPO, tag)[0])


def _pull(cli, ref, dest, *extra):
    """``bundle pull``; a tag reference (unsigned bundles here) is taken as it is (--trust-tag)."""
    trust = () if "@sha256:" in str(ref) else ("--trust-tag",)
    return cli("bundle", "pull", ref, "--out", dest, *trust, *extra)


def _refused(r, dest, code, *words, before=None):
    assert r.exit_code == code, (r.exit_code, r.stdout, r.stderr)
    if before is None:
        assert not dest.exists(), "a refused pull wrote its output"
    else:
        assert dest.read_bytes() == before, "a refused pull changed its output"
    text = r.stdout + r.stderr
    for w in words:
        assert w in text, text


@pytest.fixture
def edited(registry):  # noqa: F811
    """Edit a file of the registry's storage; put it back afterwards."""
    saved = []

    def edit(path, data):
        saved.append((path, path.read_bytes()))
        path.chmod(0o644)
        path.write_bytes(data)

    yield edit
    for path, data in reversed(saved):
        path.write_bytes(data)


# --- the round trip --------------------------------------------------------------------------


def test_push_then_pull_gives_the_same_bytes_and_they_verify(cli, registry, bundles, tmp_path):  # noqa: F811
    one, _ = bundles
    dest = tmp_path / "pulled.hcdfz"
    r = _pull(cli, registry.ref(REPO, "b1"), dest, "--json", "--cache-dir", tmp_path / "cache")
    assert r.exit_code == 0, r.stderr
    assert dest.read_bytes() == one.read_bytes()
    assert r.json["sha256"] == hashlib.sha256(one.read_bytes()).hexdigest()
    assert r.json["root"] == "scout2.hcdf" and r.json["from_cache"] is False
    assert cli("verify", dest).exit_code == 0
    assert not [p for p in (tmp_path / "cache").iterdir() if p.name.startswith(".oci-pull-")]
    # by digest, from the content store this time
    again = tmp_path / "again.hcdfz"
    r2 = _pull(cli, registry.ref(REPO, "x").replace(":x", "@" + r.json["digest"]), again, "--json",
               "--cache-dir", tmp_path / "cache")  # fmt: skip
    assert r2.exit_code == 0, r2.stderr
    assert r2.json["from_cache"] is True and again.read_bytes() == one.read_bytes()


def test_the_artifact_is_documented_shape(registry, bundles):  # noqa: F811
    one, _ = bundles
    body, digest = registry.manifest(REPO, "b1")
    doc = json.loads(body)
    data = one.read_bytes()
    with zipfile.ZipFile(one) as z:
        root = z.infolist()[0]
        root_sha = hashlib.sha256(z.read(root)).hexdigest()
    assert doc["artifactType"] == BUNDLE_TYPE
    assert doc["config"]["mediaType"] == "application/vnd.oci.empty.v1+json"
    [layer] = doc["layers"]
    assert layer["mediaType"] == LAYER_TYPE
    assert layer["digest"] == "sha256:" + hashlib.sha256(data).hexdigest() and layer["size"] == len(data)
    assert layer["annotations"] == {"org.opencontainers.image.title": "scout2.hcdfz"}
    assert doc["annotations"] == {
        "dev.hcdf.root": root.filename,
        "dev.hcdf.root-sha256": root_sha,
        "dev.hcdf.bundle-sha256": hashlib.sha256(data).hexdigest(),
    }
    assert registry.blob_path(layer["digest"]).read_bytes() == data  # what the registry holds


def test_bundle_doc_out_still_writes_and_help_lists_push_pull(cli, bundles, tmp_path):
    r = cli("bundle", "--help")
    assert r.exit_code == 0 and "push" in r.stdout and "pull" in r.stdout and "DOC OUT.hcdfz" in r.stdout
    assert cli("bundle", "push", "--help").exit_code == 0
    one, _ = bundles
    doc = one.parent / "examples" / "robot" / "robot.hcdf"
    for args in (["--json", doc, tmp_path / "a.hcdfz"], ["write", doc, tmp_path / "b.hcdfz"]):
        r = cli("bundle", *args)  # options first, and the verb's own name: the same writer
        assert r.exit_code == 0, r.stderr
    assert (tmp_path / "a.hcdfz").read_bytes() == (tmp_path / "b.hcdfz").read_bytes()  # (the fixture made b2 last)


def test_tls_registry_trusted_through_ca_bundle_only(cli, bundles, tls, tmp_path_factory, tmp_path):
    """distribution serving TLS with a test CA's certificate: the same --ca-bundle as ota push/pull."""
    one, _ = bundles
    folder = tmp_path_factory.mktemp("registry-tls")
    cert = tls.ca.issue_cert("127.0.0.1")
    cert.cert_chain_pems[0].write_to_path(str(folder / "cert.pem"))
    cert.private_key_pem.write_to_path(str(folder / "key.pem"))
    with running_registry(folder, tls=(folder / "cert.pem", folder / "key.pem")) as reg:
        ref = reg.ref(REPO, "tls")
        r = cli("bundle", "push", one, ref, "--ca-bundle", tls.ca_pem)
        assert r.exit_code == 0, r.stderr
        r = _pull(cli, ref, tmp_path / "o.hcdfz", "--ca-bundle", tls.ca_pem)
        assert r.exit_code == 0, r.stderr
        assert (tmp_path / "o.hcdfz").read_bytes() == one.read_bytes()
        other = tmp_path / "other-ca.pem"
        tls.other_ca.cert_pem.write_to_path(str(other))
        r = _pull(cli, ref, tmp_path / "o2.hcdfz", "--ca-bundle", other)
        assert r.exit_code == 3 and "CERTIFICATE_VERIFY_FAILED" in r.stderr, r.stderr
        r = _pull(cli, ref, tmp_path / "o2.hcdfz")  # loopback without a CA: plain http
        assert r.exit_code == 3, r.stderr
        assert not (tmp_path / "o2.hcdfz").exists()


def test_a_bundle_changed_while_pushed_is_refused_and_its_manifest_not_pushed(cli, registry, bundles, monkeypatch):  # noqa: F811
    import hcdf_trust.localfile as localfile

    one, _ = bundles
    real = localfile.read_chunks

    def swapped(fd):  # the file as read for the upload differs from the file verified
        for chunk in real(fd):
            yield chunk[:-1] + bytes([chunk[-1] ^ 1])

    monkeypatch.setattr(localfile, "read_chunks", swapped)
    r = cli("bundle", "push", one, registry.ref("robots/changed", "changed"))  # a repository without the blob
    assert r.exit_code != 0
    assert "changed while it was being pushed" in r.stderr, r.stderr
    with registry.http() as c:
        assert c.get("/v2/robots/changed/manifests/changed").status_code == 404


# --- attacks: each refused, nothing written --------------------------------------------------


def test_blob_edited_on_the_registry_disk(cli, registry, bundles, edited, tmp_path):  # noqa: F811
    layer = _doc(registry)["layers"][0]
    path = registry.blob_path(layer["digest"])
    data = bytearray(path.read_bytes())
    data[200] ^= 1  # same size: the registry still announces the manifest's size
    edited(path, bytes(data))
    dest = tmp_path / "out.hcdfz"
    r = _pull(cli, registry.ref(REPO, "b1"), dest)
    _refused(r, dest, 1, "the blob's SHA-256 is not its digest in the manifest", layer["digest"])


def test_manifest_swapped_under_the_tag_is_refused_when_pinned(cli, registry, bundles, tmp_path):  # noqa: F811
    _, d1 = registry.manifest(REPO, "b1")
    body2, d2 = registry.manifest(REPO, "b2")
    registry.put_manifest(REPO, "swapped", registry.manifest(REPO, "b1")[0])
    pinned = registry.ref(REPO, "x").replace(":x", "@" + d1)
    registry.put_manifest(REPO, "swapped", body2)  # the tag now names the other bundle
    dest = tmp_path / "out.hcdfz"
    assert _pull(cli, pinned, dest).exit_code == 0  # the pin fetches by digest: the tag does not matter
    dest.unlink()
    r = cli("bundle", "pull", registry.ref(REPO, "swapped"), "--out", dest, "--json")
    assert r.exit_code == 2 and "--trust-tag" in r.stderr and not dest.exists()  # an unsigned tag: refused
    r = cli("bundle", "pull", registry.ref(REPO, "swapped"), "--out", dest, "--json", "--trust-tag")
    assert r.exit_code == 0 and r.json["digest"] == d2  # a tag taken as it is: what the registry says it is


def test_manifest_edited_on_disk_under_its_digest(cli, registry, bundles, edited, tmp_path):  # noqa: F811
    body, digest = registry.manifest(REPO, "b1")
    doc = json.loads(body)
    doc["annotations"]["dev.hcdf.root"] = "other.hcdf"
    edited(registry.blob_path(digest), json.dumps(doc, sort_keys=True, separators=(",", ":")).encode())
    dest = tmp_path / "out.hcdfz"
    r = _pull(cli, registry.ref(REPO, "x").replace(":x", "@" + digest), dest)
    _refused(r, dest, 1, "the manifest received is not the one pinned", digest)


def test_layer_digest_of_another_bundle(cli, registry, bundles, tmp_path):  # noqa: F811
    """The manifest of b1 with b2's blob as its layer: every hash holds, the annotations lie."""
    doc = _doc(registry, "b1")
    doc["layers"] = _doc(registry, "b2")["layers"]
    registry.put_manifest(REPO, "mixed", json.dumps(doc).encode())
    dest = tmp_path / "out.hcdfz"
    r = _pull(cli, registry.ref(REPO, "mixed"), dest)
    _refused(r, dest, 1, "manifest annotation dev.hcdf.root is not what the verified bundle says", "scout3.hcdf")


@pytest.mark.parametrize("delta", [-1, 1])
def test_layer_size_that_is_not_the_blobs(cli, registry, bundles, tmp_path, delta):  # noqa: F811
    doc = _doc(registry)
    doc["layers"][0]["size"] += delta
    registry.put_manifest(REPO, f"size{delta}", json.dumps(doc).encode())
    dest = tmp_path / "out.hcdfz"
    r = _pull(cli, registry.ref(REPO, f"size{delta}"), dest)
    _refused(r, dest, 3, "announces another size than the manifest's")


def test_two_layers_or_a_release_are_refused(cli, registry, bundles, tmp_path):  # noqa: F811
    doc = _doc(registry)
    second = dict(doc["layers"][0], annotations={"org.opencontainers.image.title": "b.hcdfz"})
    doc["layers"].append(second)
    registry.put_manifest(REPO, "two", json.dumps(doc).encode())
    dest = tmp_path / "out.hcdfz"
    _refused(_pull(cli, registry.ref(REPO, "two"), dest), dest, 3, "exactly one layer")
    doc = _doc(registry)
    doc["artifactType"] = "application/vnd.hcdf.release.v1"
    registry.put_manifest(REPO, "release", json.dumps(doc).encode())
    _refused(_pull(cli, registry.ref(REPO, "release"), dest), dest, 3, "not an hcdf-trust bundle")


def test_oversized_blob_on_the_registry_disk(cli, registry, bundles, edited, tmp_path):  # noqa: F811
    layer = _doc(registry)["layers"][0]
    path = registry.blob_path(layer["digest"])
    edited(path, path.read_bytes() + b"\0" * 4096)
    dest = tmp_path / "out.hcdfz"
    _refused(_pull(cli, registry.ref(REPO, "b1"), dest), dest, 3, "announces another size than the manifest's")


def test_endless_blob(cli, registry, bundles, http_server, tmp_path):  # noqa: F811
    body, digest = registry.manifest(REPO, "b1")  # served by the test server (mirror() wants referrers)
    doc = json.loads(body)
    http_server.add("/v2/", b"{}", headers={"Content-Type": "application/json"})
    http_server.add(f"/v2/{REPO}/manifests/b1", body, headers={"Content-Type": MANIFEST_TYPE})
    http_server.stream(f"/v2/{REPO}/blobs/{doc['layers'][0]['digest']}", 1 << 40, chunked=True)
    dest = tmp_path / "out.hcdfz"
    r = _pull(cli, f"oci://127.0.0.1:{http_server.port}/{REPO}:b1", dest)
    _refused(r, dest, 3, "blob is longer than the manifest's")


def test_a_declared_size_above_the_bundle_cap_is_refused_before_any_fetch(cli, registry, bundles, tmp_path):  # noqa: F811
    doc = _doc(registry)
    doc["layers"][0]["size"] = (2 << 30) + 1
    registry.put_manifest(REPO, "huge", json.dumps(doc).encode())
    dest = tmp_path / "out.hcdfz"
    _refused(_pull(cli, registry.ref(REPO, "huge"), dest), dest, 3, "size is not an integer from 0 to 2147483648")


def _push_raw(registry, data: bytes, tag: str, name: str = "hostile.hcdfz") -> str:  # noqa: F811
    """What a hostile publisher pushes, past our own push's checks: the blob and a manifest of
    the documented shape (annotations copied from b1's, which the pull never gets to)."""
    digest = registry.put_blob(REPO, data)
    doc = _doc(registry)
    doc["layers"] = [
        {
            "mediaType": LAYER_TYPE,
            "digest": digest,
            "size": len(data),
            "annotations": {"org.opencontainers.image.title": name},
        }
    ]
    registry.put_manifest(REPO, tag, json.dumps(doc).encode())
    return registry.ref(REPO, tag)


@pytest.mark.parametrize("case", ["dot-dot", "symlink", "data-before", "bomb", "local-header", "compressed"])
def test_hostile_bundle_is_refused_on_push_and_on_pull(cli, registry, bundles, tmp_path, case):  # noqa: F811
    one, _ = bundles
    data, what, _ = _hostile_cases(_entries(one))[case]
    hostile = tmp_path / "hostile.hcdfz"
    hostile.write_bytes(data)
    r = cli("bundle", "push", hostile, registry.ref(REPO, f"h-{case}"))
    assert r.exit_code == 3 and what in r.stderr, r.stderr
    with registry.http() as c:  # refused before anything was sent
        assert c.get(f"/v2/{REPO}/manifests/h-{case}").status_code == 404
        assert c.head(f"/v2/{REPO}/blobs/sha256:{hashlib.sha256(data).hexdigest()}").status_code == 404
    ref = _push_raw(registry, data, f"raw-{case}")
    dest = tmp_path / "out.hcdfz"
    cache = tmp_path / "cache"
    r = _pull(cli, ref, dest, "--cache-dir", cache, "--json")
    _refused(r, dest, 3, what, '"code": "bundle-format"')
    assert not [p for p in cache.iterdir() if p.name.startswith(".oci-pull-")], "the staging folder is left"


def test_a_bundle_whose_asset_is_not_its_pin_is_refused(cli, registry, bundles, tmp_path):  # noqa: F811
    one, _ = bundles
    entries = _entries(one)
    name, blob = entries[1]
    entries[1] = (name, bytes([blob[0] ^ 1]) + blob[1:])
    dest = tmp_path / "out.hcdfz"
    dest.write_bytes(b"previous")  # an existing file is left as it was
    r = _pull(cli, _push_raw(registry, _zip(entries), "tampered"), dest, "--json")
    _refused(r, dest, 1, '"code": "digest-mismatch"', name, before=b"previous")


def test_push_refuses_a_bundle_whose_content_does_not_verify(cli, registry, bundles, tmp_path):  # noqa: F811
    one, _ = bundles
    entries = _entries(one)
    entries[1] = (entries[1][0], b"x" + entries[1][1][1:])
    bad = tmp_path / "bad.hcdfz"
    bad.write_bytes(_zip(entries))
    r = cli("bundle", "push", bad, registry.ref(REPO, "bad"))
    assert r.exit_code == 1, r.stderr
    with registry.http() as c:
        assert c.get(f"/v2/{REPO}/manifests/bad").status_code == 404


def test_out_must_be_a_bundle_name_and_not_a_document(cli, registry, bundles, tmp_path):  # noqa: F811
    r = _pull(cli, registry.ref(REPO, "b1"), tmp_path / "robot.hcdf")
    assert r.exit_code == 2 and not (tmp_path / "robot.hcdf").exists()
    doc = tmp_path / "doc.hcdfz"
    doc.write_text('<hcdf version="1.0"/>\n')  # a document named like a bundle is not replaced
    _refused(_pull(cli, registry.ref(REPO, "b1"), doc), doc, 3, before=b'<hcdf version="1.0"/>\n')


# --- credentials -----------------------------------------------------------------------------


def test_credentials_from_the_environment_never_printed(cli, auth_registry, bundles, monkeypatch, tmp_path):  # noqa: F811
    one, _ = bundles
    secrets = [PASSWORD, base64.b64encode(f"{USER}:{PASSWORD}".encode()).decode()]
    monkeypatch.setenv("HCDF_TRUST_OCI_USERNAME", USER)
    monkeypatch.setenv("HCDF_TRUST_OCI_PASSWORD", PASSWORD)
    runs = [cli("bundle", "push", one, auth_registry.ref(tag="b1"), "--json")]
    runs.append(_pull(cli, auth_registry.ref(tag="b1"), tmp_path / "o.hcdfz", "--json"))
    assert [r.exit_code for r in runs] == [0, 0], [r.stderr for r in runs]
    assert (tmp_path / "o.hcdfz").read_bytes() == one.read_bytes()
    wrong = "Wr0ng-" + PASSWORD
    monkeypatch.setenv("HCDF_TRUST_OCI_PASSWORD", wrong)
    secrets += [wrong, base64.b64encode(f"{USER}:{wrong}".encode()).decode()]
    for args in ([], ["--json"]):
        r = _pull(cli, auth_registry.ref(tag="b1"), tmp_path / "w.hcdfz", *args)
        assert r.exit_code == 3 and "the credentials were refused" in r.stdout + r.stderr
        runs.append(r)
    monkeypatch.delenv("HCDF_TRUST_OCI_PASSWORD")
    monkeypatch.delenv("HCDF_TRUST_OCI_USERNAME")
    r = cli("bundle", "push", one, auth_registry.ref(tag="anon"))
    assert r.exit_code == 3 and "(none were found)" in r.stderr
    assert not (tmp_path / "w.hcdfz").exists()
    for r in runs:
        for s in secrets:
            assert s not in r.stdout and s not in r.stderr
