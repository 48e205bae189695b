"""``ota build --provenance`` / ``ota verify --provenance`` (issue 21): the statement, its
oracles (sigstore-python's models and DSSE verifier), reproducibility and the attacks."""

from __future__ import annotations

import base64
import hashlib
import json
import os
import shutil

import pytest

from hcdf_trust.ota.keys import generate, load_private, private_pem
from hcdf_trust.ota.signer import FileSigner
from hcdf_trust.provenance import BUILD_TYPE, FILE_NAME, PAYLOAD_TYPE, dsse
from hcdf_trust.provenance.statement import serialize
from tests._ota import make_robot
from tests.test_ota_hsm import MODULE
from tests.test_ota_hsm import token as softhsm_token

EPOCH = "1780000000"


@pytest.fixture
def epoch(monkeypatch):
    monkeypatch.setenv("SOURCE_DATE_EPOCH", EPOCH)
    for name in ("GITHUB_SERVER_URL", "GITHUB_REPOSITORY", "GITHUB_RUN_ID"):
        monkeypatch.delenv(name, raising=False)


@pytest.fixture
def token(tmp_path, monkeypatch):
    """test_ota_hsm's SoftHSM2 token (ECDSA P-256 "fw-signing", Ed25519 "ed-signing")."""
    return softhsm_token.__wrapped__(tmp_path, monkeypatch)


@pytest.fixture
def built(tmp_path, cli, epoch):
    robot = make_robot(tmp_path, cli)
    out = tmp_path / "rel"
    r = robot.build(cli, out, "--provenance")
    assert r.exit_code == 0, r.stderr
    return robot, out


def verify(cli, robot, out, *extra):
    return cli("ota", "verify", out, "--key", robot.pub, "--provenance", "--json", *extra)


def envelope(out) -> dict:
    return json.loads((out / FILE_NAME).read_bytes())


def payload(out) -> bytes:
    return base64.b64decode(envelope(out)["payload"])


def resign(out, robot, statement: dict, *keys) -> None:
    """An attacker who holds ``keys`` (default: the release key) signs ``statement``."""
    signers = [FileSigner(k) for k in keys] or [FileSigner(load_private(robot.key))]
    (out / FILE_NAME).write_bytes(dsse.sign(serialize(statement), signers))


def refused(r, code: int, *words: str) -> list[dict]:
    assert r.exit_code == code, (r.exit_code, r.stdout, r.stderr)
    errors = json.loads(r.stdout)["errors"] if r.stdout.strip() else []
    text = r.stdout + r.stderr
    for w in words:
        assert w in text, (w, text)
    return errors


def test_a_release_with_provenance_verifies_with_and_without_the_flag(built, cli):
    robot, out = built
    r = verify(cli, robot, out)
    assert r.exit_code == 0, r.stderr
    r = cli("ota", "verify", out, "--key", robot.pub)
    assert r.exit_code == 0, r.stderr  # the file is part of a release, not an unaccounted one


def test_the_statement_covers_every_file_and_binds_the_signed_manifest(built):
    robot, out = built
    stmt = json.loads(payload(out))
    files = {
        p.relative_to(out).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in out.rglob("*")
        if p.is_file() and p.name != FILE_NAME
    }
    assert {s["name"]: s["digest"]["sha256"] for s in stmt["subject"]} == files
    assert "release.suit" in files and "mr_mcxn_t1/flex-io/latest.json" in files
    rendering = json.loads((out / "release.suit.json").read_bytes())
    deps = {d["name"]: d["digest"]["sha256"] for d in stmt["predicate"]["buildDefinition"]["resolvedDependencies"]}
    assert deps["hcdf-lock"] == rendering["hcdf"]["lock_sha256"]
    assert deps["hcdf-root"] == hashlib.sha256(robot.doc.read_bytes()).hexdigest() == rendering["hcdf"]["root_sha256"]
    assert stmt["predicate"]["buildDefinition"]["buildType"] == BUILD_TYPE
    meta = stmt["predicate"]["runDetails"]["metadata"]
    assert meta["startedOn"] == meta["finishedOn"] == "2026-05-28T20:26:40Z"  # SOURCE_DATE_EPOCH


def test_sigstore_models_parse_the_statement_and_its_dsse_verifier_accepts_the_envelope(built):
    from cryptography.hazmat.primitives.serialization import load_pem_public_key
    from sigstore.dsse import Envelope, Statement, _verify
    from sigstore.dsse._predicate import SLSAPredicateV1_0

    robot, out = built
    stmt = Statement(payload(out))  # in-toto Statement v1 layout (pydantic)
    assert stmt._inner.predicate_type == "https://slsa.dev/provenance/v1"
    SLSAPredicateV1_0.model_validate(json.loads(payload(out))["predicate"])  # extra fields forbidden
    evp = Envelope._from_json((out / FILE_NAME).read_bytes())
    assert _verify(load_pem_public_key(robot.pub.read_bytes()), evp) == payload(out)


def test_two_builds_with_the_same_source_date_epoch_give_byte_identical_statements(tmp_path, cli, epoch):
    # Ed25519: every signature in a release is deterministic (an ECDSA release.suit is not,
    # and its digest is a subject), so the statements of two builds must be equal bytes.
    robot = make_robot(tmp_path, cli, kind="ed25519")
    a, b = tmp_path / "a", tmp_path / "b"
    assert robot.build(cli, a, "--provenance").exit_code == 0
    assert robot.build(cli, b, "--provenance").exit_code == 0
    assert payload(a) == payload(b)
    assert (a / FILE_NAME).read_bytes() == (b / FILE_NAME).read_bytes()


def test_the_builder_id_and_ci_run_are_recorded(tmp_path, cli, epoch, monkeypatch):
    monkeypatch.setenv("GITHUB_SERVER_URL", "https://github.com")
    monkeypatch.setenv("GITHUB_REPOSITORY", "acme/robot")
    monkeypatch.setenv("GITHUB_RUN_ID", "42")
    robot = make_robot(tmp_path, cli)
    out = tmp_path / "rel"
    assert robot.build(cli, out, "--provenance", "--builder-id", "https://ci.example/b@v1").exit_code == 0
    run = json.loads(payload(out))["predicate"]["runDetails"]
    assert run["builder"]["id"] == "https://ci.example/b@v1"
    assert run["metadata"]["invocationId"] == "https://github.com/acme/robot/actions/runs/42/attempts/1"


def test_an_edited_subject_digest_is_refused(built, cli):
    robot, out = built
    env = envelope(out)
    stmt = json.loads(payload(out))
    stmt["subject"][0]["digest"]["sha256"] = "0" * 64
    env["payload"] = base64.b64encode(serialize(stmt)).decode()
    (out / FILE_NAME).write_text(json.dumps(env))
    refused(verify(cli, robot, out), 1, "do not verify")


def test_a_file_added_after_signing_is_refused(built, cli):
    robot, out = built
    (out / "mr_mcxn_t1" / "flex-io" / "9.9.9.bin").write_bytes(b"late")
    errors = refused(verify(cli, robot, out), 1)
    mine = [e for e in errors if "not a subject" in e["message"]]
    assert [e["file"] for e in mine] == ["mr_mcxn_t1/flex-io/9.9.9.bin"]


def test_a_subject_file_changed_on_disk_is_refused(built, cli):
    robot, out = built
    (out / "release.suit.json").write_bytes((out / "release.suit.json").read_bytes() + b" ")
    errors = refused(verify(cli, robot, out), 1)
    assert any(e["file"] == "release.suit.json" and "SHA-256 differs" in e["message"] for e in errors)


def test_an_envelope_resigned_by_another_key_is_refused(built, cli):
    robot, out = built
    resign(out, robot, json.loads(payload(out)), generate("ecdsa-p256"))
    refused(verify(cli, robot, out), 1, "do not verify")


def test_a_changed_payload_type_is_refused(built, cli):
    robot, out = built
    env = envelope(out)
    env["payloadType"] = "application/json"
    (out / FILE_NAME).write_text(json.dumps(env))
    refused(verify(cli, robot, out), 1, PAYLOAD_TYPE)


def test_a_second_unsigned_statement_appended_is_malformed(built, cli):
    robot, out = built
    (out / FILE_NAME).write_bytes((out / FILE_NAME).read_bytes() + payload(out))
    refused(verify(cli, robot, out), 3, "Extra data")


@pytest.mark.parametrize(
    "signature",
    [{"sig": "AAAA"}, {"keyid": "", "sig": "AAAA", "extra": 1}, {"keyid": "x", "sig": "not base64!"}],
)
def test_a_malformed_extra_signature_is_exit_3_never_a_traceback(built, cli, signature):
    robot, out = built
    env = envelope(out)
    env["signatures"].append(signature)
    (out / FILE_NAME).write_text(json.dumps(env))
    refused(verify(cli, robot, out), 3)


def test_the_provenance_of_another_robot_is_refused(built, cli, tmp_path):
    robot, out = built
    other = make_robot(tmp_path / "other", cli, size=20000)
    shutil.copy(robot.key, other.key)  # one vendor, one release key, two robots
    other.rewrite(cli, flex_version="v0.9.0")  # another description
    other_out = tmp_path / "other-rel"
    assert other.build(cli, other_out, "--provenance").exit_code == 0
    shutil.copy(other_out / FILE_NAME, out / FILE_NAME)
    errors = refused(verify(cli, robot, out), 1, "hcdf-root digest is not the one the signed manifest binds")
    assert any(e["file"].endswith("/resolvedDependencies/0/digest/sha256") for e in errors)


def test_resolved_dependencies_of_another_robot_are_refused_even_when_signed(built, cli):
    robot, out = built
    stmt = json.loads(payload(out))
    stmt["predicate"]["buildDefinition"]["resolvedDependencies"][1]["digest"]["sha256"] = "1" * 64
    resign(out, robot, stmt)
    refused(verify(cli, robot, out), 1, "hcdf-lock digest is not the one")


def test_the_provenance_of_an_older_release_is_refused_in_a_newer_one(built, cli, tmp_path):
    robot, out = built
    old = (out / FILE_NAME).read_bytes()
    robot.rewrite(cli, flex_version="v0.3.0")
    r = robot.build(cli, out, "--provenance")
    assert r.exit_code == 0, r.stderr
    assert verify(cli, robot, out).exit_code == 0
    (out / FILE_NAME).write_bytes(old)
    errors = refused(verify(cli, robot, out), 1)
    names = {e["file"] for e in errors}
    assert {"release.suit", "mr_mcxn_t1/flex-io/0.3.0.bin"} <= names


@pytest.mark.parametrize(
    ("edit", "words"),
    [
        (lambda s: s["predicate"]["buildDefinition"]["externalParameters"].update(script="curl | sh"), "'script'"),
        (lambda s: s["predicate"]["buildDefinition"].update(buildType="https://evil.example/v1"), "buildType"),
        (lambda s: s["predicate"]["buildDefinition"]["externalParameters"].update(root="x.hcdf"), "root"),
        (lambda s: s.update(predicateType="https://slsa.dev/provenance/v0.2"), "predicateType"),
        (lambda s: s.update(_type="https://in-toto.io/Statement/v0.1"), "_type"),
    ],
)
def test_a_signed_statement_that_is_not_ours_is_refused(built, cli, edit, words):
    robot, out = built
    stmt = json.loads(payload(out))
    edit(stmt)
    resign(out, robot, stmt)
    refused(verify(cli, robot, out), 1, words)


def test_a_threshold_of_two_keys(built, cli, tmp_path):
    robot, out = built
    second = generate("ed25519")
    (tmp_path / "second.pub.pem").write_bytes(second.get_public_pem())
    two = ("--provenance-key", tmp_path / "second.pub.pem", "--threshold", "2")
    refused(verify(cli, robot, out, *two), 1, "do not verify")  # one signature only
    resign(out, robot, json.loads(payload(out)), load_private(robot.key), second)
    assert verify(cli, robot, out, *two).exit_code == 0
    refused(verify(cli, robot, out, "--threshold", "2"), 2, "--threshold 2")  # one key cannot meet it
    twice = ("--provenance-key", robot.pub, "--threshold", "2")
    refused(verify(cli, robot, out, *twice), 2, "distinct keys")  # nor the same key given twice
    refused(cli("ota", "verify", out, "--key", robot.pub, "--threshold", "2"), 2, "need --provenance")


def test_verify_provenance_without_the_file_is_refused(tmp_path, cli, epoch):
    robot = make_robot(tmp_path, cli)
    out = tmp_path / "rel"
    assert robot.build(cli, out).exit_code == 0
    assert not (out / FILE_NAME).exists()
    refused(verify(cli, robot, out), 1, "no provenance")


def test_an_encrypted_key_signs_the_provenance_too(tmp_path, cli, epoch, monkeypatch):
    robot = make_robot(tmp_path, cli)
    key = load_private(robot.key)
    robot.key.write_bytes(private_pem(key, b"pw"))
    os.chmod(robot.key, 0o600)
    monkeypatch.setenv("HCDF_TRUST_PASSPHRASE", "pw")
    out = tmp_path / "rel"
    assert robot.build(cli, out, "--provenance").exit_code == 0
    assert verify(cli, robot, out).exit_code == 0


def test_a_second_signature_with_the_same_keyid_is_malformed(built, cli):
    # securesystemslib would keep one of the two; which one must not depend on the order
    robot, out = built
    env = envelope(out)
    env["signatures"].append({"keyid": env["signatures"][0]["keyid"], "sig": "AAAA"})
    (out / FILE_NAME).write_text(json.dumps(env))
    refused(verify(cli, robot, out), 3, "two signatures with one keyid")


@pytest.mark.parametrize(("kind", "label"), [("ecdsa-p256", "fw-signing"), ("ed25519", "ed-signing")])
def test_a_release_key_in_a_token_signs_the_provenance(tmp_path, cli, epoch, token, kind, label):
    # securesystemslib's HSMSigner has ECDSA only: ours signs through the build's token session,
    # Ed25519 too; the DER ECDSA signature is also checked by sigstore's verifier.
    from cryptography.hazmat.primitives.serialization import load_pem_public_key
    from sigstore.dsse import Envelope, _verify

    pubs, pin_file = token
    robot = make_robot(tmp_path, cli)
    robot.key = f"pkcs11:token=release;object={label}?module-path={MODULE}"
    robot.pub = pubs[kind]
    out = tmp_path / "rel"
    r = robot.build(cli, out, "--pin-file", pin_file, "--provenance")
    assert r.exit_code == 0, r.stderr
    assert verify(cli, robot, out).exit_code == 0
    if kind == "ecdsa-p256":
        evp = Envelope._from_json((out / FILE_NAME).read_bytes())
        assert _verify(load_pem_public_key(robot.pub.read_bytes()), evp) == payload(out)


def test_the_library_refuses_a_threshold_its_keys_cannot_meet(built):
    # securesystemslib raises ValueError there, not VerificationError (distribution.md §3.4)
    from hcdf_trust.ota.errors import KeyFileError
    from hcdf_trust.ota.keys import load_public

    robot, out = built
    env = dsse.parse((out / FILE_NAME).read_bytes(), source=FILE_NAME)
    key = dsse.sslib_key(load_public(robot.pub))
    assert dsse.verify(env, [key], 1, source=FILE_NAME) == [key.keyid]
    with pytest.raises(KeyFileError):
        dsse.verify(env, [key, key], 2, source=FILE_NAME)


def test_every_firmware_input_is_a_resolved_dependency(built):
    # the oracle: the binaries in --firmware-dir, hashed here
    robot, out = built
    deps = json.loads(payload(out))["predicate"]["buildDefinition"]["resolvedDependencies"]
    firmware = {d["name"]: (d["uri"], d["digest"]["sha256"]) for d in deps if d["name"].startswith("hcdf-firmware:")}
    sha = {
        p.relative_to(robot.fw).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest() for p in robot.fw.rglob("*.bin")
    }
    assert firmware == {
        "hcdf-firmware:mr_mcxn_t1/flex-io": ("mr_mcxn_t1/flex-io.bin", sha["mr_mcxn_t1/flex-io.bin"]),
        "hcdf-firmware:mr_mcxn_t1/rtk-gnss": ("rtk-gnss.bin", sha["rtk-gnss.bin"]),
        "hcdf-firmware:compute/scout-os": ("scout-os.bin", sha["scout-os.bin"]),
    }
    names = [d["name"] for d in deps]
    assert names[:2] == ["hcdf-root", "hcdf-lock"] and "body.glb" in names and "ota.toml" in names


def _edit_firmware(stmt: dict, image: str, edit) -> None:
    deps = stmt["predicate"]["buildDefinition"]["resolvedDependencies"]
    (i,) = [i for i, d in enumerate(deps) if d["name"] == "hcdf-firmware:" + image]
    edit(deps, i)


@pytest.mark.parametrize("image", ["mr_mcxn_t1/flex-io", "compute/scout-os"])  # MCUboot, raw
def test_a_firmware_input_the_image_does_not_hold_is_refused_even_when_signed(built, cli, image):
    robot, out = built
    stmt = json.loads(payload(out))
    _edit_firmware(stmt, image, lambda deps, i: deps[i]["digest"].update(sha256="2" * 64))
    resign(out, robot, stmt)
    errors = refused(verify(cli, robot, out), 1, f"the firmware input of {image} is not the binary")
    assert [e["actual"] for e in errors] == ["2" * 64]


def test_a_missing_extra_or_doubled_firmware_input_is_refused(built, cli):
    robot, out = built
    original = payload(out)
    stmt = json.loads(original)
    _edit_firmware(stmt, "mr_mcxn_t1/rtk-gnss", lambda deps, i: deps.pop(i))
    resign(out, robot, stmt)
    refused(verify(cli, robot, out), 1, "no firmware input for mr_mcxn_t1/rtk-gnss")
    stmt = json.loads(original)
    _edit_firmware(stmt, "compute/scout-os", lambda deps, i: deps.append(dict(deps[i], name="hcdf-firmware:x/y")))
    resign(out, robot, stmt)
    refused(verify(cli, robot, out), 1, "x/y, an image the signed manifest lacks")
    stmt = json.loads(original)
    _edit_firmware(stmt, "compute/scout-os", lambda deps, i: deps.append(dict(deps[i])))
    resign(out, robot, stmt)
    refused(verify(cli, robot, out), 1, "two firmware inputs for compute/scout-os")


def test_the_in_toto_attestation_validators_accept_the_statement(built):
    # in-toto-attestation's Python bindings: the Statement and SLSA Provenance v1 protos parse
    # the payload strictly (an unknown field, a wrong type or a malformed timestamp raises),
    # Statement.validate and ResourceDescriptor.validate pass; the bindings have no
    # Provenance.validate, so its Go validator's checks (SLSA Build L1's required fields)
    # are written out here, with the Go ResourceDescriptor's digest check (sha256: 64 hex).
    import re

    from google.protobuf import json_format
    from in_toto_attestation.predicates.provenance.v1 import provenance_pb2
    from in_toto_attestation.v1 import statement_pb2
    from in_toto_attestation.v1.resource_descriptor import ResourceDescriptor
    from in_toto_attestation.v1.statement import Statement

    _, out = built
    data = payload(out)
    Statement.copy_from_pb(json_format.Parse(data, statement_pb2.Statement())).validate()
    predicate = json.loads(data)["predicate"]
    prov = json_format.ParseDict(predicate, provenance_pb2.Provenance())
    assert json_format.MessageToDict(prov) == predicate  # nothing dropped or reinterpreted
    build, run = prov.build_definition, prov.run_details
    assert prov.HasField("build_definition") and prov.HasField("run_details") and run.HasField("builder")
    assert build.build_type == BUILD_TYPE and build.HasField("external_parameters") and run.builder.id
    subjects = json_format.Parse(data, statement_pb2.Statement()).subject
    for rd in [*build.resolved_dependencies, *subjects]:
        ResourceDescriptor.copy_from_pb(rd).validate()
        assert set(rd.digest) == {"sha256"} and re.fullmatch("[0-9a-f]{64}", rd.digest["sha256"]), rd
    assert len(build.resolved_dependencies) > 3
    with pytest.raises(json_format.ParseError):  # the oracle refuses what is not SLSA v1
        json_format.ParseDict({**predicate, "buildConfig": {}}, provenance_pb2.Provenance())


def test_an_intel_hex_input_is_listed_by_its_file_digest_and_verifies(built, cli):
    # imgtool converts the text: the image holds the binary, so the hex file's digest is
    # listed but cannot be checked against the image (verify says nothing false about it)
    from intelhex import IntelHex

    robot, out = built
    ih = IntelHex()
    ih.frombytes((robot.fw / "rtk-gnss.bin").read_bytes(), offset=0x8000)
    ih.tofile(str(robot.fw / "rtk-gnss.hex"), format="hex")
    (robot.fw / "rtk-gnss.bin").unlink()
    shutil.rmtree(out)
    assert robot.build(cli, out, "--provenance").exit_code == 0
    deps = json.loads(payload(out))["predicate"]["buildDefinition"]["resolvedDependencies"]
    (gnss,) = [d for d in deps if d["name"] == "hcdf-firmware:mr_mcxn_t1/rtk-gnss"]
    assert gnss["uri"] == "rtk-gnss.hex"
    assert gnss["digest"]["sha256"] == hashlib.sha256((robot.fw / "rtk-gnss.hex").read_bytes()).hexdigest()
    assert verify(cli, robot, out).exit_code == 0
