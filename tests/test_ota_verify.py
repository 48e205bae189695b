"""``hcdf-trust ota verify``: every refusal, each naming the device and the field."""

from __future__ import annotations

import json
import shutil

import cbor2
import pytest
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.hazmat.primitives.asymmetric.utils import decode_dss_signature
from cwt import COSE, COSEKey

from hcdf_trust.ota import suit
from hcdf_trust.ota.errors import SignatureError
from hcdf_trust.ota.keys import load_public
from hcdf_trust.ota.signer import key_id
from hcdf_trust.ota.verify import verify_envelope
from tests._ota import make_robot


@pytest.fixture
def built(tmp_path, cli):
    robot = make_robot(tmp_path, cli)
    out = tmp_path / "rel"
    r = robot.build(cli, out)
    assert r.exit_code == 0, r.stderr
    return robot, out


def verify(cli, robot, out, *extra):
    return cli("ota", "verify", out, "--key", robot.pub, *extra)


def test_a_good_release_verifies(built, cli):
    robot, out = built
    r = verify(cli, robot, out, "--json")
    assert r.exit_code == 0, r.stderr
    assert r.json["ok"] and len(r.json["components"]) == 3


def test_swapped_image_is_named_as_mix_and_match(built, cli):
    robot, out = built
    flex = out / "mr_mcxn_t1" / "flex-io" / "0.2.0.bin"
    gnss = out / "mr_mcxn_t1" / "rtk-gnss" / "1.0.0+3.bin"
    shutil.copy(gnss, flex)
    r = verify(cli, robot, out)
    assert r.exit_code == 1
    assert "mr_mcxn_t1/flex-io: file_sha256 differs" in r.stderr and "mix-and-match" in r.stderr
    assert "the image of mr_mcxn_t1/rtk-gnss" in r.stderr


def test_tampered_image_byte_is_refused(built, cli):
    robot, out = built
    flex = out / "mr_mcxn_t1" / "flex-io" / "0.2.0.bin"
    data = bytearray(flex.read_bytes())
    data[600] ^= 1
    flex.write_bytes(bytes(data))
    r = verify(cli, robot, out)
    assert r.exit_code == 1 and "mr_mcxn_t1/flex-io: file_sha256" in r.stderr


def test_image_signed_by_another_key_is_refused_even_when_the_manifest_lists_it(tmp_path, cli):
    """Both release files re-signed consistently by an attacker key are refused by the trusted key."""
    robot = make_robot(tmp_path, cli)
    out = tmp_path / "rel"
    evil = tmp_path / "evil.pem"
    cli("ota", "keygen", "-o", evil)
    robot.key = evil
    assert robot.build(cli, out).exit_code == 0
    r = verify(cli, robot, out)  # robot.pub is still the trusted key
    assert r.exit_code == 1 and "signed by another key" in r.stderr


@pytest.mark.parametrize(
    ("field", "value"),
    [("version", "9.9.9"), ("url", "https://evil.example/x.bin"), ("size", 1), ("mcuboot_hash", "0" * 64)],
)
def test_latest_json_must_match_the_signed_manifest(built, cli, field, value):
    robot, out = built
    path = out / "mr_mcxn_t1" / "rtk-gnss" / "latest.json"
    doc = json.loads(path.read_text())
    doc["latest"][field] = value
    path.write_text(json.dumps(doc))
    r = verify(cli, robot, out, "--json")
    assert r.exit_code == 1
    err = r.json["errors"][0]
    assert f"mr_mcxn_t1/rtk-gnss: latest.json latest.{field} differs" in err["message"]
    assert err["file"] == "mr_mcxn_t1/rtk-gnss/latest.json" and err["actual"] == str(value)


def test_latest_json_for_a_device_not_in_the_manifest_is_refused(built, cli):
    robot, out = built
    (out / "other_board" / "flex-io").mkdir(parents=True)
    shutil.copy(out / "mr_mcxn_t1" / "flex-io" / "latest.json", out / "other_board" / "flex-io" / "latest.json")
    r = verify(cli, robot, out)
    assert r.exit_code == 1 and "other_board/flex-io/latest.json: no such component" in r.stderr


def test_sequence_number_must_increase(built, cli, tmp_path):
    robot, out = built
    r = verify(cli, robot, out, "--previous", out)
    assert r.exit_code == 1 and "sequence-number is not greater" in r.stderr and "expected: > 1" in r.stderr
    out2 = tmp_path / "rel2"
    assert robot.build(cli, out2, "--previous", out).exit_code == 0
    assert verify(cli, robot, out2, "--previous", out).exit_code == 0
    r = verify(cli, robot, out, "--previous", out2)  # replaying the older release
    assert r.exit_code == 1 and "actual:   1" in r.stderr


def test_security_counter_that_went_down_is_refused(built, cli, tmp_path):
    robot, out = built
    # release 2 with a lower counter for flex-io, built without --previous (build itself refuses it)
    (robot.root / "ota.toml").write_text(
        '[release]\nsequence_number = 5\n[images.flex-io]\nsecurity_counter = 1\n[images.scout-os]\ntype = "raw"\n'
    )
    robot.rewrite(cli, flex_version="0.3.0")
    out2 = tmp_path / "rel2"
    assert robot.build(cli, out2).exit_code == 0
    r = verify(cli, robot, out2, "--previous", out)
    assert r.exit_code == 1
    assert "mr_mcxn_t1/flex-io: security_counter went down" in r.stderr and "expected: ≥ 131072" in r.stderr


def test_manifest_signed_by_another_key_is_refused(built, cli, tmp_path):
    robot, out = built
    cli("ota", "keygen", "-o", tmp_path / "other.pem")
    r = cli("ota", "verify", out, "--key", tmp_path / "other.pub.pem")
    assert r.exit_code == 1 and "signed by another key" in r.stderr
    r = cli("ota", "verify", out, "--key", tmp_path / "other.pem")
    assert r.exit_code == 3  # a private key where the public key is asked for


def _resign(out, robot, protected: dict) -> bytes:
    """The release's manifest re-signed with the right key under another protected header."""
    env = suit.parse_envelope((out / "release.suit").read_bytes(), source="x")
    key = serialization.load_pem_private_key(robot.key.read_bytes(), None)
    header = cbor2.dumps(protected)
    to_sign = cbor2.dumps(["Signature1", header, b"", env.digest])  # RFC 9052 Sig_structure, built here
    r, s = decode_dss_signature(key.sign(to_sign, ec.ECDSA(hashes.SHA256())))
    sign1 = cbor2.CBORTag(18, [header, {}, None, r.to_bytes(32, "big") + s.to_bytes(32, "big")])
    return suit.envelope(env.manifest, cbor2.dumps(sign1), env.payloads)


@pytest.mark.parametrize("alg", [-35, -36, -8, 0])
def test_an_algorithm_not_bound_to_the_key_is_refused_though_cwt_accepts_it(built, alg):
    robot, out = built
    pub = load_public(robot.pub)
    kid = key_id(pub)
    data = _resign(out, robot, {1: alg, 4: kid})
    # the pitfall: cwt verifies with the key's own algorithm and ignores the header's
    env = suit.parse_envelope(data, source="x")
    cwt_key = COSEKey.from_pem(robot.pub.read_bytes(), alg="ES256", kid=kid)
    assert COSE.new().decode(env.cose_sign1, cwt_key, detached_payload=env.digest) == env.digest
    with pytest.raises(SignatureError, match="is not bound to the ecdsa-p256 key"):
        verify_envelope(data, pub, source="release.suit")
    # ESP256 (-9) is the same algorithm fully specified: accepted
    assert verify_envelope(_resign(out, robot, {1: -9, 4: kid}), pub, source="x").sequence_number == 1


def test_a_wrong_key_type_is_an_unbound_algorithm(built, cli, tmp_path):
    robot, out = built
    cli("ota", "keygen", "--type", "ed25519", "-o", tmp_path / "ed.pem")
    r = cli("ota", "verify", out, "--key", tmp_path / "ed.pub.pem")
    assert r.exit_code == 1 and "'ES256' is not bound to the ed25519 key" in r.stderr


def test_manifest_digest_must_cover_this_manifest(built, cli):
    robot, out = built
    env = suit.parse_envelope((out / "release.suit").read_bytes(), source="x")
    manifest = cbor2.loads(env.manifest)
    manifest[2] = 99  # a bigger sequence number, keeping the old signature
    top = cbor2.loads((out / "release.suit").read_bytes())
    top.value[3] = cbor2.dumps(manifest)
    (out / "release.suit").write_bytes(cbor2.dumps(top))
    r = verify(cli, robot, out)
    assert r.exit_code == 1 and "authentication wrapper digest" in r.stderr


def test_signature_over_another_digest_is_refused(built, cli):
    robot, out = built
    top = cbor2.loads((out / "release.suit").read_bytes())
    auth = cbor2.loads(top.value[2])
    sign1 = cbor2.loads(auth[1])
    sig = bytearray(sign1.value[3])
    sig[5] ^= 1
    sign1.value[3] = bytes(sig)
    top.value[2] = cbor2.dumps([auth[0], cbor2.dumps(sign1)])
    (out / "release.suit").write_bytes(cbor2.dumps(top))
    r = verify(cli, robot, out)
    assert r.exit_code == 1 and "signature does not verify" in r.stderr


@pytest.mark.parametrize("cut", [1, 10, 100, -1])
def test_truncated_manifest_is_malformed_exit_3(built, cli, cut):
    robot, out = built
    data = (out / "release.suit").read_bytes()
    (out / "release.suit").write_bytes(data[:cut] if cut > 0 else data[:-1])
    r = verify(cli, robot, out, "--json")
    assert r.exit_code == 3
    assert r.json["errors"][0]["code"] == "malformed-release" and "malformed CBOR" in r.json["errors"][0]["message"]


@pytest.mark.parametrize(
    "data",
    [b"", b"\xff" * 10, cbor2.dumps([1, 2]), cbor2.dumps(cbor2.CBORTag(107, {2: b"x", 3: b"y"})), b"\x81" * 100_000],
)
def test_malformed_manifest_is_exit_3_never_a_traceback(built, cli, data):
    robot, out = built
    (out / "release.suit").write_bytes(data)
    r = verify(cli, robot, out)
    assert r.exit_code == 3 and "release.suit" in r.stderr


def test_missing_image_is_refused(built, cli):
    robot, out = built
    (out / "compute" / "scout-os" / "2026.11.bin").unlink()
    r = verify(cli, robot, out)
    assert r.exit_code == 1 and "compute/scout-os: image compute/scout-os/2026.11.bin is missing" in r.stderr


def _resign_release(out, robot, change) -> None:
    """Re-sign the release's manifest with the trusted key after ``change(component)``."""
    from dataclasses import replace

    from hcdf_trust.ota.keys import load_private
    from hcdf_trust.ota.release import sign_release
    from hcdf_trust.ota.signer import FileSigner

    release = verify_envelope((out / "release.suit").read_bytes(), load_public(robot.pub), source="x")
    comps = tuple(change(c) if c.app == "flex-io" else c for c in release.components)
    env, _alg, _kid = sign_release(replace(release, components=comps), FileSigner(load_private(robot.key)))
    (out / "release.suit").write_bytes(env)
    (out / "release.suit.json").unlink()  # the rendering would disagree too: keep each test to its one check


@pytest.mark.parametrize(
    ("change", "field"),
    [
        (lambda c: {"size": c.size + 1}, "size differs"),
        (lambda c: {"uri": "https://fw.example.com/r/other.bin"}, "uri does not name"),
        (lambda c: {"security_counter": c.security_counter + 1}, "image security_counter differs"),
        (lambda c: {"mcuboot_hash": "ab" * 32}, "mcuboot_hash differs"),
    ],
)
def test_a_signed_manifest_that_contradicts_its_image_is_refused(built, cli, change, field):
    from dataclasses import replace

    robot, out = built
    _resign_release(out, robot, lambda c: replace(c, **change(c)))
    r = verify(cli, robot, out)
    assert r.exit_code == 1 and f"mr_mcxn_t1/flex-io: {field}" in r.stderr


def test_an_image_signed_by_another_key_is_refused_under_a_good_manifest(tmp_path, cli):
    from dataclasses import replace

    robot = make_robot(tmp_path, cli)
    trusted = robot.key
    evil = tmp_path / "evil.pem"
    cli("ota", "keygen", "-o", evil)
    robot.key = evil
    out = tmp_path / "rel"
    assert robot.build(cli, out).exit_code == 0
    # the attacker's manifest is replaced by one the trusted key signed, listing the attacker's image
    from hcdf_trust.ota.keys import load_private
    from hcdf_trust.ota.release import sign_release
    from hcdf_trust.ota.signer import FileSigner

    release = verify_envelope((out / "release.suit").read_bytes(), load_public(tmp_path / "evil.pub.pem"), source="x")
    env, _a, _k = sign_release(replace(release), FileSigner(load_private(trusted)))
    (out / "release.suit").write_bytes(env)
    r = verify(cli, robot, out)
    assert r.exit_code == 1 and "mr_mcxn_t1/flex-io: MCUboot image does not verify with the key" in r.stderr


@pytest.mark.parametrize("kind", ["ed25519", "rsa-2048", "rsa-3072"])
def test_every_key_type_signs_a_release_that_verifies(tmp_path, cli, kind):
    robot = make_robot(tmp_path, cli, kind=kind)
    out = tmp_path / "rel"
    assert robot.build(cli, out).exit_code == 0
    r = verify(cli, robot, out, "--json")
    assert r.exit_code == 0, r.stderr


def test_header_version_must_be_the_listed_version(built, cli):
    from dataclasses import replace

    robot, out = built
    folder = out / "mr_mcxn_t1" / "flex-io"
    (folder / "0.2.0.bin").rename(folder / "0.2.1.bin")
    _resign_release(out, robot, lambda c: replace(c, version="0.2.1", uri=c.uri.replace("0.2.0", "0.2.1")))
    r = verify(cli, robot, out)
    assert r.exit_code == 1 and "mr_mcxn_t1/flex-io: image header version differs" in r.stderr


def test_release_files_that_are_symlinks_out_of_the_folder_are_refused(built, cli, tmp_path):
    robot, out = built
    outside = tmp_path / "outside.json"
    latest = out / "mr_mcxn_t1" / "flex-io" / "latest.json"
    outside.write_bytes(latest.read_bytes())
    latest.unlink()
    latest.symlink_to(outside)
    r = verify(cli, robot, out)
    assert r.exit_code == 3 and "outside the root" in r.stderr


def test_the_unsigned_json_rendering_must_say_what_the_manifest_says(built, cli):
    robot, out = built
    path = out / "release.suit.json"
    doc = json.loads(path.read_text())
    signed = doc["components"][0]["mcuboot_hash"]
    doc["components"][0]["mcuboot_hash"] = "ab" * 32
    path.write_text(json.dumps(doc, indent=2, ensure_ascii=False) + "\n")
    r = verify(cli, robot, out, "--json")
    assert r.exit_code == 1
    (err,) = r.json["errors"]
    assert "release.suit.json is not the rendering of the signed manifest" in err["message"]
    assert err["file"] == "release.suit.json" and err["line"] > 1
    assert err["expected"] == f'"mcuboot_hash": "{signed}",' and err["actual"] == f'"mcuboot_hash": "{"ab" * 32}",'


def test_a_reformatted_json_rendering_is_refused_too(built, cli):
    """Byte for byte: the same values in another layout are not what ota build wrote."""
    robot, out = built
    path = out / "release.suit.json"
    path.write_text(json.dumps(json.loads(path.read_text())))
    r = verify(cli, robot, out)
    assert r.exit_code == 1 and "release.suit.json is not the rendering" in r.stderr
    path.unlink()  # not shipping it is fine: the envelope is what is signed
    assert verify(cli, robot, out).exit_code == 0


def test_a_missing_latest_json_is_refused(built, cli):
    robot, out = built
    (out / "mr_mcxn_t1" / "rtk-gnss" / "latest.json").unlink()
    r = verify(cli, robot, out)
    assert r.exit_code == 1 and "mr_mcxn_t1/rtk-gnss: latest.json is missing" in r.stderr


def test_a_signed_manifest_whose_class_id_is_another_boards_is_refused(built, cli):
    """A component listed for one board with another board's class-id (a device of that board would take it)."""
    import uuid

    from hcdf_trust.ota.keys import load_private
    from hcdf_trust.ota.release import sign_manifest
    from hcdf_trust.ota.signer import FileSigner

    robot, out = built
    env = suit.parse_envelope((out / "release.suit").read_bytes(), source="x")
    manifest = cbor2.loads(env.manifest)
    common = cbor2.loads(manifest[3])
    shared = cbor2.loads(common[4])
    shared[3][2] = uuid.uuid5(suit.VENDOR_ID, "another_board").bytes
    common[4] = cbor2.dumps(shared)
    manifest[3] = cbor2.dumps(common)
    new = cbor2.dumps(manifest)
    data, _alg, _kid = sign_manifest(new, FileSigner(load_private(robot.key)), env.payloads)
    (out / "release.suit").write_bytes(data)
    r = verify(cli, robot, out)
    assert r.exit_code == 3 and "vendor-id/class-id do not match the component's board" in r.stderr


def test_a_listed_mcuboot_image_that_is_not_one_is_malformed(built, cli):
    import hashlib
    from dataclasses import replace

    robot, out = built
    garbage = b"\x00" * 4096
    (out / "mr_mcxn_t1" / "flex-io" / "0.2.0.bin").write_bytes(garbage)
    _resign_release(out, robot, lambda c: replace(c, sha256=hashlib.sha256(garbage).hexdigest(), size=len(garbage)))
    r = verify(cli, robot, out, "--json")
    assert r.exit_code == 1  # latest.json's size now disagrees too (an integrity failure outranks exit 3)
    err = next(e for e in r.json["errors"] if e["file"] == "mr_mcxn_t1/flex-io/0.2.0.bin")
    assert err["code"] == "malformed-release" and "not an MCUboot image (header magic)" in err["message"]
    assert err["expected"] == "0x96f3b83d" and err["actual"] == "0x00000000"
