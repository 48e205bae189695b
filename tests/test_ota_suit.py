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

from tests._ota import make_robot


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
    assert set(env.value) == {2, 3}
    auth = cbor2.loads(env.value[2])
    digest, sign1 = cbor2.loads(auth[0]), cbor2.loads(auth[1])
    assert len(auth) == 2
    # the digest is over the bstr-wrapped manifest, not its inner bytes
    assert digest == [-16, hashlib.sha256(cbor2.dumps(env.value[3])).digest()]
    assert digest[1] != hashlib.sha256(env.value[3]).digest()
    assert sign1.tag == 18 and sign1.value[2] is None  # detached payload
    manifest = cbor2.loads(env.value[3])
    assert manifest[1] == 1 and manifest[2] == 1  # manifest-version, sequence-number
    common = cbor2.loads(manifest[3])
    ids = common[2]
    assert [b"mr_mcxn_t1", b"flex-io"] in ids and [b"compute", b"scout-os"] in ids
    shared = cbor2.loads(common[4])
    install = cbor2.loads(manifest[20])
    assert cbor2.loads(manifest[7])[:4] == [12, 0, 3, 15]  # validate: image-match
    lock = robot.root / "hcdf.lock"
    if not lock.exists():
        lock = robot.root / "robot.hcdf.lock"
    assert cbor2.loads(manifest[-257]) == [-16, hashlib.sha256(lock.read_bytes()).digest()]
    assert cbor2.loads(manifest[-259]) == [-16, hashlib.sha256(robot.doc.read_bytes()).digest()]
    i = ids.index([b"mr_mcxn_t1", b"flex-io"])
    # shared sequence: set-component-index i, override-parameters {...}, vendor/class conditions
    params = next(shared[k + 3] for k in range(0, len(shared), 8) if shared[k : k + 2] == [12, i])
    image = (out / "mr_mcxn_t1" / "flex-io" / "0.2.0.bin").read_bytes()
    assert cbor2.loads(params[3]) == [-16, hashlib.sha256(image).digest()]  # image-digest: the downloaded file
    assert params[14] == len(image)
    assert uuid.UUID(bytes=params[2]) == uuid.uuid5(uuid.UUID(bytes=params[1]), "mr_mcxn_t1")
    latest = json.loads((out / "mr_mcxn_t1" / "flex-io" / "latest.json").read_text())
    assert cbor2.loads(params[-257]) == [-16, bytes.fromhex(latest["latest"]["mcuboot_hash"])]
    uri = next(install[k + 3][21] for k in range(0, len(install), 8) if install[k : k + 2] == [12, i])
    assert uri == latest["latest"]["url"]
    rendering = json.loads((out / "release.suit.json").read_text())
    assert "draft-ietf-suit-manifest-34" in rendering["format"]


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
