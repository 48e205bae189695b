"""Attacks on the signed release manifest, from the point of view of someone who controls the
release folder but not the key: each edit below leaves a signature that still verifies (pycose,
a second COSE implementation, says so where it matters), so only a strict reading refuses it."""

from __future__ import annotations

import json

import cbor2
import pytest
from pycose.keys import CoseKey
from pycose.messages import CoseMessage

from hcdf_trust.ota import suit
from tests._ota import make_robot


@pytest.fixture
def built(tmp_path, cli):
    robot = make_robot(tmp_path, cli)
    out = tmp_path / "rel"
    r = robot.build(cli, out, "--changelog", "fixes the GNSS drift")
    assert r.exit_code == 0, r.stderr
    assert cli("ota", "verify", out, "--key", robot.pub).exit_code == 0
    return robot, out


def verify(cli, robot, out):
    return cli("ota", "verify", out, "--key", robot.pub, "--json")


def _head(major: int, n: int) -> bytes:
    """A CBOR head in its shortest form (RFC 8949 §3), written here, not by cbor2."""
    if n < 24:
        return bytes([major << 5 | n])
    for info, size in ((24, 1), (25, 2), (26, 4), (27, 8)):
        if n < 1 << (8 * size):
            return bytes([major << 5 | info]) + n.to_bytes(size, "big")
    raise ValueError(n)


def _pycose_verifies(envelope: bytes, pub_pem: str) -> bool:
    top = cbor2.loads(envelope)
    auth = cbor2.loads(top.value[2])
    msg = CoseMessage.decode(auth[1])
    msg.payload = auth[0]
    msg.key = CoseKey.from_pem_public_key(pub_pem)
    return bool(msg.verify_signature())


def _refused(r, words: str, code: int = 3) -> None:
    assert r.exit_code == code, r.stdout + r.stderr
    assert any(words in e["message"] for e in r.json["errors"]), r.json["errors"]


# -- the envelope, taken apart strictly ------------------------------------------------


def test_trailing_bytes_after_the_envelope_are_refused(built, cli):
    robot, out = built
    path = out / "release.suit"
    path.write_bytes(path.read_bytes() + cbor2.dumps({3: b"unsigned"}))
    _refused(verify(cli, robot, out), "trailing bytes after the CBOR item")


def test_an_unsigned_manifest_before_the_signed_one_is_a_duplicate_key(built, cli):
    """cbor2 keeps the last of two equal keys (the signed manifest) and verifies it; a
    first-wins reader (another SUIT processor) would read the attacker's manifest."""
    robot, out = built
    path = out / "release.suit"
    top = cbor2.loads(path.read_bytes())
    manifest = cbor2.loads(top.value[3])
    manifest[2] = 999  # a sequence number nobody signed
    evil = cbor2.dumps(manifest, canonical=True)
    body = _head(5, 4)  # a map of four entries: 2, 3 (evil), 3 (signed), "#hcdf-release"
    body += cbor2.dumps(2) + cbor2.dumps(top.value[2])
    body += cbor2.dumps(3) + cbor2.dumps(evil)
    body += cbor2.dumps(3) + cbor2.dumps(top.value[3])
    body += cbor2.dumps(suit.RECORD_KEY) + cbor2.dumps(top.value[suit.RECORD_KEY])
    data = _head(6, 107) + body
    assert cbor2.loads(data).value[3] == top.value[3]  # the pitfall: plain cbor2 reads the signed one
    path.write_bytes(data)
    _refused(verify(cli, robot, out), "duplicate map key 03")


def test_a_duplicate_key_inside_the_signed_manifest_is_refused_too():
    """The same rule at every level: here a map nested in a bstr."""
    inner = _head(5, 2) + cbor2.dumps(1) + cbor2.dumps(1) + cbor2.dumps(1) + cbor2.dumps(2)
    with pytest.raises(suit.MalformedReleaseError, match="duplicate map key 01"):
        suit.loads(inner, source="x", what="manifest")


@pytest.mark.parametrize(
    ("data", "words"),
    [
        (bytes([0xBF, 0x01, 0x01, 0xFF]), "indefinite length"),  # indefinite-length map
        (bytes([0x18, 0x05]), "shortest encoding"),  # 5 in two bytes
        (bytes([0xA2, 0x02, 0x00, 0x01, 0x00]), "canonical order"),  # {2: 0, 1: 0}
        (bytes([0xFB]) + bytes(8), "floating-point"),
        (bytes([0x81]) * 40 + bytes([0x00]), "nested deeper"),
        (bytes([0x5A, 0xFF, 0xFF, 0xFF, 0xFF]), "ends early"),  # a 4 GiB bstr announced, none given
    ],
)
def test_cbor_outside_the_drafts_encoding_is_refused(data, words):
    with pytest.raises(suit.MalformedReleaseError, match=words):
        suit.loads(data, source="x", what="envelope")


@pytest.mark.parametrize(
    ("label", "value", "named"),
    [(1, -8, "alg (1)"), (4, b"another key", "kid (4)"), (2, [1], "crit (2)"), (33, b"cert", "33"), ("x", 1, "'x'")],
)
def test_any_label_in_the_cose_unprotected_header_is_refused(built, cli, label, value, named):
    """Nothing in the unprotected header is signed: pycose still verifies the signature."""
    robot, out = built
    path = out / "release.suit"
    top = cbor2.loads(path.read_bytes())
    auth = cbor2.loads(top.value[2])
    sign1 = cbor2.loads(auth[1])
    sign1.value[1] = {label: value}
    top.value[2] = cbor2.dumps([auth[0], cbor2.dumps(sign1)])
    data = cbor2.dumps(top, canonical=True)
    if label != 1:  # pycose itself refuses an alg in both buckets with two values
        assert _pycose_verifies(data, robot.pub.read_text()) is True
    path.write_bytes(data)
    _refused(
        verify(cli, robot, out), f"COSE unprotected header must be empty (nothing in it is signed): it holds {named}"
    )


def test_crit_in_the_protected_header_is_refused(built, cli):
    """A signed crit names extensions the verifier must understand; we implement none."""
    from hcdf_trust.ota.keys import load_public
    from hcdf_trust.ota.signer import key_id
    from tests.test_ota_verify import _resign

    robot, out = built
    data = _resign(out, robot, {1: -7, 2: [-70000], 4: key_id(load_public(robot.pub))})
    (out / "release.suit").write_bytes(data)
    _refused(verify(cli, robot, out), "labels this verifier does not implement: crit (2)")


def test_an_envelope_member_outside_the_draft_is_refused(built, cli):
    robot, out = built
    path = out / "release.suit"
    top = cbor2.loads(path.read_bytes())
    top.value[99] = b"extra"
    path.write_bytes(cbor2.dumps(top, canonical=True))
    _refused(verify(cli, robot, out), "envelope key 99 is not one of draft-ietf-suit-manifest-34")


def test_a_second_integrated_payload_is_refused(built, cli):
    """Nothing rides along unsigned: every envelope member is one the manifest binds."""
    robot, out = built
    path = out / "release.suit"
    top = cbor2.loads(path.read_bytes())
    top.value["#evil.bin"] = b"payload nobody signed"
    path.write_bytes(cbor2.dumps(top, canonical=True))
    _refused(verify(cli, robot, out), "not in the layout ota build writes")


def test_an_edited_release_record_is_an_integrity_error(built, cli):
    """The record sits outside the signed manifest bytes; its digest is inside them."""
    robot, out = built
    path = out / "release.suit"
    top = cbor2.loads(path.read_bytes())
    record = cbor2.loads(top.value[suit.RECORD_KEY])
    record["components"][0]["changelog"] = "attacker text shown to an operator"
    top.value[suit.RECORD_KEY] = cbor2.dumps(record, canonical=True)
    data = cbor2.dumps(top, canonical=True)
    assert _pycose_verifies(data, robot.pub.read_text()) is True
    path.write_bytes(data)
    _refused(verify(cli, robot, out), "release record is not the one the signed manifest binds", code=1)


def test_a_release_in_the_layout_before_draft_conformance_names_the_change(built, cli):
    """Signed by the right key, but with the old hcdf-trust custom labels: refused, and told why."""
    from hcdf_trust.ota.keys import load_private
    from hcdf_trust.ota.release import sign_manifest
    from hcdf_trust.ota.signer import FileSigner

    robot, out = built
    env = suit.parse_envelope((out / "release.suit").read_bytes(), source="x")
    manifest = cbor2.loads(env.manifest)
    manifest[-257] = cbor2.dumps([-16, bytes(32)])
    data, _alg, _kid = sign_manifest(cbor2.dumps(manifest, canonical=True), FileSigner(load_private(robot.key)))
    (out / "release.suit").write_bytes(data)
    r = verify(cli, robot, out)
    _refused(r, "layout from before draft-34 conformance")
    assert "rebuild the release" in r.json["errors"][0]["message"]


# -- what a device or a person reads: latest.json and release.suit.json ------------------


@pytest.mark.parametrize(
    ("field", "value"),
    [("changelog", "Critical fix: install now"), ("date", "2031-01-01T00:00:00Z"), ("changelog", None)],
)
def test_an_edited_latest_json_changelog_or_date_is_refused(built, cli, field, value):
    robot, out = built
    path = out / "mr_mcxn_t1" / "flex-io" / "latest.json"
    doc = json.loads(path.read_text())
    if value is None:
        del doc["latest"][field]
    else:
        doc["latest"][field] = value
    path.write_text(json.dumps(doc, indent=2) + "\n")
    r = verify(cli, robot, out)
    _refused(r, f"mr_mcxn_t1/flex-io: latest.json latest.{field} differs from the signed manifest", code=1)
    err = r.json["errors"][0]
    assert err["actual"] == (value if value is not None else "(absent)")


def test_a_changelog_added_where_none_was_signed_is_refused(tmp_path, cli):
    robot = make_robot(tmp_path, cli)
    out = tmp_path / "rel"
    assert robot.build(cli, out).exit_code == 0
    path = out / "mr_mcxn_t1" / "rtk-gnss" / "latest.json"
    doc = json.loads(path.read_text())
    assert "changelog" not in doc["latest"]
    doc["latest"]["changelog"] = "see https://evil.example/"
    path.write_text(json.dumps(doc, indent=2) + "\n")
    r = verify(cli, robot, out)
    _refused(r, "latest.json latest.changelog differs", code=1)
    assert r.json["errors"][0]["expected"] == "(absent)"


@pytest.mark.parametrize(
    "edit",
    [
        lambda d: d.update(format="SUIT envelope, audited by ACME"),
        lambda d: d["signature"].update(kid="00" * 32),
        lambda d: d.update(note="an extra key"),
        lambda d: d["components"][0].update(changelog="another story"),
    ],
)
def test_any_edit_of_release_suit_json_is_refused(built, cli, edit):
    robot, out = built
    path = out / "release.suit.json"
    doc = json.loads(path.read_text())
    edit(doc)
    path.write_text(json.dumps(doc, indent=2, ensure_ascii=False) + "\n")
    _refused(verify(cli, robot, out), "release.suit.json is not the rendering of the signed manifest", code=1)


def test_an_old_layout_release_in_the_output_folder_stops_the_build_and_the_documented_way_on_works(built, cli):
    """`ota build` reads the folder it writes into as --previous: the old layout is refused
    there too, with the way to carry the history on, and that way works."""
    from hcdf_trust.ota.keys import load_private
    from hcdf_trust.ota.release import sign_manifest
    from hcdf_trust.ota.signer import FileSigner

    robot, out = built
    env = suit.parse_envelope((out / "release.suit").read_bytes(), source="x")
    manifest = cbor2.loads(env.manifest)
    manifest[2] = 41
    manifest[-258] = "robot.hcdf"
    data, _alg, _kid = sign_manifest(cbor2.dumps(manifest, canonical=True), FileSigner(load_private(robot.key)))
    (out / "release.suit").write_bytes(data)
    robot.rewrite(cli, flex_version="0.3.0")
    r = robot.build(cli, out)
    assert r.exit_code == 3 and "layout from before draft-34 conformance" in r.stderr
    (out / "release.suit").rename(robot.root / "release.suit.old")
    (out / "release.suit.json").unlink()
    with (robot.root / "ota.toml").open("a") as f:
        f.write("[release]\nsequence_number = 42\n")
    r = robot.build(cli, out)
    assert r.exit_code == 0, r.stderr
    r = verify(cli, robot, out)
    assert r.exit_code == 0 and r.json["sequence_number"] == 42
    doc = json.loads((out / "mr_mcxn_t1" / "flex-io" / "latest.json").read_text())
    assert [e["version"] for e in doc["previous"]] == ["0.2.0"]  # history kept from latest.json
