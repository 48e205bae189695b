"""A bundle's provenance and SBOMs as OCI referrers, tag pulls, and what pull messages name
(issue 22's leftovers), against a real registry (CNCF distribution on 127.0.0.1, no referrers
API: the ``sha256-<hex>`` tag index; the referrers-API path replayed by the loopback server).

``bundle push`` attaches ``X.hcdfz.intoto.json`` (``bundle --provenance``) and each ``--sbom``
with ``subject`` = the bundle manifest; ``bundle pull --provenance-key`` verifies the provenance
as ``verify X.hcdfz --provenance`` does before anything is written, and writes it beside
``--out``. A tag is pulled only through a provenance that verifies, or with ``--trust-tag``.
Oracles: the registry's own API and storage, hashlib, ``verify --provenance`` on the result.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import pytest

from tests._oci import INDEX_TYPE, MANIFEST_TYPE, mirror, module_cli, registry  # noqa: F401 -- fixture
from tests.test_bundle import _entries, _hostile_cases, _zip

PROJECT = Path(__file__).resolve().parent.parent
REPO = "robots/signed"
PROVENANCE_TYPE = "application/vnd.hcdf.bundle.provenance.v1"
SBOM_TYPE = "application/vnd.hcdf.bundle.sbom.v1"
DSSE_TYPE = "application/vnd.dsse.envelope.v1+json"
pytestmark = pytest.mark.filterwarnings("ignore::ResourceWarning")


@pytest.fixture(scope="module")
def made(tmp_path_factory, registry):  # noqa: F811
    """Two signed bundles of one robot (key `release`), an SBOM of the first, an unsigned copy;
    pushed: `s1` (the first, its provenance and SBOM), `s2` (the second, its provenance),
    `u1` (the first without provenance)."""
    cli = module_cli()
    tmp = tmp_path_factory.mktemp("signed")
    shutil.copytree(PROJECT / "examples", tmp / "examples", ignore=shutil.ignore_patterns("out"))
    doc = tmp / "examples" / "robot" / "robot.hcdf"
    keys = {}
    for name in ("release", "other"):
        r = cli("ota", "keygen", "--type", "ed25519", "-o", tmp / f"{name}.pem")
        assert r.exit_code == 0, r.stderr
        keys[name] = (tmp / f"{name}.pem", tmp / f"{name}.pub.pem")
    one, two = tmp / "s1" / "scout2.hcdfz", tmp / "s2" / "scout2.hcdfz"
    for out in (one, two):
        out.parent.mkdir()
        r = cli("bundle", doc, out, "--provenance", "--key", keys["release"][0])
        assert r.exit_code == 0, r.stderr
        doc.write_text(doc.read_text().replace('name="scout2"', 'name="scout3"', 1))
    assert one.read_bytes() != two.read_bytes()
    unsigned = tmp / "u1" / "scout2.hcdfz"
    unsigned.parent.mkdir()
    shutil.copyfile(one, unsigned)
    sbom = tmp / "scout2.cdx.json"
    r = cli("sbom", one, "--format", "cyclonedx", "-o", sbom)
    assert r.exit_code == 0, r.stderr
    pushed = {}
    for tag, path, extra in (("s1", one, ["--sbom", sbom]), ("s2", two, []), ("u1", unsigned, [])):
        r = cli("bundle", "push", path, registry.ref(REPO, tag), "--json", *extra)
        assert r.exit_code == 0, r.stderr
        pushed[tag] = r.json
    return {"one": one, "two": two, "keys": keys, "sbom": sbom, "pushed": pushed}


def _at(registry, digest):  # noqa: F811
    return registry.ref(REPO, "x").replace(":x", "@" + digest)


def _index(registry, digest):  # noqa: F811
    return json.loads(registry.manifest(REPO, digest.replace(":", "-"))[0])


def _refused(r, dest, code, *words):
    assert r.exit_code == code, (r.exit_code, r.stdout, r.stderr)
    assert not dest.exists(), "a refused pull wrote its output"
    assert not Path(str(dest) + ".intoto.json").exists(), "a refused pull wrote a provenance"
    for w in words:
        assert w in r.stdout + r.stderr, r.stdout + r.stderr


# --- 1. push attaches, pull verifies -----------------------------------------------------------


def test_push_attaches_the_provenance_and_the_sbom_as_referrers_of_the_bundle(registry, made):  # noqa: F811
    digest = made["pushed"]["s1"]["digest"]
    _, manifest_digest = registry.manifest(REPO, "s1")
    assert digest == manifest_digest
    kinds = {e["artifactType"]: e for e in _index(registry, digest)["manifests"]}
    assert set(kinds) == {PROVENANCE_TYPE, SBOM_TYPE}
    assert {r["artifactType"] for r in made["pushed"]["s1"]["referrers"]} == set(kinds)
    envelope = made["one"].parent / "scout2.hcdfz.intoto.json"
    for kind, media_type, data in (
        (PROVENANCE_TYPE, DSSE_TYPE, envelope.read_bytes()),
        (SBOM_TYPE, "application/vnd.cyclonedx+json", made["sbom"].read_bytes()),
    ):
        doc = json.loads(registry.manifest(REPO, kinds[kind]["digest"])[0])
        assert doc["subject"]["digest"] == digest and doc["artifactType"] == kind
        [layer] = doc["layers"]
        assert layer["mediaType"] == media_type
        assert layer["digest"] == "sha256:" + hashlib.sha256(data).hexdigest()
        assert registry.blob_path(layer["digest"]).read_bytes() == data
    assert doc["config"]["mediaType"] == "application/vnd.oci.empty.v1+json"
    # the bundle's own manifest does not change with its referrers: the same bytes, the same digest
    assert made["pushed"]["u1"]["digest"] == digest
    assert made["pushed"]["s1"]["provenance_verified"] is False
    assert any(w["code"] == "unverified-provenance" for w in made["pushed"]["s1"]["warnings"])


def test_pull_verifies_the_provenance_and_writes_it_beside_out(cli, registry, made, tmp_path):  # noqa: F811
    pub = made["keys"]["release"][1]
    dest = tmp_path / "pulled.hcdfz"
    digest = made["pushed"]["s1"]["digest"]
    r = cli("bundle", "pull", _at(registry, digest), "--out", dest, "--provenance-key", pub, "--json")
    assert r.exit_code == 0, r.stderr
    assert dest.read_bytes() == made["one"].read_bytes()
    envelope = tmp_path / "pulled.hcdfz.intoto.json"
    assert envelope.read_bytes() == (made["one"].parent / "scout2.hcdfz.intoto.json").read_bytes()
    kinds = {e["artifactType"]: e["digest"] for e in _index(registry, digest)["manifests"]}
    assert r.json["provenance"] == kinds[PROVENANCE_TYPE]
    assert [s["digest"] for s in r.json["sboms"]] == [kinds[SBOM_TYPE]]
    assert cli("verify", dest, "--provenance", "--provenance-key", pub).exit_code == 0
    # without a key the provenance is listed, said unchecked, and not written
    bare = tmp_path / "bare.hcdfz"
    r = cli("bundle", "pull", _at(registry, digest), "--out", bare, "--json")
    assert r.exit_code == 0, r.stderr
    assert r.json["provenance"] is None and not (tmp_path / "bare.hcdfz.intoto.json").exists()
    assert [w["code"] for w in r.json["warnings"]] == ["oci-provenance-unchecked"]


def test_pull_through_the_referrers_api(cli, registry, made, http_server, tmp_path):  # noqa: F811
    digest, _ = mirror(http_server, registry, REPO, "s1", referrers_api=True)
    dest = tmp_path / "api.hcdfz"
    ref = f"oci://127.0.0.1:{http_server.port}/{REPO}:s1"
    r = cli("bundle", "pull", ref, "--out", dest, "--provenance-key", made["keys"]["release"][1], "--json")
    assert r.exit_code == 0, r.stderr
    assert r.json["digest"] == digest and r.json["provenance"] is not None
    assert http_server.hits[f"/v2/{REPO}/referrers/{digest}"] == 1, http_server.hits


def test_a_provenance_signed_by_another_key_is_refused(cli, registry, made, tmp_path):  # noqa: F811
    dest = tmp_path / "out.hcdfz"
    r = cli("bundle", "pull", _at(registry, made["pushed"]["s1"]["digest"]), "--out", dest,
            "--provenance-key", made["keys"]["other"][1])  # fmt: skip
    _refused(r, dest, 1, "signature")


def test_a_threshold_the_signatures_do_not_meet_is_refused(cli, registry, made, tmp_path):  # noqa: F811
    dest = tmp_path / "out.hcdfz"
    release, other = made["keys"]["release"][1], made["keys"]["other"][1]
    ref = _at(registry, made["pushed"]["s1"]["digest"])
    both = ("--provenance-key", release, "--provenance-key", other)
    _refused(cli("bundle", "pull", ref, "--out", dest, *both, "--threshold", "2"), dest, 1, "Found: 1")
    r = cli("bundle", "pull", ref, "--out", dest, "--provenance-key", release, "--threshold", "2")
    _refused(r, dest, 2, "--threshold 2 needs as many distinct keys")
    _refused(cli("bundle", "pull", ref, "--out", dest, "--threshold", "2"), dest, 2, "need --provenance-key")


def test_another_bundles_provenance_reattached_is_refused(cli, registry, made, tmp_path):  # noqa: F811
    """s2's envelope attached to s1's manifest, a well-formed referrer of s1: signed by the
    right key, but its subject is the other bundle."""
    s1 = made["pushed"]["s1"]["digest"]
    s2 = made["pushed"]["s2"]["digest"]
    [theirs] = [e for e in _index(registry, s2)["manifests"] if e["artifactType"] == PROVENANCE_TYPE]
    doc = json.loads(registry.manifest(REPO, theirs["digest"])[0])
    body, _ = registry.manifest(REPO, s1)
    doc["subject"] = {"mediaType": MANIFEST_TYPE, "digest": s1, "size": len(body)}
    forged = json.dumps(doc).encode()
    fd = registry.put_manifest(REPO, "sha256:" + hashlib.sha256(forged).hexdigest(), forged)
    saved = _index(registry, s1)
    index = {"schemaVersion": 2, "mediaType": INDEX_TYPE,
             "manifests": [e for e in saved["manifests"] if e["artifactType"] != PROVENANCE_TYPE]
             + [dict(theirs, digest=fd, size=len(forged))]}  # fmt: skip
    registry.put_manifest(REPO, s1.replace(":", "-"), json.dumps(index).encode(), INDEX_TYPE)
    try:
        dest = tmp_path / "out.hcdfz"
        r = cli("bundle", "pull", _at(registry, s1), "--out", dest, "--provenance-key", made["keys"]["release"][1])
        _refused(r, dest, 1, "the subject is not this bundle")
        assert ".oci-pull-" not in r.stderr
    finally:
        registry.put_manifest(REPO, s1.replace(":", "-"), json.dumps(saved).encode(), INDEX_TYPE)


def test_a_referrer_pointing_at_another_bundle_is_refused(cli, registry, made, tmp_path):  # noqa: F811
    """s2's own provenance referrer (subject s2) listed in s1's index."""
    s1 = made["pushed"]["s1"]["digest"]
    s2 = made["pushed"]["s2"]["digest"]
    saved = _index(registry, s1)
    index = {"schemaVersion": 2, "mediaType": INDEX_TYPE, "manifests": _index(registry, s2)["manifests"]}
    registry.put_manifest(REPO, s1.replace(":", "-"), json.dumps(index).encode(), INDEX_TYPE)
    try:
        dest = tmp_path / "out.hcdfz"
        r = cli("bundle", "pull", _at(registry, s1), "--out", dest, "--provenance-key", made["keys"]["release"][1])
        _refused(r, dest, 1, "points at another bundle", s1, s2)
    finally:
        registry.put_manifest(REPO, s1.replace(":", "-"), json.dumps(saved).encode(), INDEX_TYPE)


def test_require_provenance(cli, registry, made, tmp_path):  # noqa: F811
    pub = made["keys"]["release"][1]
    dest = tmp_path / "out.hcdfz"
    u1 = _at(registry, made["pushed"]["u1"]["digest"])  # (the same manifest as s1: its referrers are s1's)
    unsigned = tmp_path / "u.hcdfz"
    data = made["one"].read_bytes()
    entries = _entries(made["one"])
    unsigned.write_bytes(_zip(entries))
    assert unsigned.read_bytes() == data  # (the oracle rebuilds the bundle byte for byte)
    r = cli("bundle", "pull", u1, "--out", dest, "--require-provenance")
    _refused(r, dest, 2, "--provenance-key")
    # a bundle no provenance was ever attached to
    r = cli("bundle", "push", made["two"], registry.ref("robots/bare", "b"), "--json")
    assert r.exit_code == 0, r.stderr  # (s2's envelope is attached too: remove it from the index)
    bare = r.json["digest"]
    registry.put_manifest("robots/bare", bare.replace(":", "-"),
                          json.dumps({"schemaVersion": 2, "mediaType": INDEX_TYPE, "manifests": []}).encode(),
                          INDEX_TYPE)  # fmt: skip
    ref = registry.ref("robots/bare", "x").replace(":x", "@" + bare)
    r = cli("bundle", "pull", ref, "--out", dest, "--provenance-key", pub, "--require-provenance")
    _refused(r, dest, 1, "no provenance referrer is listed (--require-provenance)")
    r = cli("bundle", "pull", ref, "--out", dest, "--provenance-key", pub)  # by digest, not required: fine
    assert r.exit_code == 0, r.stderr


def test_push_verifies_the_provenance_first_given_a_key(cli, registry, made, tmp_path):  # noqa: F811
    keys = made["keys"]
    r = cli("bundle", "push", made["one"], registry.ref("robots/pv", "ok"), "--provenance-key", keys["release"][1],
            "--json")  # fmt: skip
    assert r.exit_code == 0 and r.json["provenance_verified"] is True, r.stderr
    r = cli("bundle", "push", made["one"], registry.ref("robots/pv", "bad"), "--provenance-key", keys["other"][1])
    assert r.exit_code == 1, r.stderr
    lone = tmp_path / "lone.hcdfz"
    shutil.copyfile(made["one"], lone)  # no envelope beside it
    r = cli("bundle", "push", lone, registry.ref("robots/pv", "lone"), "--provenance-key", keys["release"][1])
    assert r.exit_code == 3 and "no provenance beside the bundle" in r.stderr, r.stderr
    with registry.http() as c:
        for tag in ("bad", "lone"):
            assert c.get(f"/v2/robots/pv/manifests/{tag}").status_code == 404
    r = cli("bundle", "push", made["one"], registry.ref("robots/pv", "t2"), "--threshold", "2")
    assert r.exit_code == 2 and "--threshold needs --provenance-key" in r.stderr, r.stderr
    bad_sbom = tmp_path / "x.json"
    bad_sbom.write_text('{"not": "an sbom"}')
    r = cli("bundle", "push", made["one"], registry.ref("robots/pv", "sb"), "--sbom", bad_sbom)
    assert r.exit_code == 3 and "not a CycloneDX" in r.stderr


# --- 2. a tag is pulled only through its provenance, or on request -----------------------------


def test_a_tag_pull_needs_a_provenance_key_or_trust_tag(cli, registry, made, tmp_path):  # noqa: F811
    dest = tmp_path / "out.hcdfz"
    r = cli("bundle", "pull", registry.ref(REPO, "s1"), "--out", dest)
    _refused(r, dest, 2, "--trust-tag", "--provenance-key", "pull by digest")
    r = cli("bundle", "pull", "oci://127.0.0.1:9/none/such:t", "--out", dest)  # refused before any request
    _refused(r, dest, 2, "--trust-tag")
    # a digest needs neither
    assert cli("bundle", "pull", _at(registry, made["pushed"]["u1"]["digest"]), "--out", dest).exit_code == 0


def test_a_tag_pull_through_a_provenance_that_verifies(cli, registry, made, tmp_path):  # noqa: F811
    dest = tmp_path / "out.hcdfz"
    r = cli("bundle", "pull", registry.ref(REPO, "s2"), "--out", dest, "--provenance-key", made["keys"]["release"][1])
    assert r.exit_code == 0, r.stderr
    assert dest.read_bytes() == made["two"].read_bytes()


def test_a_tag_of_an_unsigned_bundle_is_refused_with_a_key(cli, registry, made, tmp_path):  # noqa: F811
    r = cli("bundle", "push", made["two"], registry.ref("robots/unsigned", "t"), "--json")
    assert r.exit_code == 0, r.stderr
    digest = r.json["digest"]
    registry.put_manifest(
        "robots/unsigned",
        digest.replace(":", "-"),
        json.dumps({"schemaVersion": 2, "mediaType": INDEX_TYPE, "manifests": []}).encode(),
        INDEX_TYPE,
    )  # fmt: skip: the provenance taken away
    dest = tmp_path / "out.hcdfz"
    pub = made["keys"]["release"][1]
    r = cli("bundle", "pull", registry.ref("robots/unsigned", "t"), "--out", dest, "--provenance-key", pub)
    _refused(r, dest, 1, "no provenance referrer is listed (a tag is trusted through its provenance)")
    r = cli("bundle", "pull", registry.ref("robots/unsigned", "t"), "--out", dest, "--trust-tag", "--json")
    assert r.exit_code == 0 and r.json["digest"] == digest, r.stderr


def test_a_tag_moved_to_a_bundle_signed_by_another_key_is_refused(cli, registry, made, tmp_path):  # noqa: F811
    """The tag names s1 today (signed by `release`); a user who trusts only `other` gets nothing."""
    dest = tmp_path / "out.hcdfz"
    r = cli("bundle", "pull", registry.ref(REPO, "s1"), "--out", dest, "--provenance-key", made["keys"]["other"][1])
    _refused(r, dest, 1)


# --- 3. messages name the reference and the entry, never the staging folder --------------------


def _raw(registry, data: bytes, tag: str) -> str:  # noqa: F811
    """A manifest of the documented shape over ``data``, past push's checks."""
    digest = registry.put_blob(REPO, data)
    doc = json.loads(registry.manifest(REPO, "u1")[0])
    doc["layers"][0].update(digest=digest, size=len(data))
    registry.put_manifest(REPO, tag, json.dumps(doc).encode())
    return registry.manifest(REPO, tag)[1]


@pytest.mark.parametrize("case", ["tampered", "dot-dot", "bomb"])
def test_pull_messages_name_the_reference_and_the_entry(cli, registry, made, tmp_path, case):  # noqa: F811
    entries = _entries(made["one"])
    if case == "tampered":
        name, blob = entries[1]
        entries[1] = (name, bytes([blob[0] ^ 1]) + blob[1:])
        data, words = _zip(entries), [name]  # (the url of the entry too, once a file: URL)
    else:
        data, what, _ = _hostile_cases(entries)[case]
        words = [what]
    digest = _raw(registry, data, f"m-{case}")
    cache = tmp_path / "cache"
    dest = tmp_path / "out.hcdfz"
    for extra in ([], ["--json"]):
        r = cli("bundle", "pull", _at(registry, digest), "--out", dest, "--cache-dir", cache, *extra)
        text = r.stdout + r.stderr
        _refused(r, dest, 1 if case == "tampered" else 3, *words)
        assert f"{_at(registry, digest)}/scout2.hcdfz" in text, text
        if case == "tampered":
            assert f"{_at(registry, digest)}/scout2.hcdfz/{name}" in text, text
        assert ".oci-pull-" not in text and str(cache) not in text and "file:" not in text, text


def test_ota_pull_messages_name_the_reference_not_the_staging_folder(cli, tmp_path, registry):  # noqa: F811
    """A release pulled with the wrong key: the message names the release manifest's file as
    `oci://…@sha256:…/release.suit`, never the staging folder."""
    from tests._ota import make_robot

    robot = make_robot(tmp_path, cli)
    release = tmp_path / "rel"
    assert robot.build(cli, release).exit_code == 0
    r = cli("ota", "push", release, registry.ref("robots/msg", "1"), "--key", robot.pub, "--json")
    assert r.exit_code == 0, r.stderr
    digest = r.json["digest"]
    r = cli("ota", "keygen", "-o", tmp_path / "other.pem")
    assert r.exit_code == 0, r.stderr
    cache = tmp_path / "cache"
    dest = tmp_path / "out"
    ref = registry.ref("robots/msg", "x").replace(":x", "@" + digest)
    r = cli("ota", "pull", ref, "--key", tmp_path / "other.pub.pem", "--out", dest, "--cache-dir", cache)
    assert r.exit_code == 1, r.stderr
    assert f"{ref}/release.suit" in r.stderr, r.stderr
    assert ".oci-pull-" not in r.stderr and str(cache) not in r.stderr
    assert not dest.exists()


def test_the_library_refuses_an_unbound_tag_before_any_request(tmp_path):
    """pull_bundle itself (not only the CLI) refuses a tag with neither keys nor trust_tag,
    and --require-provenance without keys: an InputError before the registry is asked."""
    from hcdf_trust.errors import InputError
    from hcdf_trust.oci.bundle import pull_bundle
    from hcdf_trust.oci.client import connect

    ref, client = connect("oci://127.0.0.1:9/none/such:t")  # nothing listens there: any request fails otherwise
    with client:
        with pytest.raises(InputError, match="a tag names whatever the registry says today"):
            pull_bundle(ref, client, out=str(tmp_path / "o.hcdfz"), cache_dir=str(tmp_path / "c"))
        pinned, _ = connect("oci://127.0.0.1:9/none/such@sha256:" + "0" * 64)
        with pytest.raises(InputError, match="--require-provenance needs --provenance-key"):
            pull_bundle(pinned, client, out=str(tmp_path / "o.hcdfz"), cache_dir=str(tmp_path / "c"),
                        require_provenance=True)  # fmt: skip
    assert not (tmp_path / "o.hcdfz").exists()
