"""``.hcdfz`` bundles: the example robot bundled verifies as its tree does, and every hostile archive
of issue 19 §2 is refused with a message naming the bundle, the entry and expected/actual.

The hostile archives are made here, by a ZIP builder of this file (``_zip``), independent of
``hcdf_trust.bundle.encode``; the readers used as oracles are Info-ZIP's ``unzip -t`` and Python's
``zipfile``.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import struct
import subprocess
import zipfile
import zlib
from pathlib import Path

import pytest

from hcdf_trust import bundle as bundle_mod

from .conftest import PROJECT

ROOT = "scout2.hcdf"


@pytest.fixture
def robot(tmp_path):
    shutil.copytree(PROJECT / "examples", tmp_path / "examples", ignore=shutil.ignore_patterns("out"))
    return tmp_path / "examples" / "robot" / "robot.hcdf"


@pytest.fixture
def bundled(cli, robot, tmp_path):
    out = tmp_path / "scout2.hcdfz"
    r = cli("bundle", robot, out)
    assert r.exit_code == 0, r.stderr
    return out


def _entries(path: Path) -> list[tuple[str, bytes]]:
    with zipfile.ZipFile(path) as z:
        return [(i.filename, z.read(i)) for i in z.infolist()]


def _zip(
    entries: list[tuple[str, bytes]],
    *,
    before: dict[int, bytes] | None = None,
    tail: bytes = b"",
    comment: bytes = b"",
    method: dict[int, int] | None = None,
    external: dict[int, tuple[int, int]] | None = None,
    local_crc: dict[int, int] | None = None,
    size: dict[int, int] | None = None,
    offsets: dict[int, int] | None = None,
) -> bytes:
    """A ZIP of ``entries`` (stored), with the defects asked for: bytes ``before`` entry i (offsets
    kept right, as a self-extracting stub would be), ``tail`` between the last entry and the
    central directory, an archive ``comment``, a ``method`` recorded for entry i, its
    (version made by, external attributes), a ``local_crc`` differing from the central one, a
    recorded ``size`` (both headers) other than the data's, a central ``offsets`` override."""
    before, method, external = before or {}, method or {}, external or {}
    local_crc, size, offsets = local_crc or {}, size or {}, offsets or {}
    out, central = b"", b""
    for i, (name, data) in enumerate(entries):
        out += before.get(i, b"")
        raw = name.encode()
        crc = zlib.crc32(data)
        n = size.get(i, len(data))
        m = method.get(i, 0)
        made_by, ext = external.get(i, (20, 0))
        offset = offsets.get(i, len(out))
        out += struct.pack("<IHHHHHIIIHH", 0x04034B50, 20, 0, m, 0, 0, local_crc.get(i, crc), n, n, len(raw), 0) + raw
        out += data
        central += struct.pack(
            "<IHHHHHHIIIHHHHHII", 0x02014B50, made_by, 20, 0, m, 0, 0, crc, n, n, len(raw), 0, 0, 0, 0, ext, offset
        )
        central += raw
    out += tail
    count = len(entries)
    end = struct.pack("<IHHHHIIH", 0x06054B50, 0, 0, count, count, len(central), len(out), len(comment))
    return out + central + end + comment


def _verify(cli, tmp_path, data: bytes, *extra: str):
    path = tmp_path / "hostile.hcdfz"
    path.write_bytes(data)
    return cli("verify", path, *extra)


# --- the oracles: the example robot, unzip, zipfile, upstream's layout --------------------------


def test_the_example_robot_bundled_verifies_as_its_tree(cli, robot, bundled):
    tree = cli("verify", robot, "--json")
    assert tree.exit_code == 0, tree.stderr
    r = cli("verify", bundled, "--json")
    assert r.exit_code == 0, r.stderr
    files = {a["sha256"] for a in tree.json["artifacts"] if a["kind"] != "include"}
    assert files == {a["sha256"] for a in r.json["artifacts"]}  # the same files, the includes flattened
    assert {a["kind"] for a in r.json["artifacts"]} == {"model", "mesh", "stream-profile", "firmware-manifest"}


def test_a_tampered_tree_gives_the_same_verdict_as_its_bundle(cli, robot, bundled, tmp_path):
    glb = robot.parent / "models" / "chassis.glb"
    entries = _entries(bundled)
    name = next(n for n, _ in entries if n.startswith("assets/chassis_"))
    tampered = [(n, d + b"\0" if n == name else d) for n, d in entries]  # CRCs right: only the pin sees it
    glb.write_bytes(glb.read_bytes() + b"\0")
    tree = cli("verify", robot)
    r = _verify(cli, tmp_path, bundle_mod.encode(tampered))
    assert tree.exit_code == r.exit_code == 1
    assert "digest mismatch" in tree.stderr and "digest mismatch" in r.stderr
    assert f"hostile.hcdfz/{name}" in r.stderr and "expected: 14662db9" in r.stderr
    # ...and a tree that does not verify is not bundled: nothing written
    out = tmp_path / "again.hcdfz"
    assert cli("bundle", robot, out).exit_code == 1
    assert not out.exists()


def test_same_tree_same_bytes_from_any_folder(cli, robot, bundled, tmp_path, monkeypatch):
    monkeypatch.chdir(robot.parent)
    assert cli("bundle", "robot.hcdf", tmp_path / "b.hcdfz").exit_code == 0
    assert (tmp_path / "b.hcdfz").read_bytes() == bundled.read_bytes()


def test_layout_is_upstreams(bundled):
    """Root first, then assets/ sorted, each <stem>_<12 hex>.<ext> (the full 64 where the reference
    has no sha site), all stored, upstream's header fields (version 2.0, MS-DOS host, time 0, no
    attributes, no extra field), document-relative uris with sha256:<hex> pins."""
    with zipfile.ZipFile(bundled) as z:
        infos = z.infolist()
        assert z.testzip() is None
        names = [i.filename for i in infos]
        assert names[0] == ROOT and names[1:] == sorted(names[1:])
        for i in infos:
            assert (i.compress_type, i.create_version, i.create_system, i.extract_version) == (0, 20, 0, 20)
            assert (i.date_time, i.external_attr, i.extra, i.flag_bits) == ((1980, 0, 0, 0, 0, 0), 0, b"", 0)
        for name in names[1:]:
            data = z.read(name)
            stem = name.rsplit(".", 1)[0]
            hexpart = stem.rsplit("_", 1)[1]
            assert name.startswith("assets/") and len(hexpart) in (12, 64)
            assert hashlib.sha256(data).hexdigest().startswith(hexpart)
        root = z.read(ROOT).decode()
    assert "<include" not in root and 'sha="sha256:' in root and 'uri="assets/chassis_14662db9eb3d.glb"' in root
    assert names == [
        ROOT,
        "assets/arm-ctrl.latest_83663e8b3d733668f11bbffc86b1e54a785ae9442b436a1fbf0027dff8b89fd5.json",
        "assets/arm-link_8b2f0ebf68f1.glb",
        "assets/camera-head_5f3fa4f7649d.glb",
        "assets/chassis-hull_6ac1a9aa6a7c.stl",
        "assets/chassis_14662db9eb3d.glb",
        "assets/gripper_adaa3b076b88.glb",
        "assets/operational.streams_03afc225badf.xml",
    ]


def test_unzip_accepts_it(bundled):
    assert shutil.which("unzip"), "Info-ZIP unzip is not installed (.ci/apt-packages lists it)"
    r = subprocess.run(["unzip", "-t", str(bundled)], capture_output=True, text=True, check=False)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "No errors detected" in r.stdout


def test_the_test_builder_agrees_with_encode(bundled):
    """``_zip`` without defects writes what ``encode`` writes (so each defect below is the only one)."""
    entries = _entries(bundled)
    assert _zip(entries) == bundle_mod.encode(entries) == bundled.read_bytes()


# --- structure: exit 3, naming the bundle and the entry -------------------------------------------


def _hostile_cases(entries):
    root, asset = entries[0], entries[1]
    return {
        "compressed": (_zip(entries, method={1: 8}), "is compressed", asset[0]),
        "absolute": (_zip([root, ("/etc/passwd", b"x")]), "absolute path", "/etc/passwd"),
        "dot-dot": (_zip([root, ("assets/../../x", b"x")]), "'..' segment", "assets/../../x"),
        "backslash": (_zip([root, ("assets\\..\\x", b"x")]), "backslash", "assets\\\\..\\\\x"),
        "drive": (_zip([root, ("C:x", b"x")]), "drive letter", "C:x"),
        "duplicate": (_zip([root, asset, asset]), "duplicate name", asset[0]),
        "case-duplicate": (_zip([root, asset, (asset[0].upper(), asset[1])]), "but for case", asset[0].upper()),
        "symlink": (_zip(entries, external={1: (0x0314, 0o120777 << 16)}), "a symlink", asset[0]),
        "fifo": (_zip(entries, external={1: (0x0314, 0o010644 << 16)}), "special file", asset[0]),
        "directory": (_zip([root, ("assets/", b"")]), "directory", "assets/"),
        "local-header": (_zip(entries, local_crc={1: 1}), "local header disagrees", asset[0]),
        "data-before": (_zip(entries, before={0: b"#!/bin/sh\nexit 0\n"}), "data before the first entry", root[0]),
        "data-between": (_zip(entries, before={2: b"hidden"}), "gap or an overlap", entries[2][0]),
        "data-after": (_zip(entries, tail=b"<hcdf/>"), "data after the last entry", "7 bytes"),
        "comment": (_zip(entries, comment=b"hi"), "a comment after it", "0x6054b50"),
        "comment-length": (_zip(entries, comment=b"hi")[:-2], "has a comment", "2 bytes"),
        "overlap": (_zip([root, asset, asset[:1] + (asset[1],)], offsets={2: 0}), "duplicate name", asset[0]),
        "bomb": (_zip([root, asset, ("assets/b_0.glb", asset[1])], offsets={2: 0}), "gap or an overlap", "starts"),
        "size": (_zip(entries[:2], size={1: len(asset[1]) + 100}), "runs past", asset[0]),
        "crc": (_zip(entries[:1]).replace(b"<hcdf ", b"<hcdX ", 1), "CRC-32", root[0]),
        "root-not-first": (_zip([asset, root]), "root .hcdf is not the first entry", ROOT),
        "not-a-zip": (b"<hcdf/>" * 10, "not the end-of-central-directory", "hostile.hcdfz"),
        "empty": (_zip([]), "no entries", "hostile.hcdfz"),
    }


@pytest.mark.parametrize(
    "case",
    [
        "compressed",
        "absolute",
        "dot-dot",
        "backslash",
        "drive",
        "duplicate",
        "case-duplicate",
        "symlink",
        "fifo",
        "directory",
        "local-header",
        "data-before",
        "data-between",
        "data-after",
        "comment",
        "comment-length",
        "overlap",
        "bomb",
        "size",
        "crc",
        "root-not-first",
        "not-a-zip",
        "empty",
    ],
)
def test_hostile_structure_is_refused(cli, bundled, tmp_path, case):
    data, what, names = _hostile_cases(_entries(bundled))[case]
    if case in ("data-before",):  # the oracle: zipfile is lenient here, which is why we check it ourselves
        path = tmp_path / "lenient.zip"
        path.write_bytes(data)
        assert zipfile.ZipFile(path).testzip() is None
    r = _verify(cli, tmp_path, data, "--json")
    assert r.exit_code == 3, r.stdout
    [error] = r.json["errors"]
    assert error["code"] == "bundle-format"
    assert what in error["message"] and "hostile.hcdfz" in error["message"], error
    assert names in " ".join(str(error.get(k)) for k in ("message", "expected", "actual")), error


def test_caps_on_entries_and_bytes(cli, bundled, tmp_path, monkeypatch):
    data = bundled.read_bytes()
    monkeypatch.setattr(bundle_mod, "MAX_ENTRIES", 7)
    r = _verify(cli, tmp_path, data)
    assert r.exit_code == 3 and "8 entries, more than the cap of 7" in r.stderr
    monkeypatch.setattr(bundle_mod, "MAX_ENTRIES", 8)
    monkeypatch.setattr(bundle_mod, "MAX_BYTES", len(data) - 1)
    r = _verify(cli, tmp_path, data)
    assert r.exit_code == 3 and f"{len(data)} bytes, more than the cap of {len(data) - 1}" in r.stderr
    monkeypatch.setattr(bundle_mod, "MAX_BYTES", len(data))
    assert _verify(cli, tmp_path, data).exit_code == 0


# --- content: exit 1 ------------------------------------------------------------------------------


def test_an_asset_no_reference_uses_is_refused(cli, bundled, tmp_path):
    extra = b"not referenced"
    name = f"assets/extra_{hashlib.sha256(extra).hexdigest()[:12]}.bin"
    r = _verify(cli, tmp_path, bundle_mod.encode([*_entries(bundled), (name, extra)]), "--json")
    assert r.exit_code == 1
    [error] = r.json["errors"]
    assert error["code"] == "bundle-integrity" and name in error["message"] and "not referenced" in error["message"]


def test_a_reference_to_something_not_in_the_bundle_is_refused(cli, bundled, tmp_path):
    entries = [(n, d) for n, d in _entries(bundled) if not n.startswith("assets/gripper_")]
    r = _verify(cli, tmp_path, bundle_mod.encode(entries), "--json")
    assert r.exit_code == 1
    [error] = r.json["errors"]
    assert error["code"] == "bundle-missing" and "assets/gripper_adaa3b076b88.glb" in error["message"]
    assert "hostile.hcdfz" in error["message"] and error["line"] is not None


def test_a_remote_reference_or_an_include_in_a_bundle_is_refused(cli, bundled, tmp_path):
    entries = _entries(bundled)
    root = entries[0][1].replace(
        b'uri="assets/chassis_14662db9eb3d.glb"', b'uri="https://example.com/chassis_14662db9eb3d.glb"'
    )
    r = _verify(cli, tmp_path, bundle_mod.encode([(ROOT, root), *entries[1:]]))
    assert r.exit_code == 1
    assert "https://example.com/chassis_14662db9eb3d.glb is not in the bundle" in r.stderr
    assert "entry 'assets/chassis_14662db9eb3d.glb' is not referenced" in r.stderr
    inc = entries[0][1].replace(b"</hcdf>", b'<include uri="assets/gripper_adaa3b076b88.glb"/></hcdf>')
    r = _verify(cli, tmp_path, bundle_mod.encode([(ROOT, inc), *entries[1:]]))
    assert r.exit_code != 0 and "<include uri='assets/gripper_adaa3b076b88.glb'> in a bundle" in r.stderr


def test_a_name_whose_hash_is_not_its_content_is_refused(cli, bundled, tmp_path):
    entries = _entries(bundled)
    old = "assets/chassis_14662db9eb3d.glb"
    new = "assets/chassis_000000000000.glb"
    root = entries[0][1].replace(old.encode(), new.encode())
    renamed = [(ROOT, root), *((new if n == old else n, d) for n, d in entries[1:])]
    r = _verify(cli, tmp_path, bundle_mod.encode(renamed), "--json")
    assert r.exit_code == 1
    [error] = r.json["errors"]
    assert "the hash in its name is not its content's" in error["message"]
    assert error["expected"] == "000000000000" and error["actual"].startswith("14662db9")


def test_a_firmware_manifest_is_pinned_by_its_name(cli, bundled, tmp_path):
    """<firmware-manifest-uri> has no sha site: the full digest in the entry's name is its pin."""
    entries = _entries(bundled)
    name = next(n for n, _ in entries if n.startswith("assets/arm-ctrl.latest_"))
    tampered = [(n, d.replace(b"1.4.2", b"9.9.9") if n == name else d) for n, d in entries]
    r = _verify(cli, tmp_path, bundle_mod.encode(tampered))
    assert r.exit_code == 1 and "digest mismatch" in r.stderr and name in r.stderr


def test_bundle_refuses_a_destination_that_is_not_hcdfz_or_an_input(cli, robot, tmp_path):
    assert cli("bundle", robot, tmp_path / "x.zip").exit_code == 2
    glb = robot.parent / "models" / "chassis.glb"
    before = glb.read_bytes()
    assert cli("bundle", robot, robot.parent / "robot.hcdfz").exit_code == 0
    link = robot.parent / "models" / "chassis.hcdfz"
    link.symlink_to(glb)
    r = cli("bundle", robot, link)
    assert r.exit_code == 3 and "input" in r.stderr
    assert glb.read_bytes() == before


def test_tree_flags_do_not_apply_to_a_bundle(cli, bundled, tmp_path):
    r = cli("verify", bundled, "--root", tmp_path)
    assert r.exit_code == 3 and "--root does not apply to a bundle" in r.stderr


# --- every verb that reads a description reads a bundle, with the tree's verdict -----------------


def test_every_verb_gives_the_trees_verdict_on_the_bundle(cli, robot, bundled, tmp_path):
    policy = robot.parent.parent / "audit-policy.toml"
    for verb in (
        ["resolve"],
        ["validate"],
        ["audit", "--policy", policy],
        ["macsec", "plan"],
        ["sbom", "--format", "cyclonedx"],
    ):
        tree, packed = cli(*verb, robot), cli(*verb, bundled)
        assert (tree.exit_code, packed.exit_code) == (0, 0), (verb, tree.stderr, packed.stderr)
    assert not (bundled.parent / "scout2.hcdfz.lock").exists()  # resolve writes no lock for a bundle
    assert cli("resolve", bundled, "--out", tmp_path / "flat.hcdf").exit_code == 2


def test_ota_build_and_the_sbom_record_the_bundles_digest(cli, robot, bundled, tmp_path):
    digest = hashlib.sha256(bundled.read_bytes()).hexdigest()
    sbom = cli("sbom", bundled, "--format", "cyclonedx")
    props = {p["name"]: p["value"] for p in json.loads(sbom.stdout)["metadata"]["properties"]}
    assert props["hcdf:bundle-sha256"] == props["hcdf:lock-sha256"] == digest
    key = tmp_path / "k.pem"
    assert cli("ota", "keygen", "--type", "ecdsa-p256", "-o", key).exit_code == 0
    firmware = robot.parent / "firmware"
    r = cli(
        "ota", "build", bundled, "--config", robot.parent / "ota.toml", "--firmware-dir", firmware,
        "--key", key, "--out", tmp_path / "rel", "--base-url", "https://firmware.example.com/scout2",
    )  # fmt: skip
    assert r.exit_code == 0, r.stderr
    record = json.loads((tmp_path / "rel" / "release.suit.json").read_text())
    assert record["hcdf"]["lock_sha256"] == digest
    assert cli("ota", "verify", tmp_path / "rel", "--key", tmp_path / "k.pub.pem").exit_code == 0


# --- remote files and pins --------------------------------------------------------------------


def _doc(folder: Path, *models: tuple[str, str | None]) -> Path:
    comps = "".join(
        f'<comp name="c{i}"><visual name="v"><model uri="{uri}"{f" sha={pin!r}" if pin else ""}/></visual></comp>'
        for i, (uri, pin) in enumerate(models)
    )
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "r.hcdf").write_text(f'<?xml version="1.0"?>\n<hcdf version="1.0" name="r">{comps}</hcdf>\n')
    return folder / "r.hcdf"


def test_remote_files_are_fetched_into_the_bundle(cli, https_server, tls, tmp_path):
    data = b"glTF" + bytes(range(200))
    digest = hashlib.sha256(data).hexdigest()
    url = https_server.add("/models/wheel.glb", data)
    doc = _doc(tmp_path / "w", (url, digest))
    out, cache = tmp_path / "r.hcdfz", tmp_path / "cache"
    r = cli("bundle", doc, out, "--cache-dir", cache)  # offline (the default) and not cached: nothing written
    assert r.exit_code == 3 and not out.exists()
    r = cli("bundle", doc, out, "--online", "--cache-dir", cache, "--ca-bundle", tls.ca_pem)
    assert r.exit_code == 0, r.stderr
    entries = dict(_entries(out))
    assert entries[f"assets/wheel_{digest[:12]}.glb"] == data
    assert b"https://" not in entries["r.hcdf"]
    assert cli("verify", out).exit_code == 0
    # the same tree bundled again from the cache alone (offline, no socket) is the same bytes
    https_server.close()
    again = tmp_path / "again.hcdfz"
    assert cli("bundle", doc, again, "--cache-dir", cache).exit_code == 0
    assert again.read_bytes() == out.read_bytes()


def test_a_reference_neither_the_document_nor_a_lock_pins_is_not_bundled(cli, tmp_path):
    folder = tmp_path / "t"
    (folder / "m").mkdir(parents=True)
    (folder / "m" / "a.glb").write_bytes(b"glTF-a")
    doc = _doc(folder, ("m/a.glb", None))
    r = cli("bundle", doc, tmp_path / "x.hcdfz")
    assert r.exit_code == 1 and "m/a.glb is not pinned" in r.stderr
    assert not (tmp_path / "x.hcdfz").exists()
    assert cli("resolve", doc).exit_code == 0  # the lock now pins it (trust on first use)
    assert cli("bundle", doc, tmp_path / "x.hcdfz").exit_code == 0
    assert cli("verify", tmp_path / "x.hcdfz").exit_code == 0


def test_pin_refuses_a_bundle_it_cannot_edit(cli, bundled):
    r = cli("pin", "--write", bundled)
    assert r.exit_code == 3 and "a bundle: every reference in it is pinned already" in r.stderr


def test_a_non_ascii_name_without_the_utf8_flag_is_refused(cli, bundled, tmp_path):
    entries = _entries(bundled)
    r = _verify(cli, tmp_path, _zip([entries[0], ("assets/ré_0.glb", b"x")]))
    assert r.exit_code == 3 and "not ASCII and not flagged UTF-8" in r.stderr


def test_a_tree_too_large_for_a_bundle_is_not_written(cli, robot, tmp_path, monkeypatch):
    monkeypatch.setattr(bundle_mod, "MAX_BYTES", 10_000)
    r = cli("bundle", robot, tmp_path / "big.hcdfz")
    assert r.exit_code == 3 and "more than a bundle holds" in r.stderr
    assert not (tmp_path / "big.hcdfz").exists()


@pytest.mark.parametrize("delta", [+10, -10])
def test_a_bundle_that_changes_size_while_read_is_refused(bundled, monkeypatch, delta):
    """The size when opened is what is read, exactly: a file that shrank (a short read) or grew
    (a byte left after it) between the fstat and the read is refused, not checked in part."""
    import os

    from hcdf_trust import localfile
    from hcdf_trust.errors import InputError

    real = os.fstat

    def fstat(fd):
        st = real(fd)
        return os.stat_result((*st[:6], st.st_size + delta, *st[7:]))

    monkeypatch.setattr(localfile.os, "fstat", fstat)
    with pytest.raises(InputError, match="changed size while it was read"):
        bundle_mod.read_archive(bundled)


def test_bundle_json_and_an_unchanged_bundle_is_left_alone(cli, robot, bundled):
    before = bundled.stat()
    r = cli("bundle", robot, bundled, "--json")
    assert r.exit_code == 0, r.stderr
    out = r.json
    assert out["ok"] is True and out["errors"] == [] and out["wrote"] == [] and len(out["unchanged"]) == 1
    assert out["sha256"] == hashlib.sha256(bundled.read_bytes()).hexdigest() and out["size"] == before.st_size
    assert [e["name"] for e in out["entries"]] == [n for n, _ in _entries(bundled)]
    after = bundled.stat()
    assert (after.st_ino, after.st_mtime_ns) == (before.st_ino, before.st_mtime_ns)


def test_bundle_replaces_a_bundle_but_never_a_document(cli, robot, bundled, tmp_path):
    from hcdf_trust.outputs import BUNDLE, kind_of

    assert kind_of(bundled.read_bytes()) == BUNDLE
    (robot.parent / "models" / "chassis.glb").write_bytes(b"glTF-new")  # another tree: other bytes
    r = cli("bundle", robot, bundled)
    assert r.exit_code == 1  # the tree no longer verifies: the old bundle stays
    doc = tmp_path / "looks.hcdfz"
    doc.write_text('<hcdf version="1.0"/>')
    r = cli("bundle", robot.parent / "assemblies" / "sensor-head.hcdf", doc, "--root", robot.parent)
    assert r.exit_code == 3 and "is an HCDF document: refusing to replace it" in r.stderr
