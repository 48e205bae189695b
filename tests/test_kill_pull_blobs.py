"""oci/blobs.py's fetch_blob (mutation-testing killers): what ``ota pull`` says, whole, when a
blob is not the manifest's, when the content store cannot take it, and that a blob taken from
the store is committed under the digest it was checked against.

A real registry (CNCF distribution on 127.0.0.1); where it must misbehave on the wire, the
loopback test server replays its content (tests/_oci.py's ``mirror``).
"""

from __future__ import annotations

import hashlib
import os

import pytest

from tests._oci import mirror, module_cli, registry  # noqa: F401 -- fixture
from tests._ota import make_robot, tree

REPO = "robots/blobs"
IMAGE = "mr_mcxn_t1/flex-io/0.2.0.bin"
pytestmark = pytest.mark.filterwarnings("ignore::ResourceWarning")


@pytest.fixture(scope="module")
def pushed(tmp_path_factory, registry):  # noqa: F811
    """One release, pushed as REPO:r1."""
    cli = module_cli()
    tmp = tmp_path_factory.mktemp("blobs")
    robot = make_robot(tmp, cli)
    out = tmp / "r1"
    assert robot.build(cli, out).exit_code == 0
    r = cli("ota", "push", out, registry.ref(REPO, "r1"), "--key", robot.pub)
    assert r.exit_code == 0, r.stderr
    return robot, out


def _where(doc, digest, http_server, title):
    """The blob's place as messages name it: the pinned manifest and the layer's index."""
    i = next(i for i, x in enumerate(doc["layers"]) if x["annotations"]["org.opencontainers.image.title"] == title)
    return f"oci://127.0.0.1:{http_server.port}/{REPO}@{digest}#/layers/{i}", doc["layers"][i]


def _errors(cli, http_server, robot, dest, *extra):
    r = cli(
        "ota",
        "pull",
        f"oci://127.0.0.1:{http_server.port}/{REPO}:r1",
        "--key",
        robot.pub,
        "--out",
        dest,
        "--json",
        *extra,
    )
    assert not dest.exists(), "a refused pull wrote its output folder"
    return r.exit_code, r.json["errors"]


def test_a_short_blob_is_named_with_both_sizes(cli, registry, pushed, http_server, tmp_path):  # noqa: F811
    """Sent chunked (no Content-Length to refuse early), ten bytes short."""
    robot, _ = pushed
    digest, doc = mirror(http_server, registry, REPO, "r1")
    where, layer = _where(doc, digest, http_server, IMAGE)
    data = registry.blob_path(layer["digest"]).read_bytes()
    http_server.add(f"/v2/{REPO}/blobs/{layer['digest']}", data[:-10], chunked=True)
    code, errors = _errors(cli, http_server, robot, tmp_path / "out")
    assert (code, errors) == (
        1,
        [
            {
                "code": "digest-mismatch",
                "message": f"{IMAGE}: the blob is shorter than the manifest says",
                "file": where,
                "line": None,
                "expected": str(len(data)),
                "actual": str(len(data) - 10),
            }
        ],
    )


def test_a_blob_with_other_bytes_is_named_with_both_digests(cli, registry, pushed, http_server, tmp_path):  # noqa: F811
    import hashlib

    robot, _ = pushed
    digest, doc = mirror(http_server, registry, REPO, "r1")
    where, layer = _where(doc, digest, http_server, IMAGE)
    data = bytearray(registry.blob_path(layer["digest"]).read_bytes())
    data[100] ^= 1
    http_server.add(f"/v2/{REPO}/blobs/{layer['digest']}", bytes(data))
    code, errors = _errors(cli, http_server, robot, tmp_path / "out")
    assert (code, errors) == (
        1,
        [
            {
                "code": "digest-mismatch",
                "message": f"{IMAGE}: the blob's SHA-256 is not its digest in the manifest",
                "file": where,
                "line": None,
                "expected": layer["digest"],
                "actual": "sha256:" + hashlib.sha256(data).hexdigest(),
            }
        ],
    )


def test_a_store_that_cannot_be_written_names_the_blob(cli, registry, pushed, http_server, tmp_path):  # noqa: F811
    """The store's temporary folder is a file (root can write anywhere, not into a file)."""
    robot, _ = pushed
    digest, doc = mirror(http_server, registry, REPO, "r1")
    cache = tmp_path / "cache"
    cache.mkdir()
    (cache / "tmp").write_bytes(b"")
    code, errors = _errors(cli, http_server, robot, tmp_path / "out", "--cache-dir", cache)
    first = doc["layers"][0]["annotations"]["org.opencontainers.image.title"]
    assert code == 3
    assert errors[0]["message"].startswith(f"cannot write to the cache {cache / 'tmp'}: "), errors
    assert errors[0]["file"] == first, errors


def test_blobs_from_the_store_are_committed_onto_another_filesystem(cli, registry, pushed, tmp_path):  # noqa: F811
    """The second pull takes every blob from the content store; with --out on another
    filesystem than the cache (no hard link), each staged file is copied and hashed again
    against the digest the store's copy was checked against."""
    robot, out = pushed
    shm = "/dev/shm"
    if not os.path.isdir(shm) or os.stat(shm).st_dev == os.stat(tmp_path).st_dev:
        pytest.skip("no second filesystem (/dev/shm) here")
    import tempfile

    with tempfile.TemporaryDirectory(dir=shm) as cache:
        ref = registry.ref(REPO, "r1")
        first = cli("ota", "pull", ref, "--key", robot.pub, "--out", tmp_path / "a", "--cache-dir", cache, "--json")
        assert first.exit_code == 0, first.stderr
        again = cli("ota", "pull", ref, "--key", robot.pub, "--out", tmp_path / "b", "--cache-dir", cache, "--json")
    assert again.exit_code == 0, again.stderr
    assert again.json["from_cache"] == len(tree(out))
    assert tree(tmp_path / "b") == tree(out)


def _pull(cli, ref, robot, dest):
    return cli("ota", "pull", ref, "--key", robot.pub, "--out", dest, "--json")


def test_a_symlink_planted_in_the_content_store_is_not_read_through(cli, registry, pushed, tmp_path):  # noqa: F811
    """A store blob replaced by a symlink to a file with its very bytes (which could change once
    hashed): the store check follows it, the copy into the staging folder does not, so that one
    blob is fetched again; the pull still verifies and writes the release."""
    from hcdf_trust.store import ContentStore, default_cache_dir

    robot, out = pushed
    ref = registry.ref(REPO, "r1")
    assert _pull(cli, ref, robot, tmp_path / "a").exit_code == 0
    blob = ContentStore(default_cache_dir()).path_for(hashlib.sha256((out / IMAGE).read_bytes()).hexdigest())
    elsewhere = tmp_path / "elsewhere.bin"
    elsewhere.write_bytes(blob.read_bytes())
    blob.chmod(0o644)
    blob.unlink()
    blob.symlink_to(elsewhere)
    r = _pull(cli, ref, robot, tmp_path / "b")
    assert r.exit_code == 0, r.stderr
    assert r.json["from_cache"] == len(tree(out)) - 1
    assert tree(tmp_path / "b") == tree(out)


@pytest.mark.parametrize("delta", [1, -1])
def test_a_store_blob_is_not_taken_for_a_layer_listing_another_size(cli, registry, pushed, tmp_path, delta):  # noqa: F811
    """The store holds the blob of this digest (an earlier pull); a manifest listing it a byte
    longer or shorter is not served from the store (shorter: the copy stops at the size and is
    dropped): the registry's answer is then refused for its size."""
    import json

    robot, out = pushed
    assert _pull(cli, registry.ref(REPO, "r1"), robot, tmp_path / "a").exit_code == 0
    doc = json.loads(registry.manifest(REPO, "r1")[0])
    layer = next(x for x in doc["layers"] if x["annotations"]["org.opencontainers.image.title"] == IMAGE)
    size = layer["size"]
    layer["size"] = size + delta
    registry.put_manifest(REPO, f"size{delta + 1}", json.dumps(doc).encode())
    r = _pull(cli, registry.ref(REPO, f"size{delta + 1}"), robot, tmp_path / "b")
    assert not (tmp_path / "b").exists()
    assert (r.exit_code, [(e["message"], e.get("expected"), e.get("actual")) for e in r.json["errors"]]) == (
        3,
        [
            (
                f"blob {layer['digest']}: the registry announces another size than the manifest's",
                str(size + delta),
                str(size),
            )
        ],
    )


def test_a_store_blob_changed_after_its_check_is_fetched_again(cli, registry, pushed, tmp_path, monkeypatch):  # noqa: F811
    """Another process rewrites a store blob between the store's check and the copy into the
    staging folder (stood in by a wrapper that edits the file right after the real check): the
    copy's hash differs, the staged file is emptied, and the blob fetched from the registry
    alone is what lands in --out."""
    from hcdf_trust.store import ContentStore

    robot, out = pushed
    ref = registry.ref(REPO, "r1")
    assert _pull(cli, ref, robot, tmp_path / "a").exit_code == 0
    image = hashlib.sha256((out / IMAGE).read_bytes()).hexdigest()
    real = ContentStore.verified_path

    def then_rewritten(self, sha256, **kw):
        path = real(self, sha256, **kw)
        if path is not None and sha256 == image:
            data = bytearray(path.read_bytes())
            data[100] ^= 1
            path.chmod(0o644)
            path.write_bytes(data)
        return path

    monkeypatch.setattr(ContentStore, "verified_path", then_rewritten)
    r = _pull(cli, ref, robot, tmp_path / "b")
    assert r.exit_code == 0, r.stderr
    assert r.json["from_cache"] == len(tree(out)) - 1
    assert tree(tmp_path / "b") == tree(out)
