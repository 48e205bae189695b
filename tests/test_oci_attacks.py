"""The attacks of issue 22 on ``ota pull``: each refused, with nothing written.

A real registry (CNCF distribution on 127.0.0.1) is edited on its disk, or fed crafted
manifests through its own API; where a registry must misbehave on the wire (an endless
blob, redirects, the referrers API), the loopback test server replays its content.
"""

from __future__ import annotations

import json
import shutil

import pytest

from tests._oci import MANIFEST_TYPE, mirror, module_cli, registry  # noqa: F401 -- fixture
from tests._ota import make_robot, tree

REPO = "robots/scout"
pytestmark = pytest.mark.filterwarnings("ignore::ResourceWarning")


@pytest.fixture(scope="module")
def releases(tmp_path_factory, registry):  # noqa: F811
    """Two releases of one robot (r2 built on r1), pushed as r1 and r2."""
    cli = module_cli()
    tmp = tmp_path_factory.mktemp("releases")
    robot = make_robot(tmp, cli)
    r1, r2 = tmp / "r1", tmp / "r2"
    assert robot.build(cli, r1).exit_code == 0
    robot.rewrite(cli, flex_version="v0.3.0")
    r = robot.build(cli, r2, "--previous", r1)
    assert r.exit_code == 0, r.stderr
    for name, folder in (("r1", r1), ("r2", r2)):
        r = cli("ota", "push", folder, registry.ref(REPO, name), "--key", robot.pub)
        assert r.exit_code == 0, r.stderr
    return robot, r1, r2


def _pull(cli, ref, robot, dest, *extra):
    return cli("ota", "pull", ref, "--key", robot.pub, "--out", dest, *extra)


def _refused(r, dest, code, *words):
    assert r.exit_code == code, (r.exit_code, r.stderr)
    assert not dest.exists(), "a refused pull wrote its output folder"
    for w in words:
        assert w in r.stderr, r.stderr


def _crafted(registry, doc, tag):  # noqa: F811
    """Push a crafted manifest (blobs already there) under ``tag``; its reference."""
    body = json.dumps(doc).encode()
    registry.put_manifest(REPO, tag, body)
    return registry.ref(REPO, tag)


def _doc(registry, tag="r1"):  # noqa: F811
    return json.loads(registry.manifest(REPO, tag)[0])


def _layer(doc, suffix):
    return next(x for x in doc["layers"] if x["annotations"]["org.opencontainers.image.title"].endswith(suffix))


@pytest.fixture
def edited(registry):  # noqa: F811
    """Edit a file of the registry's storage; put it back afterwards (blobs are shared)."""
    saved = []

    def edit(path, data):
        saved.append((path, path.read_bytes()))
        path.chmod(0o644)
        path.write_bytes(data)

    yield edit
    for path, data in reversed(saved):
        path.write_bytes(data)


def test_blob_edited_on_the_registry_disk(cli, registry, releases, edited, tmp_path):  # noqa: F811
    robot, _, _ = releases
    layer = _layer(_doc(registry), "flex-io/0.2.0.bin")
    path = registry.blob_path(layer["digest"])
    data = bytearray(path.read_bytes())
    data[100] ^= 1  # same size: the registry still announces the manifest's size and digest
    edited(path, bytes(data))
    dest = tmp_path / "out"
    r = _pull(cli, registry.ref(REPO, "r1"), robot, dest)
    _refused(r, dest, 1, "the blob's SHA-256 is not its digest in the manifest", layer["digest"])


def test_manifest_edited_on_disk_under_its_digest(cli, registry, releases, edited, tmp_path):  # noqa: F811
    robot, _, _ = releases
    body, digest = registry.manifest(REPO, "r1")
    doc = json.loads(body)
    doc["annotations"]["dev.hcdf.sequence-number"] = "99"
    new = json.dumps(doc, sort_keys=True, separators=(",", ":")).encode()
    edited(registry.blob_path(digest), new)
    dest = tmp_path / "out"
    r = _pull(cli, registry.ref(REPO, "x").replace(":x", "@" + digest), robot, dest)
    _refused(r, dest, 1, "the manifest received is not the one pinned", digest)


def test_tag_moved_back_to_the_older_release(cli, registry, releases, tmp_path):  # noqa: F811
    robot, _, r2 = releases
    older, _ = registry.manifest(REPO, "r1")
    registry.put_manifest(REPO, "moved", older)
    dest = tmp_path / "out"
    r = _pull(cli, registry.ref(REPO, "moved"), robot, dest, "--previous", r2)
    _refused(r, dest, 1, "sequence-number is not greater")


def test_tag_moved_to_a_release_signed_by_another_key(cli, registry, releases, tmp_path):  # noqa: F811
    robot, _, _ = releases
    from hcdf_trust.ota.keys import generate, public_pem

    other = tmp_path / "other.pub.pem"
    other.write_bytes(public_pem(generate("ecdsa-p256")))
    dest = tmp_path / "out"
    r = cli("ota", "pull", registry.ref(REPO, "r1"), "--key", other, "--out", dest)
    _refused(r, dest, 1, "signed by another key")


def test_layer_digests_swapped_between_files(cli, registry, releases, tmp_path):  # noqa: F811
    robot, _, _ = releases
    doc = _doc(registry)
    a, b = _layer(doc, "flex-io/0.2.0.bin"), _layer(doc, "1.0.0+3.bin")
    for key in ("digest", "size"):
        a[key], b[key] = b[key], a[key]
    dest = tmp_path / "out"
    r = _pull(cli, _crafted(registry, doc, "swapped"), robot, dest)
    _refused(r, dest, 1, "file_sha256 differs from the signed manifest")


@pytest.mark.parametrize("delta", [1, -1])
def test_layer_size_that_is_not_the_blobs(cli, registry, releases, tmp_path, delta):  # noqa: F811
    robot, _, _ = releases
    doc = _doc(registry)
    _layer(doc, "flex-io/0.2.0.bin")["size"] += delta
    dest = tmp_path / "out"
    r = _pull(cli, _crafted(registry, doc, f"size{delta + 1}"), robot, dest)
    _refused(r, dest, 3, "announces another size than the manifest's")


@pytest.mark.parametrize(
    "title",
    [
        "../x",
        "../../../../tmp/evil.bin",
        "/etc/passwd",
        "a/../release.suit",
        "a//b",
        "./release.suit",
        "",
        "link -> /etc/passwd",
        "x\nrelease.suit",
        "a\\..\\b",
        "mr_mcxn_t1/flex-io/0.2.0.bin/../../../x",
        "a/b/c/d",
        "..",
        "-rf",
    ],
)
def test_layer_title_that_is_not_a_plain_relative_path(cli, registry, releases, tmp_path, title):  # noqa: F811
    robot, _, _ = releases
    doc = _doc(registry)
    _layer(doc, "flex-io/0.2.0.bin")["annotations"]["org.opencontainers.image.title"] = title
    before = tree(tmp_path)
    dest = tmp_path / "out"
    r = _pull(cli, _crafted(registry, doc, "title"), robot, dest)
    _refused(r, dest, 3, "is not a plain relative path")
    assert tree(tmp_path) == before


@pytest.mark.parametrize("same", ["release.suit", "RELEASE.SUIT"])
def test_duplicate_layer_titles(cli, registry, releases, tmp_path, same):  # noqa: F811
    robot, _, _ = releases
    doc = _doc(registry)
    _layer(doc, "release.suit.json")["annotations"]["org.opencontainers.image.title"] = same
    dest = tmp_path / "out"
    r = _pull(cli, _crafted(registry, doc, "dup"), robot, dest)
    _refused(r, dest, 3, "is also the title of /layers/0")


def test_layer_the_signed_manifest_does_not_list(cli, registry, releases, tmp_path):  # noqa: F811
    robot, _, _ = releases
    doc = _doc(registry)
    extra = dict(_layer(doc, "1.0.0+3.bin"), annotations={"org.opencontainers.image.title": "tools/flash.sh"})
    doc["layers"].append(extra)
    dest = tmp_path / "out"
    r = _pull(cli, _crafted(registry, doc, "extra"), robot, dest)
    _refused(r, dest, 1, "'tools/flash.sh' is not a file of the signed release")


def test_layer_annotation_that_lies(cli, registry, releases, tmp_path):  # noqa: F811
    robot, _, _ = releases
    doc = _doc(registry)
    _layer(doc, "flex-io/0.2.0.bin")["annotations"]["dev.hcdf.version"] = "9.9.9"
    dest = tmp_path / "out"
    r = _pull(cli, _crafted(registry, doc, "annot"), robot, dest)
    _refused(r, dest, 1, "layer annotation dev.hcdf.version differs from the signed manifest")


def test_oversized_blob_on_the_registry_disk(cli, registry, releases, edited, tmp_path):  # noqa: F811
    robot, _, _ = releases
    layer = _layer(_doc(registry), "flex-io/0.2.0.bin")
    path = registry.blob_path(layer["digest"])
    edited(path, path.read_bytes() + b"\0" * 4096)
    dest = tmp_path / "out"
    r = _pull(cli, registry.ref(REPO, "r1"), robot, dest)
    _refused(r, dest, 3, "announces another size than the manifest's")


def test_endless_blob(cli, registry, releases, http_server, tmp_path):  # noqa: F811
    robot, _, _ = releases
    _, doc = mirror(http_server, registry, REPO, "r1")
    layer = _layer(doc, "flex-io/0.2.0.bin")
    http_server.stream(f"/v2/{REPO}/blobs/{layer['digest']}", 1 << 40, chunked=True)
    dest = tmp_path / "out"
    r = _pull(cli, f"oci://127.0.0.1:{http_server.port}/{REPO}:r1", robot, dest)
    _refused(r, dest, 3, "blob is longer than the manifest's")


def test_referrer_pointing_at_another_release(cli, registry, releases, tmp_path):  # noqa: F811
    robot, _, _ = releases
    _, d1 = registry.manifest(REPO, "r1")
    _, d2 = registry.manifest(REPO, "r2")
    idx1, _ = registry.manifest(REPO, d1.replace(":", "-"))
    idx2, _ = registry.manifest(REPO, d2.replace(":", "-"))
    try:
        registry.put_manifest(REPO, d1.replace(":", "-"), idx2, "application/vnd.oci.image.index.v1+json")
        dest = tmp_path / "out"
        r = _pull(cli, registry.ref(REPO, "r1"), robot, dest)
        _refused(r, dest, 1, "points at another release", d1, d2)
    finally:
        registry.put_manifest(REPO, d1.replace(":", "-"), idx1, "application/vnd.oci.image.index.v1+json")


def test_referrer_removed_still_verifies_and_says_so(cli, registry, releases, tmp_path):  # noqa: F811
    robot, r1, _ = releases
    _, d1 = registry.manifest(REPO, "r1")
    idx1, _ = registry.manifest(REPO, d1.replace(":", "-"))
    empty = json.dumps({"schemaVersion": 2, "mediaType": "application/vnd.oci.image.index.v1+json", "manifests": []})
    try:
        registry.put_manifest(REPO, d1.replace(":", "-"), empty.encode(), "application/vnd.oci.image.index.v1+json")
        dest = tmp_path / "out"
        r = _pull(cli, registry.ref(REPO, "r1"), robot, dest, "--json")
        assert r.exit_code == 0, r.stderr
        assert r.json["referrers"] == []
        assert [w["code"] for w in r.json["warnings"]] == ["oci-no-referrer"]
        assert tree(dest) == tree(r1)
    finally:
        registry.put_manifest(REPO, d1.replace(":", "-"), idx1, "application/vnd.oci.image.index.v1+json")


def test_referrers_api_answered(cli, registry, releases, http_server, tmp_path):  # noqa: F811
    """A registry with the OCI 1.1 referrers API: no fallback tag is read."""
    robot, r1, _ = releases
    digest, _ = mirror(http_server, registry, REPO, "r1", referrers_api=True)
    dest = tmp_path / "out"
    r = _pull(cli, f"oci://127.0.0.1:{http_server.port}/{REPO}:r1", robot, dest, "--json")
    assert r.exit_code == 0, r.stderr
    assert len(r.json["referrers"]) == 1
    assert http_server.hits[f"/v2/{REPO}/manifests/{digest.replace(':', '-')}"] == 0
    assert tree(dest) == tree(r1)


def test_manifest_redirect_to_another_host(cli, registry, releases, serve, tmp_path):  # noqa: F811
    robot, _, _ = releases
    good, evil = serve(None), serve(None)
    mirror(good, registry, REPO, "r1")
    mirror(evil, registry, REPO, "r1")
    good.redirect(f"/v2/{REPO}/manifests/r1", evil.url(f"/v2/{REPO}/manifests/r1"))
    dest = tmp_path / "out"
    r = _pull(cli, f"oci://127.0.0.1:{good.port}/{REPO}:r1", robot, dest)
    _refused(r, dest, 3, "redirect to another host is refused")
    assert evil.total_hits == 0


def test_redirect_from_https_down_to_http(cli, registry, releases, serve, tls, tmp_path):  # noqa: F811
    robot, _, _ = releases
    secure, plain = serve("good"), serve(None)
    _, doc = mirror(secure, registry, REPO, "r1")
    mirror(plain, registry, REPO, "r1")
    layer = _layer(doc, "flex-io/0.2.0.bin")
    path = f"/v2/{REPO}/blobs/{layer['digest']}"
    secure.redirect(path, plain.url(path))
    dest = tmp_path / "out"
    r = _pull(cli, f"oci://127.0.0.1:{secure.port}/{REPO}:r1", robot, dest, "--ca-bundle", tls.ca_pem)
    _refused(r, dest, 3, "redirect from https down to http is refused")
    assert plain.hits[path] == 0


def test_blob_redirect_to_a_cdn_is_still_hashed(cli, registry, releases, serve, tmp_path):  # noqa: F811
    """Registries hand blob downloads to another host (a CDN): allowed, but its bytes are
    hashed like any other (and no Authorization header goes there)."""
    robot, r1, _ = releases
    srv, cdn = serve(None), serve(None)
    _, doc = mirror(srv, registry, REPO, "r1")
    layer = _layer(doc, "flex-io/0.2.0.bin")
    path = f"/v2/{REPO}/blobs/{layer['digest']}"
    good = registry.blob_path(layer["digest"]).read_bytes()
    srv.redirect(path, cdn.url("/cdn/blob"))
    cdn.add("/cdn/blob", good[:-1] + bytes([good[-1] ^ 1]))
    dest = tmp_path / "out"
    r = _pull(cli, f"oci://127.0.0.1:{srv.port}/{REPO}:r1", robot, dest)
    _refused(r, dest, 1, "the blob's SHA-256 is not its digest")
    cdn.add("/cdn/blob", good)
    r = _pull(cli, f"oci://127.0.0.1:{srv.port}/{REPO}:r1", robot, dest)
    assert r.exit_code == 0, r.stderr
    assert tree(dest) == tree(r1)


def test_not_a_release_artifact(cli, registry, releases, tmp_path):  # noqa: F811
    robot, _, _ = releases
    doc = _doc(registry)
    doc["artifactType"] = "application/vnd.example.other"
    dest = tmp_path / "out"
    r = _pull(cli, _crafted(registry, doc, "other"), robot, dest)
    _refused(r, dest, 3, "not an hcdf-trust release")


def test_duplicate_keys_in_the_manifest(cli, registry, releases, tmp_path):  # noqa: F811
    robot, _, _ = releases
    body, _ = registry.manifest(REPO, "r1")
    text = body.decode().replace('"artifactType":', '"artifactType":"application/vnd.x","artifactType":', 1)
    registry.put_manifest(REPO, "dupkey", text.encode())
    dest = tmp_path / "out"
    r = _pull(cli, registry.ref(REPO, "dupkey"), robot, dest)
    _refused(r, dest, 3, "appears twice")


def test_nothing_written_keeps_an_existing_out_folder(cli, registry, releases, edited, tmp_path):  # noqa: F811
    robot, r1, _ = releases
    dest = tmp_path / "out"
    shutil.copytree(r1, dest)
    (dest / "keep.txt").write_text("mine")
    before = tree(dest)
    layer = _layer(_doc(registry), "flex-io/latest.json")
    path = registry.blob_path(layer["digest"])
    edited(path, path.read_bytes().replace(b"0.2.0", b"9.9.9"))
    r = _pull(cli, registry.ref(REPO, "r1"), robot, dest)
    assert r.exit_code == 1, r.stderr
    assert tree(dest) == before


def test_layer_titled_below_another_file(cli, registry, releases, tmp_path):  # noqa: F811
    robot, _, _ = releases
    doc = _doc(registry)
    _layer(doc, "release.suit.json")["annotations"]["org.opencontainers.image.title"] = "release.suit/x"
    dest = tmp_path / "out"
    r = _pull(cli, _crafted(registry, doc, "below"), robot, dest)
    _refused(r, dest, 3, "lies below the file of /layers/0")


@pytest.mark.parametrize("value", [["a"], {"a": 1}, 7, None])
def test_layer_media_type_of_another_json_type(cli, registry, releases, http_server, tmp_path, value):  # noqa: F811
    """distribution refuses such a manifest itself: the loopback server replays it."""
    robot, _, _ = releases
    _, doc = mirror(http_server, registry, REPO, "r1")
    _layer(doc, "flex-io/0.2.0.bin")["mediaType"] = value
    http_server.add(f"/v2/{REPO}/manifests/r1", json.dumps(doc).encode(), headers={"Content-Type": MANIFEST_TYPE})
    dest = tmp_path / "out"
    r = _pull(cli, f"oci://127.0.0.1:{http_server.port}/{REPO}:r1", robot, dest)
    _refused(r, dest, 3, "unknown media type")


def test_a_failed_pull_resumes_from_the_verified_blobs(cli, registry, releases, tmp_path):  # noqa: F811
    """The blobs verified before a failure stay in the content store; the next pull fetches
    only the one that failed (and still verifies everything)."""
    robot, r1, _ = releases
    layer = _layer(_doc(registry), "flex-io/0.2.0.bin")
    path = registry.blob_path(layer["digest"])
    good = path.read_bytes()
    path.chmod(0o644)
    path.write_bytes(good[:-1] + bytes([good[-1] ^ 1]))
    cache = tmp_path / "cache"
    dest = tmp_path / "out"
    try:
        r = _pull(cli, registry.ref(REPO, "r1"), robot, dest, "--cache-dir", cache)
        _refused(r, dest, 1, "the blob's SHA-256 is not its digest")
    finally:
        path.write_bytes(good)
    r = _pull(cli, registry.ref(REPO, "r1"), robot, dest, "--cache-dir", cache, "--json")
    assert r.exit_code == 0, r.stderr
    assert r.json["from_cache"] == len(r.json["files"]) - 1
    assert tree(dest) == tree(r1)


def test_a_manifest_dripped_byte_by_byte_stops_at_the_deadline(http_server):
    """Each byte comes within the read timeout; the whole answer is still bounded in time."""
    import time

    from hcdf_trust.oci.client import RegistryClient, RegistryError
    from hcdf_trust.oci.reference import parse_reference

    http_server.drip(f"/v2/{REPO}/manifests/r1", b"{" + b" " * 200 + b"}", every=0.05)
    client = RegistryClient(parse_reference(f"oci://127.0.0.1:{http_server.port}/{REPO}:r1"), deadline=0.5)
    started = time.monotonic()
    with pytest.raises(RegistryError, match="took longer than 0.5 s"):
        client.get_manifest("r1")
    assert time.monotonic() - started < 5
    client.close()
