"""Provenance and SBOM referrers (issue 22): ``ota push`` attaches a release's
``provenance.intoto.json`` and each ``--sbom`` as referrers of the release manifest;
``ota pull`` verifies the provenance it finds as ``ota verify --provenance`` does and, with
``--require-provenance``, refuses a release without one. Each attack leaves nothing written.

A real registry (CNCF distribution on 127.0.0.1, no referrers API: the ``sha256-<hex>`` tag
index) is edited through its API or on its disk; the referrers-API path is replayed by the
loopback test server.
"""

from __future__ import annotations

import hashlib
import json

import pytest

from tests._oci import INDEX_TYPE, MANIFEST_TYPE, mirror, module_cli, registry  # noqa: F401 -- fixture
from tests._ota import make_robot, tree

pytestmark = pytest.mark.filterwarnings("ignore::ResourceWarning")
PROVENANCE_TYPE = "application/vnd.hcdf.release.provenance.v1"
SIGNATURE_TYPE = "application/vnd.hcdf.release.signature.v1"
SBOM_TYPE = "application/vnd.hcdf.release.sbom.v1"


@pytest.fixture(scope="module")
def releases(tmp_path_factory):
    """Release 1 and release 2 of one robot (one key), both built with --provenance; and
    release 1 again, built without."""
    cli = module_cli()
    tmp = tmp_path_factory.mktemp("prov")
    robot = make_robot(tmp, cli)
    r1, r2, bare = tmp / "r1", tmp / "r2", tmp / "bare"
    assert robot.build(cli, r1, "--provenance").exit_code == 0
    assert robot.build(cli, bare).exit_code == 0
    robot.rewrite(cli, flex_version="v0.3.0")
    r = robot.build(cli, r2, "--previous", r1, "--provenance")
    assert r.exit_code == 0, r.stderr
    return robot, r1, r2, bare


def _push(cli, registry, repo, folder, robot, *extra):  # noqa: F811
    r = cli("ota", "push", folder, registry.ref(repo, "1"), "--key", robot.pub, "--json", *extra)
    assert r.exit_code == 0, r.stderr
    return r.json


def _pull(cli, registry, repo, robot, dest, *extra):  # noqa: F811
    return cli("ota", "pull", registry.ref(repo, "1"), "--key", robot.pub, "--out", dest, *extra)


def _refused(r, dest, code, *words):
    assert r.exit_code == code, (r.exit_code, r.stderr)
    assert not dest.exists(), "a refused pull wrote its output folder"
    for w in words:
        assert w in r.stderr, r.stderr


def _index(registry, repo, digest):  # noqa: F811
    body, _ = registry.manifest(repo, digest.replace(":", "-"))
    return json.loads(body)


def _set_index(registry, repo, digest, manifests):  # noqa: F811
    index = {"schemaVersion": 2, "mediaType": INDEX_TYPE, "manifests": manifests}
    registry.put_manifest(repo, digest.replace(":", "-"), json.dumps(index).encode(), INDEX_TYPE)


def test_provenance_is_a_referrer_and_pull_verifies_it(cli, registry, releases, tmp_path):  # noqa: F811
    robot, r1, _, _ = releases
    pushed = _push(cli, registry, "prov/happy", r1, robot)
    digest = pushed["digest"]
    # not a layer of the release: a referrer with its own type, subject = the release manifest
    titles = {x["annotations"]["org.opencontainers.image.title"] for x in pushed["layers"]}
    assert "provenance.intoto.json" not in titles
    kinds = {e["artifactType"]: e for e in _index(registry, "prov/happy", digest)["manifests"]}
    assert set(kinds) == {SIGNATURE_TYPE, PROVENANCE_TYPE}
    body, _ = registry.manifest("prov/happy", kinds[PROVENANCE_TYPE]["digest"])
    doc = json.loads(body)
    assert doc["subject"]["digest"] == digest and doc["artifactType"] == PROVENANCE_TYPE
    (layer,) = doc["layers"]
    assert layer["mediaType"] == "application/vnd.dsse.envelope.v1+json"
    assert layer["annotations"]["in-toto.io/predicate-type"] == "https://slsa.dev/provenance/v1"
    data = (r1 / "provenance.intoto.json").read_bytes()
    assert layer["digest"] == "sha256:" + hashlib.sha256(data).hexdigest()
    assert registry.blob_path(layer["digest"]).read_bytes() == data

    dest = tmp_path / "out"
    r = _pull(cli, registry, "prov/happy", robot, dest, "--require-provenance", "--json")
    assert r.exit_code == 0, r.stderr
    assert r.json["provenance"] == kinds[PROVENANCE_TYPE]["digest"]
    assert tree(dest) == tree(r1)  # provenance.intoto.json included, byte for byte
    r = cli("ota", "verify", dest, "--key", robot.pub, "--provenance")
    assert r.exit_code == 0, r.stderr


def test_require_provenance_without_one_fails_with_nothing_written(cli, registry, releases, tmp_path):  # noqa: F811
    robot, _, _, bare = releases
    _push(cli, registry, "prov/bare", bare, robot)
    dest = tmp_path / "out"
    r = _pull(cli, registry, "prov/bare", robot, dest, "--require-provenance")
    _refused(r, dest, 1, "no provenance referrer is listed (--require-provenance)")
    r = _pull(cli, registry, "prov/bare", robot, dest, "--json")  # not required: the release verifies
    assert r.exit_code == 0, r.stderr
    assert r.json["provenance"] is None and tree(dest) == tree(bare)


def test_provenance_referrer_removed(cli, registry, releases, tmp_path):  # noqa: F811
    robot, r1, _, _ = releases
    digest = _push(cli, registry, "prov/removed", r1, robot)["digest"]
    kept = [e for e in _index(registry, "prov/removed", digest)["manifests"] if e["artifactType"] != PROVENANCE_TYPE]
    _set_index(registry, "prov/removed", digest, kept)
    dest = tmp_path / "out"
    r = _pull(cli, registry, "prov/removed", robot, dest, "--require-provenance")
    _refused(r, dest, 1, "no provenance referrer", digest)
    # without the flag the release itself still verifies, and the report says no provenance
    r = _pull(cli, registry, "prov/removed", robot, dest, "--json")
    assert r.exit_code == 0, r.stderr
    assert r.json["provenance"] is None
    assert "provenance.intoto.json" not in tree(dest)


def test_provenance_referrer_of_another_release(cli, registry, releases, tmp_path):  # noqa: F811
    """Release 1's provenance referrer listed under release 2: its subject is release 1."""
    robot, r1, r2, _ = releases
    d1 = _push(cli, registry, "prov/other1", r1, robot)["digest"]
    pushed2 = cli("ota", "push", r2, registry.ref("prov/other1", "2"), "--key", robot.pub, "--json")
    assert pushed2.exit_code == 0, pushed2.stderr
    d2 = pushed2.json["digest"]
    theirs = [e for e in _index(registry, "prov/other1", d1)["manifests"] if e["artifactType"] == PROVENANCE_TYPE]
    ours = [e for e in _index(registry, "prov/other1", d2)["manifests"] if e["artifactType"] != PROVENANCE_TYPE]
    _set_index(registry, "prov/other1", d2, ours + theirs)
    dest = tmp_path / "out"
    r = cli("ota", "pull", registry.ref("prov/other1", "2"), "--key", robot.pub, "--out", dest)
    _refused(r, dest, 1, "points at another release", d1, d2)


def test_older_releases_provenance_reattached_to_a_newer_release(cli, registry, releases, tmp_path):  # noqa: F811
    """A referrer that does name release 2 as its subject, but carries release 1's statement
    (signed by the same key): the statement's subjects and dependencies are release 1's."""
    robot, r1, r2, _ = releases
    digest = _push(cli, registry, "prov/reattached", r2, robot)["digest"]
    old = (r1 / "provenance.intoto.json").read_bytes()
    blob = registry.put_blob("prov/reattached", old)
    body, _ = registry.manifest("prov/reattached", digest)
    doc = {
        "schemaVersion": 2,
        "mediaType": MANIFEST_TYPE,
        "artifactType": PROVENANCE_TYPE,
        "config": {
            "mediaType": "application/vnd.oci.empty.v1+json",
            "digest": registry.put_blob("prov/reattached", b"{}"),
            "size": 2,
        },
        "layers": [{"mediaType": "application/vnd.dsse.envelope.v1+json", "digest": blob, "size": len(old)}],
        "subject": {"mediaType": MANIFEST_TYPE, "digest": digest, "size": len(body)},
    }
    raw = json.dumps(doc).encode()
    forged = registry.put_manifest("prov/reattached", "sha256:" + hashlib.sha256(raw).hexdigest(), raw)
    kept = [e for e in _index(registry, "prov/reattached", digest)["manifests"] if e["artifactType"] != PROVENANCE_TYPE]
    entry = {"mediaType": MANIFEST_TYPE, "digest": forged, "size": len(raw), "artifactType": PROVENANCE_TYPE}
    _set_index(registry, "prov/reattached", digest, [*kept, entry])
    dest = tmp_path / "out"
    r = _pull(cli, registry, "prov/reattached", robot, dest)
    _refused(r, dest, 1, "provenance")
    assert "SHA-256 differs" in r.stderr or "differs" in r.stderr, r.stderr


def test_provenance_blob_edited_on_the_registry_disk(cli, registry, releases, tmp_path):  # noqa: F811
    robot, r1, _, _ = releases
    _push(cli, registry, "prov/edited", r1, robot)
    data = (r1 / "provenance.intoto.json").read_bytes()
    path = registry.blob_path("sha256:" + hashlib.sha256(data).hexdigest())
    edited = bytearray(data)
    edited[len(edited) // 2] ^= 1  # same size: the registry still announces the same digest
    path.chmod(0o644)
    path.write_bytes(bytes(edited))
    try:
        dest = tmp_path / "out"
        r = _pull(cli, registry, "prov/edited", robot, dest)  # verified whenever listed, required or not
        _refused(r, dest, 1, "its blob is not its digest")
    finally:
        path.write_bytes(data)


def test_two_different_provenances_are_ambiguous(cli, registry, releases, tmp_path):  # noqa: F811
    robot, r1, r2, _ = releases
    d1 = _push(cli, registry, "prov/two", r1, robot)["digest"]
    pushed2 = cli("ota", "push", r2, registry.ref("prov/two", "2"), "--key", robot.pub)
    assert pushed2.exit_code == 0, pushed2.stderr
    # release 2's provenance blob, in a referrer that names release 1 as its subject
    body, _ = registry.manifest("prov/two", d1)
    first = next(e for e in _index(registry, "prov/two", d1)["manifests"] if e["artifactType"] == PROVENANCE_TYPE)
    doc = json.loads(registry.manifest("prov/two", first["digest"])[0])
    data = (r2 / "provenance.intoto.json").read_bytes()
    doc["layers"][0]["digest"] = "sha256:" + hashlib.sha256(data).hexdigest()
    doc["layers"][0]["size"] = len(data)
    raw = json.dumps(doc).encode()
    forged = registry.put_manifest("prov/two", "sha256:" + hashlib.sha256(raw).hexdigest(), raw)
    entries = _index(registry, "prov/two", d1)["manifests"]
    _set_index(registry, "prov/two", d1, [*entries, {**first, "digest": forged, "size": len(raw)}])
    dest = tmp_path / "out"
    r = _pull(cli, registry, "prov/two", robot, dest)
    _refused(r, dest, 1, "2 provenance referrers with different envelopes")


def test_provenance_through_the_referrers_api(cli, registry, releases, http_server, tmp_path):  # noqa: F811
    robot, r1, _, _ = releases
    _push(cli, registry, "prov/api", r1, robot)
    digest, _ = mirror(http_server, registry, "prov/api", "1", referrers_api=True)
    dest = tmp_path / "out"
    r = cli(
        "ota", "pull", f"oci://127.0.0.1:{http_server.port}/prov/api:1", "--key", robot.pub, "--out", dest,
        "--require-provenance", "--json",
    )  # fmt: skip
    assert r.exit_code == 0, r.stderr
    assert r.json["provenance"] is not None
    assert http_server.hits[f"/v2/prov/api/manifests/{digest.replace(':', '-')}"] == 0
    assert tree(dest) == tree(r1)


def test_a_co_signed_provenance_needs_the_threshold(cli, registry, releases, tmp_path):  # noqa: F811
    robot, r1, _, _ = releases
    _push(cli, registry, "prov/threshold", r1, robot)
    dest = tmp_path / "out"
    r = _pull(cli, registry, "prov/threshold", robot, dest, "--threshold", "2")
    assert r.exit_code == 2 and "needs as many distinct keys" in r.stderr
    other = tmp_path / "other.pem"
    assert cli("ota", "keygen", "-o", other).exit_code == 0
    r = _pull(
        cli, registry, "prov/threshold", robot, dest, "--provenance-key", tmp_path / "other.pub.pem", "--threshold", "2"
    )
    _refused(r, dest, 1)


def test_sbom_referrer(cli, registry, releases, tmp_path):  # noqa: F811
    robot, _, r2, _ = releases  # the robot document is release 2's now
    sbom = tmp_path / "release.cdx.json"
    r = cli("sbom", robot.doc, "--format", "cyclonedx", "--release", r2, "--key", robot.pub, "-o", sbom)
    assert r.exit_code == 0, r.stderr
    pushed = _push(cli, registry, "prov/sbom", r2, robot, "--sbom", sbom)
    kinds = {e["artifactType"]: e for e in _index(registry, "prov/sbom", pushed["digest"])["manifests"]}
    assert set(kinds) == {SIGNATURE_TYPE, PROVENANCE_TYPE, SBOM_TYPE}
    (layer,) = json.loads(registry.manifest("prov/sbom", kinds[SBOM_TYPE]["digest"])[0])["layers"]
    assert layer["mediaType"] == "application/vnd.cyclonedx+json"
    assert registry.blob_path(layer["digest"]).read_bytes() == sbom.read_bytes()
    r = _pull(cli, registry, "prov/sbom", robot, tmp_path / "out", "--json")
    assert r.exit_code == 0, r.stderr
    assert [s["mediaType"] for s in r.json["sboms"]] == ["application/vnd.cyclonedx+json"]
    # not an SBOM: refused before anything is sent
    bogus = tmp_path / "bogus.json"
    bogus.write_text('{"hello": 1}')
    r = cli("ota", "push", r2, registry.ref("prov/nosbom", "1"), "--sbom", bogus)
    assert r.exit_code == 3 and "not a CycloneDX" in r.stderr
    with registry.http() as c:
        assert c.get("/v2/prov/nosbom/tags/list").status_code == 404
