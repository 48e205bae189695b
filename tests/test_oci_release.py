"""``ota push`` / ``ota pull`` against a real CNCF distribution server on 127.0.0.1."""

from __future__ import annotations

import hashlib
import json

import pytest

from tests._oci import registry  # noqa: F401 -- fixture
from tests._ota import make_robot, tree

pytestmark = pytest.mark.filterwarnings("ignore::ResourceWarning")


@pytest.fixture(scope="module")
def release(tmp_path_factory):
    """One release built by ``ota build`` (module scope: imgtool signing takes a while)."""
    from click.testing import CliRunner

    from hcdf_trust.cli import main
    from tests.conftest import CliResult

    def cli(*args):
        r = CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)
        return CliResult(r.exit_code, r.stdout, r.stderr)

    tmp = tmp_path_factory.mktemp("release")
    robot = make_robot(tmp, cli)
    out = tmp / "release"
    r = robot.build(cli, out)
    assert r.exit_code == 0, r.stderr
    return robot, out


def test_push_then_pull_into_an_empty_folder_verifies(cli, registry, release, tmp_path):  # noqa: F811
    robot, out = release
    ref = registry.ref(tag="happy")
    r = cli("ota", "push", out, ref, "--key", robot.pub, "--json")
    assert r.exit_code == 0, r.stderr
    pushed = r.json
    # the registry holds our OCI 1.1 artifact: artifactType, empty config, one titled layer per file
    body, digest = registry.manifest("robots/scout", "happy")
    assert digest == pushed["digest"]
    doc = json.loads(body)
    assert doc["artifactType"] == "application/vnd.hcdf.release.v1"
    assert doc["config"]["mediaType"] == "application/vnd.oci.empty.v1+json"
    titles = {x["annotations"]["org.opencontainers.image.title"]: x for x in doc["layers"]}
    assert set(titles) == set(tree(out))
    for title, layer in titles.items():
        assert layer["digest"] == "sha256:" + hashlib.sha256((out / title).read_bytes()).hexdigest()
    assert titles["release.suit"]["mediaType"] == "application/suit-envelope+cose"
    assert "dev.hcdf.lock-sha256" in doc["annotations"]
    # the SUIT referrer, through the sha256-<hex> tag (distribution 2.8 has no referrers API)
    index, _ = registry.manifest("robots/scout", digest.replace(":", "-"))
    (entry,) = json.loads(index)["manifests"]
    assert entry["artifactType"] == "application/vnd.hcdf.release.signature.v1"
    sig, _ = registry.manifest("robots/scout", entry["digest"])
    assert json.loads(sig)["subject"]["digest"] == digest

    dest = tmp_path / "pulled"
    r = cli("ota", "pull", ref, "--key", robot.pub, "--out", dest, "--json")
    assert r.exit_code == 0, r.stderr
    assert r.json["digest"] == digest and r.json["referrers"] == [entry["digest"]]
    assert tree(dest) == tree(out)
    r = cli("ota", "verify", dest, "--key", robot.pub)
    assert r.exit_code == 0, r.stderr
    # by digest, and resumed from the content store: nothing fetched again
    r = cli(
        "ota",
        "pull",
        registry.ref(tag="x").replace(":x", "@" + digest),
        "--key",
        robot.pub,
        "--out",
        tmp_path / "again",
        "--json",
    )
    assert r.exit_code == 0, r.stderr
    assert r.json["from_cache"] == len(titles)
    assert tree(tmp_path / "again") == tree(out)


def test_demo_release_through_the_registry_with_only_the_public_key(cli, registry, tmp_path):  # noqa: F811
    """Issue 22's "done when": the release `make demo` builds, pushed to the loopback registry,
    pulled into an empty folder with only the public key, verifies."""
    import shutil

    from tests.conftest import PROJECT

    robot = tmp_path / "robot"
    shutil.copytree(PROJECT / "examples" / "robot", robot)
    key = tmp_path / "demo.pem"
    assert cli("ota", "keygen", "-o", key).exit_code == 0
    out = tmp_path / "release"
    r = cli(
        "ota", "build", robot / "robot.hcdf", "--firmware-dir", robot / "firmware", "--key", key,
        "--out", out, "--base-url", "https://firmware.example.com/scout2",
    )  # fmt: skip
    assert r.exit_code == 0, r.stderr
    pub_only = tmp_path / "device"
    pub_only.mkdir()
    shutil.copy(tmp_path / "demo.pub.pem", pub_only / "demo.pub.pem")
    r = cli("ota", "push", out, registry.ref("demo/scout2", "1"), "--key", pub_only / "demo.pub.pem", "--json")
    assert r.exit_code == 0, r.stderr
    dest = pub_only / "release"
    r = cli("ota", "pull", registry.ref("demo/scout2", "1"), "--key", pub_only / "demo.pub.pem", "--out", dest)
    assert r.exit_code == 0, r.stderr
    assert tree(dest) == tree(out)
    assert cli("ota", "verify", dest, "--key", pub_only / "demo.pub.pem").exit_code == 0


def test_pulled_files_are_files_of_their_own_never_links_to_the_cache(cli, registry, release, tmp_path):  # noqa: F811
    """Each staged blob is a new file moved into --out (one link, mode 0644), never the content
    store's blob (a shared inode would let an edit of one change the other); the store keeps
    its read-only blobs and no staging folder is left, fetched or resumed."""
    robot, out = release
    assert cli("ota", "push", out, registry.ref(tag="own")).exit_code == 0
    cache = tmp_path / "cache"
    for dest in (tmp_path / "first", tmp_path / "again"):  # fetched, then from the content store
        r = cli("ota", "pull", registry.ref(tag="own"), "--key", robot.pub, "--out", dest, "--cache-dir", cache)
        assert r.exit_code == 0, r.stderr
        blobs = [p.stat() for p in (cache / "sha256").rglob("*") if p.is_file()]
        assert blobs and all(oct(st.st_mode & 0o777) == "0o444" for st in blobs)
        inodes = {(st.st_dev, st.st_ino) for st in blobs}
        pulled = [p.stat() for p in dest.rglob("*") if p.is_file()]
        assert len(pulled) == len(tree(out))
        for st in pulled:
            assert st.st_nlink == 1 and oct(st.st_mode & 0o777) == "0o644"
            assert (st.st_dev, st.st_ino) not in inodes
        assert tree(dest) == tree(out)
        assert not list(cache.glob(".oci-pull-*"))


def test_each_image_is_checked_from_the_pass_that_fetched_it_and_its_verdict_decides(
    cli,
    registry,  # noqa: F811
    release,
    tmp_path,
    monkeypatch,
):
    """pull hashes each image once, as it streams in (the ImageStream that computed its blob
    digest also has its MCUboot image hash): ota verify of the staged release takes those
    streams and reads no image again; a verdict other than OK for any image refuses the whole
    pull, nothing written (the check stood in by a verdict it never gives a good image)."""
    from hcdf_trust.ota import mcuboot, read

    robot, out = release
    assert cli("ota", "push", out, registry.ref(tag="verdict")).exit_code == 0
    real = mcuboot.ImageStream.verify
    checked: list[str] = []
    reread: list[str] = []

    def counted(self, key):
        checked.append(self.hexdigest())
        return real(self, key)

    monkeypatch.setattr(mcuboot.ImageStream, "verify", counted)
    monkeypatch.setattr(read.FolderImages, "scan", lambda self, rel: reread.append(rel))
    monkeypatch.setattr(read.FolderImages, "__getitem__", lambda self, rel: reread.append(rel))
    r = cli("ota", "pull", registry.ref(tag="verdict"), "--key", robot.pub, "--out", tmp_path / "ok", "--json")
    assert r.exit_code == 0, r.stderr
    images = [f for f in r.json["files"] if f["mediaType"] == "application/vnd.hcdf.mcuboot.image.v1"]
    assert images and sorted(checked) == sorted(f["digest"].split(":")[1] for f in images)
    assert reread == []

    monkeypatch.setattr(mcuboot.ImageStream, "verify", lambda self, key: mcuboot.ImageVerdict("INVALID_SIGNATURE"))
    r = cli("ota", "pull", registry.ref(tag="verdict"), "--key", robot.pub, "--out", tmp_path / "bad")
    assert r.exit_code == 3 and "not an MCUboot image (INVALID_SIGNATURE)" in r.stderr, r.stderr
    assert not (tmp_path / "bad").exists()
    monkeypatch.setattr(
        mcuboot.ImageStream,
        "verify",
        lambda self, key: mcuboot.ImageVerdict("INVALID_SIGNATURE", None, real(self, key).info),
    )
    r = cli("ota", "pull", registry.ref(tag="verdict"), "--key", robot.pub, "--out", tmp_path / "bad")
    assert r.exit_code == 1 and "does not verify with the key (INVALID_SIGNATURE)" in r.stderr, r.stderr
    assert not (tmp_path / "bad").exists()


def test_a_killed_pulls_staging_folder_is_swept_a_live_ones_kept(cli, registry, release, tmp_path):  # noqa: F811
    import fcntl
    import os

    robot, out = release
    assert cli("ota", "push", out, registry.ref(tag="sweep")).exit_code == 0
    cache = tmp_path / "cache"
    dead, live = cache / ".oci-pull-dead", cache / ".oci-pull-live"
    for folder in (dead, live):
        (folder / "mr_mcxn_t1").mkdir(parents=True)
        (folder / ".lock").write_bytes(b"")
        (folder / "mr_mcxn_t1" / "x.bin").write_bytes(b"partial")
    fd = os.open(live / ".lock", os.O_RDWR)
    fcntl.flock(fd, fcntl.LOCK_EX)  # a pull still running there
    try:
        r = cli(
            "ota", "pull", registry.ref(tag="sweep"), "--key", robot.pub, "--out", tmp_path / "o", "--cache-dir", cache
        )
        assert r.exit_code == 0, r.stderr
        assert not dead.exists() and live.exists()
        assert sorted(p.name for p in cache.glob(".oci-pull-*")) == [".oci-pull-live"]  # ours removed too
    finally:
        os.close(fd)


def test_a_release_with_history_pulls_and_verifies(cli, registry, tmp_path):  # noqa: F811
    """release.history travels as a layer: without it the pulled latest.json's previous[]
    would be vouched for by nothing, and pull's verify would refuse it."""
    robot = make_robot(tmp_path, cli)
    out = tmp_path / "rel"
    assert robot.build(cli, out).exit_code == 0
    robot.rewrite(cli, flex_version="0.3.0")
    assert robot.build(cli, out).exit_code == 0
    ref = registry.ref(tag="history")
    r = cli("ota", "push", out, ref, "--key", robot.pub, "--json")
    assert r.exit_code == 0, r.stderr
    titles = {x["annotations"]["org.opencontainers.image.title"]: x["mediaType"] for x in r.json["layers"]}
    assert titles["release.history"] == "application/vnd.hcdf.release.history.v1+cbor"
    pulled = tmp_path / "pulled"
    r = cli("ota", "pull", ref, "--key", robot.pub, "--out", pulled)
    assert r.exit_code == 0, r.stderr
    assert cli("ota", "verify", pulled, "--key", robot.pub).exit_code == 0


def test_large_blobs_go_as_chunked_patches(cli, registry, release, tmp_path, monkeypatch):  # noqa: F811
    """Above CHUNK_BYTES a blob is uploaded as PATCHes with Content-Range, then a closing PUT;
    the real registry reassembles it byte for byte, and the pull verifies."""
    from hcdf_trust.oci import client as oci_client

    robot, out = release
    monkeypatch.setattr(oci_client, "CHUNK_BYTES", 3000)  # the images are 5-10 kB: 2-4 parts each
    sent: list[tuple[str, str]] = []
    real = oci_client.RegistryClient.request

    def spy(self, method, url, **kw):
        if method in ("PATCH", "PUT") and "/blobs/uploads/" in url:
            sent.append((method, (kw.get("headers") or {}).get("Content-Range", "")))
        return real(self, method, url, **kw)

    monkeypatch.setattr(oci_client.RegistryClient, "request", spy)
    r = cli("ota", "push", out, registry.ref("chunked/scout", "1"), "--key", robot.pub)
    assert r.exit_code == 0, r.stderr
    patches = [rng for m, rng in sent if m == "PATCH"]
    assert "0-2999" in patches and "3000-5999" in patches, sent
    image = next(p for p in sorted(out.rglob("*.bin")) if p.stat().st_size > 6000)
    digest = "sha256:" + hashlib.sha256(image.read_bytes()).hexdigest()
    assert registry.blob_path(digest).read_bytes() == image.read_bytes()
    dest = tmp_path / "pulled"
    r = cli("ota", "pull", registry.ref("chunked/scout", "1"), "--key", robot.pub, "--out", dest)
    assert r.exit_code == 0, r.stderr
    assert tree(dest) == tree(out)


def test_parts_split_a_stream_exactly():
    from hcdf_trust.oci.client import RegistryError, _Parts

    data = bytes(range(256)) * 40
    chunks = [data[i : i + 777] for i in range(0, len(data), 777)]
    parts = _Parts(iter(chunks))
    got = [b"".join(parts.next(n)) for n in (1000, 1000, 1000, len(data) - 3000)]
    parts.end()
    assert b"".join(got) == data and [len(g) for g in got[:3]] == [1000, 1000, 1000]
    short = _Parts(iter([b"abc"]))
    with pytest.raises(RegistryError, match="ended 2 bytes before"):
        b"".join(short.next(5))
    long = _Parts(iter([b"abcdef"]))
    b"".join(long.next(5))
    with pytest.raises(RegistryError, match="longer than its declared size"):
        long.end()
