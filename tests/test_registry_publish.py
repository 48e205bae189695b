"""registry init / add / publish / verify / fetch: the clean path and the publish-time refusals."""

from __future__ import annotations

import hashlib
import os
import stat

import pytest

from tests._registry import GAZEBO_XSD, IEEE_XSD, PASSPHRASE, PROFILE, ROS2_XSD, Registry, build, site_json
from tests.servers import LoopbackServer


@pytest.fixture(autouse=True)
def _passphrase(monkeypatch):
    monkeypatch.setenv("HCDF_TRUST_PASSPHRASE", PASSPHRASE)


@pytest.fixture
def reg(tmp_path, cli) -> Registry:
    return build(tmp_path, cli)


def test_clean_publish_verifies_and_fetches_corpus_bytes_over_loopback(reg, tmp_path):
    with LoopbackServer(root=reg.site) as srv:
        res = reg.verify(srv.base)
        assert res.exit_code == 0, res.stderr
        assert "2 domain roles, 3 files" in res.stderr
        for what, corpus in [
            (("org.ros2",), ROS2_XSD),
            (("org.gazebosim@1.0",), GAZEBO_XSD),
            (("profile", "operational"), PROFILE),
        ]:
            out = tmp_path / "out.bin"
            res = reg.fetch(*what, out=out, site=srv.base)
            assert res.exit_code == 0, res.stderr
            assert out.read_bytes() == corpus.read_bytes()
        assert srv.hits["/metadata/1.org.ros2.json"] == 1  # cached after the first load


def test_directory_site_verifies_through_the_directory_fetcher(reg, tmp_path):
    res = reg.verify()
    assert res.exit_code == 0, res.stderr
    out = tmp_path / "ros.xsd"
    assert reg.fetch("org.ros2@1.0", out=out).exit_code == 0
    assert out.read_bytes() == ROS2_XSD.read_bytes()


def test_site_layout_is_consistent_snapshots_with_one_role_per_domain(reg):
    meta = reg.site / "metadata"
    assert site_json(meta / "1.root.json")["signed"]["consistent_snapshot"] is True
    targets = site_json(meta / "1.targets.json")["signed"]
    (shard,) = targets["delegations"]["roles"]  # two domains: one shard, signed by the targets key
    assert shard["name"] == "extensions-000" and shard["terminating"] is True
    assert sorted(shard["paths"]) == ["extensions/org.gazebosim/*", "extensions/org.ros2/*"]
    assert shard["keyids"] == site_json(meta / "1.root.json")["signed"]["roles"]["targets"]["keyids"]
    roles = {r["name"]: r for r in site_json(meta / "1.extensions-000.json")["signed"]["delegations"]["roles"]}
    assert set(roles) == {"org.ros2", "org.gazebosim"}
    assert roles["org.ros2"]["paths"] == ["extensions/org.ros2/*"]
    assert roles["org.ros2"]["terminating"] is True
    ros = site_json(meta / "1.org.ros2.json")
    # signed by the owner's key only, which the delegation lists
    assert [s["keyid"] for s in ros["signatures"]] == roles["org.ros2"]["keyids"]
    assert set(roles["org.ros2"]["keyids"]) == set(reg.source().domains["org.ros2"].keys)
    digest = hashlib.sha256(ROS2_XSD.read_bytes()).hexdigest()
    assert ros["signed"]["targets"]["extensions/org.ros2/1.0.xsd"]["hashes"]["sha256"] == digest
    published = reg.site / "targets" / "extensions" / "org.ros2" / f"{digest}.1.0.xsd"
    assert published.read_bytes() == ROS2_XSD.read_bytes()
    snapshot = site_json(meta / "1.snapshot.json")["signed"]["meta"]
    assert set(snapshot) == {"targets.json", "extensions-000.json", "org.ros2.json", "org.gazebosim.json"}


def test_shards_keep_top_level_targets_small_and_lookups_to_one_shard(tmp_path, cli):
    """70 domains: two shard roles; a lookup loads top-level targets, one shard, one domain role."""
    from hcdf_trust.registry.publish import shard_count, shard_of

    assert shard_count(4) == 1 and shard_count(64) == 1 and shard_count(65) == 2 and shard_count(1000) == 16
    names = [f"org.example{i}" for i in range(70)]
    assert {shard_of(n, 2) for n in names} == {"extensions-000", "extensions-001"}
    reg = Registry(tmp_path, cli)
    reg.run("init", reg.src, "--keys", reg.keys)
    for name in names[:3]:
        reg.add_domain(name, "1.0", ROS2_XSD)
    for name in names[3:]:  # registered, no version yet
        reg.run("keygen", "--keys", reg.owner_keys(name), "-o", tmp_path / f"{name}.pub")
        reg.run("add", reg.src, "--domain", name, "--owner", "x", "--owner-key", tmp_path / f"{name}.pub")
    reg.publish()
    top = site_json(reg.site / "metadata" / "1.targets.json")["signed"]["delegations"]["roles"]
    assert sorted(r["name"] for r in top) == ["extensions-000", "extensions-001"]
    with LoopbackServer(root=reg.site) as srv:
        out = tmp_path / "x.xsd"
        assert reg.fetch(f"{names[0]}@1.0", out=out, site=srv.base).exit_code == 0
        shard_hits = {p: n for p, n in srv.hits.items() if "extensions-" in p}
        assert shard_hits == {f"/metadata/1.{shard_of(names[0], 2)}.json": 1}
        res = reg.verify(srv.base)
        assert res.exit_code == 0 and "70 domain roles, 3 files" in res.stderr, res.stderr


def test_init_keys_are_0600_encrypted_and_outside_the_source(reg, tmp_path):
    keys = sorted(reg.keys.iterdir())
    assert len(keys) == 4
    assert stat.S_IMODE(reg.keys.stat().st_mode) == 0o700
    for k in keys:
        assert stat.S_IMODE(k.stat().st_mode) == 0o600
        assert b"ENCRYPTED PRIVATE KEY" in k.read_bytes()
    res = reg.run("init", tmp_path / "other", "--keys", tmp_path / "other" / "keys", ok=False)
    assert res.exit_code == 3 and "must not be committed" in res.stderr
    assert not (tmp_path / "other" / "root.toml").exists()


def test_wrong_passphrase_is_an_input_error(reg, monkeypatch):
    monkeypatch.setenv("HCDF_TRUST_PASSPHRASE", "wrong")
    res = reg.run(
        "add",
        reg.src,
        "--domain",
        "org.ros2",
        "--version",
        "1.1",
        "--schema",
        IEEE_XSD,
        "--content",
        reg.content,
        "--keys",
        reg.owner_keys("org.ros2"),
        ok=False,
    )
    assert res.exit_code == 3
    assert "wrong passphrase" in res.stderr


def test_republish_unchanged_needs_no_owner_key_and_bumps_only_the_timestamp_chain(reg):
    res = reg.publish("--json", owners=False)
    assert set(res.json["signed"]) <= {"snapshot", "timestamp"}  # the snapshot only if it would expire first
    assert "timestamp" in res.json["signed"]
    assert res.json["versions"]["root"] == res.json["versions"]["targets"] == 1
    assert res.json["versions"]["timestamp"] == 2
    assert reg.verify().exit_code == 0


def test_publisher_without_owner_key_cannot_add_a_version(reg):
    # the owner records 1.1 in the source (signed), the publisher lacks the owner's key
    reg.add_domain("org.ros2", "1.1", IEEE_XSD)
    before = sorted(p.name for p in (reg.site / "metadata").iterdir())
    res = reg.publish(owners=False, ok=False)
    assert res.exit_code == 1
    assert "domain org.ros2" in res.stderr and "only the owner can sign" in res.stderr
    assert sorted(p.name for p in (reg.site / "metadata").iterdir()) == before  # nothing written
    res = reg.publish()
    assert reg.verify().exit_code == 0


def test_existing_domain_gains_a_version_only_with_its_owner_key(reg):
    res = reg.run(
        "add",
        reg.src,
        "--domain",
        "org.ros2",
        "--version",
        "1.1",
        "--schema",
        IEEE_XSD,
        "--content",
        reg.content,
        "--keys",
        reg.owner_keys("org.gazebosim"),
        ok=False,
    )
    assert res.exit_code == 1 and "only the owner can sign" in res.stderr
    assert "1.1" not in reg.source().domains["org.ros2"].versions


def test_hand_added_unsigned_version_is_refused_at_publish(reg):
    entry = reg.src / "domains" / "org.ros2.toml"
    text = entry.read_text()
    digest = hashlib.sha256(IEEE_XSD.read_bytes()).hexdigest()
    text += (
        f'\n[versions."2.0"]\npath = "extensions/org.ros2/2.0.xsd"\nfile = "extensions/hcdf-ext-1722.xsd"\n'
        f'sha256 = "{digest}"\nlength = {IEEE_XSD.stat().st_size}\n'
    )
    entry.write_text(text)
    res = reg.publish(ok=False)
    assert res.exit_code == 1
    assert "org.ros2 2.0 is not signed by the domain's owner" in res.stderr


def test_cross_domain_path_is_refused_at_publish_time(reg):
    """A gazebosim entry (owner-signed) naming a path under org.ros2: refused before signing."""
    from dataclasses import replace

    from hcdf_trust.outputs import REGISTRY_SOURCE, OutputPlan
    from hcdf_trust.registry.edit import dump
    from hcdf_trust.registry.source import Release

    src = reg.source()
    gz = src.domains["org.gazebosim"]
    data = ROS2_XSD.read_bytes()
    rel = Release(
        "9.0",
        "extensions/org.ros2/9.0.xsd",
        "extensions/hcdf-ext-ros2.xsd",
        hashlib.sha256(data).hexdigest(),
        len(data),
    )
    sig = reg.owner_signer("org.gazebosim").sign(gz.statement(rel))
    gz = replace(gz, versions={**gz.versions, "9.0": replace(rel, signatures={sig.keyid: sig.signature})})
    plan = OutputPlan()
    plan.add(reg.src / "domains" / "org.gazebosim.toml", dump(gz), flag="test", replaces=(REGISTRY_SOURCE,))
    plan.commit()
    res = reg.publish(ok=False)
    assert res.exit_code == 1
    assert "cross-domain signing refused: org.gazebosim lists extensions/org.ros2/9.0.xsd" in res.stderr


def test_replaced_published_version_is_refused_by_add_and_by_publish(reg):
    res = reg.run(
        "add",
        reg.src,
        "--domain",
        "org.ros2",
        "--version",
        "1.0",
        "--schema",
        IEEE_XSD,
        "--content",
        reg.content,
        "--keys",
        reg.owner_keys("org.ros2"),
        ok=False,
    )
    assert res.exit_code == 1 and "replaced published version refused" in res.stderr
    # the same content again is a no-op
    res = reg.run(
        "add",
        reg.src,
        "--domain",
        "org.ros2",
        "--version",
        "1.0",
        "--schema",
        ROS2_XSD,
        "--content",
        reg.content,
        "--keys",
        reg.owner_keys("org.ros2"),
    )
    assert "already registered" in res.stderr
    # the owner edits the entry by hand and re-signs it: publish compares with the site
    from dataclasses import replace

    from hcdf_trust.outputs import REGISTRY_SOURCE, OutputPlan
    from hcdf_trust.registry.edit import dump

    src = reg.source()
    ros = src.domains["org.ros2"]
    data = IEEE_XSD.read_bytes()
    rel = replace(
        ros.versions["1.0"],
        file="extensions/hcdf-ext-1722.xsd",
        sha256=hashlib.sha256(data).hexdigest(),
        length=len(data),
    )
    sig = reg.owner_signer("org.ros2").sign(ros.statement(rel))
    ros = replace(ros, versions={"1.0": replace(rel, signatures={sig.keyid: sig.signature})})
    plan = OutputPlan()
    plan.add(reg.src / "domains" / "org.ros2.toml", dump(ros), flag="test", replaces=(REGISTRY_SOURCE,))
    plan.commit()
    res = reg.publish(ok=False)
    assert res.exit_code == 1
    assert "replaced published version refused: extensions/org.ros2/1.0.xsd" in res.stderr


def test_content_that_differs_from_its_entry_is_refused(reg, tmp_path):
    content = tmp_path / "content"
    (content / "extensions").mkdir(parents=True)
    for f in ("hcdf-ext-ros2.xsd", "hcdf-ext-gazebo.xsd"):
        (content / "extensions" / f).write_bytes((ROS2_XSD.parent / f).read_bytes())
    (content / "examples" / "profiles").mkdir(parents=True)
    (content / "examples" / "profiles" / PROFILE.name).write_bytes(PROFILE.read_bytes().replace(b"1kHz", b"2kHz"))
    res = reg.run("publish", reg.src, "--keys", reg.keys, "--content", content, "--out", reg.site, ok=False)
    assert res.exit_code == 1
    assert "does not match its registry entry" in res.stderr and "expected: sha256:" in res.stderr


def test_publish_refuses_an_output_inside_the_source_or_content(reg):
    res = reg.run(
        "publish",
        reg.src,
        "--keys",
        reg.keys,
        "--content",
        reg.content,
        "--out",
        reg.src / "site",
        *sum((["--keys", d] for d in reg.base.glob("keys-*")), []),
        ok=False,
    )
    assert res.exit_code == 3 and "inside the registry source" in res.stderr


def test_expires_is_validated_when_parsed(reg):
    for bad in ("0d", "7", "-1d", "99999w"):
        res = reg.publish("--expires", bad, ok=False)
        assert res.exit_code == 2, bad


def test_timestamp_lifetime_is_the_expires_option(reg):
    import datetime as dt

    reg.publish("--expires", "3h")
    ts = site_json(reg.site / "metadata" / "timestamp.json")["signed"]
    expires = dt.datetime.strptime(ts["expires"], "%Y-%m-%dT%H:%M:%SZ").replace(tzinfo=dt.UTC)
    left = expires - dt.datetime.now(dt.UTC)
    assert dt.timedelta(hours=2, minutes=55) < left <= dt.timedelta(hours=3)


def test_fetch_writes_only_verified_content_and_never_over_an_input(reg, tmp_path):
    res = reg.fetch("org.ros2", out=reg.root_json)
    assert res.exit_code == 3 and "refusing to overwrite an input" in res.stderr
    res = reg.fetch("org.ros2@7.0", out=tmp_path / "x.xsd")
    assert res.exit_code == 3 and "no version 7.0" in res.stderr
    assert not (tmp_path / "x.xsd").exists()
    res = reg.fetch("org.unknown", out=tmp_path / "x.xsd")
    assert res.exit_code == 3 and "not a registered domain" in res.stderr


def test_trusted_root_that_is_not_a_root_is_an_input_error(reg, tmp_path):
    bogus = tmp_path / "root.json"
    bogus.write_text("[]")
    res = reg.cli("registry", "verify", reg.site, "--trusted-root", bogus)
    assert res.exit_code == 3 and "not valid TUF root metadata" in res.stderr
    fifo = tmp_path / "fifo.json"
    os.mkfifo(fifo)
    res = reg.cli("registry", "verify", reg.site, "--trusted-root", fifo)
    assert res.exit_code == 3 and "FIFO" in res.stderr


def test_hostile_key_files_are_input_errors(reg, tmp_path):
    root = reg.source().root
    key = reg.keys / f"{root.roles['timestamp'].keyids[0]}.key"  # needed by every publish
    key.unlink()
    os.mkfifo(key)
    reg.add_domain("org.ros2", "1.1", IEEE_XSD)
    res = reg.publish(ok=False)
    assert res.exit_code == 3 and "FIFO" in res.stderr
    key.unlink()
    key.write_bytes(b"-----BEGIN ENCRYPTED PRIVATE KEY-----\nnot a key\n-----END ENCRYPTED PRIVATE KEY-----\n")
    res = reg.publish(ok=False)
    assert res.exit_code == 3 and "not an encrypted PEM private key" in res.stderr
    other = sorted(reg.owner_keys("org.ros2").iterdir())[0]
    key.write_bytes(other.read_bytes())  # a real key, but not the one its name promises
    res = reg.publish(ok=False)
    assert res.exit_code == 3 and "does not match the public key" in res.stderr
