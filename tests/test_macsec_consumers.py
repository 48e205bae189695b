"""Each export format read by its real consumer (tests/_consumers.py), with the consumer shown to
tell a bad file from a good one. tests/conftest.py runs the same consumers after every successful
``macsec export`` of the suite; the tests here say, by skipping, which consumer cannot run here."""

from __future__ import annotations

import json

import pytest

from tests import _consumers as consumers
from tests._macsec import comp, generate, hcdf, humanoid, link, port, tree

PASS = b"consumer test passphrase"


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """The humanoid's keys exported for one device per format: {format: out folder}."""
    from click.testing import CliRunner

    from hcdf_trust.cli import main

    def cli(*args):
        return CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)

    tmp = tmp_path_factory.mktemp("consumers")
    (tmp / "doc").mkdir()
    doc = humanoid(tmp / "doc")
    base = generate(cli, tmp, doc, PASS)
    outs = {}
    for name, device, fmt, extra in (
        ("wpa_supplicant", "s32j100", "wpa_supplicant", []),
        ("wpa_supplicant-2.11", "agx-thor", "wpa_supplicant", ["--wpa-version", "2.11"]),
        ("networkd", "s32j100", "networkd", []),
        ("iproute2", "s32j100", "iproute2", []),
    ):
        out = tmp / name
        r = cli("macsec", "export", doc, *base, "--device", device, "--format", fmt, "--out", out, "--json", *extra)
        assert r.exit_code == 0, r.output
        outs[name] = (out, json.loads(r.stdout))
    r = cli("macsec", "export", doc, *base, "--device", "s32j100", "--format", "wpa_supplicant", "--out", tmp / "w2")
    outs["summary"] = (tmp / "w2", r.output)
    # XPN (salt and SSCI on every SA): a 25G link, only iproute2 can carry it
    (tmp / "xpn").mkdir()
    caps = ("gcm-aes-xpn-256",)
    body = [comp("a", port("p0", *caps, mbps=25000)), comp("b", port("p0", *caps, mbps=25000)), '<network name="n">']
    body += [link("l0", "a/p0", "b/p0", '<macsec policy="must-secure" cipher="gcm-aes-xpn-256"/>'), "</network>"]
    doc = tree(tmp / "xpn", {"robot.hcdf": hcdf(*body)})
    base = generate(cli, tmp / "xpn", doc, PASS)
    r = cli("macsec", "export", doc, *base, "--device", "a", "--format", "iproute2", "--out", tmp / "iproute2-xpn")
    assert r.exit_code == 0, r.output
    outs["iproute2-xpn"] = (tmp / "iproute2-xpn", {})
    return outs


def _need(reason: str | None) -> None:
    if reason is not None:
        pytest.skip(reason)


def test_wpa_supplicant_target_is_2_10_by_default_and_said(exported):
    out, doc = exported["wpa_supplicant"]
    assert doc["wpa_supplicant_version"] == "2.10"
    for conf in out.glob("*.conf"):
        assert "# For wpa_supplicant 2.10: only keys it knows are written" in conf.read_text()
        assert "macsec_csindex" not in conf.read_text()
    out, doc = exported["wpa_supplicant-2.11"]
    assert doc["wpa_supplicant_version"] == "2.11"
    assert "# For wpa_supplicant 2.11:" in (out / "wpa_supplicant-wired-eth0.conf").read_text()
    _, text = exported["summary"]
    assert "written for wpa_supplicant 2.10 (--wpa-version)" in text
    assert "wpa_supplicant_version" not in exported["networkd"][1]


def test_wpa_supplicant_reads_every_file(exported):
    _need(consumers.wpa_supplicant_unavailable())
    out, _ = exported["wpa_supplicant"]
    confs = sorted(out.glob("*.conf"))
    assert len(confs) == 8
    for conf in confs:
        assert consumers.wpa_supplicant_errors(conf) == []
    # a 2.11 file: this 2.10 refuses exactly its 2.11 key, and reads the rest
    conf = exported["wpa_supplicant-2.11"][0] / "wpa_supplicant-wired-eth0.conf"
    if consumers.wpa_supplicant_version() < (2, 11):
        assert any("unknown network field 'macsec_csindex'" in e for e in consumers.wpa_supplicant_errors(conf))
    consumers.check_wpa_supplicant(conf)


def test_wpa_supplicant_tells_bad_from_good(exported, tmp_path):
    _need(consumers.wpa_supplicant_unavailable())
    conf = sorted(exported["wpa_supplicant"][0].glob("*.conf"))[0]
    text = conf.read_text()
    for bad in (
        text.replace("\tmacsec_port=1\n", "\tmacsec_port=1\n\tmacsec_bogus=1\n"),
        text.replace("mka_cak=", "mka_cak=ab", 1),  # 34 hex digits
        text.replace("network={", "network={\n\tmka_priority=256", 1),
    ):
        path = tmp_path / "bad.conf"
        path.write_text(bad)
        assert consumers.wpa_supplicant_errors(path), bad


def test_systemd_networkd_reads_every_file(exported):
    _need(consumers.networkd_unavailable())
    out, _ = exported["networkd"]
    units = sorted(out.iterdir())
    assert {u.suffix for u in units} == {".netdev", ".network"} and len(units) == 16
    assert consumers.networkd_errors(units) == []


def test_systemd_networkd_tells_bad_from_good(exported, tmp_path):
    _need(consumers.networkd_unavailable())
    out, _ = exported["networkd"]
    netdev = next(out.glob("*.netdev"))
    network = next(out.glob("*.network"))
    for name, text in (
        (netdev.name, netdev.read_text().replace("Encrypt=", "Cipher=gcm-aes-256\nEncrypt=")),
        (netdev.name, netdev.read_text().replace("Key=", "Key=00112233445566778899aabbccddeeff", 1)),  # 32 bytes
        (network.name, network.read_text() + "Bogus=1\n"),
    ):
        path = tmp_path / name
        path.write_text(text)
        assert consumers.networkd_errors([path]), text


def test_iproute2_scripts(exported, tmp_path):
    _need(consumers.iproute2_unavailable())
    kernel = set()
    for name in ("iproute2", "iproute2-xpn"):
        scripts = sorted(exported[name][0].glob("*.sh"))
        assert scripts
        for script in scripts:
            result = consumers.iproute2_check(script)
            assert result.errors == [], (script, result.errors)
            kernel.add(result.kernel)
    # the oracle: a bad argument, a shell syntax error
    script = sorted(exported["iproute2"][0].glob("*.sh"))[0]
    bad = tmp_path / "bad.sh"
    bad.write_text(script.read_text().replace("icvlen 16", "icvlen 17"))
    assert any("ICV length" in e for e in consumers.iproute2_check(bad).errors)
    bad.write_text(script.read_text().replace("set -eu", "if then"))
    assert any(e.startswith("bash -n") for e in consumers.iproute2_check(bad).errors)
    if kernel != {None}:
        pytest.skip(next(k for k in kernel if k))  # bash -n and `ip link` parsing passed; the rest needs the kernel
