"""``ota sign-provenance`` (issue 21): a second signer adds its signature to a release's
provenance for a verifier's ``--threshold``; one key never counts twice, and a signature
over other bytes than the published payload counts for nothing."""

from __future__ import annotations

import base64
import json

import pytest

from hcdf_trust.ota.keys import generate, load_private, private_pem, public_pem
from hcdf_trust.ota.signer import FileSigner
from hcdf_trust.provenance import FILE_NAME, PAYLOAD_TYPE
from tests._ota import make_robot, tree
from tests.test_ota_hsm import MODULE
from tests.test_provenance import envelope, epoch, payload, refused, token, verify  # noqa: F401 (fixtures)


@pytest.fixture
def built(tmp_path, cli, epoch):  # noqa: F811
    robot = make_robot(tmp_path, cli)
    out = tmp_path / "rel"
    assert robot.build(cli, out, "--provenance").exit_code == 0
    second = generate("ed25519")
    (tmp_path / "co.pem").write_bytes(private_pem(second, None))
    (tmp_path / "co.pem").chmod(0o600)
    (tmp_path / "co.pub.pem").write_bytes(public_pem(second))
    return robot, out, tmp_path / "co.pem", tmp_path / "co.pub.pem"


def cosign(cli, robot, out, key, *extra):
    return cli("ota", "sign-provenance", out, "--key", key, "--release-key", robot.pub, "--json", *extra)


def two(co_pub):
    return ("--provenance-key", co_pub, "--threshold", "2")


def test_a_co_signature_meets_a_threshold_of_two(built, cli):
    robot, out, co, co_pub = built
    before = envelope(out)
    refused(verify(cli, robot, out, *two(co_pub)), 1, "do not verify")
    r = cosign(cli, robot, out, co)
    assert r.exit_code == 0, r.stderr
    after = envelope(out)
    assert after["payload"] == before["payload"] and after["payloadType"] == PAYLOAD_TYPE  # the same bytes
    assert after["signatures"][0] == before["signatures"][0] and len(after["signatures"]) == 2
    assert json.loads(r.stdout)["signatures"] == sorted(s["keyid"] for s in after["signatures"])
    assert verify(cli, robot, out, *two(co_pub)).exit_code == 0
    assert verify(cli, robot, out).exit_code == 0  # one of one still holds


def test_the_same_key_never_signs_twice(built, cli):
    robot, out, co, _ = built
    was = (out / FILE_NAME).read_bytes()
    refused(cosign(cli, robot, out, robot.key), 3, "already signed")  # the release key itself
    assert (out / FILE_NAME).read_bytes() == was
    assert cosign(cli, robot, out, co).exit_code == 0
    was = (out / FILE_NAME).read_bytes()
    refused(cosign(cli, robot, out, co), 3, "already signed")
    assert (out / FILE_NAME).read_bytes() == was


def test_one_key_under_two_keyids_counts_once(built, cli, tmp_path):
    # the release key signs again (ECDSA: another valid signature) and labels it with the
    # co-signer's keyid: a verifier that counted signatures, not keys, would reach 2
    from securesystemslib.dsse import Envelope

    from hcdf_trust.ota.keys import load_public
    from hcdf_trust.provenance.dsse import sslib_key, sslib_signer

    robot, out, _, co_pub = built
    env = envelope(out)
    sig = Envelope(payload(out), PAYLOAD_TYPE, {}).sign(sslib_signer(FileSigner(load_private(robot.key))))
    assert sig.signature != env["signatures"][0]["sig"]
    co_keyid = sslib_key(load_public(co_pub)).keyid
    env["signatures"].append({"keyid": co_keyid, "sig": base64.b64encode(bytes.fromhex(sig.signature)).decode()})
    (out / FILE_NAME).write_text(json.dumps(env))
    refused(verify(cli, robot, out, *two(co_pub)), 1, "do not verify")


def test_a_co_signature_over_other_bytes_counts_for_nothing(built, cli, tmp_path):
    # the co-signer signed the same statement serialized otherwise (indented): same JSON,
    # other bytes; spliced into the envelope it must not count
    from securesystemslib.dsse import Envelope

    from hcdf_trust.provenance.dsse import sslib_signer

    robot, out, co, co_pub = built
    other = json.dumps(json.loads(payload(out)), indent=2).encode()
    sig = Envelope(other, PAYLOAD_TYPE, {}).sign(sslib_signer(FileSigner(load_private(co))))
    env = envelope(out)
    env["signatures"].append({"keyid": sig.keyid, "sig": base64.b64encode(bytes.fromhex(sig.signature)).decode()})
    (out / FILE_NAME).write_text(json.dumps(env))
    refused(verify(cli, robot, out, *two(co_pub)), 1, "do not verify")


def test_nothing_is_co_signed_that_does_not_verify(built, cli, tmp_path):
    robot, out, co, _ = built
    suit_json = (out / "release.suit.json").read_bytes()
    (out / "release.suit.json").write_bytes(suit_json + b" ")  # a subject changed after signing
    before = tree(out)
    refused(cosign(cli, robot, out, co), 1, "SHA-256 differs")
    assert tree(out) == before
    (out / "release.suit.json").write_bytes(suit_json)
    env = envelope(out)
    stmt = json.loads(payload(out))
    stmt["subject"][0]["digest"]["sha256"] = "0" * 64
    env["payload"] = base64.b64encode(json.dumps(stmt).encode()).decode()
    (out / FILE_NAME).write_text(json.dumps(env))
    before = tree(out)
    refused(cosign(cli, robot, out, co), 1, "do not verify")
    assert tree(out) == before
    (out / FILE_NAME).unlink()
    refused(cosign(cli, robot, out, co), 1, "no provenance")
    other = generate("ecdsa-p256")
    (tmp_path / "other.pub.pem").write_bytes(public_pem(other))
    refused(cli("ota", "sign-provenance", out, "--key", co, "--release-key", tmp_path / "other.pub.pem"), 1)


def test_a_key_in_a_token_co_signs(built, cli, token):  # noqa: F811
    robot, out, _, _ = built
    pubs, pin_file = token
    for label in ("fw-signing", "ed-signing"):  # ECDSA P-256, Ed25519
        uri = f"pkcs11:token=release;object={label}?module-path={MODULE}"
        r = cosign(cli, robot, out, uri, "--pin-file", pin_file)
        assert r.exit_code == 0, r.stderr
    three = ("--provenance-key", pubs["ecdsa-p256"], "--provenance-key", pubs["ed25519"], "--threshold", "3")
    assert verify(cli, robot, out, *three).exit_code == 0
