"""Attacks on ``.hcdfz`` bundles (issue 19 §2), through the CLI, beyond tests/test_bundle.py.

The archives are built here by ``_archive``, a ZIP writer of this file that can get every field
wrong on purpose (it shares no code with ``hcdf_trust.bundle``). A case that passes documents a
defence; a case marked ``xfail(strict=True)`` is a hole found by this attack, with the finding in
its reason: the builder drops the mark when the hole is closed.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import struct
import subprocess
import sys
import unicodedata
import zipfile
import zlib
from dataclasses import dataclass, field, replace
from pathlib import Path

import pytest

from .conftest import PROJECT

ROOT = "scout2.hcdf"
CHASSIS = "assets/chassis_14662db9eb3d.glb"


# --- a ZIP writer that can lie ------------------------------------------------------------------


@dataclass
class Z:
    """One entry and every field of its two headers; ``None`` means "what a honest writer writes"."""

    name: str | bytes
    data: bytes
    local_name: bytes | None = None
    flags: int = 0
    local_flags: int | None = None
    method: int = 0
    made_by: int = 20
    needed: int = 20
    external: int = 0
    internal: int = 0
    time: int = 0
    date: int = 0
    crc: int | None = None
    size: int | None = None  # both sizes, both headers
    central_extra: bytes = b""
    local_extra: bytes = b""
    comment: bytes = b""
    before: bytes = b""  # bytes before its local header (offsets kept right)

    @property
    def raw(self) -> bytes:
        return self.name if isinstance(self.name, bytes) else self.name.encode()


@dataclass
class Tail:
    """What follows the entries: extra records between them and the end record, the end record's fields."""

    between: bytes = b""  # after the central directory, before the end record (cd_size keeps honest)
    count: int | None = None
    count_disk: int | None = None
    cd_size_delta: int = 0
    comment: bytes = b""
    comment_len: int | None = None
    after: bytes = b""
    extra: list[bytes] = field(default_factory=list)


def _archive(entries: list[Z], tail: Tail | None = None) -> bytes:
    tail = tail or Tail()
    out, central = b"", b""
    for e in entries:
        out += e.before
        offset = len(out)
        crc = zlib.crc32(e.data) if e.crc is None else e.crc
        n = len(e.data) if e.size is None else e.size
        lname = e.raw if e.local_name is None else e.local_name
        lflags = e.flags if e.local_flags is None else e.local_flags
        out += struct.pack(
            "<IHHHHHIIIHH", 0x04034B50, e.needed, lflags, e.method, e.time, e.date, crc, n, n, len(lname),
            len(e.local_extra),
        )  # fmt: skip
        out += lname + e.local_extra + e.data
        central += struct.pack(
            "<IHHHHHHIIIHHHHHII", 0x02014B50, e.made_by, e.needed, e.flags, e.method, e.time, e.date, crc, n, n,
            len(e.raw), len(e.central_extra), len(e.comment), 0, e.internal, e.external, offset,
        )  # fmt: skip
        central += e.raw + e.central_extra + e.comment
    cd_offset = len(out)
    count = len(entries) if tail.count is None else tail.count
    disk = count if tail.count_disk is None else tail.count_disk
    comment_len = len(tail.comment) if tail.comment_len is None else tail.comment_len
    end = struct.pack(
        "<IHHHHIIH", 0x06054B50, 0, 0, disk, count, len(central) + tail.cd_size_delta, cd_offset, comment_len
    )
    return out + central + tail.between + end + tail.comment + tail.after


def _zip64_eocd(count: int, cd_size: int, cd_offset: int, at: int) -> bytes:
    """A ZIP64 end record at offset ``at`` and its locator (APPNOTE 4.3.14, 4.3.15)."""
    record = struct.pack("<IQHHIIQQQQ", 0x06064B50, 44, 45, 45, 0, 0, count, count, cd_size, cd_offset)
    return record + struct.pack("<IIQI", 0x07064B50, 0, at, 1)


# --- fixtures -------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def pristine(tmp_path_factory):
    """The example robot bundled once, as (name, bytes) entries; and its tree, for the tree's verdicts."""
    from click.testing import CliRunner

    from hcdf_trust.cli import main

    base = tmp_path_factory.mktemp("pristine")
    shutil.copytree(PROJECT / "examples", base / "examples", ignore=shutil.ignore_patterns("out"))
    out = base / "scout2.hcdfz"
    env = {"XDG_CACHE_HOME": str(base / "cache")}
    r = CliRunner().invoke(main, ["bundle", str(base / "examples" / "robot" / "robot.hcdf"), str(out)], env=env)
    assert r.exit_code == 0, r.output
    with zipfile.ZipFile(out) as z:
        return [(i.filename, z.read(i)) for i in z.infolist()]


@pytest.fixture
def robot(tmp_path):
    shutil.copytree(PROJECT / "examples", tmp_path / "examples", ignore=shutil.ignore_patterns("out"))
    return tmp_path / "examples" / "robot" / "robot.hcdf"


def _zs(pristine) -> list[Z]:
    return [Z(n, d) for n, d in pristine]


def _root(pristine) -> bytes:
    return pristine[0][1]


def _renamed(pristine, old: str, new: str | bytes, **fields) -> list[Z]:
    """The pristine bundle with entry ``old`` renamed to ``new`` everywhere (entry and reference)."""
    shown = new if isinstance(new, str) else new.decode("utf-8", "surrogateescape")
    root = _root(pristine).replace(f'"{old}"'.encode(), f'"{shown}"'.encode("utf-8", "surrogateescape"))
    assert root != _root(pristine)
    zs = [Z(ROOT, root)]
    for n, d in pristine[1:]:
        zs.append(Z(new, d, **fields) if n == old else Z(n, d))
    return zs


def _verify(cli, tmp_path, data: bytes, *extra, name: str = "hostile.hcdfz"):
    path = tmp_path / name
    path.write_bytes(data)
    return cli("verify", path, "--json", *extra)


def _refused(r, code: str = "bundle-format", exit_code: int = 3) -> dict:
    assert r.exit_code == exit_code, (r.exit_code, r.stdout, r.stderr)
    errors = r.json["errors"]
    assert errors and all(e["code"] == code for e in errors), errors
    assert all("hostile.hcdfz" in e["message"] for e in errors), errors
    return errors[0]


def test_the_writer_of_this_file_writes_what_the_bundle_verb_writes(cli, pristine, tmp_path):
    """No defect asked, no defect written: each case below differs from a good bundle in what it names."""
    good = _archive(_zs(pristine))
    r = _verify(cli, tmp_path, good)
    assert r.exit_code == 0, r.stderr
    from hcdf_trust.bundle import encode

    assert good == encode(list(pristine))


# --- structure the builder's tests do not cover: exit 3, bundle-format ----------------------------

ZIP64_EXTRA = struct.pack("<HHQQ", 0x0001, 16, 0, 0)  # sizes in the ZIP64 field, as zip -fz writes them


def _zip64_record(zs: list[Z]) -> bytes:
    """The honest archive with a ZIP64 end record and locator between the central directory and the end record."""
    plain = _archive(zs)
    cd_offset, cd_size = struct.unpack_from("<II", plain, len(plain) - 10)
    return _archive(zs, Tail(between=_zip64_eocd(len(zs), cd_size, cd_offset, cd_offset + cd_size)))


def _two_end_records(zs: list[Z]) -> bytes:
    """The real end record, whose comment is a second, fake end record with no comment (the last 22 bytes)."""
    plain = _archive(zs)
    return plain[:-2] + struct.pack("<H", 22) + plain[-22:]


def _structure_cases(pristine):
    zs = _zs(pristine)
    root, chassis = zs[0], next(z for z in zs if z.name == CHASSIS)
    i = zs.index(chassis)

    def one(**fields):
        return [*zs[:i], replace(chassis, **fields), *zs[i + 1 :]]

    nfd = unicodedata.normalize("NFD", "é")
    return {
        # ZIP64, however it is spelt
        "zip64-extra-central": (_archive(one(central_extra=ZIP64_EXTRA)), "extra field"),
        "zip64-extra-local": (_archive(one(local_extra=ZIP64_EXTRA)), "extra field length"),
        "zip64-end-record": (_zip64_record(zs), "does not end where the end record starts"),
        "zip64-count": (_archive(zs, Tail(count=0xFFFF, count_disk=0xFFFF)), "ZIP64"),
        "unknown-extra-field": (_archive(one(central_extra=b"UT\x05\x00\x01\x00\x00\x00\x00")), "extra field"),
        # the end record lies
        "count-low": (_archive(zs, Tail(count=len(zs) - 1, count_disk=len(zs) - 1)), "more than its records"),
        "count-high": (_archive(zs, Tail(count=len(zs) + 1, count_disk=len(zs) + 1)), "truncated"),
        "count-disk-differs": (_archive(zs, Tail(count_disk=len(zs) - 1)), "multi-disk"),
        "cd-size-short": (_archive(zs, Tail(cd_size_delta=-46)), "does not end where"),
        "two-end-records": (_two_end_records(zs), "does not end where"),
        "second-archive-appended": (_archive(zs) + _archive(zs[:1]), "does not end where"),
        "entry-comment": (_archive(one(comment=b"hidden")), "comment"),
        # the two headers name the entry differently
        "local-name-case": (_archive(one(local_name=CHASSIS.upper().encode())), "name"),
        "local-name-nfd": (
            _archive(
                _renamed(
                    pristine,
                    CHASSIS,
                    f"assets/caf{'é'}_14662db9eb3d.glb",
                    local_name=(f"assets/caf{nfd}_14662db9eb3d.glb".encode()),
                )
            ),
            "name",
        ),  # fmt: skip
        "local-name-fullwidth-dot": (_archive(one(local_name=CHASSIS.replace(".", "\uff0e").encode())), "name"),
        "local-name-nul-suffix": (_archive(one(local_name=CHASSIS.encode() + b"\0")), "name"),
        "local-utf8-flag-only": (_archive(one(local_flags=0x800)), "flags"),
        # names a honest writer never writes
        "nul": (_archive(_renamed(pristine, CHASSIS, "assets/chassis\0_14662db9eb3d.glb")), "control character"),
        "newline": (_archive(_renamed(pristine, CHASSIS, "assets/chassis\n_14662db9eb3d.glb")), "control"),
        "dot-segment": (_archive(_renamed(pristine, CHASSIS, "assets/./chassis_14662db9eb3d.glb")), "'.'"),
        "empty-segment": (_archive(_renamed(pristine, CHASSIS, "assets//chassis_14662db9eb3d.glb")), "empty"),
        "trailing-slash": (_archive([*zs, Z("assets/dir/", b"")]), "directory entry"),
        "directory-attribute": (_archive(one(external=0x10)), "a directory"),
        "not-utf8": (_archive(_renamed(pristine, CHASSIS, b"assets/caf\xe9_14662db9eb3d.glb")), "not ASCII"),
        # flags
        "encrypted": (_archive(one(flags=0x1)), "flags"),
        "data-descriptor": (_archive(one(flags=0x8)), "flags"),
        "strong-encryption": (_archive(one(flags=0x41)), "flags"),
        "aes-method": (_archive(one(method=99)), "compressed"),
        # sizes and checksums
        "crc-wrong-size-right": (_archive(one(crc=zlib.crc32(chassis.data) ^ 1)), "CRC-32"),
        "huge-declared-size": (_archive(one(size=0xFFFFFFFE)), "runs past"),
        "zip64-entry-sizes": (_archive(one(size=0xFFFFFFFF, central_extra=ZIP64_EXTRA)), "extra field"),
        "size-0xfffffff0": (_archive(one(size=0xFFFFFFF0)), "runs past"),
        "size-short": (_archive(one(size=len(chassis.data) - 1)), "CRC-32"),
        "root-only-local-header": (_archive([root])[: 30 + len(ROOT)], "not the end-of-central-directory"),
        "truncated-last-byte": (_archive(zs)[:-1], "not the end-of-central-directory"),
    }


STRUCTURE = [
    "zip64-extra-central", "zip64-extra-local", "zip64-end-record", "zip64-count", "unknown-extra-field",
    "count-low", "count-high", "count-disk-differs", "cd-size-short", "two-end-records", "second-archive-appended",
    "entry-comment", "local-name-case", "local-name-nfd", "local-name-fullwidth-dot", "local-name-nul-suffix",
    "local-utf8-flag-only", "nul", "newline", "dot-segment", "empty-segment", "trailing-slash",
    "directory-attribute", "not-utf8", "encrypted", "data-descriptor", "strong-encryption", "aes-method",
    "crc-wrong-size-right", "huge-declared-size", "zip64-entry-sizes", "size-0xfffffff0", "size-short",
    "root-only-local-header", "truncated-last-byte",
]  # fmt: skip


@pytest.mark.parametrize("case", STRUCTURE)
def test_hostile_structure_beyond_the_builders_cases_is_refused(cli, pristine, tmp_path, case):
    data, what = _structure_cases(pristine)[case]
    error = _refused(_verify(cli, tmp_path, data))
    assert what in error["message"] + str(error.get("expected")) + str(error.get("actual")), error


# --- the writer writes only what its reader reads -------------------------------------------------


@pytest.mark.parametrize("cap", ["MAX_BYTES", "MAX_ENTRIES"])
def test_the_writer_refuses_a_bundle_its_reader_would_refuse(cli, robot, tmp_path, monkeypatch, cap):
    """Over the reader's caps the writer must stop, with nothing written (the caps made small here)."""
    from hcdf_trust import bundle as bundle_mod

    out = tmp_path / "big.hcdfz"
    monkeypatch.setattr(bundle_mod, cap, 5 if cap == "MAX_ENTRIES" else 10_000)
    r = cli("bundle", robot, out)
    assert r.exit_code != 0 and not out.exists(), (r.exit_code, r.stderr)
    assert "more than a bundle holds" in r.stderr


# --- names and header fields the writer never writes ----------------------------------------------
# The writer names every asset ``assets/<[0-9A-Za-z._-]+>`` (safe_stem) and writes every header field
# as upstream does (version 2.0, MS-DOS host, no attributes, time 0). The reader's docstring promises
# it "accepts exactly the archives the writer writes": a name outside that alphabet is refused (exit 3).


@pytest.mark.parametrize(
    "name",
    [
        # NTFS: 'chassis' with an alternate data stream 'x_14662db9eb3d.glb' (the file itself is empty)
        pytest.param("assets/chassis:x_14662db9eb3d.glb", id="ntfs-stream"),
        # Windows: a folder named after a device cannot be created
        pytest.param("assets/con/chassis_14662db9eb3d.glb", id="windows-device"),
        # Windows' best-fit mapping turns U+FF0E into '.' for an ANSI extractor: '../chassis...' ("WorstFit")
        pytest.param("assets/\uff0e\uff0e/chassis_14662db9eb3d.glb", id="fullwidth-dot-dot"),
        pytest.param("assets/sub/chassis_14662db9eb3d.glb", id="subfolder"),
        pytest.param("assets/chassis\u0085_14662db9eb3d.glb", id="c1-control"),
        pytest.param("assets/chassis\u202e_14662db9eb3d.glb", id="bidi-override"),
        pytest.param("assets/chassis_14662db9eb3d.glb.", id="trailing-dot"),
    ],
)  # fmt: skip
def test_a_name_the_writer_never_writes_is_refused(cli, pristine, tmp_path, name):
    r = _verify(cli, tmp_path, _archive(_renamed(pristine, CHASSIS, name, flags=0x800)))
    assert r.exit_code in (1, 3), (r.exit_code, r.stderr)
    assert r.json["errors"], r.stdout


def test_the_writer_names_every_asset_in_the_alphabet_its_reader_accepts():
    """The extension was kept as found (``m.gl b``): the reader would refuse the writer's own bundle."""
    from hcdf_trust.bundle import _WRITTEN_NAME, asset_name

    sha = hashlib.sha256(b"x").hexdigest()
    for source in ("dir/m.gl b", "caf\u00e9.st\uff0el", "m.a:b", "con"):
        name = asset_name(source, sha, full=False)
        assert _WRITTEN_NAME.fullmatch(name), name


def test_names_equal_but_for_unicode_normalization_are_refused_as_case_duplicates_are(cli, pristine, tmp_path):
    nfc = "assets/caf\u00e9_14662db9eb3d.glb"
    nfd = unicodedata.normalize("NFD", nfc)
    assert nfc != nfd and nfc.casefold() != nfd.casefold()  # the case rule does not see them
    chassis = dict(pristine)[CHASSIS]
    sha = hashlib.sha256(chassis).hexdigest()
    root = _root(pristine).replace(f'"{CHASSIS}"'.encode(), f'"{nfc}"'.encode())
    camera = next(n for n, _ in pristine if n.startswith("assets/camera-head_"))
    camera_sha = hashlib.sha256(dict(pristine)[camera]).hexdigest()
    root = root.replace(
        f'uri="{camera}" sha="sha256:{camera_sha}"'.encode(), f'uri="{nfd}" sha="sha256:{sha}"'.encode()
    )
    zs = [Z(ROOT, root), *(Z(n, d) for n, d in pristine[1:] if n not in (CHASSIS, camera))]
    zs += [Z(nfc, chassis, flags=0x800), Z(nfd, chassis, flags=0x800)]
    error = _refused(_verify(cli, tmp_path, _archive(zs)))
    assert "case" in error["message"] or "normaliz" in error["message"], error


@pytest.mark.parametrize(
    "fields, oracle",
    [
        # Info-ZIP restores the mode: the verified mesh lands world-writable for anyone to swap afterwards
        pytest.param({"made_by": 0x0314, "external": 0o100777 << 16}, "mode", id="mode-0777"),
        pytest.param({"made_by": 0x0314, "external": 0o104755 << 16}, None, id="setuid"),
        # Info-ZIP skips an entry that needs a later version: it reads a bundle without the file we verified
        pytest.param({"needed": 63}, "skipping", id="version-needed-6.3"),
    ],
)
def test_header_fields_the_writer_never_writes_are_refused(cli, pristine, tmp_path, fields, oracle):
    zs = [replace(z, **fields) if z.name == CHASSIS else z for z in _zs(pristine)]
    data = _archive(zs)
    if oracle is not None:  # what another reader makes of this archive (independent of hcdf-trust)
        assert shutil.which("unzip"), "Info-ZIP unzip is not installed"
        (tmp_path / "x.zip").write_bytes(data)
        out = tmp_path / "x"
        r = subprocess.run(["unzip", "-o", "x.zip", "-d", out], cwd=tmp_path, capture_output=True, text=True)
        if oracle == "mode":
            assert (out / CHASSIS).stat().st_mode & 0o777 == 0o777
        else:
            assert "skipping" in r.stdout + r.stderr and not (out / CHASSIS).exists()
    error = _refused(_verify(cli, tmp_path, data))
    assert CHASSIS in error["message"], error


# --- the bundle is its own lock: pins must be full ------------------------------------------------


def test_a_weak_pin_in_a_bundle_is_refused(cli, pristine, tmp_path):
    full = hashlib.sha256(dict(pristine)[CHASSIS]).hexdigest()
    root = _root(pristine).replace(f"sha256:{full}".encode(), f"sha256:{full[:8]}".encode())
    r = _verify(cli, tmp_path, _archive([Z(ROOT, root), *_zs(pristine)[1:]]))
    assert r.exit_code == 1, r.stderr
    assert any(CHASSIS in e["message"] for e in r.json["errors"])


def test_an_unpinned_reference_in_a_bundle_is_refused(cli, pristine, tmp_path):
    full = hashlib.sha256(dict(pristine)[CHASSIS]).hexdigest()
    root = _root(pristine).replace(f' sha="sha256:{full}"'.encode(), b"")
    r = _verify(cli, tmp_path, _archive([Z(ROOT, root), *_zs(pristine)[1:]]))
    assert r.exit_code == 1 and r.json["errors"][0]["code"] == "unpinned"


# --- the archive changes under the reader ---------------------------------------------------------

_TRUNCATE = """
import os, sys
target = sys.argv[1]
from hcdf_trust import bundle
real = bundle.check_structure
def racing(data, **kw):
    entries = real(data, **kw)
    os.truncate(target, 0)  # another process truncates the bundle once it is checked
    return entries
bundle.check_structure = racing
from hcdf_trust.cli import main
main(["verify", target], prog_name="hcdf-trust")
"""


def test_a_bundle_truncated_while_it_is_read_does_not_kill_the_run(pristine, tmp_path):
    path = tmp_path / "racing.hcdfz"
    path.write_bytes(_archive(_zs(pristine)))
    env = {**os.environ, "XDG_CACHE_HOME": str(tmp_path / "cache")}
    r = subprocess.run(
        [sys.executable, "-c", _TRUNCATE, path], capture_output=True, text=True, timeout=120, env=env, check=False
    )
    # read whole before its check (3c22669): the bytes checked are the bytes read; either they verify
    # or the run says why; never a signal (SIGBUS was -7 with the mapping)
    assert r.returncode in (0, 3), (r.returncode, r.stderr[-500:])
    assert "Traceback" not in r.stderr


def test_the_recorded_digest_is_of_the_bytes_that_were_checked(cli, pristine, tmp_path, monkeypatch):
    from hcdf_trust import bundle as bundle_mod

    checked = _archive(_zs(pristine))
    # Same size, same data: only the chassis entry's method now says deflate, which no reader accepts.
    swapped = _archive([replace(z, method=8) if z.name == CHASSIS else z for z in _zs(pristine)])
    assert len(swapped) == len(checked)
    path = tmp_path / "racing.hcdfz"
    path.write_bytes(checked)
    real = bundle_mod.check_structure

    def racing(data, **kw):
        entries = real(data, **kw)
        with open(path, "r+b") as f:  # in place, as another writer would: the mapping sees it
            f.write(swapped)
        return entries

    monkeypatch.setattr(bundle_mod, "check_structure", racing)
    r = cli("sbom", path, "--format", "cyclonedx")
    assert r.exit_code == 0, r.stderr
    import json

    props = {p["name"]: p["value"] for p in json.loads(r.stdout)["metadata"]["properties"]}
    assert props["hcdf:bundle-sha256"] == hashlib.sha256(checked).hexdigest()


# --- where a bundle is read from ------------------------------------------------------------------


def test_a_fifo_a_folder_or_a_dangling_link_named_hcdfz_is_an_input_error_without_blocking(pristine, tmp_path):
    fifo, folder, dangling = tmp_path / "f.hcdfz", tmp_path / "d.hcdfz", tmp_path / "l.hcdfz"
    os.mkfifo(fifo)
    folder.mkdir()
    (folder / ROOT).write_bytes(_root(pristine))
    dangling.symlink_to(tmp_path / "nowhere.hcdfz")
    for path in (fifo, folder, dangling):
        for verb in ("verify", "validate"):
            r = subprocess.run(
                [sys.executable, "-m", "hcdf_trust.cli", verb, path], capture_output=True, text=True, timeout=60,
                env={**os.environ, "XDG_CACHE_HOME": str(tmp_path / "cache")}, check=False,
            )  # fmt: skip
            expected = 2 if path == folder else 3  # a folder: click's usage error, as for a tree's DOC
            assert r.returncode == expected and path.name in r.stderr and "Traceback" not in r.stderr, (verb, r.stderr)


def test_a_symlink_to_a_bundle_is_read_as_the_bundle(cli, pristine, tmp_path):
    real = tmp_path / "real.hcdfz"
    real.write_bytes(_archive(_zs(pristine)))
    (tmp_path / "link.hcdfz").symlink_to(real)
    assert cli("verify", tmp_path / "link.hcdfz").exit_code == 0


def test_bundling_a_bundle_gives_the_same_bytes_or_says_why_not(cli, pristine, tmp_path):
    src = tmp_path / "src.hcdfz"
    src.write_bytes(_archive(_zs(pristine)))
    out = tmp_path / "out.hcdfz"
    r = cli("bundle", src, out)
    if r.exit_code == 0:
        assert out.read_bytes() == src.read_bytes()
    else:
        assert r.exit_code in (2, 3) and "Not a directory" not in r.stderr and "bundle" in r.stderr, r.stderr
        assert not out.exists()


def test_a_root_name_too_long_for_a_zip_name_is_an_input_error(cli, tmp_path):
    """Fixed here: a root whose name attribute is longer than 65,535 bytes crashed `bundle` with struct.error
    (a traceback): the entry name (the document's name) does not fit a ZIP header."""
    (tmp_path / "m.stl").write_bytes(b"x")
    sha = hashlib.sha256(b"x").hexdigest()
    doc = tmp_path / "r.hcdf"
    doc.write_text(
        f'<?xml version="1.0"?>\n<hcdf version="1.0" name="{"A" * 70_000}"><comp name="c"><visual>'
        f'<model uri="m.stl" sha="sha256:{sha}"/></visual></comp></hcdf>\n'
    )
    out = tmp_path / "r.hcdfz"
    r = cli("bundle", doc, out)
    assert r.exit_code == 3 and "name" in r.stderr and not out.exists(), r.stderr


# --- what a bundle is given as, where something is written ----------------------------------------


def test_pin_and_a_lock_path_refuse_a_bundle_and_leave_it_alone(cli, pristine, robot, tmp_path):
    path = tmp_path / "s.hcdfz"
    data = _archive(_zs(pristine))
    path.write_bytes(data)
    r = cli("pin", path, "--write")
    assert r.exit_code in (2, 3) and "bundle" in r.stderr and "lock file" not in r.stderr, r.stderr
    assert cli("resolve", robot, "--lock", path).exit_code == 3  # read as a lock first: not one
    assert cli("resolve", path, "--no-lock").exit_code == 0
    assert cli("verify", path, "--lock", tmp_path / "x.lock").exit_code == 3
    assert path.read_bytes() == data
    assert sorted(p.name for p in tmp_path.iterdir()) == ["examples", "s.hcdfz"]  # no s.hcdfz.lock, no stray


# --- outputs: OUT is a symlink, a key, an older bundle; another verb's output over a bundle -------


def test_bundle_out_that_is_a_symlink_is_replaced_not_followed(cli, robot, tmp_path):
    victim = tmp_path / "victim.txt"
    victim.write_bytes(b"not yours\n")
    out = tmp_path / "out.hcdfz"
    out.symlink_to(victim)
    r = cli("bundle", robot, out)
    assert r.exit_code == 0, r.stderr
    assert victim.read_bytes() == b"not yours\n"
    assert not out.is_symlink() and cli("verify", out).exit_code == 0


def test_bundle_out_that_is_a_key_is_refused(cli, robot, tmp_path):
    key = tmp_path / "signing.hcdfz"
    assert cli("ota", "keygen", "--type", "ecdsa-p256", "-o", key).exit_code == 0
    before = key.read_bytes()
    r = cli("bundle", robot, key)
    assert r.exit_code == 3 and "private key" in r.stderr, r.stderr
    assert key.read_bytes() == before


def test_bundle_replaces_its_own_older_bundle(cli, robot, tmp_path):
    out = tmp_path / "scout2.hcdfz"
    assert cli("bundle", robot, out).exit_code == 0
    older = out.read_bytes()
    robot.write_bytes(robot.read_bytes().replace(b"example robot<", b"example robot, revised<", 1))
    r = cli("bundle", robot, out)
    assert r.exit_code == 0, r.stderr
    assert out.read_bytes() != older and cli("verify", out).exit_code == 0


def _long_prolog(robot: Path) -> None:
    """A licence header of 5 KiB before <hcdf>: the bundle's first 4 KiB then hold no '<hcdf '."""
    licence = b"<!--\n" + b"  Licensed under the Apache License, Version 2.0; see LICENSE.\n" * 80 + b"-->\n"
    data = robot.read_bytes()
    robot.write_bytes(data.replace(b"<hcdf ", licence + b"<hcdf ", 1))


@pytest.mark.parametrize(
    "prolog",
    [
        "short",
        "long",
    ],
)  # fmt: skip
def test_an_sbom_does_not_replace_a_bundle(cli, robot, tmp_path, prolog):
    if prolog == "long":
        _long_prolog(robot)
        assert cli("resolve", robot).exit_code == 0
    out = tmp_path / "scout2.hcdfz"
    assert cli("bundle", robot, out).exit_code == 0
    before = out.read_bytes()
    assert (b"<hcdf " in before[:4096]) == (prolog == "short")
    r = cli("sbom", robot, "--format", "cyclonedx", "-o", out)
    assert r.exit_code == 3 and "refusing to replace" in r.stderr, r.stderr
    assert out.read_bytes() == before


def test_resolve_out_does_not_write_xml_over_a_bundle_or_under_a_bundles_name(cli, robot, tmp_path):
    """Fixed here (the existing bundle by the builder's BUNDLE kind): `resolve --out X.hcdfz` wrote flattened
    XML under a bundle's name, exit 0; every reading verb then took it for a broken ZIP."""
    out = tmp_path / "scout2.hcdfz"
    assert cli("bundle", robot, out).exit_code == 0
    before = out.read_bytes()
    r = cli("resolve", robot, "--no-lock", "--out", out)
    assert r.exit_code in (2, 3), r.stderr
    assert out.read_bytes() == before
    new = tmp_path / "new.HCDFZ"
    r = cli("resolve", robot, "--no-lock", "--out", new)
    assert r.exit_code == 2 and "not a bundle" in r.stderr and not new.exists(), r.stderr


def test_a_killed_bundle_leaves_the_older_bundle_and_no_stray_once_the_next_run_ran(cli, robot, tmp_path):
    from ._macsec import KILLER

    out = tmp_path / "scout2.hcdfz"
    other = tmp_path / "other.hcdfz"  # a name nobody wrote yet: a kill must not leave half of it
    env = {**os.environ, "XDG_CACHE_HOME": str(tmp_path / "cache")}
    proc = subprocess.run(
        [sys.executable, "-c", KILLER, "before", other.name, "bundle", robot, other],
        cwd=PROJECT, capture_output=True, timeout=120, env=env, check=False,
    )  # fmt: skip
    assert proc.returncode == -9, proc.stderr
    assert not other.exists()
    assert any(p.name.startswith(".other.hcdfz.") for p in tmp_path.iterdir())  # the kill left its staged file
    assert cli("bundle", robot, other).exit_code == 0
    assert cli("verify", other).exit_code == 0
    assert not [p.name for p in tmp_path.iterdir() if p.name.startswith(".")]
    assert not out.exists()


# --- every verb: the bundle's verdict is the tree's ------------------------------------------------

VERBS = {
    "resolve": ["resolve"],
    "verify": ["verify"],
    "validate": ["validate"],
    "audit": ["audit", "--policy", "{policy}"],
    "sbom-cyclonedx": ["sbom", "--format", "cyclonedx"],
    "sbom-spdx": ["sbom", "--format", "spdx"],
    "macsec-plan": ["macsec", "plan"],
    "ota-build": ["ota", "build", "--config", "{ota}", "--firmware-dir", "{fw}", "--key", "{key}", "--out", "{rel}",
                  "--base-url", "https://firmware.example.com/scout2"],
}  # fmt: skip


def _run_verb(cli, verb: str, doc, robot: Path, tmp_path: Path, tag: str):
    key = tmp_path / "k.pem"
    if not key.exists():
        assert cli("ota", "keygen", "--type", "ecdsa-p256", "-o", key).exit_code == 0
    values = {
        "policy": robot.parent.parent / "audit-policy.toml",
        "ota": robot.parent / "ota.toml",
        "fw": robot.parent / "firmware",
        "key": key,
        "rel": tmp_path / f"rel-{tag}",
    }
    args = [a.format(**{k: str(v) for k, v in values.items()}) for a in VERBS[verb]]
    return cli(
        *args[: 2 if args[0] in ("macsec", "ota") else 1], doc, *args[2 if args[0] in ("macsec", "ota") else 1 :]
    )


@pytest.mark.parametrize("verb", list(VERBS))
def test_every_verb_gives_the_trees_verdict_on_a_tampered_bundle(cli, robot, tmp_path, verb):
    """One byte appended to the chassis GLB in the tree, and to its entry in the bundle (CRC kept right)."""
    bundled = tmp_path / "scout2.hcdfz"
    assert cli("bundle", robot, bundled).exit_code == 0
    with zipfile.ZipFile(bundled) as z:
        entries = [Z(i.filename, z.read(i)) for i in z.infolist()]
    bundled.write_bytes(_archive([replace(e, data=e.data + b"\0") if e.name == CHASSIS else e for e in entries]))
    glb = robot.parent / "models" / "chassis.glb"
    glb.write_bytes(glb.read_bytes() + b"\0")
    tree = _run_verb(cli, verb, robot, robot, tmp_path, "tree")
    packed = _run_verb(cli, verb, bundled, robot, tmp_path, "bundle")
    assert tree.exit_code == packed.exit_code, (tree.stderr, packed.stderr)
    assert tree.exit_code == (0 if verb == "validate" else 1), tree.stderr  # validate reads no asset
    if verb != "validate":
        assert "digest mismatch" in packed.stderr and f"scout2.hcdfz/{ROOT}:" in packed.stderr, packed.stderr
        assert CHASSIS in packed.stderr
    assert not (tmp_path / "rel-tree").exists() and not (tmp_path / "rel-bundle").exists()


@pytest.mark.parametrize("verb", [v for v in VERBS if v != "validate"])
@pytest.mark.parametrize("defect", ["remote", "include", "unused-entry"])
def test_every_verb_refuses_a_bundle_breaking_its_content_rules(cli, robot, pristine, tmp_path, verb, defect):
    root, rest = _root(pristine), _zs(pristine)[1:]
    if defect == "remote":
        root = root.replace(f'"{CHASSIS}"'.encode(), b'"https://example.com/chassis_14662db9eb3d.glb"')
    elif defect == "include":
        root = root.replace(b"</hcdf>", b'<include uri="assets/gripper_adaa3b076b88.glb"/></hcdf>')
    else:
        extra = b"hidden"
        rest.append(Z(f"assets/extra_{hashlib.sha256(extra).hexdigest()[:12]}.bin", extra))
    path = tmp_path / "hostile.hcdfz"
    path.write_bytes(_archive([Z(ROOT, root), *rest]))
    r = _run_verb(cli, verb, path, robot, tmp_path, "x")
    assert r.exit_code == 1, (r.exit_code, r.stderr)
    assert "hostile.hcdfz" in r.stderr


def test_audit_does_not_ask_a_bundle_for_a_lock_file(cli, robot, tmp_path):
    policy = tmp_path / "policy.toml"
    policy.write_text(
        (robot.parent.parent / "audit-policy.toml").read_text() + '\n[checks.not-locked]\nseverity = "error"\n'
    )
    bundled = tmp_path / "scout2.hcdfz"
    assert cli("bundle", robot, bundled).exit_code == 0
    tree = cli("audit", robot, "--policy", policy)
    assert tree.exit_code == 0, tree.stderr
    packed = cli("audit", bundled, "--policy", policy)
    assert packed.exit_code == 0, packed.stderr
