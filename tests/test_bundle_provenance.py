"""``bundle --provenance`` / ``verify X.hcdfz --provenance`` (issues 19 + 21): the envelope
beside a bundle, its statement read back by hand (base64 + json, not our parser), and the
attacks: an edited bundle, another bundle's provenance, a wrong key."""

from __future__ import annotations

import base64
import hashlib
import json
import shutil
import zipfile

import pytest

from .conftest import PROJECT

EPOCH = "1780000000"
BUNDLE_TYPE = "https://hcdf.cognipilot.org/hcdf-trust/buildtypes/bundle/v1"


@pytest.fixture
def setup(cli, tmp_path, monkeypatch):
    monkeypatch.setenv("SOURCE_DATE_EPOCH", EPOCH)
    for name in ("GITHUB_SERVER_URL", "GITHUB_REPOSITORY", "GITHUB_RUN_ID"):
        monkeypatch.delenv(name, raising=False)
    shutil.copytree(PROJECT / "examples", tmp_path / "examples", ignore=shutil.ignore_patterns("out"))
    robot = tmp_path / "examples" / "robot" / "robot.hcdf"
    keys = {}
    for name in ("release", "other"):
        key = tmp_path / f"{name}.pem"
        r = cli("ota", "keygen", "--type", "ed25519", "-o", key)
        assert r.exit_code == 0, r.stderr
        keys[name] = (key, tmp_path / f"{name}.pub.pem")
    assert keys["release"][1].exists()
    return robot, keys


def _bundle(cli, robot, out, key):
    r = cli("bundle", robot, out, "--provenance", "--key", key)
    assert r.exit_code == 0, r.stderr
    return out.parent / (out.name + ".intoto.json")


def _statement(envelope) -> dict:
    return json.loads(base64.b64decode(json.loads(envelope.read_bytes())["payload"]))


def _verify(cli, out, pub, *extra):
    return cli("verify", out, "--provenance", "--provenance-key", pub, *extra)


def test_round_trip_and_the_statement(cli, setup, tmp_path):
    robot, keys = setup
    out = tmp_path / "scout2.hcdfz"
    env = _bundle(cli, robot, out, keys["release"][0])
    r = _verify(cli, out, keys["release"][1])
    assert r.exit_code == 0, r.stderr
    stmt = _statement(env)
    sha = hashlib.sha256(out.read_bytes()).hexdigest()
    assert stmt["subject"] == [{"name": "scout2.hcdfz", "digest": {"sha256": sha}}]
    build = stmt["predicate"]["buildDefinition"]
    assert build["buildType"] == BUNDLE_TYPE
    assert build["externalParameters"] == {"root": "robot.hcdf", "bundle": "scout2.hcdfz"}
    deps = build["resolvedDependencies"]
    by_name = {d["name"]: d["digest"]["sha256"] for d in deps}
    assert by_name["hcdf-root"] == hashlib.sha256(robot.read_bytes()).hexdigest()
    lock = robot.parent / "robot.hcdf.lock"
    assert by_name["hcdf-lock"] == hashlib.sha256(lock.read_bytes()).hexdigest()
    # every lock entry is a dependency with the lock's digest (the oracle: the lock file itself)
    locked = json.loads(lock.read_bytes())["artifacts"]
    for a in locked:
        name = ("hcdf-include:" if a["kind"] == "include" else "") + a["url"]
        assert by_name[name] == a["sha256"], name
    # the non-include dependencies are the bundle's assets (the oracle: zipfile)
    with zipfile.ZipFile(out) as z:
        assets = {hashlib.sha256(z.read(n)).hexdigest() for n in z.namelist() if n.startswith("assets/")}
    assert assets == {a["sha256"] for a in locked if a["kind"] != "include"}
    # without --provenance the bundle still verifies; the flags need each other
    assert cli("verify", out).exit_code == 0
    assert cli("verify", out, "--provenance").exit_code == 2
    assert cli("bundle", robot, tmp_path / "b.hcdfz", "--provenance").exit_code == 2


def test_reproducible_with_source_date_epoch(cli, setup, tmp_path):
    robot, keys = setup
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    a = _bundle(cli, robot, tmp_path / "a" / "scout2.hcdfz", keys["release"][0])
    b = _bundle(cli, robot, tmp_path / "b" / "scout2.hcdfz", keys["release"][0])
    assert a.read_bytes() == b.read_bytes()  # Ed25519 is deterministic: the whole envelope
    assert _statement(a)["predicate"]["runDetails"]["metadata"]["startedOn"] == "2026-05-28T20:26:40Z"


def test_a_bundle_edited_after_signing_is_refused(cli, setup, tmp_path):
    from hcdf_trust.bundle import encode

    robot, keys = setup
    out = tmp_path / "scout2.hcdfz"
    _bundle(cli, robot, out, keys["release"][0])
    # the root entry edited (a comment: the bundle itself still verifies), re-archived
    with zipfile.ZipFile(out) as z:
        entries = [(n, z.read(n)) for n in z.namelist()]
    entries[0] = (entries[0][0], entries[0][1].replace(b"<hcdf", b"<!-- edited -->\n<hcdf", 1))
    out.write_bytes(encode(entries))
    assert cli("verify", out).exit_code == 0
    r = _verify(cli, out, keys["release"][1])
    assert r.exit_code == 1, (r.stdout, r.stderr)
    assert "the subject is not this bundle" in r.stderr


def test_another_bundles_provenance_is_refused(cli, setup, tmp_path):
    robot, keys = setup
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    first = tmp_path / "a" / "scout2.hcdfz"
    env = _bundle(cli, robot, first, keys["release"][0])
    # another robot's bundle (the tree edited), with its own provenance, which verifies
    robot.write_text(robot.read_text().replace("<hcdf", "<!-- another robot -->\n<hcdf", 1))
    assert cli("resolve", robot).exit_code == 0
    other = tmp_path / "b" / "scout2.hcdfz"
    _bundle(cli, robot, other, keys["release"][0])
    assert _verify(cli, other, keys["release"][1]).exit_code == 0
    shutil.copy(env, other.parent / (other.name + ".intoto.json"))
    r = _verify(cli, other, keys["release"][1])
    assert r.exit_code == 1, (r.stdout, r.stderr)
    assert "the subject is not this bundle" in r.stderr


def test_a_wrong_key_is_refused(cli, setup, tmp_path):
    robot, keys = setup
    out = tmp_path / "scout2.hcdfz"
    _bundle(cli, robot, out, keys["other"][0])
    r = _verify(cli, out, keys["release"][1])
    assert r.exit_code == 1, (r.stdout, r.stderr)


def test_dependencies_must_be_the_bundles_assets(cli, setup, tmp_path):
    """An envelope re-signed by the key holder over a statement whose subject is right but
    whose dependencies drop an asset: the bundle's contents are checked, not just its digest."""
    from hcdf_trust.ota.keys import load_private
    from hcdf_trust.ota.signer import FileSigner
    from hcdf_trust.provenance import dsse
    from hcdf_trust.provenance.statement import serialize

    robot, keys = setup
    out = tmp_path / "scout2.hcdfz"
    env = _bundle(cli, robot, out, keys["release"][0])
    stmt = _statement(env)
    deps = stmt["predicate"]["buildDefinition"]["resolvedDependencies"]
    dropped = next(i for i, d in enumerate(deps) if not d["name"].startswith("hcdf-"))
    del deps[dropped]
    env.write_bytes(dsse.sign(serialize(stmt), [FileSigner(load_private(str(keys["release"][0])))]))
    r = _verify(cli, out, keys["release"][1])
    assert r.exit_code == 1, (r.stdout, r.stderr)
    assert "not a dependency of its provenance" in r.stderr


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("buildType", "https://hcdf.cognipilot.org/hcdf-trust/buildtypes/ota-build/v1", "buildType is not a bundle's"),
        ("externalParameters", {"root": "robot.hcdf", "bundle": "scout2.hcdfz", "extra": "x"}, "unexpected"),
    ],
)
def test_a_statement_of_another_build_type_is_refused(cli, setup, tmp_path, field, value, message):
    """Signed by the right key over the right subject, but a release's build type, or a
    parameter a bundle build never sets (SLSA: refuse unexpected externalParameters)."""
    from hcdf_trust.ota.keys import load_private
    from hcdf_trust.ota.signer import FileSigner
    from hcdf_trust.provenance import dsse
    from hcdf_trust.provenance.statement import serialize

    robot, keys = setup
    out = tmp_path / "scout2.hcdfz"
    env = _bundle(cli, robot, out, keys["release"][0])
    stmt = _statement(env)
    stmt["predicate"]["buildDefinition"][field] = value
    env.write_bytes(dsse.sign(serialize(stmt), [FileSigner(load_private(str(keys["release"][0])))]))
    r = _verify(cli, out, keys["release"][1])
    assert r.exit_code == 1, (r.stdout, r.stderr)
    assert message in r.stderr


def test_nothing_is_written_when_the_key_fails(cli, setup, tmp_path):
    robot, _keys = setup
    out = tmp_path / "scout2.hcdfz"
    r = cli("bundle", robot, out, "--provenance", "--key", tmp_path / "missing.pem")
    assert r.exit_code != 0
    assert not out.exists() and not (tmp_path / "scout2.hcdfz.intoto.json").exists()
