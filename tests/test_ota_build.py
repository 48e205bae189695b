"""``hcdf-trust ota build``: images checked by imgtool's CLI and by the raw header fields."""

from __future__ import annotations

import hashlib
import json
import shutil
import struct
import subprocess
import sys
from pathlib import Path

import pytest

from tests._ota import make_robot, tree
from tests.conftest import CORPUS

IMGTOOL = str(Path(sys.executable).with_name("imgtool"))
RELEASES = CORPUS / "firmware_releases"


@pytest.fixture
def robot(tmp_path, cli):
    return make_robot(tmp_path, cli)


def mcuboot_hash_from_header(data: bytes) -> str:
    """The oracle: SHA-256 over header + payload + protected TLVs, from the raw header fields."""
    magic, _load, hdr_size, protect_tlv_size, img_size = struct.unpack_from("<IIHHI", data)
    assert magic == 0x96F3B83D
    return hashlib.sha256(data[: hdr_size + img_size + protect_tlv_size]).hexdigest()


@pytest.mark.parametrize("kind", ["ecdsa-p256", "ed25519", "rsa-2048"])
def test_imgtool_cli_verifies_every_image_with_the_key_and_hashes_match_the_header(tmp_path, cli, kind):
    robot = make_robot(tmp_path, cli, kind=kind)
    out = tmp_path / "rel"
    r = robot.build(cli, out, "--json")
    assert r.exit_code == 0, r.stderr
    images = {(i["component_id"][0], i["component_id"][1]): i for i in r.json["images"]}
    assert set(images) == {("mr_mcxn_t1", "flex-io"), ("mr_mcxn_t1", "rtk-gnss"), ("compute", "scout-os")}
    for board, app in [("mr_mcxn_t1", "flex-io"), ("mr_mcxn_t1", "rtk-gnss")]:
        latest = json.loads((out / board / app / "latest.json").read_text())
        image = out / board / app / f"{latest['latest']['version']}.bin"
        proc = subprocess.run([IMGTOOL, "verify", "-k", robot.pub, image], capture_output=True, text=True)
        assert proc.returncode == 0 and "correctly validated" in proc.stdout, proc.stdout + proc.stderr
        data = image.read_bytes()
        assert latest["latest"]["mcuboot_hash"] == mcuboot_hash_from_header(data)
        assert f"Image digest: {latest['latest']['mcuboot_hash']}" in proc.stdout
        assert latest["latest"]["size"] == len(data)
        assert latest["latest"]["url"] == f"https://fw.example.com/r/{board}/{app}/{latest['latest']['version']}.bin"
        # the downloaded file's digest is a different thing, and the manifest says which is which
        assert images[(board, app)]["file_sha256"] == hashlib.sha256(data).hexdigest()
        assert images[(board, app)]["file_sha256"] != latest["latest"]["mcuboot_hash"]
    # imgtool with another key refuses (so the check above is not vacuous)
    other = tmp_path / "other.pem"
    cli("ota", "keygen", "--type", kind, "-o", other)
    image = out / "mr_mcxn_t1" / "flex-io" / "0.2.0.bin"
    proc = subprocess.run([IMGTOOL, "verify", "-k", tmp_path / "other.pub.pem", image], capture_output=True)
    assert proc.returncode != 0
    # the raw image is copied as it is, with no MCUboot header
    raw = out / "compute" / "scout-os" / "2026.11.bin"
    assert raw.read_bytes() == (robot.fw / "scout-os.bin").read_bytes()
    assert not (out / "compute" / "scout-os" / "latest.json").exists()


def test_version_and_build_number_land_in_the_header(robot, cli, tmp_path):
    out = tmp_path / "rel"
    assert robot.build(cli, out).exit_code == 0
    proc = subprocess.run(
        [IMGTOOL, "verify", "-k", robot.pub, out / "mr_mcxn_t1" / "rtk-gnss" / "1.0.0+3.bin"],
        capture_output=True,
        text=True,
    )
    assert "Image version: 1.0.0+3" in proc.stdout


def test_json_stdout_is_clean_of_imgtool_prints(robot, tmp_path):
    out = tmp_path / "rel"
    proc = subprocess.run(
        [
            str(Path(sys.executable).with_name("hcdf-trust")),
            "ota",
            "build",
            robot.doc,
            "--firmware-dir",
            robot.fw,
            "--key",
            robot.key,
            "--out",
            out,
            "--json",
        ],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["ok"] is True
    assert "image.py" not in proc.stdout + proc.stderr


def test_corpus_latest_json_is_our_previous_and_history_is_kept(robot, cli, tmp_path):
    out = tmp_path / "rel"
    r = robot.build(cli, out, "--previous", RELEASES)
    assert r.exit_code == 3 and "--import-unsigned-history" in r.stderr and not out.exists()
    r = robot.build(cli, out, "--previous", RELEASES, "--import-unsigned-history")
    assert r.exit_code == 0, r.stderr
    for app in ("flex-io", "rtk-gnss"):
        before = json.loads((RELEASES / "mr_mcxn_t1" / app / "latest.json").read_text())
        after = json.loads((out / "mr_mcxn_t1" / app / "latest.json").read_text())
        assert list(after) == ["board", "app", "latest", "previous"]
        assert list(after["latest"])[:5] == ["version", "date", "mcuboot_hash", "size", "url"]
        assert after["previous"] == [before["latest"], *before["previous"]]
    # a second release on top keeps both earlier entries, newest first
    out2 = tmp_path / "rel2"
    robot.rewrite(cli, flex_version="0.3.0")
    r = robot.build(cli, out2, "--previous", out, "--json")  # 0.1.0 came from the unsigned folder
    assert r.exit_code == 0, r.stderr
    assert [w["code"] for w in r.json["warnings"]] == ["unsigned-history", "unsigned-history"]
    after = json.loads((out2 / "mr_mcxn_t1" / "flex-io" / "latest.json").read_text())
    assert [e["version"] for e in after["previous"]] == ["0.2.0"]  # not carried without the flag
    assert robot.build(cli, out2, "--previous", out, "--import-unsigned-history").exit_code == 0
    after = json.loads((out2 / "mr_mcxn_t1" / "flex-io" / "latest.json").read_text())
    assert [e["version"] for e in after["previous"]] == ["0.2.0", "0.1.0"]
    manifest = json.loads((out2 / "release.suit.json").read_text())
    assert manifest["sequence_number"] == 2


@pytest.mark.parametrize(
    ("version", "why"),
    [
        ("1.2.3-rc1", "pre-release"),
        ("v2024.03-rc1", "pre-release"),
        ("2026.11", "major 2026 > 255"),
        ("1.256.0", "minor 256 > 255"),
    ],
)
def test_versions_that_do_not_fit_the_header_name_the_comp_and_mcuboot_version(robot, cli, tmp_path, version, why):
    robot.rewrite(cli, flex_version=version)
    out = tmp_path / "rel"
    r = robot.build(cli, out)
    assert r.exit_code == 3
    assert "comp 'main'" in r.stderr and why in r.stderr and "mcuboot_version" in r.stderr
    assert "robot.hcdf:6:" in r.stderr
    assert not out.exists()
    # giving mcuboot_version fixes it
    (robot.root / "ota.toml").write_text(
        '[images.flex-io]\nmcuboot_version = "26.11.0+5"\n[images.scout-os]\ntype = "raw"\n'
    )
    r = robot.build(cli, out, "--json")
    assert r.exit_code == 0, r.stderr
    assert any(i["version"] == "26.11.0+5" for i in r.json["images"])


def test_missing_binary_is_an_input_error_naming_the_comp(robot, cli, tmp_path):
    (robot.fw / "rtk-gnss.bin").unlink()
    out = tmp_path / "rel"
    r = robot.build(cli, out)
    assert r.exit_code == 3
    assert "comp 'gnss'" in r.stderr and "mr_mcxn_t1/rtk-gnss.bin" in r.stderr
    assert not out.exists()


def test_excluded_software_is_reported_not_built(robot, cli, tmp_path):
    (robot.root / "ota.toml").write_text("[images.scout-os]\nexclude = true\n")
    r = robot.build(cli, tmp_path / "rel", "--json")
    assert r.exit_code == 0, r.stderr
    assert r.json["excluded"] == ["compute/scout-os"]
    assert any(w["code"] == "excluded" and w["line"] for w in r.json["warnings"])
    assert all(i["component_id"][1] != "scout-os" for i in r.json["images"])


def test_hcdf_hash_must_be_the_mcuboot_hash(robot, cli, tmp_path):
    first = tmp_path / "first"
    r = robot.build(cli, first, "--json")
    real = next(i["mcuboot_hash"] for i in r.json["images"] if i["component_id"][1] == "flex-io")
    file_sha = next(i["file_sha256"] for i in r.json["images"] if i["component_id"][1] == "flex-io")
    robot.rewrite(cli, flex_hash=file_sha)  # the classic mistake: the whole-file hash
    out = tmp_path / "rel"
    r = robot.build(cli, out)
    assert r.exit_code == 1
    assert "comp 'main'" in r.stderr and "MCUboot image hash" in r.stderr
    assert f"expected: {file_sha}" in r.stderr and f"actual:   {real}" in r.stderr
    assert not out.exists()
    robot.rewrite(cli, flex_hash=real.upper())
    assert robot.build(cli, out).exit_code == 0


def test_an_unverified_tree_builds_nothing(robot, cli, tmp_path):
    (robot.root / "body.glb").write_bytes(b"tampered model")
    out = tmp_path / "rel"
    r = robot.build(cli, out)
    assert r.exit_code == 1 and "body.glb: digest mismatch" in r.stderr
    assert not out.exists()
    (robot.root / "body.glb").write_bytes(b"glTF model stand-in")
    (robot.root / "robot.hcdf.lock").unlink(missing_ok=True)
    (robot.root / "hcdf.lock").unlink(missing_ok=True)
    r = robot.build(cli, out)
    assert r.exit_code == 3 and "lock" in r.stderr
    assert not out.exists()


def test_wrong_or_missing_passphrase_exits_3_and_writes_nothing(robot, cli, tmp_path):
    pw = tmp_path / "pw"
    pw.write_text("right\n")
    key = tmp_path / "enc.pem"
    assert cli("ota", "keygen", "-o", key, "--passphrase-file", pw).exit_code == 0
    robot.key = key
    out = tmp_path / "rel"
    r = robot.build(cli, out)
    assert r.exit_code == 3 and "--passphrase-file" in r.stderr
    wrong = tmp_path / "wrong"
    wrong.write_text("wrong\n")
    r = robot.build(cli, out, "--passphrase-file", wrong)
    assert r.exit_code == 3 and "wrong passphrase" in r.stderr
    assert not out.exists()
    assert robot.build(cli, out, "--passphrase-file", pw).exit_code == 0


def test_a_build_that_fails_after_some_images_leaves_the_release_folder_untouched(robot, cli, tmp_path):
    out = tmp_path / "rel"
    assert robot.build(cli, out).exit_code == 0
    before = tree(out)
    robot.rewrite(cli, flex_version="0.3.0")
    # the second image no longer fits its slot: imgtool fails after the first image was signed
    (robot.root / "ota.toml").write_text(
        "[boards.default]\nslot_size = 0x1800\n[boards.mr_mcxn_t1]\nslot_size = 0x1800\n"
        '[images.scout-os]\ntype = "raw"\n'
    )
    (robot.fw / "mr_mcxn_t1" / "flex-io.bin").write_bytes(b"\x01" * 100)
    r = robot.build(cli, out, "--previous", out, "-j", "1")
    assert r.exit_code == 3 and "exceeds requested size" in r.stderr and "comp 'gnss'" in r.stderr
    assert tree(out) == before
    assert not [p for p in out.rglob(".*.tmp")]


def test_outputs_never_land_on_inputs(robot, cli, tmp_path):
    r = robot.build(cli, robot.fw)
    assert r.exit_code == 3 and "firmware folder" in r.stderr
    r = robot.build(cli, robot.root)  # release.suit beside the document is fine, but not over the tree's files
    assert r.exit_code == 0, r.stderr
    assert (robot.root / "release.suit").exists()


def test_dependency_tlvs_and_explicit_security_counter(robot, cli, tmp_path):
    (robot.root / "ota.toml").write_text(
        '[images.flex-io]\nsecurity_counter = 42\ndependencies = [{ image = 1, version = "1.0.0+3" }]\n'
        '[images.scout-os]\ntype = "raw"\n'
    )
    out = tmp_path / "rel"
    r = robot.build(cli, out, "--json")
    assert r.exit_code == 0, r.stderr
    data = (out / "mr_mcxn_t1" / "flex-io" / "0.2.0.bin").read_bytes()
    _m, _l, hdr, ptlv, size = struct.unpack_from("<IIHHI", data)
    area = data[hdr + size : hdr + size + ptlv]
    assert struct.unpack_from("<HH", area) == (0x6908, ptlv)
    tlvs, pos = {}, 4
    while pos < len(area):
        kind, length = struct.unpack_from("<HH", area, pos)
        tlvs[kind] = area[pos + 4 : pos + 4 + length]
        pos += 4 + length
    assert struct.unpack("<I", tlvs[0x50]) == (42,)
    assert struct.unpack("<B3xBBHI", tlvs[0x40]) == (1, 1, 0, 0, 3)
    # a lower counter than the previous release's is refused
    (robot.root / "ota.toml").write_text('[images.flex-io]\nsecurity_counter = 41\n[images.scout-os]\ntype = "raw"\n')
    robot.rewrite(cli, flex_version="0.3.0")
    r = robot.build(cli, tmp_path / "rel2", "--previous", out)
    assert r.exit_code == 1 and "security counter went down" in r.stderr and "≥ 42" in r.stderr


def test_ota_toml_typos_are_refused(robot, cli, tmp_path):
    (robot.root / "ota.toml").write_text('[images.flex-io]\nmcuboot_verison = "1.0.0"\n')
    r = robot.build(cli, tmp_path / "rel")
    assert r.exit_code == 3 and "unknown key 'mcuboot_verison'" in r.stderr


def test_intel_hex_input(robot, cli, tmp_path):
    from intelhex import IntelHex

    payload = (robot.fw / "rtk-gnss.bin").read_bytes()
    ih = IntelHex()
    ih.frombytes(payload, offset=0x8000)
    ih.tofile(str(robot.fw / "rtk-gnss.hex"), format="hex")
    (robot.fw / "rtk-gnss.bin").unlink()
    out = tmp_path / "rel"
    assert robot.build(cli, out).exit_code == 0
    data = (out / "mr_mcxn_t1" / "rtk-gnss" / "1.0.0+3.bin").read_bytes()
    _m, _l, hdr, _p, size = struct.unpack_from("<IIHHI", data)
    assert data[hdr : hdr + size] == payload
    shutil.rmtree(out)


def test_previous_release_over_https(robot, cli, tmp_path, serve, tls):
    first = tmp_path / "rel"
    assert robot.build(cli, first, "--previous", RELEASES, "--import-unsigned-history").exit_code == 0
    server = serve("good", root=first)
    robot.rewrite(cli, flex_version="0.3.0")
    out = tmp_path / "rel2"
    url = server.url("/")
    r = robot.build(cli, out, "--previous", url, "--ca-bundle", tls.ca_pem, "--json", "--import-unsigned-history")
    assert r.exit_code == 0, r.stderr
    assert r.json["sequence_number"] == 2
    after = json.loads((out / "mr_mcxn_t1" / "flex-io" / "latest.json").read_text())
    assert [e["version"] for e in after["previous"]] == ["0.2.0", "0.1.0"]
    r = cli(
        "ota",
        "verify",
        out,
        "--key",
        robot.pub,
        "--previous",
        url,
        "--ca-bundle",
        tls.ca_pem,
        "--import-unsigned-history",
    )
    assert r.exit_code == 0, r.stderr
    r = cli(
        "ota",
        "verify",
        first,
        "--key",
        robot.pub,
        "--previous",
        url,
        "--ca-bundle",
        tls.ca_pem,
        "--import-unsigned-history",
    )
    assert r.exit_code == 1 and "sequence-number is not greater" in r.stderr
    # the fleet's own unsigned folder served over https is a previous too (no release.suit: HTTP 404)
    corpus = serve("good", root=RELEASES)
    r = robot.build(
        cli,
        tmp_path / "rel3",
        "--previous",
        corpus.url("/"),
        "--ca-bundle",
        tls.ca_pem,
        "--json",
        "--import-unsigned-history",
    )
    assert r.exit_code == 0, r.stderr
    assert r.json["sequence_number"] == 1
    # an untrusted server is an input error, nothing written
    r = robot.build(cli, tmp_path / "rel4", "--previous", url)
    assert r.exit_code == 3 and not (tmp_path / "rel4").exists()


def test_building_into_a_release_folder_keeps_its_history(robot, cli, tmp_path):
    out = tmp_path / "rel"
    assert robot.build(cli, out, "--previous", RELEASES, "--import-unsigned-history").exit_code == 0
    robot.rewrite(cli, flex_version="0.3.0")
    r = robot.build(
        cli, out, "--json", "--import-unsigned-history"
    )  # no --previous: the folder's own release is the previous one
    assert r.exit_code == 0, r.stderr
    assert r.json["sequence_number"] == 2
    assert any(w["code"] == "previous" for w in r.json["warnings"])
    after = json.loads((out / "mr_mcxn_t1" / "flex-io" / "latest.json").read_text())
    assert [e["version"] for e in after["previous"]] == ["0.2.0", "0.1.0"]
    assert (out / "mr_mcxn_t1" / "flex-io" / "0.2.0.bin").exists()  # the older image stays published


def test_an_older_version_than_the_previous_latest_is_refused(robot, cli, tmp_path):
    out = tmp_path / "rel"
    assert robot.build(cli, out).exit_code == 0
    before = tree(out)
    robot.rewrite(cli, flex_version="0.1.9")
    r = robot.build(cli, out)
    assert r.exit_code == 1 and "version 0.1.9 is older than the previous release's 0.2.0" in r.stderr
    assert tree(out) == before


def test_hostile_inputs_are_refused_without_hanging(robot, cli, tmp_path):
    import os

    out = tmp_path / "rel"
    # a firmware "binary" that is a FIFO, then a symlink out of the firmware folder
    flex = robot.fw / "mr_mcxn_t1" / "flex-io.bin"
    flex.unlink()
    os.mkfifo(flex)
    r = robot.build(cli, out)
    assert r.exit_code == 3 and "FIFO" in r.stderr
    flex.unlink()
    secret = tmp_path / "secret.bin"
    secret.write_bytes(b"not firmware")
    flex.symlink_to(secret)
    r = robot.build(cli, out)
    assert r.exit_code == 3 and "outside the root" in r.stderr
    flex.unlink()
    flex.write_bytes(b"\x00" * 100)
    # ota.toml as a FIFO
    toml = robot.root / "ota.toml"
    toml.unlink()
    os.mkfifo(toml)
    r = robot.build(cli, out)
    assert r.exit_code == 3 and "FIFO" in r.stderr
    assert not out.exists()


def test_two_comps_of_one_board_and_app_share_one_image_but_not_two_versions(robot, cli, tmp_path):
    text = robot.doc.read_text()
    twin = (
        '  <comp name="main2">\n    <board>mr_mcxn_t1</board>\n'
        '    <software name="flex-io"><version>{v}</version></software>\n  </comp>\n</hcdf>'
    )
    robot.doc.write_text(text.replace("</hcdf>", twin.format(v="v0.2.0")))
    assert cli("resolve", robot.doc).exit_code == 0
    r = robot.build(cli, tmp_path / "rel", "--json")
    assert r.exit_code == 0, r.stderr
    flex = next(i for i in r.json["images"] if i["component_id"] == ["mr_mcxn_t1", "flex-io"])
    assert flex["comps"] == ["main", "main2"]
    robot.doc.write_text(text.replace("</hcdf>", twin.format(v="0.3.0")))
    assert cli("resolve", robot.doc).exit_code == 0
    r = robot.build(cli, tmp_path / "rel2")
    assert r.exit_code == 3 and "comps 'main' and 'main2' run mr_mcxn_t1/flex-io at different versions" in r.stderr


def test_a_raw_image_hash_is_its_file_sha256(robot, cli, tmp_path):
    text = robot.doc.read_text()
    raw_sha = hashlib.sha256((robot.fw / "scout-os.bin").read_bytes()).hexdigest()
    robot.doc.write_text(
        text.replace("<version>2026.11</version>", f"<version>2026.11</version><hash>{'0' * 64}</hash>")
    )
    assert cli("resolve", robot.doc).exit_code == 0
    r = robot.build(cli, tmp_path / "rel")
    assert r.exit_code == 1 and "comp 'compute'" in r.stderr and "SHA-256 of the raw image" in r.stderr
    assert f"actual:   {raw_sha}" in r.stderr
    robot.doc.write_text(
        text.replace("<version>2026.11</version>", f"<version>2026.11</version><hash>{raw_sha}</hash>")
    )
    assert cli("resolve", robot.doc).exit_code == 0
    assert robot.build(cli, tmp_path / "rel").exit_code == 0


def test_a_build_interrupted_after_some_images_leaves_the_release_folder_untouched(robot, cli, tmp_path, monkeypatch):
    """Ctrl-C (KeyboardInterrupt) while the second image is being signed: nothing is written."""
    from hcdf_trust.ota import release as release_mod
    from hcdf_trust.ota.keys import load_private
    from hcdf_trust.ota.signer import FileSigner

    out = tmp_path / "rel"
    assert robot.build(cli, out).exit_code == 0
    before = tree(out)
    robot.rewrite(cli, flex_version="0.3.0")
    signed = []
    real = release_mod.sign_image

    def interrupted(*args, **kw):
        if signed:
            raise KeyboardInterrupt
        signed.append(real(*args, **kw))
        return signed[-1]

    monkeypatch.setattr(release_mod, "sign_image", interrupted)
    options = release_mod.BuildOptions(
        firmware_dir=str(robot.fw), out_dir=str(out), signer=FileSigner(load_private(robot.key)), jobs=1
    )
    with pytest.raises(KeyboardInterrupt):
        release_mod.build_release(str(robot.doc), options)
    assert len(signed) == 1
    assert tree(out) == before


def test_same_inputs_give_a_byte_identical_release(tmp_path, cli, monkeypatch):
    """Ed25519 signatures are deterministic and SOURCE_DATE_EPOCH fixes the date: nothing else varies."""
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1767225600")
    robot = make_robot(tmp_path, cli, kind="ed25519")
    a, b = tmp_path / "a", tmp_path / "b"
    assert robot.build(cli, a, "-j", "1").exit_code == 0
    assert robot.build(cli, b).exit_code == 0
    assert tree(a) == tree(b)
    latest = json.loads((a / "mr_mcxn_t1" / "flex-io" / "latest.json").read_text())
    assert latest["latest"]["date"] == "2026-01-01T00:00:00Z"


def test_a_remote_reference_is_fetched_only_under_online(robot, cli, tmp_path, https_server, tls):
    model = b"remote glTF model"
    url = https_server.add("/m.glb", model)
    text = robot.doc.read_text()
    robot.doc.write_text(
        text.replace("</hcdf>", f'  <comp name="extra"><visual><model uri="{url}"/></visual></comp>\n</hcdf>')
    )
    assert cli("resolve", robot.doc, "--ca-bundle", tls.ca_pem, "--cache-dir", tmp_path / "c1").exit_code == 0
    out = tmp_path / "rel"
    r = robot.build(cli, out, "--cache-dir", tmp_path / "c2")
    assert r.exit_code == 3 and "forbids the network" in r.stderr
    assert not out.exists()
    r = robot.build(cli, out, "--cache-dir", tmp_path / "c2", "--online", "--ca-bundle", tls.ca_pem)
    assert r.exit_code == 0, r.stderr
    https_server.add("/m.glb", b"swapped on the server")
    r = robot.build(cli, tmp_path / "rel2", "--cache-dir", tmp_path / "c3", "--online", "--ca-bundle", tls.ca_pem)
    assert r.exit_code == 1 and not (tmp_path / "rel2").exists()


def test_the_same_version_with_another_image_is_refused(robot, cli, tmp_path):
    out = tmp_path / "rel"
    assert robot.build(cli, out).exit_code == 0
    assert robot.build(cli, out).exit_code == 0  # the same image again: fine, history unchanged
    (robot.fw / "mr_mcxn_t1" / "flex-io.bin").write_bytes(b"other firmware, same version")
    r = robot.build(cli, out)
    assert r.exit_code == 3 and "version 0.2.0 was already released with another image: bump the version" in r.stderr


def test_a_previous_latest_json_of_another_device_is_refused(robot, cli, tmp_path):
    prev = tmp_path / "prev"
    shutil.copytree(RELEASES, prev)
    doc = json.loads((prev / "mr_mcxn_t1" / "flex-io" / "latest.json").read_text())
    doc["app"] = "optical-flow"
    (prev / "mr_mcxn_t1" / "flex-io" / "latest.json").write_text(json.dumps(doc))
    r = robot.build(cli, tmp_path / "rel", "--previous", prev, "--import-unsigned-history")
    assert r.exit_code == 3 and "the previous latest.json is for mr_mcxn_t1/optical-flow" in r.stderr


@pytest.mark.parametrize("board", ["../evil", ".", "a/b", "-x"])
def test_a_board_that_cannot_name_a_folder_is_refused(robot, cli, tmp_path, board):
    robot.doc.write_text(robot.doc.read_text().replace("<board>mr_mcxn_t1</board>", f"<board>{board}</board>", 1))
    assert cli("resolve", robot.doc).exit_code == 0
    r = robot.build(cli, tmp_path / "rel")
    assert r.exit_code == 3 and "cannot name a release folder" in r.stderr and "comp 'main'" in r.stderr


def test_a_tree_without_software_is_an_input_error(robot, cli, tmp_path):
    robot.doc.write_text('<?xml version="1.0"?>\n<hcdf version="1.0" name="t"><comp name="c"/></hcdf>\n')
    assert cli("resolve", robot.doc).exit_code == 0
    r = robot.build(cli, tmp_path / "rel")
    assert r.exit_code == 3 and "no <software> entry to build" in r.stderr


def test_an_explicit_sequence_number_must_exceed_the_previous(robot, cli, tmp_path):
    out = tmp_path / "rel"
    assert robot.build(cli, out).exit_code == 0
    (robot.root / "ota.toml").write_text('[release]\nsequence_number = 1\n[images.scout-os]\ntype = "raw"\n')
    robot.rewrite(cli, flex_version="0.3.0")
    r = robot.build(cli, tmp_path / "rel2", "--previous", out)
    assert r.exit_code == 1 and "sequence_number must be greater" in r.stderr and "expected: > 1" in r.stderr
    (robot.root / "ota.toml").write_text('[release]\nsequence_number = 7\n[images.scout-os]\ntype = "raw"\n')
    r = robot.build(cli, tmp_path / "rel2", "--previous", out, "--json")
    assert r.exit_code == 0 and r.json["sequence_number"] == 7


def test_an_unknown_image_type_is_refused(robot, cli, tmp_path):
    (robot.root / "ota.toml").write_text('[images.scout-os]\ntype = "zip"\n')
    r = robot.build(cli, tmp_path / "rel")
    assert r.exit_code == 3 and 'type must be "mcuboot" or "raw"' in r.stderr
