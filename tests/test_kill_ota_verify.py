"""Mutation-testing killers for ota/verify.py: the pure checks, every field of every error.

The attacks themselves are in test_attack_ota.py and test_ota_verify.py; these pin what each
refusal says (file, expected, actual) and the edges of each comparison, through the public
functions, on a real signed release.
"""

from __future__ import annotations

import dataclasses
import hashlib

import cbor2
import pytest

from hcdf_trust.ota.errors import MalformedReleaseError, RollbackError
from hcdf_trust.ota.keys import load_private, load_public
from hcdf_trust.ota.release import read_release, sign_release
from hcdf_trust.ota.signer import FileSigner
from hcdf_trust.ota.verify import check_rollback, verify_history
from tests._ota import make_robot


@pytest.fixture(scope="module")
def signed(tmp_path_factory):
    """A real release, its public key, and a function signing a changed copy of it."""
    from click.testing import CliRunner

    from hcdf_trust.cli import main
    from tests.conftest import CliResult

    def cli(*args):
        r = CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)
        return CliResult(r.exit_code, r.stdout, r.stderr)

    tmp = tmp_path_factory.mktemp("kill-ota-verify")
    robot = make_robot(tmp, cli)
    out = tmp / "rel"
    assert robot.build(cli, out).exit_code == 0
    pub = load_public(str(robot.pub))
    release, _ = read_release(str(out), pub)
    signer = FileSigner(load_private(str(robot.key), None))

    def sign(**changes):
        return sign_release(dataclasses.replace(release, **changes), signer)[0]

    return release, pub, sign


def with_counter(release, app, counter):
    return tuple(dataclasses.replace(c, security_counter=counter) if c.app == app else c for c in release.components)


# --- check_rollback ---------------------------------------------------------------------


def test_a_sequence_number_not_above_the_previous_is_named_in_full(signed):
    release, _, _ = signed
    errors = check_rollback(release, release, source="rel/release.suit")
    assert [e.to_dict() for e in errors] == [
        {
            "code": "rollback",
            "message": "manifest sequence-number is not greater than the previous release's",
            "file": "rel/release.suit",
            "line": None,
            "expected": f"> {release.sequence_number}",
            "actual": str(release.sequence_number),
        }
    ]
    assert isinstance(errors[0], RollbackError) and errors[0].exit_code == 1


def test_a_security_counter_that_went_down_is_named_in_full(signed):
    release, _, _ = signed
    before = dataclasses.replace(release, sequence_number=0, components=with_counter(release, "rtk-gnss", 1 << 30))
    errors = check_rollback(release, before, source="rel/release.suit")
    gnss = release.component("mr_mcxn_t1", "rtk-gnss")
    assert [(e.message, e.file, e.expected, e.actual) for e in errors] == [
        (
            "mr_mcxn_t1/rtk-gnss: security_counter went down since the previous release",
            "rel/release.suit",
            f"≥ {1 << 30}",
            str(gnss.security_counter),
        )
    ]


def test_a_component_new_in_this_release_does_not_end_the_counter_checks(signed):
    """The first component has no previous counterpart; the ones after it are still checked."""
    release, _, _ = signed
    first = release.components[0]
    others = with_counter(dataclasses.replace(release, components=release.components[1:]), "rtk-gnss", 1 << 30)
    before = dataclasses.replace(release, sequence_number=0, components=others)
    assert before.component(first.board, first.app) is None
    assert [e.message for e in check_rollback(release, before, source="s")] == [
        "mr_mcxn_t1/rtk-gnss: security_counter went down since the previous release"
    ]


def test_an_equal_security_counter_is_not_a_rollback(signed):
    release, _, _ = signed
    assert check_rollback(release, dataclasses.replace(release, sequence_number=0), source="s") == []


# --- verify_history -----------------------------------------------------------------------


def test_history_that_is_not_cbor_is_named_with_its_file(signed):
    _, pub, _ = signed
    with pytest.raises(MalformedReleaseError) as info:
        verify_history(b"\x9f", pub, source="rel/release.history", below=5)
    assert info.value.file == "rel/release.history" and info.value.message.startswith("release history is not CBOR: ")


@pytest.mark.parametrize("data", [b"\x80\x00", b"\xa0", b"\x81\x01", cbor2.dumps([b"x", 1])])
def test_history_that_is_not_one_array_of_byte_strings_is_named_with_its_file(signed, data):
    _, pub, _ = signed
    with pytest.raises(MalformedReleaseError) as info:
        verify_history(data, pub, source="rel/release.history", below=5)
    assert (info.value.message, info.value.file) == (
        "release history is not one CBOR array of envelopes",
        "rel/release.history",
    )


def test_history_sequence_numbers_go_strictly_down(signed):
    release, pub, sign = signed
    n = release.sequence_number
    two, one = sign(sequence_number=n + 1), sign(sequence_number=n)
    assert [r.sequence_number for _, r in verify_history(cbor2.dumps([two, one]), pub, source="h", below=n + 2)] == [
        n + 1,
        n,
    ]
    with pytest.raises(RollbackError) as info:  # equal to the release it is the history of
        verify_history(cbor2.dumps([two]), pub, source="h", below=n + 1)
    assert (info.value.message, info.value.file, info.value.expected, info.value.actual) == (
        "release history is not in decreasing sequence-number order",
        "h[0]",
        f"< {n + 1}",
        str(n + 1),
    )
    with pytest.raises(RollbackError) as info:  # two entries with one number
        verify_history(cbor2.dumps([one, one]), pub, source="h", below=n + 2)
    assert (info.value.file, info.value.expected, info.value.actual) == ("h[1]", f"< {n}", str(n))


def test_history_envelopes_are_returned_with_their_bytes(signed):
    release, pub, sign = signed
    env = sign(sequence_number=release.sequence_number)
    [(data, got)] = verify_history(cbor2.dumps([env]), pub, source="h", below=release.sequence_number + 1)
    assert data == env and got == release


# --- check_release over a folder: each error as --json reports it ------------------------


@pytest.fixture
def built(tmp_path, cli):
    robot = make_robot(tmp_path, cli)
    out = tmp_path / "rel"
    assert robot.build(cli, out).exit_code == 0
    return robot, out


def errors_of(cli, robot, out, *extra):
    r = cli("ota", "verify", out, "--key", robot.pub, "--json", *extra)
    assert r.exit_code != 0
    return [{k: v for k, v in e.items() if k != "line"} for e in r.json["errors"]]


def test_a_symlinked_folder_is_named_with_its_file(built, cli, tmp_path):
    robot, out = built
    (tmp_path / "elsewhere").mkdir()
    (out / "zz").symlink_to(tmp_path / "elsewhere", target_is_directory=True)
    assert errors_of(cli, robot, out) == [
        {
            "code": "release",
            "message": "zz is a symlink: a release folder holds its files itself (a link can hide another "
            "latest.json from this check)",
            "file": "zz",
        }
    ]


def test_an_unaccounted_file_is_named_with_its_file_and_what_is_accounted_for(built, cli):
    robot, out = built
    (out / "notes.txt").write_text("x")
    assert errors_of(cli, robot, out) == [
        {
            "code": "release",
            "message": "notes.txt is in the release folder but no signed release accounts for it",
            "file": "notes.txt",
            "expected": "release.suit, release.suit.json, release.history and the files the manifests list",
        }
    ]


def test_a_stray_latest_json_does_not_end_the_checks_of_the_others(built, cli):
    """a_board/x/latest.json sorts before every real one: each real one is still checked."""
    robot, out = built
    stray = out / "a_board" / "x"
    stray.mkdir(parents=True)
    (stray / "latest.json").write_text((out / "mr_mcxn_t1" / "flex-io" / "latest.json").read_text())
    path = out / "mr_mcxn_t1" / "flex-io" / "latest.json"
    path.write_text(path.read_text().replace("https://fw.example.com/r/", "https://evil.example/r/"))
    got = errors_of(cli, robot, out)
    assert got[0] == {
        "code": "release",
        "message": "a_board/x/latest.json: no such component in the signed manifest (mix-and-match)",
        "file": "a_board/x/latest.json",
    }
    assert [e["message"] for e in got[1:]] == [
        "mr_mcxn_t1/flex-io: latest.json latest.url differs from the signed manifest"
    ]


def test_a_missing_latest_json_is_named_with_its_file(built, cli):
    robot, out = built
    (out / "mr_mcxn_t1" / "flex-io" / "latest.json").unlink()
    assert errors_of(cli, robot, out) == [
        {
            "code": "release",
            "message": "mr_mcxn_t1/flex-io: latest.json is missing",
            "file": "mr_mcxn_t1/flex-io/latest.json",
        }
    ]


# --- the history's images, the re-release check, the rollback source ----------------------


@pytest.fixture
def two_releases(built, cli):
    """A folder holding release 2 (flex-io 0.3.0) and, as its history, release 1 (0.2.0)."""
    robot, out = built
    robot.rewrite(cli, flex_version="0.3.0")
    assert robot.build(cli, out).exit_code == 0
    return robot, out


def _tamper(path):
    data = bytearray(path.read_bytes())
    data[-1] ^= 1
    path.write_bytes(bytes(data))


def test_an_image_the_current_release_also_lists_does_not_end_the_history_images_checks(two_releases):
    """Release 1 read with rtk-gnss (also in release 2) listed before flex-io 0.2.0."""
    from hcdf_trust.ota.verify import check_release

    robot, out = two_releases
    _tamper(out / "mr_mcxn_t1" / "flex-io" / "0.2.0.bin")
    pub = load_public(str(robot.pub))
    release, files = read_release(str(out), pub)
    [r1] = files.history
    reordered = dataclasses.replace(r1, components=tuple(reversed(r1.components)))
    for history in ((r1,), (reordered,)):
        errors = check_release(release, dataclasses.replace(files, history=history), pub)
        assert [e.message for e in errors] == [
            "mr_mcxn_t1/flex-io: image mr_mcxn_t1/flex-io/0.2.0.bin of release 1 is not the one that release signed"
        ]


def test_an_older_image_that_is_the_signed_one_does_not_end_the_checks_of_the_next(two_releases):
    """Release 1 as history, with flex-io 0.2.0 (intact) listed before another older image
    whose bytes are not the ones it lists: that one is still checked."""
    from hcdf_trust.ota.verify import check_release

    robot, out = two_releases
    pub = load_public(str(robot.pub))
    release, files = read_release(str(out), pub)
    [r1] = files.history
    flex = r1.component("mr_mcxn_t1", "flex-io")
    older = dataclasses.replace(flex, version="0.1.0", uri=flex.uri.replace("0.2.0.bin", "0.1.0.bin"))
    r1 = dataclasses.replace(r1, components=(flex, older))
    images = {**files.history_images, "mr_mcxn_t1/flex-io/0.1.0.bin": b"not the image"}
    errors = check_release(release, dataclasses.replace(files, history=(r1,), history_images=images), pub)
    assert [(e.message, e.actual) for e in errors] == [
        (
            "mr_mcxn_t1/flex-io: image mr_mcxn_t1/flex-io/0.1.0.bin of release 1 is not the one that release signed",
            f"{hashlib.sha256(b'not the image').hexdigest()} (13 bytes)",
        )
    ]


def test_an_image_two_history_releases_list_is_reported_once(two_releases):
    from hcdf_trust.ota.verify import check_release

    robot, out = two_releases
    _tamper(out / "mr_mcxn_t1" / "flex-io" / "0.2.0.bin")
    pub = load_public(str(robot.pub))
    release, files = read_release(str(out), pub)
    errors = check_release(release, dataclasses.replace(files, history=files.history * 2), pub)
    assert len(errors) == 1


def test_an_older_image_of_another_size_is_named_with_its_size(two_releases):
    robot, out = two_releases
    image = out / "mr_mcxn_t1" / "flex-io" / "0.2.0.bin"
    signed_size = image.stat().st_size
    with image.open("r+b") as f:
        f.truncate(signed_size + 7)
    pub = load_public(str(robot.pub))
    release, files = read_release(str(out), pub)
    from hcdf_trust.ota.verify import check_release

    [error] = check_release(release, files, pub)
    assert error.file == "mr_mcxn_t1/flex-io/0.2.0.bin"
    assert error.expected.endswith(f" ({signed_size} bytes)")
    assert error.actual == f"(not read) ({signed_size + 7} bytes)"


def test_an_older_image_that_cannot_be_opened_is_named_missing(two_releases, cli):
    """A dangling symlink in place of release 1's image: refused, and named missing (not a size)."""
    robot, out = two_releases
    image = out / "mr_mcxn_t1" / "flex-io" / "0.2.0.bin"
    signed_size, signed_sha = image.stat().st_size, hashlib.sha256(image.read_bytes()).hexdigest()
    image.unlink()
    image.symlink_to("gone.bin")
    [error] = errors_of(cli, robot, out)
    assert error == {
        "code": "release",
        "message": "mr_mcxn_t1/flex-io: image mr_mcxn_t1/flex-io/0.2.0.bin of release 1 "
        "is not the one that release signed",
        "file": "mr_mcxn_t1/flex-io/0.2.0.bin",
        "expected": f"{signed_sha} ({signed_size} bytes)",
        "actual": "(missing)",
    }


def test_a_re_release_names_both_contents(signed, tmp_path):
    """check_release against a history release that listed flex-io 0.2.0 with another hash."""
    from hcdf_trust.ota.verify import ReleaseFiles, check_release

    release, pub, _ = signed
    flex = release.component("mr_mcxn_t1", "flex-io")
    before = dataclasses.replace(
        release,
        sequence_number=0,
        components=tuple(
            dataclasses.replace(c, mcuboot_hash="cd" * 32) if c is flex else c for c in release.components
        ),
    )
    files = ReleaseFiles(manifest=b"", manifest_source="rel/release.suit", history=(before,))
    got = [e for e in check_release(release, files, pub) if "already released" in e.message]
    assert [(e.message, e.file, e.expected, e.actual) for e in got] == [
        (
            "mr_mcxn_t1/flex-io: version 0.2.0 was already released with another image (release 0)",
            "rel/release.suit",
            "cd" * 32,
            flex.mcuboot_hash,
        )
    ]


def test_a_rollback_found_through_previous_names_the_manifest(signed):
    from hcdf_trust.ota.verify import ReleaseFiles, check_release

    release, pub, _ = signed
    files = ReleaseFiles(manifest=b"", manifest_source="rel/release.suit", previous=release)
    got = [e for e in check_release(release, files, pub) if "sequence-number" in e.message]
    assert [e.file for e in got] == ["rel/release.suit"]


def test_a_swapped_older_image_is_named_with_its_digest(two_releases):
    from hcdf_trust.ota.verify import check_release

    robot, out = two_releases
    image = out / "mr_mcxn_t1" / "flex-io" / "0.2.0.bin"
    _tamper(image)
    pub = load_public(str(robot.pub))
    release, files = read_release(str(out), pub)
    [error] = check_release(release, files, pub)
    assert error.actual == f"{hashlib.sha256(image.read_bytes()).hexdigest()} ({image.stat().st_size} bytes)"


def test_an_image_of_another_size_is_named_with_both_sizes_unread(built, cli):
    robot, out = built
    image = out / "mr_mcxn_t1" / "flex-io" / "0.2.0.bin"
    signed_size = image.stat().st_size
    with image.open("r+b") as f:
        f.truncate(3 << 30)
    assert errors_of(cli, robot, out) == [
        {
            "code": "release",
            "message": "mr_mcxn_t1/flex-io: size differs from the signed manifest (the file was not read)",
            "file": "mr_mcxn_t1/flex-io/0.2.0.bin",
            "expected": str(signed_size),
            "actual": str(3 << 30),
        }
    ]


# --- _check_image: each refusal, field by field --------------------------------------------


def _flex_errors(release, files, pub):
    from hcdf_trust.ota.verify import check_release

    return [e for e in check_release(release, files, pub) if e.message.startswith("mr_mcxn_t1/flex-io:")]


def test_a_missing_image_and_a_uri_that_does_not_name_it_are_named_in_full(built):
    robot, out = built
    pub = load_public(str(robot.pub))
    release, files = read_release(str(out), pub)
    rel = "mr_mcxn_t1/flex-io/0.2.0.bin"
    missing = dataclasses.replace(files, images={**files.images, rel: None})
    [e] = _flex_errors(release, missing, pub)
    assert (e.message, e.file) == (f"mr_mcxn_t1/flex-io: image {rel} is missing", rel)
    moved = tuple(
        dataclasses.replace(c, uri="https://fw.example.com/r/other.bin") if c.app == "flex-io" else c
        for c in release.components
    )
    errors = _flex_errors(dataclasses.replace(release, components=moved), files, pub)
    [e] = [e for e in errors if "latest.json" not in e.message]  # latest.json's url differs too
    assert (e.message, e.file, e.expected, e.actual) == (
        f"mr_mcxn_t1/flex-io: uri does not name {rel}",
        rel,
        rel,
        "https://fw.example.com/r/other.bin",
    )


def test_an_image_of_the_signed_size_with_other_bytes_is_named_in_full(built):
    robot, out = built
    pub = load_public(str(robot.pub))
    release, files = read_release(str(out), pub)
    rel = "mr_mcxn_t1/flex-io/0.2.0.bin"
    data = bytearray(files.images[rel])
    data[-1] ^= 1
    [e] = _flex_errors(release, dataclasses.replace(files, images={**files.images, rel: bytes(data)}), pub)
    flex = release.component("mr_mcxn_t1", "flex-io")
    assert (e.message, e.file, e.expected, e.actual) == (
        "mr_mcxn_t1/flex-io: file_sha256 differs from the signed manifest",
        rel,
        flex.sha256,
        hashlib.sha256(data).hexdigest(),
    )


def test_another_components_image_in_place_is_named_with_both_sizes(built):
    robot, out = built
    pub = load_public(str(robot.pub))
    release, files = read_release(str(out), pub)
    rel, other = "mr_mcxn_t1/flex-io/0.2.0.bin", "mr_mcxn_t1/rtk-gnss/1.0.0+3.bin"
    swapped = dataclasses.replace(files, images={**files.images, rel: files.images[other]})
    got = [(e.message, e.file, e.expected, e.actual) for e in _flex_errors(release, swapped, pub)]
    flex, gnss = release.component("mr_mcxn_t1", "flex-io"), release.component("mr_mcxn_t1", "rtk-gnss")
    assert got == [
        (
            "mr_mcxn_t1/flex-io: file_sha256 differs from the signed manifest "
            "(mix-and-match: it is the image of mr_mcxn_t1/rtk-gnss)",
            rel,
            flex.sha256,
            gnss.sha256,
        ),
        ("mr_mcxn_t1/flex-io: size differs from the signed manifest", rel, str(flex.size), str(gnss.size)),
    ]


def test_an_image_another_key_signed_is_named_with_imgtools_result(built, tmp_path):
    """The manifest lists the file's digest and size, but MCUboot's signature is not this key's."""
    from hcdf_trust.ota.keys import generate, public_pem

    robot, out = built
    pub = load_public(str(robot.pub))
    release, files = read_release(str(out), pub)
    (tmp_path / "other.pub.pem").write_bytes(public_pem(generate("ecdsa-p256")))
    other = load_public(str(tmp_path / "other.pub.pem"))
    got = [(e.code, e.message, e.file) for e in _flex_errors(release, files, other)]
    assert got == [
        (
            "bad-signature",
            "mr_mcxn_t1/flex-io: MCUboot image does not verify with the key (INVALID_SIGNATURE)",
            "mr_mcxn_t1/flex-io/0.2.0.bin",
        )
    ]


def test_each_mcuboot_field_the_manifest_lists_otherwise_is_named_in_full(built):
    """A manifest (not signed: check_release is pure) listing flex-io's file as it is, but another
    MCUboot hash, header version or security counter than the image's own."""
    robot, out = built
    pub = load_public(str(robot.pub))
    release, files = read_release(str(out), pub)
    flex = release.component("mr_mcxn_t1", "flex-io")
    rel, moved = "mr_mcxn_t1/flex-io/0.2.0.bin", "mr_mcxn_t1/flex-io/0.9.0.bin"
    files = dataclasses.replace(files, images={**files.images, moved: files.images[rel]})

    def errors(**changes):
        listed = tuple(dataclasses.replace(c, **changes) if c is flex else c for c in release.components)
        got = _flex_errors(dataclasses.replace(release, components=listed), files, pub)
        return [(e.message, e.file, e.expected, e.actual) for e in got if "latest.json" not in e.message]

    assert errors(mcuboot_hash="ab" * 32) == [
        ("mr_mcxn_t1/flex-io: mcuboot_hash differs from the signed manifest", rel, "ab" * 32, flex.mcuboot_hash)
    ]
    assert errors(version="0.9.0", uri=flex.uri.replace("0.2.0.bin", "0.9.0.bin")) == [
        ("mr_mcxn_t1/flex-io: image header version differs from the signed manifest", moved, "0.9.0", "0.2.0")
    ]
    assert errors(security_counter=flex.security_counter + 1) == [
        (
            "mr_mcxn_t1/flex-io: image security_counter differs from the signed manifest",
            rel,
            str(flex.security_counter + 1),
            str(flex.security_counter),
        )
    ]


# --- _check_rendering: a release.suit.json that is not what the envelope renders ----------


def test_a_rendering_that_is_not_utf8_is_named_at_its_line_not_a_crash(built, cli):
    """Bytes that do not decode are shown replaced (U+FFFD), on the line where they are."""
    robot, out = built
    path = out / "release.suit.json"
    lines = path.read_bytes().split(b"\n")
    want = lines[2].decode().strip()
    lines[2] = lines[2].replace(b'"', b'"\xff', 1)
    path.write_bytes(b"\n".join(lines))
    r = cli("ota", "verify", out, "--key", robot.pub, "--json")
    assert r.exit_code == 1
    assert [(e["message"], e["file"], e["line"], e["expected"], e["actual"]) for e in r.json["errors"]] == [
        (
            "release.suit.json is not the rendering of the signed manifest (delete it, or rebuild the release)",
            "release.suit.json",
            3,
            want,
            want.replace('"', '"\ufffd', 1),
        )
    ]


def test_a_truncated_or_extended_rendering_is_named_at_the_first_line_past_the_shorter(built, cli):
    robot, out = built
    path = out / "release.suit.json"
    full = path.read_bytes()
    lines = full.decode().splitlines()
    message = "release.suit.json is not the rendering of the signed manifest (delete it, or rebuild the release)"
    path.write_text("\n".join(lines[:4]) + "\n")
    r = cli("ota", "verify", out, "--key", robot.pub, "--json")
    assert r.exit_code == 1
    assert [(e["message"], e["line"], e["expected"], e["actual"]) for e in r.json["errors"]] == [
        (message, 5, lines[4].strip(), "end of file")
    ]
    path.write_bytes(full + b'{"extra": 1}\n')
    r = cli("ota", "verify", out, "--key", robot.pub, "--json")
    assert r.exit_code == 1
    assert [(e["message"], e["line"], e["expected"], e["actual"]) for e in r.json["errors"]] == [
        (message, len(lines) + 1, "end of file", '{"extra": 1}')
    ]


def test_a_long_line_of_the_rendering_is_cut_to_200_characters_each_side(built):
    """The signed changelog is long (the expected line), the tampered line longer (the actual one)."""
    from hcdf_trust.ota.verify import check_release

    robot, out = built
    pub = load_public(str(robot.pub))
    release, files = read_release(str(out), pub)
    long = tuple(dataclasses.replace(c, changelog="c" * 300) for c in release.components)
    lines = files.rendering.decode().splitlines()
    i = next(n for n, text in enumerate(lines) if '"changelog"' in text)
    lines[i] = '    "changelog": "' + "d" * 300 + '",'
    tampered = dataclasses.replace(files, rendering=("\n".join(lines) + "\n").encode())
    errors = check_release(dataclasses.replace(release, components=long), tampered, pub)
    [e] = [e for e in errors if e.file == "release.suit.json"]
    want, got = '"changelog": "' + "c" * 300, '"changelog": "' + "d" * 300
    assert (e.line, e.expected, e.actual) == (i + 1, want[:200], got[:200])


# --- check_history: every previous[] entry is a release this key signed --------------------


def _entry(release, c, **changes):
    from hcdf_trust.ota.latest import Entry

    entry = Entry(c.version, release.date, c.mcuboot_hash, c.size, c.uri, c.changelog)
    return dataclasses.replace(entry, **changes)


def test_a_signed_previous_entry_does_not_end_the_checks_of_the_ones_after_it(signed):
    from hcdf_trust.ota.latest import Latest
    from hcdf_trust.ota.verify import check_history

    release, _, _ = signed
    c = release.component("mr_mcxn_t1", "flex-io")
    good, forged = _entry(release, c), _entry(release, c, url="https://evil.example/x.bin")
    doc = Latest(c.board, c.app, good, (good, forged))
    entries = (("previous[0]", good), ("previous[1]", forged))
    errors = check_history(doc, (release,), rel="mr_mcxn_t1/flex-io/latest.json", entries=entries)
    assert [e.to_dict() for e in errors] == [
        {
            "code": "release",
            "message": f"mr_mcxn_t1/flex-io: latest.json previous[1] ({c.version}) is not a release this key signed",
            "file": "mr_mcxn_t1/flex-io/latest.json",
            "line": None,
            "expected": "an image of an earlier signed release (release.history or --previous); history "
            "imported from an unsigned folder needs --previous DIR --import-unsigned-history",
            "actual": f"{c.version} {c.mcuboot_hash} {c.size} https://evil.example/x.bin",
        }
    ]
    assert errors[0].exit_code == 1
    # an entry the user chose to import unsigned is taken on their word, and only that one
    assert check_history(doc, (release,), rel="r", entries=entries, unsigned=(forged,)) == []
    assert len(check_history(doc, (), rel="r", entries=entries, unsigned=(forged,))) == 1


# --- _check_latest: every field of latest.json, named in full ------------------------------

FLEX_LATEST = "mr_mcxn_t1/flex-io/latest.json"


def _latest_errors(built, change, changelog=None):
    """check_release's errors about flex-io's latest.json after ``change(doc)`` edited it
    (and, given ``changelog``, with the signed release's flex-io changelog that one)."""
    import json

    from hcdf_trust.ota.verify import check_release

    robot, out = built
    pub = load_public(str(robot.pub))
    release, files = read_release(str(out), pub)
    if changelog is not None:
        changed = (dataclasses.replace(c, changelog=changelog) if c.app == "flex-io" else c for c in release.components)
        release = dataclasses.replace(release, components=tuple(changed))
    doc = json.loads(files.latest[FLEX_LATEST])
    change(doc)
    edited = dataclasses.replace(files, latest={**files.latest, FLEX_LATEST: json.dumps(doc).encode()})
    errors = [e for e in check_release(release, edited, pub) if e.file == FLEX_LATEST]
    return release, [(e.code, e.message, e.file, e.expected, e.actual) for e in errors]


@pytest.mark.parametrize(
    ("name", "value"),
    [
        ("board", "other_board"),
        ("app", "other-app"),
        ("latest.version", "9.9.9"),
        ("latest.mcuboot_hash", "ab" * 32),
        ("latest.size", 7),
        ("latest.url", "https://evil.example/x.bin"),
        ("latest.date", "2020-01-01T00:00:00Z"),
        ("latest.changelog", "rewritten"),
    ],
)
def test_each_latest_json_field_that_differs_is_named_with_both_values(built, name, value):
    def change(doc):
        *parents, key = name.split(".")
        for p in parents:
            doc = doc[p]
        doc[key] = value

    release, got = _latest_errors(built, change)
    flex = release.component("mr_mcxn_t1", "flex-io")
    signed = {
        "board": flex.board,
        "app": flex.app,
        "latest.version": flex.version,
        "latest.mcuboot_hash": flex.mcuboot_hash,
        "latest.size": str(flex.size),
        "latest.url": flex.uri,
        "latest.date": release.date,
        "latest.changelog": "(absent)",  # the test robot's releases have no changelog
    }[name]
    assert got == [
        (
            "release",
            f"mr_mcxn_t1/flex-io: latest.json {name} differs from the signed manifest",
            FLEX_LATEST,
            signed,
            str(value),
        )
    ]


def test_an_absent_changelog_is_named_absent_not_none(built):
    _, got = _latest_errors(built, lambda doc: doc["latest"].pop("changelog", None), changelog="fixes")
    assert got == [
        (
            "release",
            "mr_mcxn_t1/flex-io: latest.json latest.changelog differs from the signed manifest",
            FLEX_LATEST,
            "fixes",
            "(absent)",
        )
    ]


def test_a_latest_json_that_does_not_parse_is_its_own_error_and_the_others_are_checked(built):
    _, got = _latest_errors(built, lambda doc: doc["latest"].update(size=-1))
    assert got == [("malformed-release", "latest.size is not a u64", FLEX_LATEST, None, "-1")]


def test_a_previous_entry_no_release_signed_is_named_with_its_latest_json(built):
    def forge(doc):
        doc["previous"] = [dict(doc["latest"], version="0.0.1", url="https://evil.example/x.bin")]

    release, got = _latest_errors(built, forge)
    flex = release.component("mr_mcxn_t1", "flex-io")
    assert [(code, message, file, actual) for code, message, file, _, actual in got] == [
        (
            "release",
            "mr_mcxn_t1/flex-io: latest.json previous[0] (0.0.1) is not a release this key signed",
            FLEX_LATEST,
            f"0.0.1 {flex.mcuboot_hash} {flex.size} https://evil.example/x.bin",
        )
    ]


# --- open_envelope / verify_envelope: what the CLI refuses before any image is read -------


def _edit_sign1(out, index, change):
    """Replace item ``index`` of the COSE_Sign1 in ``out/release.suit`` by ``change(item)``, the
    wrapper digest left as it is, and write the envelope back; its path."""
    from hcdf_trust.ota import suit

    path = out / "release.suit"
    tag = cbor2.loads(path.read_bytes())
    top = dict(tag.value)
    digest, sign1 = cbor2.loads(top[suit.AUTHENTICATION])
    sign1 = cbor2.loads(sign1)
    sign1.value[index] = change(sign1.value[index])
    top[suit.AUTHENTICATION] = cbor2.dumps([digest, cbor2.dumps(sign1)])
    path.write_bytes(cbor2.dumps(cbor2.CBORTag(tag.tag, top), canonical=True))
    return path


def _resigned(data: bytes, private, *, protected: dict) -> bytes:
    """``data``'s envelope with its COSE_Sign1 made again, for real, by ``private`` over the same
    manifest digest, with ``protected`` as the protected header (cwt adds nothing to it)."""
    from cwt import COSE

    from hcdf_trust.ota import suit
    from hcdf_trust.ota.signer import FileSigner

    tag = cbor2.loads(data)
    top = dict(tag.value)
    digest = cbor2.loads(top[suit.AUTHENTICATION])[0]
    sign1 = COSE.new(deterministic_header=True).encode_and_sign(
        digest, FileSigner(private).cose_key(b""), protected=protected, out="cbor2/CBORTag"
    )
    sign1.value[2] = None  # detached, as ota build writes it
    top[suit.AUTHENTICATION] = cbor2.dumps([digest, cbor2.dumps(sign1)])
    return cbor2.dumps(cbor2.CBORTag(tag.tag, top), canonical=True)


def test_a_manifest_signed_by_the_key_without_a_kid_is_refused(built, cli):
    """The signature is good and made by the trusted key, but the protected header names no key:
    ota verify demands the kid (only the working group's examples may lack it)."""
    from hcdf_trust.ota.signer import COSE_ALGS, key_id
    from hcdf_trust.ota.verify import open_envelope

    robot, out = built
    private = load_private(str(robot.key), None)
    pub = load_public(str(robot.pub))
    manifest = out / "release.suit"
    data = _resigned(manifest.read_bytes(), private, protected={1: COSE_ALGS["ecdsa-p256"][0]})
    # the oracle: a correct signature by this key, with no kid anywhere
    env = open_envelope(data, pub, source="x", require_kid=False)
    assert 4 not in env.protected_map and env.protected_map == {1: COSE_ALGS["ecdsa-p256"][0]}
    manifest.write_bytes(data)
    assert errors_of(cli, robot, out) == [
        {
            "code": "bad-signature",
            "message": "manifest was signed by another key (COSE kid)",
            "file": str(manifest),
            "expected": key_id(pub).hex(),
            "actual": "None",
        }
    ]


@pytest.mark.parametrize(("alg", "named", "actual"), [(-8, "'EdDSA'", "EdDSA"), (-35, "-35", "-35")])
def test_a_cose_alg_not_bound_to_the_key_is_named_with_the_ones_that_are(built, cli, alg, named, actual):
    """The protected header says EdDSA, or ES384 (which ota does not know by name), for an ECDSA
    P-256 key: refused before any signature check."""
    from hcdf_trust.ota.signer import key_id

    robot, out = built
    protected = cbor2.dumps({1: alg, 4: key_id(load_public(str(robot.pub)))})
    path = _edit_sign1(out, 0, lambda _: protected)
    assert errors_of(cli, robot, out) == [
        {
            "code": "bad-signature",
            "message": f"manifest COSE alg {named} is not bound to the ecdsa-p256 key",
            "file": str(path),
            "expected": "ESP256 or ES256",
            "actual": actual,
        }
    ]


@pytest.mark.parametrize(("kid", "shown"), [(b"another key", b"another key".hex()), (7, "7")])
def test_another_kid_is_named_as_found(built, cli, kid, shown):
    """A kid that is not the key's: a byte string shown in hex, anything else as it is."""
    from hcdf_trust.ota.signer import key_id

    robot, out = built
    path = _edit_sign1(out, 0, lambda _: cbor2.dumps({1: -7, 4: kid}))
    assert errors_of(cli, robot, out) == [
        {
            "code": "bad-signature",
            "message": "manifest was signed by another key (COSE kid)",
            "file": str(path),
            "expected": key_id(load_public(str(robot.pub))).hex(),
            "actual": shown,
        }
    ]


def test_a_signature_that_does_not_verify_is_named_with_its_file(built, cli):
    """alg, kid and wrapper digest right, one bit of the signature changed."""
    robot, out = built
    path = _edit_sign1(out, 3, lambda signature: signature[:-1] + bytes([signature[-1] ^ 1]))
    [error] = errors_of(cli, robot, out)
    assert (error["code"], error["file"]) == ("bad-signature", str(path))
    assert error["message"].startswith("manifest signature does not verify with the key: "), error["message"]


@pytest.mark.parametrize(("alg", "flip", "shown"), [(-16, 1, "SHA-256"), (-44, 0, "algorithm -44")])
def test_a_wrapper_digest_that_is_not_the_manifests_is_named_with_both_digests(built, cli, alg, flip, shown):
    """Another SHA-256, or the right bytes labelled with another algorithm (SHA-384): both
    digests shown in one form, with the algorithm the wrapper names."""
    from hcdf_trust.ota import suit

    robot, out = built
    path = out / "release.suit"
    tag = cbor2.loads(path.read_bytes())
    top = dict(tag.value)
    manifest_sha = hashlib.sha256(cbor2.dumps(top[suit.MANIFEST])).digest()  # over the bstr-wrapped manifest
    digest, sign1 = cbor2.loads(top[suit.AUTHENTICATION])
    assert cbor2.loads(digest) == [-16, manifest_sha]
    wrong = bytes([manifest_sha[0] ^ flip]) + manifest_sha[1:]
    top[suit.AUTHENTICATION] = cbor2.dumps([cbor2.dumps([alg, wrong]), sign1])
    path.write_bytes(cbor2.dumps(cbor2.CBORTag(tag.tag, top), canonical=True))
    assert errors_of(cli, robot, out) == [
        {
            "code": "release",
            "message": "authentication wrapper digest is not the manifest's",
            "file": str(path),
            "expected": f"SHA-256 {manifest_sha.hex()}",
            "actual": f"{shown} {wrong.hex()}",
        }
    ]


def test_a_signed_manifest_ota_build_would_not_write_is_named_with_its_file(built, cli):
    """An envelope that verifies with the key, around a manifest parse_release refuses (its
    sequence number is a string): the refusal names the manifest file."""
    from hcdf_trust.ota import suit
    from hcdf_trust.ota.release import sign_manifest
    from hcdf_trust.ota.signer import FileSigner
    from hcdf_trust.ota.verify import open_envelope

    robot, out = built
    pub = load_public(str(robot.pub))
    path = out / "release.suit"
    env = open_envelope(path.read_bytes(), pub, source="x")
    manifest = cbor2.loads(env.manifest)
    manifest[suit.SEQUENCE_NUMBER] = "7"
    data = sign_manifest(
        cbor2.dumps(manifest, canonical=True), FileSigner(load_private(str(robot.key), None)), env.payloads
    )[0]
    open_envelope(data, pub, source="x")  # the oracle: it verifies
    path.write_bytes(data)
    r = cli("ota", "verify", out, "--key", robot.pub, "--json")
    assert r.exit_code == 3, r.stderr
    [error] = r.json["errors"]
    assert (error["code"], error["message"], error["file"]) == (
        "malformed-release",
        "manifest sequence-number is not an unsigned integer",
        str(path),
    )


# --- ota/read.py's FolderImages: the image reader behind ota verify and fleet update --------


@pytest.mark.parametrize("how", ["lookup", "scan"])
def test_an_image_over_the_firmware_limit_is_refused_naming_it(tmp_path, how):
    """A (sparse) file one byte over 256 MiB, listed readable (its size is a signed one): the
    lookup (fleet update) and the streaming scan (ota verify) refuse it by name, never read it."""
    from hcdf_trust.errors import InputError
    from hcdf_trust.ota.read import FolderImages

    (tmp_path / "b").mkdir()
    with open(tmp_path / "b" / "app.bin", "wb") as f:
        f.truncate((256 << 20) + 1)
    images = FolderImages(str(tmp_path))
    images.add("b/app.bin", True)
    with pytest.raises(InputError) as info:
        images["b/app.bin"] if how == "lookup" else images.scan("b/app.bin")
    assert (info.value.message, info.value.file) == (f"image is over the {256 << 20}-byte limit", "b/app.bin")


def test_ota_verify_streams_an_image_from_its_folder_never_holding_it_whole(built, tmp_path):
    """check_release over a release folder (FolderImages) reads each image in chunks through the
    MCUboot check: an 8 MiB image the manifest lists is checked with well under 8 MiB allocated."""
    import tracemalloc

    from hcdf_trust.ota.read import FolderImages
    from hcdf_trust.ota.verify import image_path

    robot, out = built
    pub = load_public(str(robot.pub))
    release, files = read_release(str(out), pub)
    rel, size = "mr_mcxn_t1/flex-io/0.2.0.bin", 8 << 20
    folder = tmp_path / "big"
    (folder / "mr_mcxn_t1" / "flex-io").mkdir(parents=True)
    (folder / rel).write_bytes(bytes(size))
    images = FolderImages(str(folder))
    for c in release.components:
        images.add(image_path(c), image_path(c) == rel)  # the others: not to be read
    listed = tuple(
        dataclasses.replace(c, size=size, sha256=hashlib.sha256(bytes(size)).hexdigest()) if c.app == "flex-io" else c
        for c in release.components
    )
    tracemalloc.start()
    try:
        errors = _flex_errors(
            dataclasses.replace(release, components=listed), dataclasses.replace(files, images=images), pub
        )
        _current, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert [(e.code, e.message, e.file, e.expected, e.actual) for e in errors if "latest.json" not in e.message] == [
        (
            "malformed-release",
            "mr_mcxn_t1/flex-io: not an MCUboot image (header magic)",
            rel,
            "0x96f3b83d",
            "0x00000000",
        )
    ]
    assert peak < 3 << 20, peak  # a chunk or two (1 MiB each), not the 8 MiB image


def test_an_image_with_the_magic_and_no_tlvs_is_named_not_mcuboot_with_its_file(built):
    """The listed file is flex-io's MCUboot header alone (the manifest lists its digest and
    size): the header magic is right, its TLVs are not there."""
    robot, out = built
    pub = load_public(str(robot.pub))
    release, files = read_release(str(out), pub)
    rel = "mr_mcxn_t1/flex-io/0.2.0.bin"
    head = files.images[rel][:32]
    listed = tuple(
        dataclasses.replace(c, size=len(head), sha256=hashlib.sha256(head).hexdigest()) if c.app == "flex-io" else c
        for c in release.components
    )
    errors = _flex_errors(
        dataclasses.replace(release, components=listed),
        dataclasses.replace(files, images={**files.images, rel: head}),
        pub,
    )
    [e] = [e for e in errors if "latest.json" not in e.message]
    assert (e.code, e.file) == ("malformed-release", rel)
    assert e.message.startswith("mr_mcxn_t1/flex-io: not an MCUboot image ("), e.message
    assert "header magic" not in e.message


@pytest.mark.parametrize("how", ["lookup", "scan"])
def test_an_image_swapped_for_a_link_out_of_the_folder_is_refused_naming_it(tmp_path, how):
    """Listed readable, then replaced by a symlink leading outside the release folder (as
    between ota verify's listing and its read): refused on the descriptor, named by its path."""
    from hcdf_trust.errors import PathEscapeError
    from hcdf_trust.ota.read import FolderImages

    (tmp_path / "secret.bin").write_bytes(b"not the release's")
    folder = tmp_path / "rel"
    (folder / "b").mkdir(parents=True)
    (folder / "b" / "app.bin").symlink_to(tmp_path / "secret.bin")
    images = FolderImages(str(folder))
    images.add("b/app.bin", True)
    with pytest.raises(PathEscapeError) as info:
        images["b/app.bin"] if how == "lookup" else images.scan("b/app.bin")
    assert info.value.file == "b/app.bin"
