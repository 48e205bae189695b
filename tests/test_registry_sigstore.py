"""sigstore bundles as an owner's approval of a new domain version, verified offline."""

from __future__ import annotations

import json
import socket

import pytest

from tests._registry import IEEE_XSD, PASSPHRASE, ROS2_XSD, Registry

pytest.importorskip("sigstore")

from tests._fake_sigstore import FakeSigstore  # noqa: E402

IDENTITY = "ci@ros2.example"
ISSUER = "https://token.actions.example"


@pytest.fixture(autouse=True)
def _offline(monkeypatch):
    """Every test here runs with networking disabled: verification must never need it."""
    monkeypatch.setenv("HCDF_TRUST_PASSPHRASE", PASSPHRASE)

    def refuse(*args, **kwargs):
        raise OSError("network disabled in this test")

    monkeypatch.setattr(socket.socket, "connect", refuse)


@pytest.fixture
def fake(tmp_path):
    fs = FakeSigstore()
    (tmp_path / "trusted_root.json").write_text(json.dumps(fs.trusted_root()))
    return fs


@pytest.fixture
def reg(tmp_path, cli) -> Registry:
    reg = Registry(tmp_path, cli)
    reg.run("init", reg.src, "--keys", reg.keys)
    pub = tmp_path / "org.ros2.pub"
    reg.run("keygen", "--keys", reg.owner_keys("org.ros2"), "-o", pub)
    reg.run("add", reg.src, "--domain", "org.ros2", "--owner", "ROS 2", "--owner-key", pub,
            "--sigstore-identity", IDENTITY, "--sigstore-issuer", ISSUER)  # fmt: skip
    return reg


def _bundle(reg, fake, version, schema, *, identity=IDENTITY):
    stmt = reg.base / f"{version}.statement.json"
    reg.run("statement", "--domain", "org.ros2", "--version", version, "--schema", schema,
            "--content", reg.content, "-o", stmt)  # fmt: skip
    bundle = reg.base / f"{version}.sigstore.json"
    bundle.write_text(fake.sign(stmt.read_bytes(), identity=identity, issuer=ISSUER))
    return bundle


def _add(reg, version, schema, bundle, *, ok=True):
    return reg.run("add", reg.src, "--domain", "org.ros2", "--version", version, "--schema", schema,
                   "--content", reg.content, "--sigstore-bundle", bundle,
                   "--sigstore-trusted-root", reg.base / "trusted_root.json", ok=ok)  # fmt: skip


def test_a_sigstore_bundle_approves_a_version_offline_and_publishes(reg, fake, tmp_path):
    _add(reg, "1.0", ROS2_XSD, _bundle(reg, fake, "1.0", ROS2_XSD))
    release = reg.source().domains["org.ros2"].versions["1.0"]
    assert release.sigstore and not release.signatures  # no owner key signature was needed
    assert (reg.src / "bundles" / "org.ros2" / "1.0.sigstore.json").is_file()
    reg.publish("--sigstore-trusted-root", tmp_path / "trusted_root.json")
    out = tmp_path / "ros.xsd"
    assert reg.verify().exit_code == 0
    assert reg.fetch("org.ros2@1.0", out=out).exit_code == 0
    assert out.read_bytes() == ROS2_XSD.read_bytes()


def test_a_bundle_from_another_identity_is_refused(reg, fake):
    res = _add(reg, "1.0", ROS2_XSD, _bundle(reg, fake, "1.0", ROS2_XSD, identity="mallory@evil.example"), ok=False)
    assert res.exit_code == 1 and "does not verify as ci@ros2.example" in res.stderr
    assert "1.0" not in reg.source().domains["org.ros2"].versions


def test_a_bundle_for_another_version_or_content_is_refused(reg, fake):
    bundle = _bundle(reg, fake, "1.0", ROS2_XSD)
    res = _add(reg, "1.1", ROS2_XSD, bundle, ok=False)  # the statement names version 1.0
    assert res.exit_code == 1 and "sigstore bundle does not verify" in res.stderr
    res = _add(reg, "1.0", IEEE_XSD, bundle, ok=False)  # other content under the approved version
    assert res.exit_code == 1


def test_a_bundle_from_another_sigstore_instance_is_refused(reg, fake):
    other = FakeSigstore()
    bundle = reg.base / "other.sigstore.json"
    stmt = _bundle(reg, fake, "1.0", ROS2_XSD).with_name("1.0.statement.json")
    bundle.write_text(other.sign(stmt.read_bytes(), identity=IDENTITY, issuer=ISSUER))
    res = _add(reg, "1.0", ROS2_XSD, bundle, ok=False)
    assert res.exit_code == 1 and "sigstore bundle does not verify" in res.stderr


def test_publish_checks_the_bundle_again(reg, fake, tmp_path):
    _add(reg, "1.0", ROS2_XSD, _bundle(reg, fake, "1.0", ROS2_XSD))
    res = reg.publish(ok=False)
    assert res.exit_code == 1 and "give --sigstore-trusted-root" in res.stderr
    # a bundle swapped in the source after review
    stored = reg.src / "bundles" / "org.ros2" / "1.0.sigstore.json"
    stored.write_text(fake.sign(b"something else", identity=IDENTITY, issuer=ISSUER))
    res = reg.publish("--sigstore-trusted-root", tmp_path / "trusted_root.json", ok=False)
    assert res.exit_code == 1 and "org.ros2 1.0: the sigstore bundle does not verify" in res.stderr
    assert not (reg.site / "metadata").exists()


def test_malformed_bundle_and_trusted_root_are_clear_errors(reg, fake, tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text("{}")
    res = _add(reg, "1.0", ROS2_XSD, bad, ok=False)
    assert res.exit_code == 1 and "Traceback" not in res.stderr
    (tmp_path / "trusted_root.json").write_text("[]")
    res = _add(reg, "1.0", ROS2_XSD, _bundle(reg, fake, "1.0", ROS2_XSD), ok=False)
    assert res.exit_code == 3 and "not a sigstore trusted root" in res.stderr
