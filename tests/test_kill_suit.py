"""The SUIT parser (hcdf_trust/ota/suit.py) rule by rule, in memory: fast enough to run for every
mutant. Envelopes are signed for real (an Ed25519 file key) and taken apart by the public
functions ``ota verify`` uses."""

from __future__ import annotations

import hashlib
import json
import re
from dataclasses import replace
from typing import Any

import cbor2
import pytest

from hcdf_trust.ota import keys, suit
from hcdf_trust.ota.errors import MalformedReleaseError, ReleaseIntegrityError, SignatureError
from hcdf_trust.ota.release import sign_manifest, sign_release
from hcdf_trust.ota.signer import FileSigner
from hcdf_trust.ota.verify import open_envelope, verify_envelope

KEY = keys.generate("ed25519")
SIGNER = FileSigner(KEY)

RELEASE = suit.Release(
    sequence_number=7,
    lock_sha256="11" * 32,
    root="robot.hcdf",
    root_sha256="22" * 32,
    date="2026-12-01T00:00:00Z",
    components=(
        suit.Component(
            board="b1",
            app="app",
            type="mcuboot",
            version="1.2.3+4",
            uri="https://fw/b1/app/1.2.3+4.bin",
            size=1000,
            sha256="33" * 32,
            mcuboot_hash="44" * 32,
            security_counter=5,
            comps=("main", "spare"),
            changelog="fixes",
        ),
        suit.Component(
            board="pc",
            app="os",
            type="raw",
            version="2026.11",
            uri="https://fw/pc/os/2026.11.bin",
            size=300,
            sha256="55" * 32,
            mcuboot_hash=None,
            security_counter=None,
            comps=("compute",),
        ),
    ),
)


def signed(release: suit.Release = RELEASE) -> bytes:
    return sign_release(release, SIGNER)[0]


def opened(data: bytes) -> suit.Release:
    return verify_envelope(data, KEY, source="r.suit")


def resign(manifest: Any, payloads: dict[str, bytes] | None = None) -> bytes:
    """A manifest (CBOR value) signed with the trusted key, with the release's own payloads unless given."""
    if payloads is None:
        payloads = suit.encode(RELEASE)[1]
    return sign_manifest(cbor2.dumps(manifest, canonical=True), SIGNER, payloads)[0]


def manifest_of(release: suit.Release = RELEASE) -> dict[Any, Any]:
    return cbor2.loads(suit.encode(release)[0])


NOT_OUR_LAYOUT = "manifest is not in the layout ota build writes \\(draft-ietf-suit-manifest-34, docs/suit.md\\)$"


def malformed(data: bytes, words: str) -> None:
    """Refused as malformed, ``words`` found in the message itself (not its expected/actual lines)."""
    with pytest.raises(MalformedReleaseError) as info:
        opened(data)
    assert re.match(words, info.value.message), info.value.message  # the message begins with them
    assert info.value.file == "r.suit" and info.value.line is None


# -- round trip ------------------------------------------------------------------------


def test_a_release_round_trips_field_for_field():
    assert opened(signed()) == RELEASE


def test_every_field_is_carried():
    """Each field changed alone comes back changed: none is dropped or defaulted."""
    c = RELEASE.components[0]
    for changed in (
        replace(RELEASE, sequence_number=8),
        replace(RELEASE, lock_sha256="66" * 32),
        replace(RELEASE, root="other.hcdf"),
        replace(RELEASE, root_sha256="77" * 32),
        replace(RELEASE, date="2027-01-01T00:00:00Z"),
        *(
            replace(RELEASE, components=(replace(c, **{k: v}), RELEASE.components[1]))
            for k, v in (
                ("board", "b2"),
                ("app", "app2"),
                ("version", "1.2.4"),
                ("uri", "https://fw/x.bin"),
                ("size", 1001),
                ("sha256", "88" * 32),
                ("mcuboot_hash", "99" * 32),
                ("security_counter", 0),
                ("comps", ()),
                ("changelog", None),
                ("type", "raw"),
            )
        ),
    ):
        assert opened(signed(changed)) == changed


def test_the_record_is_the_last_component_bound_by_digest_and_size():
    env = suit.parse_envelope(signed(), source="x")
    record = env.payloads[suit.RECORD_KEY]
    common = cbor2.loads(cbor2.loads(env.manifest)[suit.COMMON])
    assert common[suit.COMPONENTS][-1] == suit.RECORD_ID and len(common[suit.COMPONENTS]) == 3
    shared = cbor2.loads(common[suit.SHARED_SEQUENCE])
    assert shared[16:20] == [12, 2, 20, shared[19]]
    assert shared[19] == {
        1: suit.VENDOR_ID.bytes,
        2: suit.RECORD_CLASS.bytes,
        3: cbor2.dumps([-16, hashlib.sha256(record).digest()]),
        14: len(record),
    }
    assert shared[20:24] == [1, 15, 2, 15]
    install = cbor2.loads(cbor2.loads(env.manifest)[suit.INSTALL])
    assert install[16:] == [12, 2, 20, {21: "#hcdf-release"}, 21, 2, 3, 15]
    assert cbor2.loads(cbor2.loads(env.manifest)[suit.VALIDATE]) == [12, 0, 3, 15, 12, 1, 3, 15, 12, 2, 3, 15]


def test_the_record_encoding():
    rec = cbor2.loads(suit.record_bytes(RELEASE))
    assert rec == {
        "record-version": 1,
        "date": "2026-12-01T00:00:00Z",
        "hcdf-root": "robot.hcdf",
        "hcdf-root-digest": [-16, bytes.fromhex("22" * 32)],
        "hcdf-lock-digest": [-16, bytes.fromhex("11" * 32)],
        "components": [
            {
                "type": "mcuboot",
                "version": "1.2.3+4",
                "comps": ["main", "spare"],
                "mcuboot-digest": [-16, bytes.fromhex("44" * 32)],
                "security-counter": 5,
                "changelog": "fixes",
            },
            {
                "type": "raw",
                "version": "2026.11",
                "comps": ["compute"],
                "mcuboot-digest": None,
                "security-counter": None,
                "changelog": None,
            },
        ],
    }


def test_render_json_is_derived_from_the_release():
    text = suit.render_json(RELEASE, alg="EdDSA", kid="ab").decode()
    assert text.endswith("}\n") and '"changelog": "fixes"' in text and '"date": "2026-12-01T00:00:00Z"' in text
    assert '"signature": {\n    "alg": "EdDSA",\n    "kid": "ab"\n  }' in text
    assert "draft-ietf-suit-manifest-34, COSE_Sign1 EdDSA (detached)" in text
    assert f'"class_id": "{suit.class_id("b1")}"' in text


# -- strict CBOR -------------------------------------------------------------------------


@pytest.mark.parametrize(
    "data",
    [
        bytes([0x17]),  # 23: the largest one-byte head
        bytes([0x18, 0x18]),  # 24: the smallest one-byte argument
        bytes([0x19, 0x01, 0x00]),  # 256 in two bytes
        bytes([0x1A, 0x00, 0x01, 0x00, 0x00]),  # 65536 in four
        bytes([0x1B, 0, 0, 0, 1, 0, 0, 0, 0]),  # 2**32 in eight
        bytes([0x38, 0x18]),  # -25
        bytes([0xF4]),
        bytes([0xF5]),
        bytes([0xF6]),  # false, true, null
        bytes([0x43, 1, 2, 3]),
        bytes([0x63]) + b"abc",
        bytes([0xD8, 0x6B, 0x80]),  # 107([])
        bytes([0xA2, 0x01, 0x00, 0x02, 0x00]),
        bytes([0xA2, 0x17, 0x00, 0x18, 0x18, 0x00]),  # 23 < 24 bytewise
        bytes([0xA2, 0x18, 0x18, 0x20, 0x00]) + bytes([0x00])[:0],  # placeholder trimmed below
    ][:-1]
    + [bytes([0xA2, 0x18, 0x18, 0x00, 0x20, 0x00])],  # 24 (0x1818) before -1 (0x20): bytewise, not length-first
)
def test_wellformed_items_are_accepted(data):
    suit.check_wellformed(data, source="x", what="item")


def test_nesting_up_to_the_limit_is_accepted_and_one_more_is_not():
    ok = bytes([0x81]) * suit.MAX_DEPTH + bytes([0x00])
    suit.check_wellformed(ok, source="x", what="item")
    with pytest.raises(
        MalformedReleaseError, match=f"nested deeper than {suit.MAX_DEPTH} \\(byte {suit.MAX_DEPTH + 1}\\)"
    ):
        suit.check_wellformed(bytes([0x81]) + ok, source="x", what="item")


@pytest.mark.parametrize(
    ("data", "words"),
    [
        (b"", "ends early \\(byte 0\\)"),
        (bytes([0x18]), "ends early \\(byte 0\\)"),
        (bytes([0x19, 0x01]), "ends early \\(byte 0\\)"),
        (bytes([0x43, 1, 2]), "ends early \\(byte 0\\)"),
        (bytes([0x82, 0x00]), "ends early \\(byte 2\\)"),
        (bytes([0xA1, 0x00]), "ends early \\(byte 2\\)"),
        (bytes([0xD8, 0x6B]), "ends early \\(byte 2\\)"),
        (bytes([0x18, 0x17]), "not in its shortest encoding \\(byte 0\\)"),
        (bytes([0x19, 0x00, 0xFF]), "not in its shortest encoding \\(byte 0\\)"),
        (bytes([0x1A, 0x00, 0x00, 0xFF, 0xFF]), "not in its shortest encoding \\(byte 0\\)"),
        (bytes([0x82, 0x00, 0x1B, 0, 0, 0, 0, 0xFF, 0xFF, 0xFF, 0xFF]), "not in its shortest encoding \\(byte 2\\)"),
        (bytes([0x58, 0x01, 0x00]), "not in its shortest encoding \\(byte 0\\)"),  # a bstr length too
        (bytes([0x1C]), "indefinite length or reserved encoding \\(byte 0\\)"),
        (bytes([0x1F]), "indefinite length or reserved encoding \\(byte 0\\)"),
        (bytes([0x81, 0x5F, 0xFF]), "indefinite length or reserved encoding \\(byte 1\\)"),
        (bytes([0xF9, 0x3C, 0x00]), "floating-point value \\(byte 0\\)"),
        (bytes([0xFA, 0, 0, 0, 0]), "floating-point value \\(byte 0\\)"),
        (bytes([0xA2, 0x02, 0x00, 0x02, 0x00]), "duplicate map key 02 \\(byte 3\\)"),
        (bytes([0xA2, 0x20, 0x00, 0x18, 0x18, 0x00]), "not in canonical order \\(byte 3\\)"),
        (bytes([0x00, 0x00]), "1 trailing bytes after the CBOR item \\(byte 1\\)"),
        (bytes([0x80, 0x00, 0x00, 0x00]), "3 trailing bytes after the CBOR item \\(byte 1\\)"),
    ],
)
def test_cbor_outside_the_drafts_encoding_is_refused(data, words):
    with pytest.raises(MalformedReleaseError) as info:
        suit.check_wellformed(data, source="x", what="item")
    prefix = "(truncated or malformed CBOR: it |argument |map keys )?"
    assert re.fullmatch(f"item: {prefix}{words}", info.value.message), info.value.message
    assert info.value.file == "x"


def test_a_duplicate_key_is_found_among_more_than_two():
    data = bytes([0xA3, 0x01, 0x00, 0x02, 0x00, 0x02, 0x00])
    with pytest.raises(MalformedReleaseError, match="duplicate map key 02 \\(byte 5\\)"):
        suit.check_wellformed(data, source="x", what="item")


def test_loads_checks_before_it_decodes_and_names_the_file():
    assert suit.loads(bytes([0x82, 0x01, 0x02]), source="x", what="item") == [1, 2]
    with pytest.raises(MalformedReleaseError) as info:
        suit.loads(bytes([0x01, 0x01]), source="r.suit", what="manifest")
    assert info.value.file == "r.suit" and info.value.message.startswith("manifest: 1 trailing bytes")
    with pytest.raises(MalformedReleaseError, match="item: malformed CBOR"):
        suit.loads(bytes([0x62, 0xFF, 0xFE]), source="x", what="item")  # not UTF-8


# -- the envelope ----------------------------------------------------------------------------


def top_of(data: bytes) -> dict[Any, Any]:
    return cbor2.loads(data).value


def envelope_with(top: dict[Any, Any], tag: int = 107) -> bytes:
    return cbor2.dumps(cbor2.CBORTag(tag, top), canonical=True)


def with_sign1(data: bytes, change) -> bytes:
    top = top_of(data)
    auth = cbor2.loads(top[2])
    sign1 = cbor2.loads(auth[1])
    change(sign1)
    top[2] = cbor2.dumps([auth[0], cbor2.dumps(sign1, canonical=True)])
    return envelope_with(top)


def test_not_an_envelope():
    data = signed()
    malformed(cbor2.dumps(top_of(data), canonical=True), "not a SUIT envelope")
    malformed(envelope_with(top_of(data), tag=106), "not a SUIT envelope")
    malformed(cbor2.dumps(cbor2.CBORTag(107, [1])), "not a SUIT envelope")


@pytest.mark.parametrize("key", [2, 3, 16, 20, 23, "#x"])
def test_every_envelope_member_must_be_a_bstr(key):
    top = top_of(signed())
    top[key] = 5
    malformed(envelope_with(top), f"envelope member {key!r} is not a bstr")


@pytest.mark.parametrize("key", [1, 4, 99, -1])
def test_an_envelope_key_outside_the_draft_is_refused(key):
    top = top_of(signed())
    top[key] = b""
    malformed(envelope_with(top), f"envelope key {key} is not one of draft-ietf-suit-manifest-34$")


def test_a_private_envelope_key_names_the_layout_change():
    top = top_of(signed())
    top[-256] = b""
    malformed(envelope_with(top), "envelope key -256 .*layout from before draft-34")
    top = top_of(signed())
    top[-255] = b""
    with pytest.raises(MalformedReleaseError) as info:
        opened(envelope_with(top))
    assert "layout" not in info.value.message


@pytest.mark.parametrize("key", [2, 3])
def test_the_wrapper_and_the_manifest_are_required(key):
    top = top_of(signed())
    del top[key]
    malformed(envelope_with(top), "envelope lacks an authentication wrapper \\(2\\) or manifest \\(3\\)")


@pytest.mark.parametrize(
    ("wrapper", "words"),
    [
        ({}, "authentication wrapper is not \\[bstr digest, bstr signature\\.\\.\\.\\]$"),
        ([b"d"], "authentication wrapper is not \\[bstr digest, bstr signature\\.\\.\\.\\]$"),
        ([b"d", 5], "authentication wrapper is not \\[bstr digest, bstr signature\\.\\.\\.\\]$"),
        ([5, b"s"], "authentication wrapper is not \\[bstr digest, bstr signature\\.\\.\\.\\]$"),
        ([b"d", b"s", b"t"], "authentication wrapper must hold exactly one signature$"),
    ],
)
def test_the_authentication_wrapper_shape(wrapper, words):
    top = top_of(signed())
    top[2] = cbor2.dumps(wrapper)
    malformed(envelope_with(top), words)


@pytest.mark.parametrize("digest", [[-16], [-16, b"x", 1], ["sha", b"x"], [-16, "x"], {1: 2}, [True, b"x"]])
def test_the_wrapper_digest_must_be_a_suit_digest(digest):
    top = top_of(signed())
    auth = cbor2.loads(top[2])
    top[2] = cbor2.dumps([cbor2.dumps(digest), auth[1]])
    malformed(envelope_with(top), "authentication wrapper digest is not a SUIT_Digest")


def test_a_wrapper_digest_of_another_algorithm_is_not_the_manifests():
    top = top_of(signed())
    auth = cbor2.loads(top[2])
    digest = cbor2.loads(auth[0])
    top[2] = cbor2.dumps([cbor2.dumps([-44, digest[1]]), auth[1]])
    with pytest.raises(ReleaseIntegrityError, match="authentication wrapper digest is not the manifest's"):
        opened(envelope_with(top))


@pytest.mark.parametrize(
    "change",
    [
        lambda s: setattr(s, "tag", 98),
        lambda s: setattr(s, "value", s.value[:3]),
        lambda s: setattr(s, "value", {}),
    ],
)
def test_the_signature_must_be_a_tagged_cose_sign1(change):
    malformed(with_sign1(signed(), change), "signature is not a tagged COSE_Sign1")


def test_the_signature_must_be_cbor_tag_18_not_a_bare_array():
    top = top_of(signed())
    auth = cbor2.loads(top[2])
    top[2] = cbor2.dumps([auth[0], cbor2.dumps(cbor2.loads(auth[1]).value)])
    malformed(envelope_with(top), "signature is not a tagged COSE_Sign1")


@pytest.mark.parametrize(("index", "value"), [(0, {}), (2, b"attached"), (3, "sig")])
def test_cose_sign1_members(index, value):
    def change(s):
        s.value[index] = value

    malformed(with_sign1(signed(), change), "COSE_Sign1 must have a bstr protected header, nil payload, bstr signature")


def test_the_unprotected_header_must_be_a_map_and_empty():
    def not_a_map(s):
        s.value[1] = []

    malformed(with_sign1(signed(), not_a_map), "COSE unprotected header is not a map")

    def two(s):
        s.value[1] = {4: b"k", 1: -8}

    malformed(
        with_sign1(signed(), two),
        "COSE unprotected header must be empty \\(nothing in it is signed\\): it holds alg \\(1\\), kid \\(4\\)$",
    )


@pytest.mark.parametrize(
    ("protected", "words"),
    [
        ({1: -8, 3: 0}, "COSE protected header holds labels this verifier does not implement: content type \\(3\\)"),
        ({1: -8, 5: b"iv"}, "COSE protected header holds labels this verifier does not implement: IV \\(5\\)"),
        ({1: -8, 6: b"iv"}, "COSE protected header holds labels this verifier does not implement: Partial IV \\(6\\)"),
        (
            {1: -8, 2: [1], 99: 0},
            "COSE protected header holds labels this verifier does not implement: crit \\(2\\), 99$",
        ),
    ],
)
def test_the_protected_header_holds_alg_and_kid_only(protected, words):
    def change(s):
        s.value[0] = cbor2.dumps(protected, canonical=True)

    malformed(with_sign1(signed(), change), words)


def test_the_protected_header_must_be_a_map():
    def change(s):
        s.value[0] = cbor2.dumps([1])

    malformed(with_sign1(signed(), change), "COSE protected header is not a map")


def test_an_empty_protected_header_has_no_alg():
    def change(s):
        s.value[0] = b""

    with pytest.raises(SignatureError, match="alg None is not bound"):
        opened(with_sign1(signed(), change))


def test_kid_is_required_for_our_releases_but_not_for_the_working_groups():
    def no_kid(s):
        s.value[0] = cbor2.dumps({1: -8})

    data = with_sign1(signed(), no_kid)
    with pytest.raises(SignatureError, match="signed by another key"):
        opened(data)
    # without a kid the signature is then checked (and fails: the header changed)
    with pytest.raises(SignatureError, match="signature does not verify"):
        open_envelope(data, KEY, source="x", require_kid=False)

    def other_kid(s):
        s.value[0] = cbor2.dumps({1: -8, 4: b"another"})

    with pytest.raises(SignatureError, match="signed by another key"):
        open_envelope(with_sign1(signed(), other_kid), KEY, source="x", require_kid=False)


def test_open_envelope_returns_the_parts():
    data = signed()
    env = open_envelope(data, KEY, source="x")
    top = top_of(data)
    auth = cbor2.loads(top[2])
    assert env.manifest == top[3] and env.digest == auth[0] and env.cose_sign1 == auth[1]
    assert env.payloads == {suit.RECORD_KEY: top[suit.RECORD_KEY]} and env.severable == {}
    sign1 = cbor2.loads(auth[1]).value
    assert env.protected == sign1[0] and env.signature == sign1[3]
    assert env.protected_map == {1: -8, 4: hashlib.sha256(KEY.get_public_bytes()).digest()}


# -- the draft's manifest --------------------------------------------------------------------


def test_the_manifest_must_be_a_map():
    malformed(resign([1, 2]), "manifest is not a map")


@pytest.mark.parametrize("key", [5, 6, 10, 17, 24, -1, "x"])
def test_a_manifest_key_outside_the_draft_is_refused(key):
    m = manifest_of()
    m[key] = 0
    malformed(resign(m), f"manifest key {key!r} is not one of draft-ietf-suit-manifest-34$")


@pytest.mark.parametrize("key", [-256, -257, -259, -1000])
def test_a_private_manifest_key_names_the_layout_change(key):
    m = manifest_of()
    m[key] = b""
    malformed(resign(m), f"manifest key {key} .*: this release uses hcdf-trust's layout from before draft-34")


@pytest.mark.parametrize("version", [2, 0, True, "1", None])
def test_the_manifest_version_must_be_1(version):
    m = manifest_of()
    if version is None:
        del m[1]
    else:
        m[1] = version
    malformed(resign(m), "manifest is not a version-1 SUIT manifest")


@pytest.mark.parametrize("seq", [-1, "7", True, None])
def test_the_sequence_number_must_be_unsigned(seq):
    m = manifest_of()
    if seq is None:
        del m[2]
    else:
        m[2] = seq
    malformed(resign(m), "manifest sequence-number is not an unsigned integer$")


def test_sequence_number_zero_is_accepted_by_the_draft_parser():
    m = manifest_of()
    m[2] = 0
    env = open_envelope(resign(m), KEY, source="x")
    assert suit.parse_suit_manifest(env, source="x").sequence_number == 0


def test_the_reference_uri_must_be_text():
    m = manifest_of()
    m[4] = b"uri"
    malformed(resign(m), "manifest reference-uri is not text$")
    m[4] = "https://example/r.suit"
    env = open_envelope(resign(m), KEY, source="x")
    assert suit.parse_suit_manifest(env, source="x").reference_uri == "https://example/r.suit"
    malformed(
        resign(m),
        NOT_OUR_LAYOUT,
    )  # but ota build never writes one


def _common(m: dict[Any, Any], change) -> dict[Any, Any]:
    common = cbor2.loads(m[3])
    change(common)
    m[3] = cbor2.dumps(common, canonical=True)
    return m


@pytest.mark.parametrize(
    ("change", "words"),
    [
        (lambda c: c.update({1: 0}), "manifest common is not a map of components \\(2\\) and shared-sequence \\(4\\)$"),
        (lambda c: c.pop(2), "manifest components is not a list of \\[\\* bstr\\] identifiers$"),
        (lambda c: c.update({2: []}), "manifest components is not a list of \\[\\* bstr\\] identifiers$"),
        (lambda c: c.update({2: [[b"a", "b"]]}), "manifest components is not a list of \\[\\* bstr\\] identifiers$"),
        (lambda c: c.update({2: [b"a"]}), "manifest components is not a list of \\[\\* bstr\\] identifiers$"),
        (lambda c: c.update({2: {}}), "manifest components is not a list of \\[\\* bstr\\] identifiers$"),
        (lambda c: c.pop(4), "manifest shared-sequence is not a bstr$"),
        (lambda c: c.update({4: cbor2.dumps([])}), "shared-sequence is not a SUIT command sequence"),
        (lambda c: c.update({4: cbor2.dumps([12])}), "shared-sequence is not a SUIT command sequence"),
        (lambda c: c.update({4: cbor2.dumps(["12", 0])}), "shared-sequence is not a SUIT command sequence"),
        (lambda c: c.update({4: cbor2.dumps({12: 0})}), "shared-sequence is not a SUIT command sequence"),
    ],
)
def test_common(change, words):
    malformed(resign(_common(manifest_of(), change)), words)


def test_common_must_be_a_map_in_a_bstr():
    m = manifest_of()
    m[3] = cbor2.loads(m[3])
    malformed(resign(m), "manifest common is not a bstr")
    m[3] = cbor2.dumps([1])
    malformed(resign(m), "manifest common is not a map")


@pytest.mark.parametrize("key", [7, 8, 9, 16, 20])
def test_every_command_sequence_must_be_one(key):
    m = manifest_of()
    m[key] = cbor2.dumps({1: 2})
    malformed(resign(m), f"command sequence {key} is not a SUIT command sequence")
    m[key] = [1, 2]
    if key in (16, 20):
        malformed(resign(m), f"manifest member {key} is not a SHA-256 SUIT_Digest")
    else:
        malformed(resign(m), f"manifest command sequence {key} is not a bstr$")


def test_the_text_must_be_a_map():
    m = manifest_of()
    m[23] = cbor2.dumps([1])
    malformed(resign(m), "manifest text is not a map")
    m[23] = cbor2.dumps({"en": {1: "release"}})
    env = open_envelope(resign(m), KEY, source="x")
    assert suit.parse_suit_manifest(env, source="x").text == {"en": {1: "release"}}


def _severed(key: int, member: bytes, *, in_envelope: bytes | None = None, digest: Any = None) -> bytes:
    m = manifest_of()
    m[key] = digest if digest is not None else [-16, hashlib.sha256(cbor2.dumps(member)).digest()]
    data = resign(m)
    top = top_of(data)
    top[key] = member if in_envelope is None else in_envelope
    return envelope_with(top)


def test_a_severable_member_in_the_envelope_is_checked_against_its_digest():
    install = cbor2.dumps([12, 0, 3, 15])
    env = open_envelope(_severed(16, install), KEY, source="x")
    assert suit.parse_suit_manifest(env, source="x").sequences[16] == [12, 0, 3, 15]
    other = cbor2.dumps([12, 1, 3, 15])
    env = open_envelope(_severed(16, install, in_envelope=other), KEY, source="x")
    with pytest.raises(
        ReleaseIntegrityError, match="envelope member 16 is not the one the manifest's digest names"
    ) as info:
        suit.parse_suit_manifest(env, source="y")
    assert info.value.file == "y"
    assert info.value.expected == hashlib.sha256(cbor2.dumps(install)).hexdigest()
    assert info.value.actual == hashlib.sha256(cbor2.dumps(other)).hexdigest()


def test_a_severed_member_absent_from_the_envelope_is_none():
    m = manifest_of()
    m[16] = [-16, bytes(32)]
    m[23] = [-16, bytes(32)]
    env = open_envelope(resign(m), KEY, source="x")
    parsed = suit.parse_suit_manifest(env, source="x")
    assert parsed.sequences[16] is None and parsed.text is None and 23 not in parsed.sequences
    assert parsed.sequences[20] == cbor2.loads(m[20])  # the members after a severed one are read too


@pytest.mark.parametrize("digest", [[-44, bytes(64)], [-16], [-16, "x"]])
def test_a_severable_members_digest_must_be_sha256(digest):
    m = manifest_of()
    m[23] = digest
    malformed(resign(m), "manifest member 23 is not a SHA-256 SUIT_Digest")


def test_a_member_the_manifest_does_not_cover_or_covers_twice_is_refused():
    data = signed()
    top = top_of(data)
    top[23] = cbor2.dumps({"en": {1: "unsigned"}})
    malformed(envelope_with(top), "envelope member 23 is not covered by the manifest")
    top = top_of(data)
    top[20] = top_of(data)[3]  # an install member beside the manifest's own install
    malformed(envelope_with(top), "member 20 is both in the manifest and in the envelope")


# -- hcdf-trust's layout ---------------------------------------------------------------------


def test_the_record_component_must_be_last():
    def swap(c):
        c[2] = [c[2][2], c[2][0], c[2][1]]

    malformed(resign(_common(manifest_of(), swap)), "manifest has no hcdf-trust release record component$")

    def only(c):
        c[2] = [suit.RECORD_ID]

    malformed(resign(_common(manifest_of(), only)), "manifest has no hcdf-trust release record component$")


def test_the_record_must_be_in_the_envelope():
    malformed(resign(manifest_of(), payloads={}), "envelope has no release record \\('#hcdf-release'\\)")


def test_a_record_that_is_not_the_bound_one_is_an_integrity_error():
    record = suit.record_bytes(replace(RELEASE, date="2030-01-01T00:00:00Z"))
    with pytest.raises(ReleaseIntegrityError, match="release record is not the one the signed manifest binds") as info:
        opened(resign(manifest_of(), payloads={suit.RECORD_KEY: record}))
    assert info.value.file == "r.suit"
    assert info.value.expected == hashlib.sha256(suit.record_bytes(RELEASE)).hexdigest()
    assert info.value.actual == hashlib.sha256(record).hexdigest()


def test_a_record_of_the_right_digest_but_another_size_is_refused():
    m = manifest_of()
    record = suit.encode(RELEASE)[1][suit.RECORD_KEY]

    def size(c):
        shared = cbor2.loads(c[4])
        shared[19][14] = len(record) + 1
        c[4] = cbor2.dumps(shared, canonical=True)

    with pytest.raises(ReleaseIntegrityError, match="release record is not the one"):
        opened(resign(_common(m, size)))


def _bound(record: Any) -> bytes:
    """A manifest that binds ``record`` (whatever it holds) and the envelope carrying it."""
    raw = cbor2.dumps(record, canonical=True)

    def bind(c):
        shared = cbor2.loads(c[4])
        shared[19][3] = cbor2.dumps([-16, hashlib.sha256(raw).digest()])
        shared[19][14] = len(raw)
        c[4] = cbor2.dumps(shared, canonical=True)

    return resign(_common(manifest_of(), bind), payloads={suit.RECORD_KEY: raw})


def record_of(release: suit.Release = RELEASE) -> dict[str, Any]:
    return cbor2.loads(suit.record_bytes(release))


@pytest.mark.parametrize(
    ("change", "words"),
    [
        (lambda r: r.update({"record-version": 2}), "release record is not a version-1 record$"),
        (lambda r: r.pop("date"), "release record is not a version-1 record$"),
        (lambda r: r.update({"extra": 1}), "release record is not a version-1 record$"),
        (lambda r: r.update({"date": 5}), "release record date is not text"),
        (lambda r: r.update({"hcdf-root": b"x"}), "release record hcdf-root is not text"),
        (
            lambda r: r.update({"components": r["components"][:1]}),
            "release record does not describe every image component$",
        ),
        (lambda r: r.update({"components": {}}), "release record does not describe every image component$"),
        (lambda r: r["components"].__setitem__(0, []), "release record component 0 has other keys$"),
        (lambda r: r["components"][1].pop("changelog"), "release record component 1 has other keys$"),
        (lambda r: r["components"][1].update({"x": 1}), "release record component 1 has other keys$"),
        (lambda r: r["components"][0].update({"type": 1}), "release record component 0: type is not str"),
        (lambda r: r["components"][0].update({"version": None}), "release record component 0: version is not str"),
        (lambda r: r["components"][0].update({"comps": "main"}), "release record component 0: comps is not list"),
        (
            lambda r: r["components"][0].update({"security-counter": "5"}),
            "release record component 0: security-counter is not int$",
        ),
        (
            lambda r: r["components"][0].update({"security-counter": True}),
            "release record component 0: security-counter is not int$",
        ),
        (lambda r: r["components"][0].update({"changelog": 5}), "release record component 0: changelog is not str"),
        (
            lambda r: r["components"][0].update({"mcuboot-digest": b"x"}),
            "release record component 0: mcuboot-digest is not list$",
        ),
        (lambda r: r["components"][0].update({"type": "zephyr"}), "release record component 0: bad type or comps"),
        (lambda r: r["components"][0].update({"comps": ["a", 1]}), "release record component 0: bad type or comps"),
        (
            lambda r: r["components"][0].update({"security-counter": -1}),
            "release record component 0: negative security-counter",
        ),
        (
            lambda r: r["components"][0].update({"mcuboot-digest": [-16, b"x"]}),
            "component b1/app: mcuboot-digest is not a SHA-256 SUIT_Digest$",
        ),
        (
            lambda r: r.update({"hcdf-lock-digest": [-44, bytes(32)]}),
            "release record: hcdf-lock-digest is not a SHA-256 SUIT_Digest$",
        ),
        (
            lambda r: r.update({"hcdf-root-digest": [-16, bytes(31)]}),
            "release record: hcdf-root-digest is not a SHA-256 SUIT_Digest$",
        ),
    ],
)
def test_the_record_is_read_strictly(change, words):
    record = record_of()
    change(record)
    malformed(_bound(record), words)


def test_a_record_that_is_not_a_map_is_refused():
    malformed(_bound([1]), "release record is not a version-1 record$")


def test_a_component_id_must_be_board_and_app_in_utf8():
    def three(c):
        c[2][0] = [b"b1", b"app", b"x"]

    malformed(resign(_common(manifest_of(), three)), "component 0 id is not \\[bstr board, bstr app\\]")

    def latin1(c):
        c[2][1] = [b"p\xe9", b"os"]

    malformed(resign(_common(manifest_of(), latin1)), "component 1 id is not UTF-8")


@pytest.mark.parametrize(("key", "value"), [(1, b"v" * 16), (2, suit.class_id("pc").bytes), (2, None)])
def test_vendor_and_class_must_be_the_boards(key, value):
    def change(c):
        shared = cbor2.loads(c[4])
        if value is None:
            del shared[3][key]
        else:
            shared[3][key] = value
        c[4] = cbor2.dumps(shared, canonical=True)

    malformed(resign(_common(manifest_of(), change)), "component b1/app: vendor-id/class-id do not match")


@pytest.mark.parametrize(
    ("key", "value", "words"),
    [
        (14, "1000", "component b1/app: image-size is missing or not int"),
        (14, True, "component b1/app: image-size is missing or not int$"),
        (3, cbor2.dumps([-16, bytes(31)]), "component b1/app: image-digest is not a SHA-256 SUIT_Digest"),
        (3, cbor2.dumps([-43, bytes(32)]), "component b1/app: image-digest is not a SHA-256 SUIT_Digest$"),
        (3, None, "component b1/app: image-digest is not a SHA-256 SUIT_Digest$"),
    ],
)
def test_the_image_parameters(key, value, words):
    def change(c):
        shared = cbor2.loads(c[4])
        if value is None:
            del shared[3][key]
        else:
            shared[3][key] = value
        c[4] = cbor2.dumps(shared, canonical=True)

    malformed(resign(_common(manifest_of(), change)), words)


def test_the_uri_must_be_text():
    m = manifest_of()
    install = cbor2.loads(m[20])
    install[3] = {21: b"https://fw/x"}
    m[20] = cbor2.dumps(install, canonical=True)
    malformed(resign(m), "component b1/app: uri is missing or not str")


@pytest.mark.parametrize(
    ("seq", "words"),
    [
        ([12, 3, 3, 15], "install: component index 3 out of range"),
        ([12, -1, 3, 15], "install: component index -1 out of range"),
        ([12, True, 3, 15], "install: component index True out of range"),
        ([20, {21: "x"}, 12, 0, 3, 15], "install: parameters without a component index"),
        ([12, 0, 20, [21, "x"]], "install: parameters without a component index"),
    ],
)
def test_component_indexes_and_parameters(seq, words):
    m = manifest_of()
    m[20] = cbor2.dumps(seq)
    malformed(resign(m), words)


def test_an_install_sequence_is_required():
    m = manifest_of()
    del m[20]
    malformed(resign(m), "manifest has no install sequence")


def test_a_later_override_wins_and_the_index_sticks():
    """Parameters are per index and accumulate (§8.4.10.3); only the exact layout is accepted."""
    m = manifest_of()
    install = cbor2.loads(m[20])
    install[3:4] = [{21: "https://fw/first"}, 20, {21: RELEASE.components[0].uri}]
    m[20] = cbor2.dumps(install, canonical=True)
    malformed(
        resign(m),
        NOT_OUR_LAYOUT,
    )


@pytest.mark.parametrize(
    "change",
    [
        lambda m: m.update({7: cbor2.dumps([12, 0, 3, 15])}),  # validate of one component only
        lambda m: m.update({9: cbor2.dumps([12, 0, 23, 2])}),  # an invoke nobody wrote
        lambda m: _common(m, lambda c: c.update({4: cbor2.dumps(cbor2.loads(c[4]) + [1, 15])})),
    ],
)
def test_anything_but_the_exact_layout_is_refused(change):
    m = manifest_of()
    change(m)
    malformed(resign(m), "manifest is not in the layout ota build writes \\(draft-ietf-suit-manifest-34")


def test_a_severed_member_is_not_our_layout():
    install = cbor2.loads(manifest_of()[20])
    m = manifest_of()
    m[20] = [-16, hashlib.sha256(cbor2.dumps(cbor2.dumps(install))).digest()]
    top = top_of(resign(m))
    top[20] = cbor2.dumps(install)
    malformed(
        envelope_with(top),
        NOT_OUR_LAYOUT,
    )


def test_refusals_name_what_was_expected():
    def change(s):
        s.value[0] = cbor2.dumps({1: -8, 3: 0})

    with pytest.raises(MalformedReleaseError) as info:
        opened(with_sign1(signed(), change))
    assert info.value.expected == "alg (1) and kid (4) only"
    record = record_of()
    record["extra"] = 1
    with pytest.raises(MalformedReleaseError) as info:
        opened(_bound(record))
    assert info.value.expected == "components, date, hcdf-lock-digest, hcdf-root, hcdf-root-digest, record-version"
    record = record_of()
    record["components"] = record["components"][:1]
    with pytest.raises(MalformedReleaseError) as info:
        opened(_bound(record))
    assert info.value.expected == "2"


def test_release_component_finds_by_board_and_app():
    assert RELEASE.component("pc", "os") is RELEASE.components[1]
    assert RELEASE.component("b1", "app") is RELEASE.components[0]
    assert RELEASE.component("pc", "app") is None and RELEASE.component("b1", "os") is None
    assert RELEASE.components[0].name == "b1/app"


def test_to_json_literally():
    """The rendering people read (and ``ota verify`` compares byte for byte), written out here."""
    assert suit.to_json(RELEASE, alg="EdDSA", kid="ab") == {
        "format": "SUIT envelope (CBOR), draft-ietf-suit-manifest-34, COSE_Sign1 EdDSA (detached)",
        "file": "release.suit",
        "sequence_number": 7,
        "date": "2026-12-01T00:00:00Z",
        "hcdf": {"root": "robot.hcdf", "root_sha256": "22" * 32, "lock_sha256": "11" * 32},
        "signature": {"alg": "EdDSA", "kid": "ab"},
        "digests": {
            "file_sha256": "SHA-256 of the file a device downloads (SUIT image-digest; MCUmgr upload 'sha')",
            "mcuboot_hash": "MCUboot image hash over header + payload + protected TLVs "
            "(what MCUmgr 'image list' reports from a device)",
        },
        "components": [
            {
                "component_id": ["b1", "app"],
                "comps": ["main", "spare"],
                "type": "mcuboot",
                "version": "1.2.3+4",
                "uri": "https://fw/b1/app/1.2.3+4.bin",
                "size": 1000,
                "file_sha256": "33" * 32,
                "mcuboot_hash": "44" * 32,
                "security_counter": 5,
                "changelog": "fixes",
                "class_id": str(suit.class_id("b1")),
            },
            {
                "component_id": ["pc", "os"],
                "comps": ["compute"],
                "type": "raw",
                "version": "2026.11",
                "uri": "https://fw/pc/os/2026.11.bin",
                "size": 300,
                "file_sha256": "55" * 32,
                "mcuboot_hash": None,
                "security_counter": None,
                "changelog": None,
                "class_id": str(suit.class_id("pc")),
            },
        ],
    }
    text = suit.render_json(RELEASE, alg="EdDSA", kid="ab")
    assert (
        text == (json.dumps(suit.to_json(RELEASE, alg="EdDSA", kid="ab"), indent=2, ensure_ascii=False) + "\n").encode()
    )
    assert "é" in suit.render_json(replace(RELEASE, root="é.hcdf"), alg="", kid="").decode()


def test_class_ids_are_uuid5_of_the_vendor_and_the_board():
    import uuid

    assert suit.VENDOR_ID == uuid.uuid5(uuid.NAMESPACE_DNS, "hcdf-trust.invalid")
    assert suit.class_id("b1") == uuid.uuid5(suit.VENDOR_ID, "b1") != suit.class_id("b2")


def test_a_one_byte_simple_value_is_wellformed():
    suit.check_wellformed(bytes([0xF8, 0x20]), source="x", what="item")
    suit.check_wellformed(bytes([0xC1, 0x00]), source="x", what="item")  # tag 1 in the head


def test_a_one_image_release_round_trips():
    one = replace(RELEASE, components=RELEASE.components[:1])
    assert opened(signed(one)) == one


@pytest.mark.parametrize(
    ("where", "what"),
    [
        ("common", "common"),
        ("shared", "shared-sequence"),
        ("install", "command sequence 20"),
        ("text", "text"),
        ("digest", "component b1/app image-digest"),
        ("record", "release record"),
    ],
)
def test_malformed_cbor_inside_a_bstr_is_named_by_its_place(where, what):
    bad = b"\x01\x01"  # one item and a trailing byte
    m = manifest_of()
    payloads = None
    if where == "common":
        m[3] = bad
    elif where == "shared":
        _common(m, lambda c: c.update({4: bad}))
    elif where == "install":
        m[20] = bad
    elif where == "text":
        m[23] = bad
    elif where == "digest":

        def digest(c):
            shared = cbor2.loads(c[4])
            shared[3][3] = bad
            c[4] = cbor2.dumps(shared, canonical=True)

        _common(m, digest)
    else:

        def bind(c):
            shared = cbor2.loads(c[4])
            shared[19][3] = cbor2.dumps([-16, hashlib.sha256(bad).digest()])
            shared[19][14] = len(bad)
            c[4] = cbor2.dumps(shared, canonical=True)

        _common(m, bind)
        payloads = {suit.RECORD_KEY: bad}
    malformed(resign(m, payloads), f"{what}: 1 trailing bytes after the CBOR item \\(byte 1\\)$")


@pytest.mark.parametrize(
    ("where", "what"),
    [
        ("envelope", "envelope"),
        ("wrapper", "authentication wrapper"),
        ("digest", "authentication wrapper digest"),
        ("sign1", "COSE_Sign1"),
        ("protected", "COSE protected header"),
        ("manifest", "manifest"),
    ],
)
def test_malformed_cbor_in_each_part_of_the_envelope_is_named_by_its_part(where, what):
    bad = b"\x01\x01"
    data = signed()
    top = top_of(data)
    auth = cbor2.loads(top[2])
    if where == "envelope":
        data = data + b"\x01"
        words = f"{what}: 1 trailing bytes after the CBOR item \\(byte {len(data) - 1}\\)$"
    else:
        if where == "wrapper":
            top[2] = bad
        elif where == "digest":
            top[2] = cbor2.dumps([bad, auth[1]])
        elif where == "sign1":
            top[2] = cbor2.dumps([auth[0], bad])
        elif where == "protected":
            sign1 = cbor2.loads(auth[1])
            sign1.value[0] = bad
            top[2] = cbor2.dumps([auth[0], cbor2.dumps(sign1)])
        else:
            data = resign({})  # a well-formed start, then the manifest bstr replaced
            top = top_of(data)
            top[3] = bad
        data = envelope_with(top)
        words = f"{what}: 1 trailing bytes after the CBOR item \\(byte 1\\)$"
    if where == "manifest":  # the manifest is read after the signature check: through the parser
        env = suit.parse_envelope(data, source="r.suit")
        with pytest.raises(MalformedReleaseError) as info:
            suit.parse_suit_manifest(env, source="r.suit")
        assert re.match(words, info.value.message) and info.value.file == "r.suit"
    else:
        malformed(data, words)


def test_a_text_that_is_not_a_bstr_is_named():
    m = manifest_of()
    m[23] = 5
    malformed(resign(m), "manifest text is not a bstr$")


def test_an_index_out_of_range_in_the_shared_sequence_is_named():
    malformed(
        resign(_common(manifest_of(), lambda c: c.update({4: cbor2.dumps([12, 9, 1, 15])}))),
        "shared-sequence: component index 9 out of range$",
    )


def test_the_records_own_image_digest_must_be_a_suit_digest():
    def bad(c):
        shared = cbor2.loads(c[4])
        shared[19][3] = cbor2.dumps([-16, bytes(3)])
        c[4] = cbor2.dumps(shared, canonical=True)

    malformed(resign(_common(manifest_of(), bad)), "release record: image-digest is not a SHA-256 SUIT_Digest$")


def test_an_unbound_record_message_begins_with_what_happened():
    record = suit.record_bytes(replace(RELEASE, date="2030-01-01T00:00:00Z"))
    with pytest.raises(ReleaseIntegrityError) as info:
        opened(resign(manifest_of(), payloads={suit.RECORD_KEY: record}))
    assert info.value.message == "release record is not the one the signed manifest binds (image-digest/size)"


def test_manifest_digest_is_over_the_bstr_wrapped_manifest():
    m = cbor2.dumps({1: 1})
    assert suit.manifest_digest(m) == cbor2.dumps([-16, hashlib.sha256(cbor2.dumps(m)).digest()])


def test_a_decoding_error_names_the_file():
    with pytest.raises(MalformedReleaseError) as info:
        suit.loads(bytes([0x62, 0xFF, 0xFE]), source="r.suit", what="item")
    assert info.value.file == "r.suit" and info.value.message.startswith("item: malformed CBOR (")


@pytest.mark.parametrize("one", [bytes([0xA1, 0x00]), bytes([0xC1])], ids=["map value", "tag"])
def test_maps_and_tags_count_toward_the_depth(one):
    leaf = bytes([0x00])
    ok = one * suit.MAX_DEPTH + leaf
    suit.check_wellformed(ok, source="x", what="item")
    with pytest.raises(MalformedReleaseError, match="nested deeper than"):
        suit.check_wellformed(one + ok, source="x", what="item")


def test_a_map_key_counts_toward_the_depth():
    leaf = bytes([0x00])
    ok = bytes([0x81]) * (suit.MAX_DEPTH - 1) + bytes([0xA1]) + leaf + leaf  # a map at the last level
    suit.check_wellformed(ok, source="x", what="item")
    deep_key = bytes([0x81]) * (suit.MAX_DEPTH - 1) + bytes([0xA1, 0x81]) + leaf + leaf  # its key one deeper
    with pytest.raises(MalformedReleaseError, match="nested deeper than"):
        suit.check_wellformed(deep_key, source="x", what="item")
