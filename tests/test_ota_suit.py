"""The release manifest: plain cbor2 sees the pinned draft's structure, and pycose (a second,
independent COSE implementation) verifies our COSE_Sign1."""

from __future__ import annotations

import hashlib
import json
import uuid

import cbor2
import pytest
from pycose.keys import CoseKey
from pycose.messages import CoseMessage

from hcdf_trust.ota import suit
from hcdf_trust.ota.errors import ReleaseIntegrityError, SignatureError
from tests._ota import make_robot
from tests._suit import DRAFT, EXAMPLES, zcbor_validate


@pytest.fixture(params=["ecdsa-p256", "ed25519"])
def release(request, tmp_path, cli):
    robot = make_robot(tmp_path, cli, kind=request.param)
    out = tmp_path / "rel"
    r = robot.build(cli, out)
    assert r.exit_code == 0, r.stderr
    return robot, out


def test_envelope_decodes_with_plain_cbor2_into_the_draft_34_structure(release):
    robot, out = release
    env = cbor2.loads((out / "release.suit").read_bytes())
    assert isinstance(env, cbor2.CBORTag) and env.tag == 107
    assert set(env.value) == {2, 3, "#hcdf-release"}  # wrapper, manifest, one integrated payload (§7.5)
    auth = cbor2.loads(env.value[2])
    digest, sign1 = cbor2.loads(auth[0]), cbor2.loads(auth[1])
    assert len(auth) == 2
    # the digest is over the bstr-wrapped manifest, not its inner bytes
    assert digest == [-16, hashlib.sha256(cbor2.dumps(env.value[3])).digest()]
    assert digest[1] != hashlib.sha256(env.value[3]).digest()
    assert sign1.tag == 18 and sign1.value[2] is None and sign1.value[1] == {}  # detached, nothing unprotected
    manifest = cbor2.loads(env.value[3])
    assert set(manifest) == {1, 2, 3, 7, 20}  # no key outside the draft's
    assert manifest[1] == 1 and manifest[2] == 1  # manifest-version, sequence-number
    common = cbor2.loads(manifest[3])
    ids = common[2]
    assert [b"mr_mcxn_t1", b"flex-io"] in ids and [b"compute", b"scout-os"] in ids
    assert ids[-1] == [b"hcdf-trust", b"release-record"]
    shared = cbor2.loads(common[4])
    install = cbor2.loads(manifest[20])
    assert cbor2.loads(manifest[7])[:4] == [12, 0, 3, 15]  # validate: image-match

    def params(seq, i):  # set-component-index i, override-parameters {...}
        return next(seq[k + 3] for k in range(0, len(seq), 8) if seq[k : k + 2] == [12, i])

    for i in range(len(ids)):  # §8.4.8.16: no custom parameter in the shared sequence
        assert set(params(shared, i)) == {1, 2, 3, 14} and set(params(install, i)) == {21}
    i = ids.index([b"mr_mcxn_t1", b"flex-io"])
    image = (out / "mr_mcxn_t1" / "flex-io" / "0.2.0.bin").read_bytes()
    assert cbor2.loads(params(shared, i)[3]) == [-16, hashlib.sha256(image).digest()]  # image-digest: the file
    assert params(shared, i)[14] == len(image)
    assert uuid.UUID(bytes=params(shared, i)[2]) == uuid.uuid5(uuid.UUID(bytes=params(shared, i)[1]), "mr_mcxn_t1")
    latest = json.loads((out / "mr_mcxn_t1" / "flex-io" / "latest.json").read_text())
    assert params(install, i)[21] == latest["latest"]["url"]
    # the release record: bound by the last component's image-digest and size, fetched from the envelope
    record_raw = env.value["#hcdf-release"]
    n = len(ids) - 1
    assert params(install, n)[21] == "#hcdf-release"
    assert cbor2.loads(params(shared, n)[3]) == [-16, hashlib.sha256(record_raw).digest()]
    assert params(shared, n)[14] == len(record_raw)
    record = cbor2.loads(record_raw)
    lock = robot.root / "hcdf.lock"
    if not lock.exists():
        lock = robot.root / "robot.hcdf.lock"
    assert record["hcdf-lock-digest"] == [-16, hashlib.sha256(lock.read_bytes()).digest()]
    assert record["hcdf-root-digest"] == [-16, hashlib.sha256(robot.doc.read_bytes()).digest()]
    assert record["hcdf-root"] == "robot.hcdf" and record["date"] == latest["latest"]["date"]
    entry = record["components"][i]
    assert entry["mcuboot-digest"] == [-16, bytes.fromhex(latest["latest"]["mcuboot_hash"])]
    assert entry["version"] == "0.2.0" and entry["comps"] == ["main"] and entry["type"] == "mcuboot"
    assert entry["security-counter"] == 0x20000
    raw = record["components"][ids.index([b"compute", b"scout-os"])]
    assert raw["type"] == "raw" and raw["mcuboot-digest"] is None and raw["security-counter"] is None
    rendering = json.loads((out / "release.suit.json").read_text())
    assert "draft-ietf-suit-manifest-34" in rendering["format"]


def test_zcbor_accepts_every_envelope_against_the_drafts_cddl(release, tmp_path):
    """A tool nobody here wrote, with the draft's own CDDL (no private-use extension)."""
    _robot, out = release
    proc = zcbor_validate((out / "release.suit").read_bytes(), tmp_path)
    assert proc.returncode == 0, proc.stdout + proc.stderr


@pytest.mark.parametrize("kind", ["ed25519", "rsa-2048"])
def test_zcbor_accepts_a_one_image_release(tmp_path, cli, kind):
    robot = make_robot(tmp_path, cli, kind=kind)
    (robot.root / "ota.toml").write_text(
        '[images.scout-os]\ntype = "raw"\nexclude = true\n[images.rtk-gnss]\nexclude = true\n'
    )
    out = tmp_path / "rel"
    r = robot.build(cli, out)
    assert r.exit_code == 0, r.stderr
    data = (out / "release.suit").read_bytes()
    assert len(cbor2.loads(cbor2.loads(cbor2.loads(data).value[3])[3])[2]) == 2  # one image + the record
    proc = zcbor_validate(data, tmp_path)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert cli("ota", "verify", out, "--key", robot.pub).exit_code == 0


def test_zcbor_refuses_the_layout_before_draft_conformance(tmp_path):
    """The oracle can fail: the old layout (custom parameters in the shared sequence, an
    array-valued one) is what zcbor refused in issue 17."""
    params = {1: b"v" * 16, 2: b"c" * 16, 3: cbor2.dumps([-16, b"\0" * 32]), 14: 1, -261: ["main"]}
    common = {2: [[b"b", b"a"]], 4: cbor2.dumps([12, 0, 20, params, 1, 15, 2, 15])}
    manifest = cbor2.dumps({1: 1, 2: 1, 3: cbor2.dumps(common)}, canonical=True)
    sign1 = cbor2.dumps(cbor2.CBORTag(18, [cbor2.dumps({1: -7}), {}, None, b"s" * 64]))
    auth = cbor2.dumps([cbor2.dumps([-16, b"\0" * 32]), sign1])
    data = cbor2.dumps(cbor2.CBORTag(107, {2: auth, 3: manifest}))
    assert zcbor_validate(data, tmp_path).returncode != 0
    del params[-261]
    common[4] = cbor2.dumps([12, 0, 20, params, 1, 15, 2, 15])
    manifest = cbor2.dumps({1: 1, 2: 1, 3: cbor2.dumps(common)}, canonical=True)
    data = cbor2.dumps(cbor2.CBORTag(107, {2: auth, 3: manifest}))
    assert zcbor_validate(data, tmp_path).returncode == 0


@pytest.mark.parametrize("example", EXAMPLES, ids=lambda p: p.name)
def test_the_working_groups_examples_decode_through_our_envelope_step(example, tmp_path):
    """Our parser is a draft-34 parser, not only a reader of what we write: each of the six
    examples is taken apart strictly and its signature checked with the group's key."""
    from hcdf_trust.ota.keys import load_public
    from hcdf_trust.ota.verify import open_envelope

    data = example.read_bytes()
    assert zcbor_validate(data, tmp_path).returncode == 0
    pub = load_public(DRAFT / "public_key.pem")
    env = open_envelope(data, pub, source=example.name, require_kid=False)
    m = suit.parse_suit_manifest(env, source=example.name)
    assert m.sequence_number == int(example.name[7])  # exampleN has sequence number N
    assert m.components and 7 in m.sequences
    # a flipped signature bit is refused by the same step
    top = cbor2.loads(data)
    auth = cbor2.loads(top.value[2])
    sign1 = cbor2.loads(auth[1])
    sign1.value[3] = bytes([sign1.value[3][0] ^ 1]) + sign1.value[3][1:]
    top.value[2] = cbor2.dumps([auth[0], cbor2.dumps(sign1)])
    with pytest.raises(SignatureError, match="signature does not verify"):
        open_envelope(cbor2.dumps(top, canonical=True), pub, source=example.name, require_kid=False)


def test_a_severed_member_must_match_its_digest():
    """Example 2 carries install and text severed (§8.6): another text under the same digest is refused."""
    from hcdf_trust.ota.keys import load_public
    from hcdf_trust.ota.verify import open_envelope

    top = cbor2.loads((DRAFT / "example2.signed.cbor").read_bytes())
    top.value[23] = cbor2.dumps({"en": {1: "another description"}})
    pub = load_public(DRAFT / "public_key.pem")
    env = open_envelope(cbor2.dumps(top, canonical=True), pub, source="x", require_kid=False)
    with pytest.raises(ReleaseIntegrityError, match="envelope member 23 is not the one the manifest's digest names"):
        suit.parse_suit_manifest(env, source="x")


def test_pycose_verifies_our_cose_sign1(release):
    robot, out = release
    env = cbor2.loads((out / "release.suit").read_bytes())
    auth = cbor2.loads(env.value[2])
    msg = CoseMessage.decode(auth[1])
    msg.payload = auth[0]  # the detached payload: the encoded SUIT_Digest
    msg.key = CoseKey.from_pem_public_key(robot.pub.read_text())
    assert msg.verify_signature() is True
    msg.payload = auth[0][:-1] + bytes([auth[0][-1] ^ 1])
    assert msg.verify_signature() is False  # pycose returns False rather than raising


@pytest.mark.parametrize(("kind", "alg"), [("ecdsa-p256", -7), ("ed25519", -8), ("rsa-2048", -37), ("rsa-3072", -37)])
def test_cwt_made_cose_sign1_is_detached_bound_to_the_key_and_pycose_verifies_it(kind, alg):
    """Every file-key type: cwt signs, the payload is nil, and pycose checks the Sig_structure
    over the detached SUIT_Digest with the public key alone."""
    from hcdf_trust.ota import keys
    from hcdf_trust.ota.release import sign_manifest
    from hcdf_trust.ota.signer import FileSigner, key_id

    key = keys.generate(kind)
    manifest = cbor2.dumps({1: 1, 2: 7})
    data, got_alg, kid = sign_manifest(manifest, FileSigner(key))
    env = cbor2.loads(data)
    digest, sign1 = cbor2.loads(env.value[2])
    assert digest == cbor2.dumps([-16, hashlib.sha256(cbor2.dumps(manifest)).digest()])
    protected, unprotected, payload, _sig = cbor2.loads(sign1).value
    assert (got_alg, payload, unprotected) == (alg, None, {})
    assert cbor2.loads(protected) == {1: alg, 4: key_id(key)} and kid == key_id(key)
    msg = CoseMessage.decode(sign1)
    msg.payload = digest
    msg.key = CoseKey.from_pem_public_key(keys.public_pem(key).decode())
    assert msg.verify_signature() is True
    msg.payload = digest[:-1] + bytes([digest[-1] ^ 1])
    assert msg.verify_signature() is False
