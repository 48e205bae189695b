"""``ota build``/``ota verify`` from an attacker's point of view (issue 16 §4, §5, §8).

The attacker controls the release folder (web server, bucket) or hands the release
engineer a URL or a folder; every case below was accepted before its fix. Each test
names the byte a device or a person would read and the refusal that now stops it.
"""

from __future__ import annotations

import json
import os
import shutil
import time

import pytest

from tests._ota import make_robot, tree
from tests.conftest import CORPUS

RELEASES = CORPUS / "firmware_releases"
FLEX = ("mr_mcxn_t1", "flex-io")
UNSIGNED = "--import-unsigned-history"


@pytest.fixture
def robot(tmp_path, cli):
    return make_robot(tmp_path, cli)


@pytest.fixture
def built(robot, cli, tmp_path):
    out = tmp_path / "rel"
    r = robot.build(cli, out)
    assert r.exit_code == 0, r.stderr
    return robot, out


def verify(cli, robot, out, *extra):
    return cli("ota", "verify", out, "--key", robot.pub, *extra)


def latest_path(out, board="mr_mcxn_t1", app="flex-io"):
    return out / board / app / "latest.json"


def second_release(robot, cli, out, version="0.3.0"):
    """A second release built into the same folder (its first release is the previous one)."""
    robot.rewrite(cli, flex_version=version)
    r = robot.build(cli, out)
    assert r.exit_code == 0, r.stderr
    return out


# --- one strict JSON reader ---------------------------------------------------------------


def test_a_duplicated_url_key_with_the_evil_value_first_is_refused(built, cli):
    """json keeps the last "url" (the signed one, so the check passed); a parser that keeps
    the first (many do) sends the device to the attacker's host."""
    robot, out = built
    path = latest_path(out)
    text = path.read_text()
    good = json.loads(text)["latest"]["url"]
    path.write_text(text.replace(f'"url": "{good}"', f'"url": "https://evil.example/x.bin", "url": "{good}"', 1))
    r = verify(cli, robot, out)
    assert r.exit_code == 3, r.stderr
    assert "'url' appears twice in the object at /latest" in r.stderr


@pytest.mark.parametrize(
    ("insert", "why"),
    [
        ('"note": NaN, ', "NaN is not a JSON number"),
        ('"note": -Infinity, ', "Infinity is not a JSON number"),
        ('"note": 1e999, ', "out of range"),
        ('"note": "\\ud800", ', "lone surrogate"),
    ],
)
def test_latest_json_values_no_two_parsers_agree_on_are_refused(built, cli, insert, why):
    robot, out = built
    path = latest_path(out)
    path.write_text(path.read_text().replace("{", "{" + insert, 1))
    r = verify(cli, robot, out)
    assert r.exit_code == 3 and why in r.stderr, r.stderr


def test_json_nested_deeper_than_any_release_file_is_refused(built, cli):
    robot, out = built
    path = latest_path(out)
    path.write_text(path.read_text().replace("{", '{"x": ' + "[" * 200 + "]" * 200 + ", ", 1))
    r = verify(cli, robot, out)
    assert r.exit_code == 3 and "nested too deeply" in r.stderr and "Traceback" not in r.stderr


def test_the_rendering_with_a_duplicated_key_is_refused(built, cli):
    robot, out = built
    path = out / "release.suit.json"
    text = path.read_text()
    path.write_text(text.replace('"sequence_number"', '"sequence_number": 99, "sequence_number"', 1))
    r = verify(cli, robot, out)
    assert r.exit_code == 1 and "is not the rendering of the signed manifest" in r.stderr  # byte for byte


def test_a_tuf_timestamp_with_two_signed_keys_is_refused(tmp_path, cli, monkeypatch):
    """python-tuf keeps the last "signed" (the validly signed one) and verifies; another
    client reading the first sees the attacker's snapshot version."""
    from tests._registry import PASSPHRASE, build

    monkeypatch.setenv("HCDF_TRUST_PASSPHRASE", PASSPHRASE)
    reg = build(tmp_path, cli)
    path = reg.site / "metadata" / "timestamp.json"
    doc = json.loads(path.read_bytes())
    evil = json.dumps({**doc["signed"], "version": 999})
    text = path.read_text()
    assert text.count('"signed":') == 1
    path.write_text(text.replace('"signed":', f'"signed": {evil}, "signed":', 1))
    res = reg.verify()
    assert res.exit_code == 1, res.stderr
    assert "ambiguous or malformed metadata" in res.stderr and "'signed' appears twice" in res.stderr


def test_a_lock_with_a_duplicated_key_is_refused_by_the_one_reader(robot, cli):
    lock = robot.doc.parent / "robot.hcdf.lock"
    doc = json.loads(lock.read_text())
    text = json.dumps(doc, indent=1)  # not render's form: the general (json) path
    lock.write_text(text.replace('"root":', '"root": "evil.hcdf", "root":', 1))
    r = cli("verify", robot.doc)
    assert r.exit_code == 3 and "'root' appears twice" in r.stderr, r.stderr


# --- every byte of the release folder -----------------------------------------------------


def test_a_symlinked_board_folder_hiding_a_rogue_latest_json_is_refused(built, cli, tmp_path):
    """The scan skipped symlinked board folders, so their latest.json was never checked."""
    robot, out = built
    rogue = tmp_path / "rogue" / "flex-io"
    rogue.mkdir(parents=True)
    (rogue / "latest.json").write_text('{"evil": true}')
    (out / "other_board").symlink_to(tmp_path / "rogue", target_is_directory=True)
    r = verify(cli, robot, out)
    assert r.exit_code == 1 and "other_board is a symlink" in r.stderr, r.stderr


def test_a_symlinked_app_folder_is_refused(built, cli, tmp_path):
    robot, out = built
    app = out / "mr_mcxn_t1" / "flex-io"
    shutil.move(app, tmp_path / "moved")
    app.symlink_to(tmp_path / "moved", target_is_directory=True)
    r = verify(cli, robot, out)
    assert r.exit_code == 1 and "mr_mcxn_t1/flex-io is a symlink" in r.stderr


@pytest.mark.parametrize("rel", ["payload.bin", "mr_mcxn_t1/flex-io/0.9.9.bin", "mr_mcxn_t1/flex-io/.x.tmp"])
def test_files_no_signed_release_accounts_for_are_reported(built, cli, rel):
    robot, out = built
    (out / rel).write_bytes(b"unsigned")
    r = verify(cli, robot, out, "--json")
    assert r.exit_code == 1
    assert any(e["file"] == rel and "no signed release accounts for it" in e["message"] for e in r.json["errors"])


def test_a_sparse_2gb_file_in_place_of_an_image_is_an_integrity_error_read_no_further(built, cli):
    robot, out = built
    image = out / "mr_mcxn_t1" / "flex-io" / "0.2.0.bin"
    with image.open("r+b") as f:
        f.truncate(2 << 30)  # sparse: no disk used
    t = time.monotonic()
    r = verify(cli, robot, out)
    assert r.exit_code == 1, r.stderr
    assert "size differs from the signed manifest" in r.stderr and "over the" not in r.stderr
    assert time.monotonic() - t < 30


def test_an_image_of_another_size_that_is_another_components_is_still_a_mix_and_match(built, cli):
    robot, out = built
    shutil.copy(out / "mr_mcxn_t1" / "rtk-gnss" / "1.0.0+3.bin", out / "mr_mcxn_t1" / "flex-io" / "0.2.0.bin")
    r = verify(cli, robot, out)
    assert r.exit_code == 1 and "mix-and-match" in r.stderr


def test_a_raw_image_re_released_under_the_same_version_with_other_content_is_refused(built, cli, tmp_path):
    robot, out = built
    before = tree(out)
    (robot.fw / "scout-os.bin").write_bytes(b"other content, same version 2026.11")
    r = robot.build(cli, out)
    assert r.exit_code == 3 and "compute/scout-os version 2026.11 was already released with another image" in r.stderr
    assert tree(out) == before


def test_verify_names_a_raw_image_re_released_under_the_same_version(built, cli, tmp_path):
    """The attacker builds a second release with their own sequence of steps (same key,
    e.g. a compromised CI) in which the raw image's content changed but not its version."""
    import dataclasses
    import hashlib

    from hcdf_trust.ota.keys import load_private, load_public
    from hcdf_trust.ota.release import read_release, sign_release
    from hcdf_trust.ota.signer import FileSigner
    from hcdf_trust.ota.verify import check_release

    robot, out = built
    prev = tmp_path / "prev"
    shutil.copytree(out, prev)
    pub = load_public(str(robot.pub))
    release, _ = read_release(str(out), pub)
    evil = b"evil raw payload"
    (out / "compute" / "scout-os" / "2026.11.bin").write_bytes(evil)
    comps = tuple(
        dataclasses.replace(c, sha256=hashlib.sha256(evil).hexdigest(), size=len(evil)) if c.type == "raw" else c
        for c in release.components
    )
    forged = dataclasses.replace(release, sequence_number=2, components=comps)
    env, _, _ = sign_release(forged, FileSigner(load_private(str(robot.key), None)))
    (out / "release.suit").write_bytes(env)
    (out / "release.suit.json").unlink()
    again, files = read_release(str(out), pub, previous=str(prev))
    errors = check_release(again, files, pub)
    assert [str(e).splitlines()[0] for e in errors] == [
        f"{out / 'release.suit'}: compute/scout-os: version 2026.11 was already released with another image (release 1)"
    ]


# --- previous[] is a release this key signed ----------------------------------------------


def test_a_forged_previous_entry_is_refused(built, cli):
    """previous[] is what an operator rolls back to: an entry pointing at the attacker's
    image (any validly signed one) was never checked."""
    robot, out = built
    second_release(robot, cli, out)
    assert verify(cli, robot, out).exit_code == 0  # the signed history vouches for previous[0]
    path = latest_path(out)
    doc = json.loads(path.read_text())
    doc["previous"][0]["url"] = "https://evil.example/0.2.0.bin"
    path.write_text(json.dumps(doc, indent=2))
    r = verify(cli, robot, out)
    assert r.exit_code == 1 and "previous[0] (0.2.0) is not a release this key signed" in r.stderr


def test_an_invented_previous_entry_is_refused_and_sbom_and_audit_inherit_it(built, cli):
    robot, out = built
    path = latest_path(out)
    doc = json.loads(path.read_text())
    doc["previous"] = [{**doc["latest"], "version": "0.1.5", "url": "https://evil.example/old.bin"}]
    path.write_text(json.dumps(doc, indent=2))
    r = verify(cli, robot, out)
    assert r.exit_code == 1 and "previous[0] (0.1.5) is not a release this key signed" in r.stderr
    r = cli("sbom", robot.doc, "--format", "cyclonedx", "--release", out, "--key", robot.pub)
    assert r.exit_code == 1 and "previous[0] (0.1.5)" in r.stderr
    r = cli("audit", robot.doc, "--release", out, "--key", robot.pub, "--json")
    assert r.exit_code != 0 and "previous[0] (0.1.5)" in r.stdout + r.stderr


def test_a_history_signed_by_another_key_is_refused(built, cli, tmp_path):
    robot, out = built
    second_release(robot, cli, out)
    other = make_robot(tmp_path / "other", cli)
    other_out = tmp_path / "other-rel"
    assert other.build(cli, other_out).exit_code == 0
    other.rewrite(cli, flex_version="0.3.0")
    assert other.build(cli, other_out).exit_code == 0
    shutil.copy(other_out / "release.history", out / "release.history")
    r = verify(cli, robot, out)
    assert r.exit_code == 1 and "release.history[0]" in r.stderr and "another key" in r.stderr


def test_a_history_replayed_from_a_later_release_is_refused(built, cli, tmp_path):
    """release.history must go back in sequence: a later manifest listed as history is a replay."""
    robot, out = built
    first = tmp_path / "first"
    shutil.copytree(out, first)
    second_release(robot, cli, out)
    third = tmp_path / "third"
    shutil.copytree(out, third)
    robot.rewrite(cli, flex_version="0.4.0")
    assert robot.build(cli, third).exit_code == 0
    shutil.copy(third / "release.history", first / "release.history")
    r = verify(cli, robot, first)
    assert r.exit_code == 1 and "decreasing sequence-number order" in r.stderr


def test_an_older_image_the_history_lists_must_be_the_signed_one(built, cli):
    robot, out = built
    second_release(robot, cli, out)
    old = out / "mr_mcxn_t1" / "flex-io" / "0.2.0.bin"
    data = bytearray(old.read_bytes())
    data[700] ^= 1
    old.write_bytes(bytes(data))
    r = verify(cli, robot, out)
    assert r.exit_code == 1 and "image mr_mcxn_t1/flex-io/0.2.0.bin of release 1 is not the one" in r.stderr


# --- --previous on a folder without a signed manifest: one meaning in build and verify -----


def test_an_unsigned_previous_folder_is_refused_by_build_and_verify_alike(robot, cli, tmp_path):
    out = tmp_path / "rel"
    r = robot.build(cli, out, "--previous", RELEASES)
    assert r.exit_code == 3 and UNSIGNED in r.stderr and not out.exists()  # was: exit 0, sequence 1
    r = robot.build(cli, out, "--previous", RELEASES, UNSIGNED, "--json")
    assert r.exit_code == 0, r.stderr
    assert any(w["code"] == "unsigned-history" for w in r.json["warnings"])
    r = verify(cli, robot, out, "--previous", RELEASES)
    assert r.exit_code == 3 and UNSIGNED in r.stderr
    # the imported entries are unsigned: only the same explicit choice accepts them
    r = verify(cli, robot, out)
    assert r.exit_code == 1 and "is not a release this key signed" in r.stderr
    r = verify(cli, robot, out, "--previous", RELEASES, UNSIGNED)
    assert r.exit_code == 0, r.stderr


def test_an_unsigned_folder_built_into_is_refused_too(robot, cli, tmp_path):
    """--out already holding the fleet's unsigned latest.json is the previous release as well."""
    out = tmp_path / "rel"
    shutil.copytree(RELEASES, out)
    r = robot.build(cli, out)
    assert r.exit_code == 3 and UNSIGNED in r.stderr


# --- ota build --base-url ---------------------------------------------------------------


@pytest.mark.parametrize(
    ("url", "why"),
    [
        ("https://user:pw@fw.example.com/r", "carries credentials"),
        ("file:///etc/", "is not an https:// URL"),
        ("javascript:alert(1)//", "is not an https:// URL"),
        ("ftp://fw.example.com/r", "is not an https:// URL"),
        ("http://fw.example.com/r", "plain http needs --allow-http"),
        ("https://fw.example.com/r?token=abc", "has a query or fragment"),
        ("https://fw.example.com/r#x", "has a query or fragment"),
        ("https:///r", "is not a valid URL"),
        ("https://fw.example.com/a b", "is not a valid URL"),
    ],
)
def test_a_base_url_that_would_publish_a_secret_or_name_nothing_is_refused(robot, cli, tmp_path, url, why):
    out = tmp_path / "rel"
    r = cli("ota", "build", robot.doc, "--firmware-dir", robot.fw, "--key", robot.key, "--out", out, "--base-url", url)
    assert r.exit_code == 3 and why in r.stderr, r.stderr
    assert "pw@" not in r.stderr and "token=abc" not in r.stderr
    assert not out.exists()


def test_a_base_url_from_ota_toml_is_checked_the_same(robot, cli, tmp_path):
    (robot.root / "ota.toml").write_text(
        '[release]\nbase_url = "https://u:secret@fw.example.com/"\n[images.scout-os]\ntype = "raw"\n'
    )
    out = tmp_path / "rel"
    r = cli("ota", "build", robot.doc, "--firmware-dir", robot.fw, "--key", robot.key, "--out", out)
    assert r.exit_code == 3 and "base_url https://***@fw.example.com/ carries credentials" in r.stderr, r.stderr
    assert "u:secret" not in r.stderr and not out.exists()


def test_plain_http_is_an_explicit_choice(robot, cli, tmp_path):
    out = tmp_path / "rel"
    r = cli("ota", "build", robot.doc, "--firmware-dir", robot.fw, "--key", robot.key, "--out", out,
            "--base-url", "http://fw.lan/r", "--allow-http")  # fmt: skip
    assert r.exit_code == 0, r.stderr
    assert json.loads(latest_path(out).read_text())["latest"]["url"] == "http://fw.lan/r/mr_mcxn_t1/flex-io/0.2.0.bin"
    assert os.path.exists(out / "release.suit")


# --- each field of the history, each shape of release.history ----------------------------


@pytest.mark.parametrize(
    ("field", "value"),
    [("version", "0.2.1"), ("mcuboot_hash", "ab" * 32), ("size", 12345), ("url", "https://evil.example/a.bin")],
)
def test_every_field_of_a_previous_entry_is_the_signed_one(built, cli, field, value):
    robot, out = built
    second_release(robot, cli, out)
    path = latest_path(out)
    doc = json.loads(path.read_text())
    doc["previous"][0][field] = value
    path.write_text(json.dumps(doc, indent=2))
    r = verify(cli, robot, out)
    assert r.exit_code == 1 and "previous[0]" in r.stderr and "is not a release this key signed" in r.stderr


@pytest.mark.parametrize(
    ("data", "why"),
    [
        (b"\x80\x00", "not one CBOR array of envelopes"),  # an empty array, then a trailing byte
        (b"\xa0", "not one CBOR array of envelopes"),  # a map
        (b"\x81\x01", "not one CBOR array of envelopes"),  # an array of an integer
        (b"\x9f", "is not CBOR"),  # an indefinite array that never ends
    ],
)
def test_a_release_history_that_is_not_an_array_of_envelopes_is_refused(built, cli, data, why):
    robot, out = built
    (out / "release.history").write_bytes(data)
    r = verify(cli, robot, out)
    assert r.exit_code == 3 and why in r.stderr and "Traceback" not in r.stderr, r.stderr


def test_an_empty_history_is_an_empty_history(built, cli):
    robot, out = built
    (out / "release.history").write_bytes(b"\x80")
    assert verify(cli, robot, out).exit_code == 0


def test_a_history_without_the_entries_previous_names_is_refused(built, cli):
    """Deleting release.history does not make previous[] unchecked: it makes it unsigned."""
    robot, out = built
    second_release(robot, cli, out)
    (out / "release.history").unlink()
    r = verify(cli, robot, out)
    assert r.exit_code == 1 and "previous[0] (0.2.0) is not a release this key signed" in r.stderr
    assert "mr_mcxn_t1/flex-io/0.2.0.bin is in the release folder but no signed release accounts for it" in r.stderr


def test_an_older_image_removed_from_the_folder_is_not_an_error(built, cli):
    robot, out = built
    second_release(robot, cli, out)
    (out / "mr_mcxn_t1" / "flex-io" / "0.2.0.bin").unlink()
    r = verify(cli, robot, out)
    assert r.exit_code == 0, r.stderr


def test_an_older_image_of_another_size_is_refused_unread(built, cli):
    robot, out = built
    second_release(robot, cli, out)
    with (out / "mr_mcxn_t1" / "flex-io" / "0.2.0.bin").open("r+b") as f:
        f.truncate(1 << 30)
    r = verify(cli, robot, out)
    assert r.exit_code == 1 and "0.2.0.bin of release 1 is not the one that release signed" in r.stderr
    assert "(not read)" in r.stderr


def test_the_history_carries_through_three_releases(built, cli):
    robot, out = built
    second_release(robot, cli, out)
    second_release(robot, cli, out, version="0.4.0")
    doc = json.loads(latest_path(out).read_text())
    assert [e["version"] for e in doc["previous"]] == ["0.3.0", "0.2.0"]
    r = verify(cli, robot, out, "--json")
    assert r.exit_code == 0, r.stderr
    import cbor2

    assert len(cbor2.loads((out / "release.history").read_bytes())) == 2


def test_verify_names_an_mcuboot_image_re_released_under_the_same_version(built, cli, tmp_path):
    import dataclasses

    from hcdf_trust.ota.keys import load_private, load_public
    from hcdf_trust.ota.release import read_release, sign_release
    from hcdf_trust.ota.signer import FileSigner
    from hcdf_trust.ota.verify import check_release

    robot, out = built
    prev = tmp_path / "prev"
    shutil.copytree(out, prev)
    pub = load_public(str(robot.pub))
    release, _ = read_release(str(out), pub)
    comps = tuple(
        dataclasses.replace(c, mcuboot_hash="cd" * 32) if c.app == "flex-io" else c for c in release.components
    )
    forged = dataclasses.replace(release, sequence_number=2, components=comps)
    env, _, _ = sign_release(forged, FileSigner(load_private(str(robot.key), None)))
    (out / "release.suit").write_bytes(env)
    again, files = read_release(str(out), pub, previous=str(prev))
    messages = [str(e).splitlines()[0] for e in check_release(again, files, pub)]
    assert any("mr_mcxn_t1/flex-io: version 0.2.0 was already released with another image" in m for m in messages)


def test_a_cached_tuf_file_with_two_signed_keys_counts_as_absent(tmp_path, cli, monkeypatch):
    """A cached timestamp.json made ambiguous is not trusted: ngclient fetches and stores a
    fresh one (it kept the ambiguous file before, the server's version being the same)."""
    from tests._registry import PASSPHRASE, build

    monkeypatch.setenv("HCDF_TRUST_PASSPHRASE", PASSPHRASE)
    reg = build(tmp_path, cli)
    assert reg.verify().exit_code == 0
    cached = reg.base / "client" / "metadata" / "timestamp.json"
    text = cached.read_text()
    evil = json.dumps({**json.loads(text)["signed"], "version": 999})
    cached.write_text(text.replace('"signed":', f'"signed": {evil}, "signed":', 1))
    res = reg.verify()
    assert res.exit_code == 0, res.stderr
    assert cached.read_text().count('"signed"') == 1


def test_an_entry_injected_into_the_previous_latest_json_is_not_carried(built, cli):
    """The server's latest.json gains an entry for the attacker's image; the next build
    carries only what a release this key signed lists (it carried the whole file before)."""
    robot, out = built
    path = latest_path(out)
    doc = json.loads(path.read_text())
    doc["previous"] = [{**doc["latest"], "version": "0.1.0", "url": "https://evil.example/0.1.0.bin"}]
    path.write_text(json.dumps(doc, indent=2))
    robot.rewrite(cli, flex_version="0.3.0")
    r = robot.build(cli, out, "--json")
    assert r.exit_code == 0, r.stderr
    [warning] = [w for w in r.json["warnings"] if w["code"] == "unsigned-history"]
    assert warning["message"].startswith("mr_mcxn_t1/flex-io: 0.1.0 not carried into the new latest.json")
    after = json.loads(path.read_text())
    assert [e["version"] for e in after["previous"]] == ["0.2.0"] and "evil" not in path.read_text()
    assert verify(cli, robot, out).exit_code == 0
