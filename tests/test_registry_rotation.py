"""Key rotation: a domain owner's key and the root keys; clients walk the chain of root versions."""

from __future__ import annotations

import pytest

from tests._registry import IEEE_XSD, PASSPHRASE, ROS2_XSD, Registry, build, site_json
from tests.servers import LoopbackServer


@pytest.fixture(autouse=True)
def _passphrase(monkeypatch):
    monkeypatch.setenv("HCDF_TRUST_PASSPHRASE", PASSPHRASE)


@pytest.fixture
def reg(tmp_path, cli) -> Registry:
    return build(tmp_path, cli)


def test_owner_key_rotation(reg, tmp_path):
    old = reg.source().domains["org.ros2"]
    old_signer = reg.owner_signer("org.ros2")
    with LoopbackServer(root=reg.site) as srv:
        assert reg.verify(srv.base).exit_code == 0
        # without the current owner key, no rotation
        res = reg.run("rotate", reg.src, "--domain", "org.ros2", "--keys", reg.owner_keys("org.gazebosim"), ok=False)
        assert res.exit_code == 1 and "only the owner can sign" in res.stderr
        reg.run("rotate", reg.src, "--domain", "org.ros2", "--keys", reg.owner_keys("org.ros2"))
        new = reg.source().domains["org.ros2"]
        assert set(new.keys).isdisjoint(old.keys)
        res = reg.publish("--json")
        assert {"extensions-000", "org.ros2"} <= set(res.json["signed"])  # the shard holds the delegation
        assert "targets" not in res.json["signed"]
        # a client that trusted the old key follows the delegation to the new one
        res = reg.verify(srv.base)
        assert res.exit_code == 0, res.stderr
        out = tmp_path / "ros.xsd"
        assert reg.fetch("org.ros2@1.0", out=out, site=srv.base).exit_code == 0
        assert out.read_bytes() == ROS2_XSD.read_bytes()
        # the new key signs new versions; the old key no longer can
        reg.add_domain("org.ros2", "1.1", IEEE_XSD)
        reg.publish()
        assert reg.fetch("org.ros2@1.1", out=out, site=srv.base).exit_code == 0

        def add(signed):
            signed.targets["extensions/org.ros2/1.2.xsd"] = reg.put_target("extensions/org.ros2/1.2.xsd", b"<x/>")

        reg.forge("org.ros2", add, signer=old_signer)
        res = reg.verify(srv.base)
        assert res.exit_code == 1 and "bad signature: org.ros2.json" in res.stderr


@pytest.mark.parametrize("cache", ["client", "fresh"])
def test_root_key_rotation_clients_walk_the_root_chain(reg, cache):
    """A client bootstrapped with 1.root.json (with or without a cache) reaches root v3."""
    old_root = reg.top_signer("root")
    with LoopbackServer(root=reg.site) as srv:
        assert reg.verify(srv.base).exit_code == 0
        reg.run("rotate", reg.src, "--role", "root", "--keys", reg.keys)
        reg.publish()
        reg.run("rotate", reg.src, "--role", "timestamp", "--keys", reg.keys)
        res = reg.publish("--json")
        assert res.json["versions"]["root"] == 3
        meta = reg.site / "metadata"
        v2 = site_json(meta / "2.root.json")
        # v2 is signed by the old root key and the new one
        assert {s["keyid"] for s in v2["signatures"]} == {
            old_root.public_key.keyid,
            *v2["signed"]["roles"]["root"]["keyids"],
        }
        srv.hits.clear()
        res = reg.verify(srv.base, cache=cache)
        assert res.exit_code == 0, res.stderr
        assert "root v3" in res.stderr
        assert srv.hits["/metadata/2.root.json"] == 1 and srv.hits["/metadata/3.root.json"] == 1
        assert srv.hits["/metadata/4.root.json"] == 1  # the probe that ends the walk (404)


def test_old_timestamp_key_is_refused_after_rotation(reg):
    old_ts = reg.top_signer("timestamp")
    reg.run("rotate", reg.src, "--role", "timestamp", "--keys", reg.keys)
    reg.publish()
    from tuf.api.metadata import Metadata

    path = reg.site / "metadata" / "timestamp.json"
    ts = Metadata.from_file(str(path))
    ts.signed.version += 1
    ts.signatures.clear()
    ts.sign(old_ts)
    path.write_bytes(ts.to_bytes())
    res = reg.verify(cache="fresh")
    assert res.exit_code == 1 and "bad signature" in res.stderr


def test_root_rotation_without_the_old_root_key_is_refused(reg, tmp_path):
    reg.run("rotate", reg.src, "--role", "root", "--keys", reg.keys)
    from tuf.api.metadata import Metadata

    root1 = Metadata.from_file(str(reg.root_json))
    for keyid in root1.signed.roles["root"].keyids:
        (reg.keys / f"{keyid}.key").unlink()
    res = reg.publish(ok=False)
    assert res.exit_code == 1 and "root rotation (the previous root's keys)" in res.stderr
    assert not (reg.site / "metadata" / "2.root.json").exists()
