"""The TUF attacks against a published registry served by a real HTTP server on 127.0.0.1.

Each attack is refused with exit 1 and a message that names it; the client is
``hcdf-trust registry verify`` / ``fetch`` (tuf.ngclient underneath).
"""

from __future__ import annotations

import datetime as dt
import shutil

import pytest

from tests._registry import IEEE_XSD, PASSPHRASE, PROFILE, ROS2_XSD, Registry, build
from tests.servers import LoopbackServer


@pytest.fixture(autouse=True)
def _passphrase(monkeypatch):
    monkeypatch.setenv("HCDF_TRUST_PASSPHRASE", PASSPHRASE)


@pytest.fixture
def reg(tmp_path, cli) -> Registry:
    return build(tmp_path, cli)


@pytest.fixture
def srv(reg):
    with LoopbackServer(root=reg.site) as server:
        yield server


def _refused(res, name: str) -> None:
    assert res.exit_code == 1, (res.exit_code, res.stderr)
    assert name in res.stderr, res.stderr
    assert "Traceback" not in res.stderr


def test_rollback_old_targets_served_as_the_new_version(reg, srv):
    assert reg.verify(srv.base).exit_code == 0
    reg.run("add", reg.src, "--core", "hcdf", "--version", "1.0", "--schema", PROFILE, "--content", reg.content)
    reg.publish()  # targets v2 (a new core schema), snapshot and timestamp bumped
    meta = reg.site / "metadata"
    shutil.copy(meta / "1.targets.json", meta / "2.targets.json")
    _refused(reg.verify(srv.base), "rollback attack")


def test_rollback_older_timestamp_and_snapshot_served(reg, srv):
    meta = reg.site / "metadata"
    old_ts = (meta / "timestamp.json").read_bytes()
    reg.add_domain("org.ros2", "1.1", IEEE_XSD)
    reg.publish()
    assert reg.verify(srv.base).exit_code == 0  # the client now trusts timestamp v2
    (meta / "timestamp.json").write_bytes(old_ts)
    _refused(reg.verify(srv.base), "rollback attack")


def test_rollback_of_a_domain_role_by_a_compromised_snapshot_key(reg, srv):
    reg.add_domain("org.ros2", "1.1", IEEE_XSD)
    reg.publish()
    assert reg.verify(srv.base).exit_code == 0  # trusts org.ros2 v2
    from tuf.api.metadata import Metadata, MetaFile

    meta = reg.site / "metadata"
    ts = Metadata.from_file(str(meta / "timestamp.json"))
    snap = Metadata.from_file(str(meta / f"{ts.signed.snapshot_meta.version}.snapshot.json"))
    snap.signed.meta["org.ros2.json"] = MetaFile(1)  # points back at the role without 1.1
    reg.resign_snapshot_timestamp(snap)
    _refused(reg.verify(srv.base), "rollback attack")


def test_freeze_expired_timestamp(reg, srv):
    from hcdf_trust.outputs import OutputPlan
    from hcdf_trust.registry.publish import publish

    plan = OutputPlan()
    now = dt.datetime.now(dt.UTC).replace(microsecond=0) - dt.timedelta(hours=2)
    publish(
        reg.source(), reg.ring(), reg.content, reg.site, plan=plan, timestamp_lifetime=dt.timedelta(hours=1), now=now
    )
    plan.commit()
    res = reg.verify(srv.base)
    _refused(res, "freeze attack")
    assert "timestamp" in res.stderr


def test_freeze_also_refuses_a_client_that_never_saw_the_site(reg, srv):
    reg.forge(
        "org.ros2",
        lambda signed: None,
        signer=reg.owner_signer("org.ros2"),
        expires=dt.datetime.now(dt.UTC).replace(microsecond=0) - dt.timedelta(days=1),
    )
    _refused(reg.verify(srv.base, cache="fresh"), "freeze attack")


def test_mix_and_match_snapshot_from_another_publication(reg, srv):
    meta = reg.site / "metadata"
    reg.add_domain("org.ros2", "1.1", IEEE_XSD)
    reg.publish()  # snapshot v2 lists org.ros2 v2
    shutil.copy(meta / "1.snapshot.json", meta / "2.snapshot.json")  # publication 1's snapshot
    _refused(reg.verify(srv.base, cache="fresh"), "mix-and-match attack")


def test_arbitrary_content_a_target_swapped_on_the_server(reg, srv, tmp_path):
    target = reg.target_file("extensions/org.ros2/1.0.xsd")
    data = bytearray(target.read_bytes())
    data[100] ^= 0x01  # same length, one bit
    target.write_bytes(bytes(data))
    out = tmp_path / "ros.xsd"
    _refused(reg.fetch("org.ros2", out=out, site=srv.base), "arbitrary content")
    assert not out.exists()
    _refused(reg.verify(srv.base), "arbitrary content")


def test_endless_data_a_target_longer_than_its_signed_length(reg, srv, tmp_path):
    target = reg.target_file("profiles/operational/1.0.streams.xml")
    srv.stream("/targets/profiles/operational/" + target.name, 64 << 20)  # 64 MiB for a 3 KB profile
    out = tmp_path / "op.xml"
    _refused(reg.fetch("profile", "operational", out=out, site=srv.base), "endless data")
    assert not out.exists()


def test_endless_data_on_the_timestamp(reg, srv):
    srv.stream("/metadata/timestamp.json", 8 << 20)
    res = reg.verify(srv.base)
    _refused(res, "endless data")


def test_cross_domain_signing_is_invisible_to_clients_and_reported_by_verify(reg, srv, tmp_path):
    """The gazebosim owner lists a file under org.ros2's path: clients ask only org.ros2 about it."""
    evil = b"<xs:schema xmlns:xs='http://www.w3.org/2001/XMLSchema'/>"

    def hijack(signed):
        for path in ("extensions/org.ros2/1.0.xsd", "extensions/org.ros2/9.0.xsd"):
            signed.targets[path] = reg.put_target(path, evil)

    reg.forge("org.gazebosim", hijack, signer=reg.owner_signer("org.gazebosim"))
    out = tmp_path / "ros.xsd"
    res = reg.fetch("org.ros2", out=out, site=srv.base)  # the latest version ros2's own role lists
    assert res.exit_code == 0, res.stderr
    assert out.read_bytes() == ROS2_XSD.read_bytes()
    res = reg.fetch("org.ros2@9.0", out=out, site=srv.base)
    assert res.exit_code == 3 and "no version 9.0" in res.stderr
    res = reg.verify(srv.base)
    _refused(res, "cross-domain signing: org.gazebosim lists extensions/org.ros2/1.0.xsd")


def test_domain_role_signed_by_another_domains_owner(reg, srv):
    def add(signed):
        signed.targets["extensions/org.ros2/2.0.xsd"] = reg.put_target("extensions/org.ros2/2.0.xsd", b"x")

    reg.forge("org.ros2", add, signer=reg.owner_signer("org.gazebosim"))
    _refused(reg.verify(srv.base), "bad signature: org.ros2.json")


def test_publisher_without_the_owner_key_adding_a_version(reg, srv, tmp_path):
    """The registry's own targets key signs a new org.ros2 version: the delegation does not list it."""

    def add(signed):
        signed.targets["extensions/org.ros2/1.1.xsd"] = reg.put_target("extensions/org.ros2/1.1.xsd", b"<x/>")

    reg.forge("org.ros2", add, signer=reg.top_signer("targets"))
    res = reg.fetch("org.ros2@1.1", out=tmp_path / "x", site=srv.base)
    _refused(res, "publisher without the owner's key")


def test_replaced_published_version_is_noticed_by_a_client_that_saw_it(reg, srv, tmp_path):
    assert reg.verify(srv.base).exit_code == 0
    evil = IEEE_XSD.read_bytes()

    def replace(signed):
        signed.targets["extensions/org.ros2/1.0.xsd"] = reg.put_target("extensions/org.ros2/1.0.xsd", evil)

    reg.forge("org.ros2", replace, signer=reg.owner_signer("org.ros2"))  # even the owner may not
    out = tmp_path / "ros.xsd"
    _refused(reg.fetch("org.ros2@1.0", out=out, site=srv.base), "replaced published version")
    assert not out.exists()
    # and again on the next run: the trusted role was restored, not replaced
    _refused(reg.verify(srv.base), "replaced published version")


def test_metadata_edited_without_resigning(reg, srv):
    meta = reg.site / "metadata"
    path = meta / "1.org.ros2.json"
    path.write_bytes(path.read_bytes().replace(b'"length":6862', b'"length":6863'))
    _refused(reg.verify(srv.base), "bad signature")


def test_unreachable_registry_is_an_input_error(reg, srv, tmp_path):
    srv.close()
    res = reg.verify(srv.base)
    assert res.exit_code == 3 and "cannot reach the registry at 127.0.0.1:" in res.stderr
    assert "(Connection refused)" in res.stderr and "check SITE " in res.stderr


def test_stalled_server_is_a_transport_error_within_the_timeout(reg, srv):
    import time

    srv.stall("/metadata/timestamp.json")
    t = time.monotonic()
    res = reg.cli("registry", "verify", srv.base, "--trusted-root", reg.root_json, "--cache-dir", reg.base / "c",
                  "--timeout", "0.5")  # fmt: skip
    assert res.exit_code == 3 and "(timed out)" in res.stderr and "cannot reach the registry" in res.stderr, res.stderr
    assert time.monotonic() - t < 10
    res = reg.cli("registry", "verify", srv.base, "--trusted-root", reg.root_json, "--timeout", "0")
    assert res.exit_code == 2


def test_directory_site_refuses_symlinks_out_and_fifos(reg, tmp_path):
    import os

    meta = reg.site / "metadata"
    outside = tmp_path / "elsewhere.json"
    outside.write_bytes((meta / "timestamp.json").read_bytes())
    (meta / "timestamp.json").unlink()
    (meta / "timestamp.json").symlink_to(outside)
    res = reg.verify()
    assert res.exit_code == 3 and "outside the root" in res.stderr and "Traceback" not in res.stderr
    (meta / "timestamp.json").unlink()
    os.mkfifo(meta / "timestamp.json")
    res = reg.verify()
    assert res.exit_code == 3 and "FIFO" in res.stderr


def test_directory_site_endless_data(reg, tmp_path):
    target = reg.target_file("extensions/org.ros2/1.0.xsd")
    with target.open("ab") as f:
        f.write(b"\0" * (8 << 20))
    _refused(reg.fetch("org.ros2", out=tmp_path / "x"), "endless data")


def test_publish_onto_a_site_with_malformed_metadata_is_an_input_error(reg):
    (reg.site / "metadata" / "timestamp.json").write_text('{"signed": 1e999}')
    res = reg.publish(ok=False)
    assert res.exit_code == 3 and "not TUF metadata" in res.stderr and "Traceback" not in res.stderr


def test_a_shard_listing_a_domain_file_is_reported(reg, srv):
    """A shard (targets key) listing extensions/org.ros2/... would shadow the owner's role."""

    def shadow(signed):
        signed.targets["extensions/org.ros2/1.0.xsd"] = reg.put_target("extensions/org.ros2/1.0.xsd", b"<x/>")

    reg.forge("extensions-000", shadow, signer=reg.top_signer("targets"))
    res = reg.verify(srv.base)
    _refused(res, "extensions-000 lists extensions/org.ros2/1.0.xsd: only a domain's own role may list its files")
