"""The export index (hcdf_trust/macsec/index.py) attacked: the full resolve+plan path is the oracle.

Every export through the index must give exactly the bytes (and the exit code and message)
that the same export gives with the index deleted; anything the full path refuses, or any
index that is not the one this store wrote for this description, must fall back to it.
``export --json`` says which path ran (``planned_from``).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import stat
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from hcdf_trust.macsec import index
from hcdf_trust.macsec.backends import PassphraseWrapper
from hcdf_trust.macsec.store import INDEX_NAME, STORE_NAME, KeyStore

from ._macsec import KILLER, comp, hcdf, humanoid, link, lock, port, tree

PROJECT = Path(__file__).resolve().parents[1]
PASS = b"export index passphrase"
T0 = "2026-01-01T00:00:00Z"
T1 = "2026-01-01T00:30:00Z"
FORMATS = ("wpa_supplicant", "networkd", "iproute2", "json")
CAPS = ("gcm-aes-128",)
GLB = b"glTF\x02\x00\x00\x00" + bytes(range(256)) * 8

ARM = hcdf(
    comp("ctrl", port("eth0", *CAPS), port("eth1", *CAPS), port("eth2", *CAPS)),
    '<comp name="hand"><visual><model uri="models/hand.glb"/></visual>' + port("eth0", *CAPS) + "</comp>",
    comp("wrist", port("eth0", *CAPS)),
    '<network name="arm-net">',
    link("ctrl_to_hand", "ctrl/eth1", "hand/eth0", '<macsec policy="must-secure" key-ref="arm-links"/>'),
    link("ctrl_to_wrist", "ctrl/eth2", "wrist/eth0", '<macsec policy="must-secure" key-ref="arm-links"/>'),
    link("ctrl_to_body", "ctrl/eth0", "body/eth0"),
    '<mesh name="skin" standard="802.15.4" network-key-ref="thread">'
    '<node device="ctrl" antenna="x"/><node device="hand" antenna="x"/></mesh>',
    '<macsec policy="should-secure" cipher="gcm-aes-128"/>',
    "</network>",
)


def _robot(cam_policy: str = "must-secure") -> str:
    body = [
        comp("body", port("eth0", *CAPS), port("eth1", *CAPS), port("eth2", *CAPS)),
        comp("cam", port("p0", *CAPS)),
        comp("imu", port("p0", *CAPS)),
        '<include uri="arm.hcdf" name="left_arm"/>',
        '<include uri="arm.hcdf" name="right_arm"/>',
        '<network name="base">',
        link("body_cam", "body/eth1", "cam/p0", f'<macsec policy="{cam_policy}"/>'),
        "</network>",
        '<network name="eap">',
        link("body_imu", "body/eth2", "imu/p0"),
        '<macsec policy="must-secure" key-agreement="eap-tls"/>',
        "</network>",
    ]
    return hcdf(*body)


def _with_spare() -> str:
    """The robot with two more devices on a new keyed link (generate then writes a key and the index)."""
    spare = comp("spare", port("p0", *CAPS)) + comp("spare2", port("p0", *CAPS))
    new_link = link("spare_link", "spare/p0", "spare2/p0", '<macsec policy="must-secure"/>')
    return _robot().replace('<network name="base">', spare + '\n<network name="base">\n' + new_link)


def _small(folder: Path, cam_policy: str = "must-secure") -> Path:
    """An arm sub-assembly included twice (a shared key-ref, a mesh key, a GLB model), a psk
    link and an eap-tls network, locked."""
    (folder / "models").mkdir(parents=True, exist_ok=True)
    (folder / "models" / "hand.glb").write_bytes(GLB)
    return tree(folder, {"arm.hcdf": ARM, "robot.hcdf": _robot(cam_policy)})


class Env:
    """A locked description, its store (generated at T0) and the CLI to export from it."""

    def __init__(self, cli: Any, tmp: Path, doc: Path) -> None:
        self.cli, self.tmp, self.doc = cli, tmp, doc
        self.pp = tmp / "pass"
        self.pp.write_bytes(PASS)
        self.store = tmp / "keys"
        self.index = self.store / INDEX_NAME
        self.runs = 0

    def base(self, store: Path | None = None, pp: Path | None = None) -> list[Any]:
        return ["--store", store or self.store, "--passphrase-file", pp or self.pp]

    def generate(self, doc: Path | None = None, *, store: Path | None = None, ok: bool = True) -> Any:
        r = self.cli("macsec", "generate", doc or self.doc, *self.base(store), "--now", T0)
        if ok:
            assert r.exit_code == 0, r.stderr
        return r

    def export(self, device: str, fmt: str = "json", *extra: Any, doc: Path | None = None, pp: Path | None = None):
        """``export --json`` into a new folder; (result, folder)."""
        self.runs += 1
        out = self.tmp / f"out{self.runs}-{device}-{fmt}"
        args = ["--device", device, "--format", fmt, "--out", out, "--now", T1, "--json", *extra]
        r = self.cli("macsec", "export", doc or self.doc, *self.base(pp=pp), *args)
        return r, out

    @contextlib.contextmanager
    def without_index(self) -> Iterator[None]:
        """The index moved out of the store folder (restored after): the full path."""
        aside = self.tmp / "index-aside"
        moved = os.path.lexists(self.index)
        if moved:
            os.rename(self.index, aside)
        try:
            yield
        finally:
            if moved:
                os.rename(aside, self.index)

    def full(self, device: str, fmt: str = "json", *extra: Any, **kw: Any):
        with self.without_index():
            r, out = self.export(device, fmt, *extra, **kw)
        if r.exit_code == 0:
            assert r.json["planned_from"] == "description"
        return r, out


def _files(out: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(out.iterdir())} if out.exists() else {}


def _stdout(r: Any) -> Any:
    """The JSON stdout without what names the path taken or the output folder."""
    if r.exit_code != 0:
        return r.stdout
    d = dict(r.json)
    d.pop("planned_from")
    d["files"] = [os.path.basename(f) for f in d["files"]]
    return d


def _same(a: tuple[Any, Path], b: tuple[Any, Path]) -> None:
    (ra, oa), (rb, ob) = a, b
    assert (ra.exit_code, ra.stderr) == (rb.exit_code, rb.stderr)
    assert _stdout(ra) == _stdout(rb)
    assert _files(oa) == _files(ob)


def _path(r: Any) -> str:
    """Which path planned the export ("index" or "description"); the export must have succeeded."""
    assert r.exit_code == 0, r.stdout + r.stderr
    return str(r.json["planned_from"])


def _all_secrets(store: Path) -> dict[str, list[str]]:
    """CA id -> the hex of every key and CKN of its generations (EAP-TLS PEM bundles too)."""
    ks = KeyStore.open(store, PassphraseWrapper(PASS))
    out: dict[str, list[str]] = {}
    for ca, e in ks.entries.items():
        for g in e.generations:
            key = ks.key(e, g)
            out.setdefault(ca, []).extend([key.hex(), g.ckn.hex()] if len(key) in (16, 32) else [g.ckn.hex()])
    return out


_SCRYPT: dict[tuple[bytes, ...], bytes] = {}


@pytest.fixture(autouse=True)
def _scrypt_once(monkeypatch):
    """scrypt (0.1 s per store open: the store's wrapping, not what is tested here) runs once per
    passphrase and salt in this file's hundreds of exports: the very key it derives, kept."""
    real = PassphraseWrapper._derive

    def derive(self: PassphraseWrapper, salt: bytes, n: int, r: int, p: int) -> bytes:
        key = (self._passphrase, salt, bytes([n.bit_length(), r, p]))
        if key not in _SCRYPT:
            _SCRYPT[key] = real(self, salt, n, r, p)
        return _SCRYPT[key]

    monkeypatch.setattr(PassphraseWrapper, "_derive", derive)


@pytest.fixture
def env(tmp_path, cli) -> Env:
    e = Env(cli, tmp_path, _small(tmp_path / "doc"))
    e.generate()
    assert stat.S_ISREG(os.lstat(e.index).st_mode)
    return e


def _devices(cli: Any, doc: Path) -> list[str]:
    r = cli("macsec", "plan", doc, "--json")
    assert r.exit_code == 0, r.stderr
    return sorted({m["device"] for ca in r.json["associations"] if ca["keyed"] for m in ca["members"]})


# --- 1. the differential oracle ---------------------------------------------------------------


def _differential(e: Env, extra: tuple[str, ...] = ()) -> int:
    devices = _devices(e.cli, e.doc)
    via_index = {(d, f): e.export(d, f, *extra) for d in devices for f in FORMATS}
    with e.without_index():
        full = {(d, f): e.export(d, f, *extra) for d in devices for f in FORMATS}
    ok = 0
    for key, (r, out) in via_index.items():
        if r.exit_code == 0:
            ok += 1
            assert r.json["planned_from"] == "index", key
            assert full[key][0].json["planned_from"] == "description", key
        _same((r, out), full[key])
    return ok


def test_index_and_full_path_agree_on_every_device_and_format_of_the_humanoid(tmp_path, cli):
    (tmp_path / "doc").mkdir()
    e = Env(cli, tmp_path, humanoid(tmp_path / "doc"))
    e.generate()
    assert len(_devices(cli, e.doc)) == 17
    # 2.11 so that the gcm-aes-256 backbone exports for wpa_supplicant too
    assert _differential(e, ("--wpa-version", "2.11")) >= 40


def test_index_and_full_path_agree_on_an_include_tree(env):
    devices = _devices(env.cli, env.doc)
    assert {"left_arm_ctrl", "right_arm_hand", "cam", "imu", "body"} <= set(devices)
    head = json.loads(env.index.read_bytes().split(b"\n")[0])
    kinds = sorted(f[0] for f in head["files"])
    assert kinds == ["include", "model"]  # the included arm (once, though included twice) and its GLB
    assert _differential(env) >= 20


# --- 2-6. a description that changed ------------------------------------------------------------


@pytest.mark.parametrize("relock", [False, True])
def test_changed_root_document_takes_the_full_path(env, relock):
    assert b"macsec_integ_only=0" in _files(env.export("cam", "wpa_supplicant")[1])["wpa_supplicant-wired-p0.conf"]
    env.doc.write_text(_robot("integrity-only"))  # one attribute of the root document
    if relock:
        lock(env.doc)
    got = env.export("cam", "wpa_supplicant")
    assert _path(got[0]) == "description"
    _same(got, env.full("cam", "wpa_supplicant"))
    assert b"macsec_integ_only=1" in _files(got[1])["wpa_supplicant-wired-p0.conf"]


def test_lock_reformatted_or_drifted_fails_as_without_index(env):
    lockfile = env.doc.with_name("robot.hcdf.lock")
    good = lockfile.read_bytes()
    # equivalent JSON in another layout: other bytes than were verified, so the full path
    lockfile.write_text(json.dumps(json.loads(good), indent=1))
    got = env.export("cam")
    assert _path(got[0]) == "description"
    _same(got, env.full("cam"))
    # a drifted pin: the lock's digest of the arm no longer is the file's
    arm_sha = hashlib.sha256(ARM.encode()).hexdigest()
    assert arm_sha.encode() in good
    lockfile.write_bytes(good.replace(arm_sha.encode(), b"0" * 64))
    got = env.export("cam")
    assert got[0].exit_code != 0 and not got[1].exists()
    _same(got, env.full("cam"))
    lockfile.write_bytes(good)
    assert _path(env.export("cam")[0]) == "index"


def _tamper(env: Env, name: str, new: bytes) -> None:
    path = env.doc.parent / name
    assert path.read_bytes() != new
    path.write_bytes(new)


@pytest.mark.parametrize(
    "name,new",
    [
        ("arm.hcdf", ARM.replace('key-ref="arm-links"/>', 'key-ref="arm-linkz"/>', 1).encode()),
        ("models/hand.glb", GLB[:-1] + b"\x00"),
    ],
)
def test_tampered_include_or_artifact_fails_as_without_index(env, name, new):
    _tamper(env, name, new)
    for device in ("left_arm_ctrl", "cam"):
        got = env.export(device)
        assert got[0].exit_code == 1 and "changed since it was locked" in got[0].stdout, got[0].stdout
        assert not got[1].exists()
        _same(got, env.full(device))


@pytest.mark.parametrize("name", ["arm.hcdf", "models/hand.glb"])
def test_a_file_replaced_by_a_symlink_outside_the_root_is_refused_as_without_index(env, tmp_path, name):
    path = env.doc.parent / name
    outside = tmp_path / "outside" / path.name
    outside.parent.mkdir()
    outside.write_bytes(path.read_bytes())  # the very same bytes
    path.unlink()
    path.symlink_to(outside)
    got = env.export("left_arm_hand")
    assert got[0].exit_code != 0 and "(symlink escape)" in got[0].stdout, got[0].stdout
    assert not got[1].exists()
    _same(got, env.full("left_arm_hand"))


def test_a_symlink_inside_the_root_is_accepted_as_without_index(env):
    arm = env.doc.parent / "arm.hcdf"
    (env.doc.parent / "copy").mkdir()
    (env.doc.parent / "copy" / "arm.hcdf").write_bytes(arm.read_bytes())
    arm.unlink()
    arm.symlink_to("copy/arm.hcdf")
    got = env.export("left_arm_hand")
    _same(got, env.full("left_arm_hand"))
    assert got[0].exit_code == 0


def test_a_file_replaced_by_a_fifo_is_refused_as_without_index(env):
    glb = env.doc.parent / "models" / "hand.glb"
    glb.unlink()
    os.mkfifo(glb)
    proc = _subprocess_export(env, env.tmp / "fifo-out", "left_arm_hand")
    with env.without_index():
        full = _subprocess_export(env, env.tmp / "fifo-full", "left_arm_hand")
    assert proc.returncode == full.returncode != 0
    assert proc.stdout == full.stdout and "FIFO" in proc.stdout
    assert not (env.tmp / "fifo-out").exists()


def test_a_device_the_index_does_not_list_fails_as_without_index(env):
    for device in ("ghost", "left_arm", "left_arm/ctrl", "CAM"):
        got = env.export(device)
        assert got[0].exit_code == 3 and "member of no keyed MACsec association" in got[0].stdout
        _same(got, env.full(device))


def test_root_document_turned_into_a_link_stub_takes_the_full_path(env):
    """``robot.hcdf`` made a symlink to a sibling with the same bytes: a resolve follows the stub
    (and its lock no longer belongs to the root it reaches), so the index is not used."""
    real = env.doc.with_name("real.hcdf")
    env.doc.rename(real)
    env.doc.symlink_to(real.name)
    got = env.export("cam")
    assert got[0].exit_code == 3 and "belongs to" in got[0].stdout, got[0].stdout
    _same(got, env.full("cam"))


# --- 7-10. an index that is not this store's index of this description ------------------------


def _lines(raw: bytes) -> list[bytes]:
    return raw.split(b"\n")


def test_index_with_a_flipped_byte_falls_back(env):
    raw = env.index.read_bytes()
    at = raw.index(b'"cam/p0":1000.0')
    env.index.write_bytes(raw[: at + 9] + b"9" + raw[at + 10 :])  # cam's port speed 1 -> 9 Gb/s
    for fmt in ("json", "iproute2"):
        got = env.export("cam", fmt)
        assert _path(got[0]) == "description"
        _same(got, env.full("cam", fmt))


def _compact(value: Any) -> bytes:
    return json.dumps(value, separators=(",", ":")).encode()


def test_index_granting_a_device_another_association_is_refused(env):
    """Least privilege: the left arm's rows edited to make cam a member (on a port of its own)
    of the arm's associations: the MAC does not match, nothing is granted."""
    lines = _lines(env.index.read_bytes())
    stolen = ["key-ref:left_arm_arm-links", "mesh-key:left_arm_thread"]
    edited = 0
    for i, line in enumerate(lines[1:-1], start=1):  # after the header, before the final newline
        row = json.loads(line)
        if row[0] in stolen:
            row[5].append(["cam", ["p9"]])  # members
            lines[i] = _compact(row)
            edited += 1
    assert edited == len(stolen)
    env.index.write_bytes(b"\n".join(lines))
    got = env.export("cam")
    assert _path(got[0]) == "description"
    assert got[0].json["associations"] == ["link:base/body_cam"]
    _same(got, env.full("cam"))
    text = b"".join(_files(got[1]).values()).decode()
    secrets = _all_secrets(env.store)
    for ca, values in secrets.items():
        for v in values:
            assert (v in text) == (ca == "link:base/body_cam"), ca


@pytest.mark.parametrize("same_passphrase", [True, False])
def test_index_from_another_store_falls_back(env, tmp_path, same_passphrase):
    other, pp = tmp_path / "other-keys", env.pp
    if not same_passphrase:
        pp = tmp_path / "other-pass"
        pp.write_bytes(b"another passphrase")
    r = env.cli("macsec", "generate", env.doc, "--store", other, "--passphrase-file", pp, "--now", T0)
    assert r.exit_code == 0, r.stderr
    shutil.copy(other / INDEX_NAME, env.index)
    assert _path(env.export("cam")[0]) == "description"
    # its store id written over with this store's: still another store's MAC
    mine = json.loads(KeyStore.file_in(env.store).read_bytes().split(b"\n")[0])["store_id"]
    raw = env.index.read_bytes()
    theirs = json.loads(raw.split(b"\n")[0])["store_id"]
    env.index.write_bytes(raw.replace(theirs.encode(), mine.encode()))
    got = env.export("cam")
    assert _path(got[0]) == "description"
    _same(got, env.full("cam"))


def test_index_of_another_description_in_the_same_store_falls_back(env, tmp_path):
    other = _small(tmp_path / "other", cam_policy="integrity-only")
    env.generate(other)  # the store folder's index is now the other description's
    head = json.loads(env.index.read_bytes().split(b"\n")[0])
    assert head["document"] == str(other)
    for fmt in ("wpa_supplicant", "json"):
        got = env.export("cam", fmt)
        assert _path(got[0]) == "description"
        _same(got, env.full("cam", fmt))
    assert b"macsec_integ_only=0" in _files(env.export("cam", "wpa_supplicant")[1])["wpa_supplicant-wired-p0.conf"]
    assert _path(env.export("cam", doc=other)[0]) == "index"


def test_export_from_another_working_folder_falls_back(env, tmp_path, monkeypatch):
    here = env.export("cam", "iproute2")
    assert _path(here[0]) == "index"
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    got = env.export("cam", "iproute2")
    assert _path(got[0]) == "description"
    _same(got, env.full("cam", "iproute2"))
    _same(got, here)


def test_another_build_or_index_version_falls_back(env, monkeypatch):
    assert _path(env.export("cam")[0]) == "index"
    monkeypatch.setattr(index, "code_digest", lambda: "0" * 64)  # another build of hcdf-trust
    assert _path(env.export("cam")[0]) == "description"
    monkeypatch.undo()
    monkeypatch.setattr(index, "INDEX_VERSION", index.INDEX_VERSION + 1)
    got = env.export("cam")
    assert _path(got[0]) == "description"
    monkeypatch.undo()
    _same(got, env.export("cam"))


@pytest.mark.parametrize(
    "target",
    [
        "robot.hcdf",
        "arm.hcdf",
        "models/hand.glb",
        "robot.hcdf.lock",
        "keys/" + STORE_NAME,
        "keys/" + INDEX_NAME,
        "../pass",
    ],
)
@pytest.mark.parametrize("how", ["symlink", "hard link"])
def test_export_through_the_index_never_writes_over_an_input(env, target, how):
    path = env.doc.parent / target if not target.startswith("keys/") else env.store / target[5:]
    before = path.read_bytes()
    trap = env.tmp / "trap"
    trap.mkdir()
    if how == "symlink":
        (trap / "cam.macsec.json").symlink_to(path)
    else:
        os.link(path, trap / "cam.macsec.json")
    r = env.cli("macsec", "export", env.doc, *env.base(), "--device", "cam", "--format", "json", "--out", trap)
    assert r.exit_code == 3 and "refusing to overwrite an input" in r.stderr, r.stderr
    assert path.read_bytes() == before and (trap / "cam.macsec.json").read_bytes() == before
    if target != "keys/" + INDEX_NAME:  # (without an index, a symlink to it dangles, a hard link is no input)
        with env.without_index():
            r = env.cli("macsec", "export", env.doc, *env.base(), "--device", "cam", "--format", "json", "--out", trap)
        assert r.exit_code == 3 and path.read_bytes() == before


# --- 11. hostile index files ------------------------------------------------------------------


def _subprocess_export(env: Env, out: Path, device: str = "cam") -> subprocess.CompletedProcess[str]:
    """The export in a child process, killed after 30 s: a blocking read fails the test, never hangs it."""
    code = "import sys; from hcdf_trust.cli import main; main(sys.argv[1:], prog_name='hcdf-trust')"
    args = ["macsec", "export", str(env.doc), "--store", str(env.store), "--passphrase-file", str(env.pp)]
    args += ["--device", device, "--format", "json", "--out", str(out), "--now", T1, "--json"]
    return subprocess.run(
        [sys.executable, "-c", code, *args], cwd=os.getcwd(), capture_output=True, text=True, timeout=30
    )


def _hostile(env: Env, kind: str) -> None:
    raw = env.index.read_bytes()
    env.index.unlink()
    if kind == "fifo":
        os.mkfifo(env.index)
    elif kind == "symlink to the store":
        env.index.symlink_to(STORE_NAME)
    elif kind == "directory":
        env.index.mkdir()
    elif kind == "empty":
        env.index.write_bytes(b"")
    elif kind == "header only":
        env.index.write_bytes(raw.split(b"\n")[0])  # no newline at all
    elif kind == "truncated":
        env.index.write_bytes(raw[: len(raw) // 2])
    elif kind == "not JSON":
        env.index.write_bytes(b"\x00\xff" * 100 + b"\n")
    elif kind == "deep JSON":
        env.index.write_bytes(b"[" * 100_000 + b"\n")
    elif kind == "huge":
        env.index.write_bytes(raw)
        os.truncate(env.index, index.MAX_INDEX_BYTES + 1)  # sparse: no disk used
    else:
        raise AssertionError(kind)


@pytest.mark.parametrize(
    "kind",
    ["fifo", "symlink to the store", "directory", "empty", "header only", "truncated", "not JSON", "deep JSON", "huge"],
)
def test_hostile_index_falls_back_without_hanging(env, kind):
    reference = env.full("cam")
    _hostile(env, kind)
    proc = _subprocess_export(env, env.tmp / "hostile-out")
    assert proc.returncode == 0, proc.stderr
    d = json.loads(proc.stdout)
    assert d["planned_from"] == "description"
    assert _files(env.tmp / "hostile-out") == _files(reference[1])


def test_index_over_the_size_limit_is_not_read(env, monkeypatch):
    assert _path(env.export("cam")[0]) == "index"
    monkeypatch.setattr(index, "MAX_INDEX_BYTES", env.index.stat().st_size - 1)
    got = env.export("cam")
    assert _path(got[0]) == "description"
    _same(got, env.full("cam"))


@pytest.mark.parametrize("kind", ["fifo", "directory"])
def test_generate_with_a_special_file_at_the_index_path(env, tmp_path, kind):
    # a changed description, so that generate writes both the store and the index
    env.doc.write_text(_with_spare())
    lock(env.doc)
    store = KeyStore.file_in(env.store)
    before = store.read_bytes()
    env.index.unlink()
    os.mkfifo(env.index) if kind == "fifo" else env.index.mkdir()
    code = "import sys; from hcdf_trust.cli import main; main(sys.argv[1:], prog_name='hcdf-trust')"
    args = ["macsec", "generate", str(env.doc), "--store", str(env.store), "--passphrase-file", str(env.pp)]
    proc = subprocess.run([sys.executable, "-c", code, *args, "--now", T0], capture_output=True, text=True, timeout=60)
    # fails closed: exit 3 naming the index path, the store as it was, nothing left behind
    assert proc.returncode == 3, proc.stderr
    assert f"--store {env.index} " in proc.stderr and "Traceback" not in proc.stderr
    assert store.read_bytes() == before
    assert sorted(os.listdir(env.store)) == [".macsec-keys.lock", INDEX_NAME, STORE_NAME]
    proc = _subprocess_export(env, env.tmp / "after")  # the special file is still there: never read
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["planned_from"] == "description"
    assert _files(env.tmp / "after") == _files(env.full("cam")[1])


# --- 12. wrong passphrase ---------------------------------------------------------------------


def test_wrong_passphrase_with_a_valid_index_is_exit_3_as_without_index(env, tmp_path):
    wrong = tmp_path / "wrong"
    wrong.write_bytes(b"not the passphrase")
    got = env.export("cam", pp=wrong)
    assert got[0].exit_code == 3 and "wrong passphrase" in got[0].stdout
    assert not got[1].exists()
    _same(got, env.full("cam", pp=wrong))
    # a tampered include too: the description's error comes first, as on the full path
    _tamper(env, "arm.hcdf", ARM.replace("should-secure", "must-secure").encode())
    got = env.export("cam", pp=wrong)
    assert got[0].exit_code == 1 and "changed since it was locked" in got[0].stdout
    assert "wrong passphrase" not in got[0].stdout
    _same(got, env.full("cam", pp=wrong))


# --- 13-14. the index's life: an older store, generate, rotate, retire -------------------------


def test_an_older_store_without_index_gets_one_and_keeps_it(env):
    env.index.unlink()
    reference = env.export("left_arm_ctrl")
    assert _path(reference[0]) == "description"
    assert not os.path.lexists(env.index)  # export only reads an index, never writes one
    store = KeyStore.file_in(env.store)
    st_store = store.stat()
    r = env.generate()
    assert "nothing to do" in r.stderr
    assert (store.stat().st_ino, store.stat().st_mtime_ns) == (st_store.st_ino, st_store.st_mtime_ns)
    assert stat.S_IMODE(os.lstat(env.index).st_mode) == 0o600
    got = env.export("left_arm_ctrl")
    assert _path(got[0]) == "index"
    _same(got, reference)
    st = env.index.stat()
    env.export("left_arm_ctrl")
    env.generate()
    assert (env.index.stat().st_ino, env.index.stat().st_mtime_ns) == (st.st_ino, st.st_mtime_ns)


def test_rotate_and_retire_keep_exports_equal_to_the_full_path(env):
    st = env.index.stat()
    r = env.cli("macsec", "rotate", env.doc, *env.base(), "--key-ref", "left_arm_arm-links", "--now", T0)
    assert r.exit_code == 0, r.stderr
    assert (env.index.stat().st_ino, env.index.stat().st_mtime_ns) == (st.st_ino, st.st_mtime_ns)  # same plan
    for fmt in FORMATS:  # during the overlap: both generations
        got = env.export("left_arm_ctrl", fmt)
        assert _path(got[0]) == "index"
        _same(got, env.full("left_arm_ctrl", fmt))
    assert _files(got[1])["left_arm_ctrl.macsec.json"].count(b'"generation":') >= 2
    r = env.cli("macsec", "retire", *env.base(), "--now", "2026-01-02T00:00:00Z", "--json")
    assert r.exit_code == 0 and r.json["retired"] == [{"id": "key-ref:left_arm_arm-links", "generation": 1}]
    for fmt in ("json", "wpa_supplicant"):
        got = env.export("left_arm_ctrl", fmt, "--now", "2026-01-02T00:00:00Z")
        assert _path(got[0]) == "index"
        _same(got, env.full("left_arm_ctrl", fmt, "--now", "2026-01-02T00:00:00Z"))
    # a changed description: rotate writes the index of the new plan
    env.doc.write_text(_robot("integrity-only"))
    lock(env.doc)
    later = "2026-01-02T00:00:00Z"
    r = env.cli("macsec", "rotate", env.doc, *env.base(), "--key-ref", "left_arm_arm-links", "--now", later)
    assert r.exit_code == 0, r.stderr
    head = json.loads(env.index.read_bytes().split(b"\n")[0])
    assert head["document_sha256"] == hashlib.sha256(env.doc.read_bytes()).hexdigest()
    got = env.export("cam", "wpa_supplicant", "--now", later)
    assert _path(got[0]) == "index"
    _same(got, env.full("cam", "wpa_supplicant", "--now", later))
    assert b"macsec_integ_only=1" in _files(got[1])["wpa_supplicant-wired-p0.conf"]


# --- 16. what the index holds -----------------------------------------------------------------


def test_index_is_0600_and_holds_no_key_material(env):
    assert stat.S_IMODE(os.lstat(env.index).st_mode) == 0o600
    raw = env.index.read_bytes().decode().lower()
    secrets = _all_secrets(env.store)
    assert sum(map(len, secrets.values())) >= 15
    for values in secrets.values():
        for v in values:
            assert v not in raw
    # and the exported bundles' own keys (an independent reading of the same secrets)
    for device in ("left_arm_ctrl", "imu", "cam"):
        r, out = env.export(device)
        bundle = json.loads(_files(out)[f"{device}.macsec.json"])
        text = json.dumps(bundle)
        assert "PRIVATE KEY" not in raw
        for a in [*bundle["associations"], *bundle["mesh_keys"]]:
            for g in a["generations"]:
                for k in ("cak", "ckn", "key"):
                    if g.get(k):
                        assert g[k].lower() not in raw and g[k] in text


# --- 17. an interrupted generate --------------------------------------------------------------


@pytest.mark.parametrize("when", ["before", "after"])
def test_killed_generate_leaves_store_and_index_each_before_or_after(env, when):
    store = KeyStore.file_in(env.store)
    old_store, old_index = store.read_bytes(), env.index.read_bytes()
    # a new device on a new link: generate writes a new key and a new index
    env.doc.write_text(_with_spare())
    lock(env.doc)
    args = ["macsec", "generate", str(env.doc), *map(str, env.base()), "--now", T0]
    cmd = [sys.executable, "-c", KILLER, when, INDEX_NAME, *args]
    proc = subprocess.run(cmd, cwd=PROJECT, capture_output=True, timeout=60)
    assert proc.returncode == -9, proc.stderr
    ks = KeyStore.open(env.store, PassphraseWrapper(PASS))  # opens: never half-written
    assert "link:base/spare_link" in ks.entries and store.read_bytes() != old_store  # the store is renamed first
    assert (env.index.read_bytes() == old_index) == (when == "before")
    for device in ("spare", "cam", "left_arm_ctrl"):
        got = env.export(device)
        assert _path(got[0]) == ("description" if when == "before" else "index")
        _same(got, env.full(device))
    env.generate()  # under the lock: a killed run's leftovers are removed
    assert sorted(os.listdir(env.store)) == [".macsec-keys.lock", INDEX_NAME, STORE_NAME]
    assert _path(env.export("spare")[0]) == "index"


def test_killed_retire_leaves_no_copy_of_the_retired_generation(env):
    """A retire killed once the store is renamed leaves OutputPlan's link to the store it replaced;
    the next locked run removes it: the retired generation's ciphertext is nowhere in the folder."""
    r = env.cli("macsec", "rotate", env.doc, *env.base(), "--key-ref", "left_arm_arm-links", "--now", T0)
    assert r.exit_code == 0, r.stderr
    line = next(x for x in KeyStore.file_in(env.store).read_text().splitlines() if "left_arm_arm-links" in x)
    retired = json.loads(line)[1]["generations"][0]["ciphertext"].encode()
    args = ["macsec", "retire", *map(str, env.base()), "--now", "2026-01-02T00:00:00Z"]
    proc = subprocess.run([sys.executable, "-c", KILLER, "after", STORE_NAME, *args], cwd=PROJECT, capture_output=True)
    assert proc.returncode == -9, proc.stderr
    assert retired not in KeyStore.file_in(env.store).read_bytes()
    env.generate()
    assert sorted(os.listdir(env.store)) == [".macsec-keys.lock", INDEX_NAME, STORE_NAME]
    assert not [f for f in env.store.iterdir() if retired in f.read_bytes()]
    got = env.export("left_arm_ctrl", "json", "--now", "2026-01-02T00:00:00Z")
    assert _path(got[0]) == "index"
    _same(got, env.full("left_arm_ctrl", "json", "--now", "2026-01-02T00:00:00Z"))


def test_document_named_relatively_at_generate_and_absolutely_at_export(tmp_path, cli, monkeypatch):
    """The index keys on the absolute root path: how it was spelt on either command line changes nothing."""
    e = Env(cli, tmp_path, _small(tmp_path / "doc"))
    monkeypatch.chdir(tmp_path / "doc")
    e.doc = Path("robot.hcdf")
    e.generate()
    e.doc = tmp_path / "doc" / "robot.hcdf"
    assert _differential(e) >= 20
    e.doc = Path("../doc/./robot.hcdf")
    got = e.export("left_arm_ctrl", "wpa_supplicant")
    assert _path(got[0]) == "index"
    _same(got, e.full("left_arm_ctrl", "wpa_supplicant"))


def test_rows_hold_every_field_of_an_association(tmp_path):
    """ROW_FIELDS is every field of Association but its warning memo, and a row read back is the
    association planned (so a new field cannot be dropped silently from exports through the index)."""
    import dataclasses

    from hcdf_trust.macsec.plan import Association, Element, Member, Policy, plan

    assert index.ROW_FIELDS == tuple(f.name for f in dataclasses.fields(Association) if f.name != "warned")
    assert len(dataclasses.fields(Element)) == 6 and len(dataclasses.fields(Member)) == 2
    assert len(dataclasses.fields(Policy)) == 7
    (tmp_path / "h").mkdir()
    for doc in (_small(tmp_path / "s"), humanoid(tmp_path / "h")):
        p = plan(doc)
        for ca in p.keyed():
            back = index._association(json.loads(json.dumps(index._row(ca))))
            ca.warned = set()
            assert back == ca, ca.id
