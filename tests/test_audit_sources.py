"""audit against a signed release (--release), a key store (--store) and a registry (--registry)."""

from __future__ import annotations

import pytest

from hcdf_trust.ota.release import MANIFEST_NAME

from ._macsec import comp, hcdf, link, port, tree
from ._ota import make_robot
from ._registry import PASSPHRASE, build

T0 = "2026-01-01T00:00:00Z"


def _unreleased(r) -> list[str]:
    return [f["message"] for f in r.json["findings"] if f["code"] == "firmware-unreleased"]


def test_firmware_against_the_latest_signed_release(cli, tmp_path):
    robot = make_robot(tmp_path, cli)
    out = tmp_path / "release"
    assert robot.build(cli, out).exit_code == 0
    verified = cli("ota", "verify", out, "--key", robot.pub, "--json").json
    flex = next(c for c in verified["components"] if c["component_id"][1] == "flex-io")
    args = ["--release", out, "--key", robot.pub, "--json"]

    r = cli("audit", robot.doc, *args)
    assert _unreleased(r) == [] and "release" in r.json["checked"]
    robot.rewrite(cli, flex_hash=flex["mcuboot_hash"])
    assert _unreleased(cli("audit", robot.doc, *args)) == []
    robot.rewrite(cli, flex_hash="ab" * 32)  # a hash the release does not sign
    (msg,) = _unreleased(cli("audit", robot.doc, *args))
    assert "flex-io" in msg and flex["mcuboot_hash"] in msg
    text = robot.doc.read_text().replace("</hcdf>", '<comp name="x"><software name="new-fw"/></comp></hcdf>')
    robot.doc.write_text(text)
    msgs = _unreleased(cli("audit", robot.doc, *args))
    assert any("mr_mcxn_t1/flex-io" in m for m in msgs) and any("x/new-fw is not in release" in m for m in msgs)
    assert _unreleased(cli("audit", robot.doc, "--json")) == []  # no --release: not checked

    image = next(out.rglob("flex-io/*.bin"))
    image.write_bytes(image.read_bytes()[:-1] + b"\0")  # one image byte
    r = cli("audit", robot.doc, *args)
    assert r.exit_code == 1
    (bad,) = [f for f in r.json["findings"] if f["check"] == "integrity"]
    assert bad["code"] == "release" and bad["file"] == str(out / "mr_mcxn_t1/flex-io/0.2.0.bin"), bad
    manifest = out / MANIFEST_NAME
    data = bytearray(manifest.read_bytes())
    data[-1] ^= 1  # the signature
    manifest.write_bytes(bytes(data))
    r = cli("audit", robot.doc, *args)
    (bad,) = [f for f in r.json["findings"] if f["check"] == "integrity"]
    assert bad["code"] in ("release", "bad-signature") and bad["file"].endswith(MANIFEST_NAME), bad
    assert r.exit_code == 1
    assert _unreleased(r) == []  # nothing is compared with a manifest that does not verify


def test_release_needs_its_key(cli, tmp_path):
    doc = tmp_path / "r.hcdf"
    doc.write_text(hcdf('<comp name="c"/>'))
    r = cli("audit", doc, "--release", tmp_path)
    assert r.exit_code == 2 and "--release and --key go together" in r.stderr


@pytest.fixture
def keyed(tmp_path, cli):
    devices = comp("a", port("p0", "gcm-aes-128")) + comp("b", port("p0", "gcm-aes-128"))
    body = [devices, '<network name="n">', link("l", "a/p0", "b/p0"),
            '<macsec policy="must-secure" rekey-interval-sec="3600"/>', "</network>"]  # fmt: skip
    doc = tree(tmp_path, {"robot.hcdf": hcdf(*body)})
    pp = tmp_path / "pass"
    pp.write_text("correct horse battery staple\n")
    store = tmp_path / "keys"
    r = cli("macsec", "generate", doc, "--store", store, "--passphrase-file", pp, "--now", T0)
    assert r.exit_code == 0, r.stderr
    return doc, store, pp


def test_keys_past_their_rekey_interval(cli, keyed):
    doc, store, pp = keyed
    args = ["--store", store, "--passphrase-file", pp, "--json"]
    r = cli("audit", doc, *args, "--now", "2026-01-01T00:30:00Z")
    assert [f for f in r.json["findings"] if f["code"] == "macsec-rekey-due"] == []
    assert "key-store" in r.json["checked"]
    r = cli("audit", doc, *args, "--now", "2026-01-01T02:00:00Z")
    (due,) = [f for f in r.json["findings"] if f["code"] == "macsec-rekey-due"]
    assert "link:n/l" in due["message"] and "7200 s old" in due["message"] and due["line"] == 5
    assert r.exit_code == 1


def test_a_wrong_store_passphrase_is_an_input_error(cli, keyed, tmp_path):
    doc, store, _ = keyed
    wrong = tmp_path / "wrong"
    wrong.write_text("not it\n")
    r = cli("audit", doc, "--store", store, "--passphrase-file", wrong)
    assert r.exit_code == 3, r.stderr
    assert cli("audit", doc, "--passphrase-file", wrong).exit_code == 2  # store options need --store


def test_extensions_against_the_registry(cli, tmp_path, monkeypatch):
    monkeypatch.setenv("HCDF_TRUST_PASSPHRASE", PASSPHRASE)
    reg = build(tmp_path / "reg", cli)
    body = (
        '<comp name="c">\n<extension domain="com.example.unknown" version="1.0"><x/></extension>\n'
        '<extension domain="org.ros2" version="1.0"><not-ros/></extension>\n</comp>'
    )
    doc = tmp_path / "robot.hcdf"
    doc.write_text(hcdf(body))
    args = ["--registry", reg.site, "--trusted-root", reg.root_json, "--json"]
    r = cli("audit", doc, *args)
    found = {(f["code"], f["line"]) for f in r.json["findings"] if f["code"].startswith("extension")}
    assert found == {("extension-unregistered", 4), ("extension-content", 5)}
    assert "extensions" in r.json["checked"] and r.exit_code == 1
    off = tmp_path / "off.toml"
    off.write_text("[checks.extension-content]\nenabled = false\n[checks.extension-unregistered]\nenabled = false\n")
    r = cli("audit", doc, *args, "--policy", off)
    assert [f for f in r.json["findings"] if f["code"].startswith("extension")] == []
    assert cli("audit", doc, "--registry", reg.site).exit_code == 2  # needs --trusted-root


def _provenance(r) -> list[dict]:
    return [f for f in r.json["findings"] if f["code"] == "release-no-provenance"]


def test_a_release_without_provenance_is_reported_and_the_policy_switches_it(cli, tmp_path):
    from hcdf_trust.provenance import FILE_NAME

    robot = make_robot(tmp_path, cli)
    out = tmp_path / "release"
    assert robot.build(cli, out).exit_code == 0
    args = ["--release", out, "--key", robot.pub, "--json"]
    r = cli("audit", robot.doc, *args)
    (finding,) = _provenance(r)
    assert finding["severity"] == "warning" and finding["file"] == str(out / FILE_NAME)
    assert "release 1 has no provenance.intoto.json" in finding["message"]
    assert "provenance" in r.json["checked"]
    policy = tmp_path / "policy.toml"
    policy.write_text('[checks.release-no-provenance]\nseverity = "error"\n')
    r = cli("audit", robot.doc, *args, "--policy", policy)
    assert r.exit_code == 1 and "release-no-provenance" in [f["code"] for f in r.json["errors"]]
    policy.write_text("[checks.release-no-provenance]\nenabled = false\n")
    assert _provenance(cli("audit", robot.doc, *args, "--policy", policy)) == []

    assert robot.build(cli, out, "--provenance").exit_code == 0  # the next release, with provenance
    r = cli("audit", robot.doc, *args)
    assert _provenance(r) == [] and not [f for f in r.json["findings"] if f["check"] == "integrity"]


def test_a_provenance_that_does_not_verify_is_an_integrity_finding(cli, tmp_path):
    import base64
    import json

    from hcdf_trust.provenance import FILE_NAME

    robot = make_robot(tmp_path, cli)
    out = tmp_path / "release"
    assert robot.build(cli, out, "--provenance").exit_code == 0
    env = json.loads((out / FILE_NAME).read_bytes())
    stmt = json.loads(base64.b64decode(env["payload"]))
    stmt["subject"][0]["digest"]["sha256"] = "0" * 64
    env["payload"] = base64.b64encode(json.dumps(stmt).encode()).decode()
    (out / FILE_NAME).write_text(json.dumps(env))
    r = cli("audit", robot.doc, "--release", out, "--key", robot.pub, "--json")
    assert r.exit_code == 1 and _provenance(r) == []
    (bad,) = [f for f in r.json["findings"] if f["check"] == "integrity"]
    assert bad["code"] == "provenance" and "do not verify" in bad["message"]
    assert bad["file"] == str(out / FILE_NAME), bad
    (out / FILE_NAME).write_text("{")  # malformed: an integrity finding too, not a crash nor exit 3
    r = cli("audit", robot.doc, "--release", out, "--key", robot.pub, "--json")
    (bad,) = [f for f in r.json["findings"] if f["check"] == "integrity"]
    assert r.exit_code == 1 and bad["code"] == "malformed-json" and bad["file"] == str(out / FILE_NAME), bad
