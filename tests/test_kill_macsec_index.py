"""Mutation-killing tests for hcdf_trust/macsec/index.py (issue 16), kept fast: one small
locked tree, a few exports each, through the CLI and the module's public functions.

The oracle of every export through the index is the same export with the index moved
aside (the full resolve and plan): same exit code, stderr, JSON and files. ``planned_from``
says which path ran, so an index that is ignored, or used when it must not be, is seen
even where both paths would write the same bytes.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path

import pytest

from hcdf_trust.macsec import index
from hcdf_trust.macsec.store import INDEX_NAME
from hcdf_trust.store import default_cache_dir

from ._macsec import lock
from .test_macsec_index import ARM, Env, _files, _path, _same, _scrypt_once, _small  # noqa: F401

T1 = "2026-01-01T00:30:00Z"


@pytest.fixture
def env(tmp_path, cli) -> Env:
    e = Env(cli, tmp_path, _small(tmp_path / "doc"))
    e.generate()
    return e


# --- the index is written where it belongs and used ------------------------------------------


def test_the_index_is_written_beside_the_store_and_used(env):
    assert os.path.isfile(env.store / INDEX_NAME)
    assert index.path_in(env.store) == os.path.join(env.store, INDEX_NAME)
    got = env.export("cam")
    assert _path(got[0]) == "index"
    assert got[0].json["associations"] == ["link:base/body_cam"]
    _same(got, env.full("cam"))


@pytest.mark.parametrize(
    "device,fmt",
    [
        ("left_arm_ctrl", "json"),  # a shared key-ref, a network default and a mesh key (no policy)
        ("right_arm_hand", "json"),  # the last rows
        ("imu", "json"),  # eap-tls
        ("right_arm_ctrl", "iproute2"),
    ],
)
def test_each_device_through_the_index_as_through_the_description(env, device, fmt):
    got = env.export(device, fmt)
    assert _path(got[0]) == "index"
    _same(got, env.full(device, fmt))


def test_a_device_in_three_associations_gets_all_three(env):
    got = env.export("left_arm_ctrl")
    assert _path(got[0]) == "index"
    assert got[0].json["associations"] == [
        "key-ref:left_arm_arm-links",
        "link:left_arm_arm-net/left_arm_ctrl_to_body",
        "mesh-key:left_arm_thread",
    ]


def test_a_device_in_four_associations_is_refused_as_without_the_index(env):
    """body's eth0 is on both arms' links (rows 5 and 8 of 10): the same refusal naming both."""
    got = env.export("body")
    assert got[0].exit_code == 3
    assert [e["message"] for e in json.loads(got[0].stdout)["errors"]] == [
        "port body/eth0 is in two associations (link:left_arm_arm-net/left_arm_ctrl_to_body and "
        "link:right_arm_arm-net/right_arm_ctrl_to_body): one port, one connectivity association"
    ]
    _same(got, env.full("body"))


def test_a_device_the_index_does_not_list_is_refused_as_without_it(env):
    got = env.export("ghost")
    assert got[0].exit_code == 3
    assert [e["message"] for e in json.loads(got[0].stdout)["errors"]] == [
        "device 'ghost' is a member of no keyed MACsec association"
    ]
    _same(got, env.full("ghost"))


# --- each header field is checked on its own --------------------------------------------------


@pytest.mark.parametrize(
    "name,value",
    [("INDEX_FORMAT", "another-index-format"), ("INDEX_VERSION", index.INDEX_VERSION + 1), ("code_digest", None)],
)
def test_an_index_written_by_other_code_is_not_used(env, monkeypatch, name, value):
    """A sealed index of this very description that differs only in its format, version or
    code digest (written by a patched generate): planned from the description."""
    env.index.unlink()
    with monkeypatch.context() as m:
        m.setattr(index, name, (lambda: "0" * 64) if name == "code_digest" else value)
        env.generate()
    assert os.path.isfile(env.index)
    got = env.export("cam")
    assert _path(got[0]) == "description"
    _same(got, env.full("cam"))
    env.generate()  # the index of this code again: used
    assert _path(env.export("cam")[0]) == "index"


def test_an_index_written_from_another_working_folder_is_not_used(env, tmp_path, monkeypatch):
    env.index.unlink()
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    with monkeypatch.context() as m:
        m.chdir(elsewhere)
        env.generate()
    assert json.loads(env.index.read_bytes().split(b"\n")[0])["cwd"] == str(elsewhere)
    got = env.export("cam")
    assert _path(got[0]) == "description"
    _same(got, env.full("cam"))


def test_the_index_of_another_description_in_the_store_folder_is_not_used(env, tmp_path):
    other = _small(tmp_path / "other", cam_policy="integrity-only")
    env.generate(other)
    got = env.export("cam", "wpa_supplicant")
    assert _path(got[0]) == "description"
    _same(got, env.full("cam", "wpa_supplicant"))
    assert b"macsec_integ_only=0" in _files(got[1])["wpa_supplicant-wired-p0.conf"]
    assert _path(env.export("cam", doc=other)[0]) == "index"


def test_a_changed_lock_is_read_again(env):
    lockfile = env.doc.with_name("robot.hcdf.lock")
    good = lockfile.read_bytes()
    lockfile.write_text(json.dumps(json.loads(good), indent=1))  # the same pins, other bytes
    got = env.export("cam")
    assert _path(got[0]) == "description"
    arm_sha = hashlib.sha256(ARM.encode()).hexdigest().encode()
    lockfile.write_bytes(good.replace(arm_sha, b"0" * 64))  # a drifted pin: the full path fails
    got = env.export("cam")
    assert got[0].exit_code == 1 and not got[1].exists()
    _same(got, env.full("cam"))


def test_a_changed_listed_file_is_read_again(env):
    glb = env.doc.parent / "models" / "hand.glb"
    glb.write_bytes(glb.read_bytes()[:-1] + b"\x00")
    got = env.export("cam")
    assert got[0].exit_code == 1 and "changed since it was locked" in got[0].stdout
    _same(got, env.full("cam"))


def test_an_edited_index_is_not_used(env):
    raw = env.index.read_bytes()
    at = raw.index(b'"cam/p0":1000.0')
    env.index.write_bytes(raw[: at + 9] + b"9" + raw[at + 10 :])  # cam's port speed 1 -> 9 Gb/s, same store id
    got = env.export("cam")
    assert _path(got[0]) == "description"
    _same(got, env.full("cam"))


# --- what is indexed ---------------------------------------------------------------------------


def test_a_model_reached_through_a_symlink_to_another_folder_of_the_root_is_indexed(env):
    """A file is confined to the root the resolver confined it to, not to its own folder."""
    glb = env.doc.parent / "models" / "hand.glb"
    (env.doc.parent / "assets").mkdir()
    shutil.move(glb, env.doc.parent / "assets" / "hand.glb")
    glb.symlink_to("../assets/hand.glb")
    env.generate()
    got = env.export("left_arm_hand")
    assert _path(got[0]) == "index"
    _same(got, env.full("left_arm_hand"))


def test_a_model_over_the_document_limit_is_streamed(env, tmp_path):
    """Only an include is read whole (bounded like a document); any other file is streamed,
    so a large model does not keep an export from the index."""
    from hcdf_trust.xml import MAX_DOCUMENT_BYTES

    glb = env.doc.parent / "models" / "hand.glb"
    with open(glb, "ab") as f:
        f.truncate(MAX_DOCUMENT_BYTES + 1)  # sparse
    env.doc.with_name("robot.hcdf.lock").unlink()
    lock(env.doc)
    env.generate()
    got = env.export("left_arm_hand")
    assert _path(got[0]) == "index"


def test_a_root_document_reached_through_a_link_stub_is_not_indexed(tmp_path, cli):
    doc = _small(tmp_path / "doc")
    stub = doc.with_name("stub.hcdf")
    stub.symlink_to(doc.name)
    lock(stub)
    e = Env(cli, tmp_path, stub)
    assert "10 keys created" in e.generate().stderr
    assert not os.path.lexists(e.index)
    assert e.export("cam")[0].exit_code == 0


# --- an export through the index protects what a resolve would -----------------------------------


@pytest.mark.parametrize(
    "target,what",
    [
        ("robot.hcdf", "the root document"),
        ("arm.hcdf", "an included document"),
        ("models/hand.glb", "a verified model file"),
        ("robot.hcdf.lock", "the lock file"),
    ],
)
def test_an_export_through_the_index_never_writes_over_an_input(env, target, what):
    path = env.doc.parent / target
    trap = env.tmp / "trap"
    trap.mkdir()
    (trap / "cam.macsec.json").symlink_to(path)
    got = env.export("cam", "json", doc=None)
    r = env.cli("macsec", "export", env.doc, *env.base(), "--device", "cam", "--format", "json", "--out", trap)
    assert r.exit_code == 3 and f" is {what} ({path}): refusing to overwrite an input" in r.stderr, r.stderr
    with env.without_index():
        full = env.cli("macsec", "export", env.doc, *env.base(), "--device", "cam", "--format", "json", "--out", trap)
    assert (r.exit_code, r.stdout, r.stderr) == (full.exit_code, full.stdout, full.stderr)
    assert _path(got[0]) == "index"


def test_an_export_through_the_index_never_writes_into_the_cache(env):
    out = default_cache_dir() / "exports"
    got = env.export("cam", "json", "--out", out)
    assert got[0].exit_code == 3
    [error] = json.loads(got[0].stdout)["errors"]
    assert error["message"] == f"--out {out / 'cam.macsec.json'} is inside the cache ({default_cache_dir()})"
    _same(got, env.full("cam", "json", "--out", out))
    assert not out.exists()


# --- tree_digest, the code digest an index is bound to ------------------------------------------


def _package(root: Path) -> Path:
    files = {
        "pkg/__init__.py": "",
        "pkg/b.py": "B = 2\n",
        "pkg/a.py": "A = 1\n",
        "pkg/notes.txt": "not source\n",
        "pkg/sub/c.py": "C = 3\n",
        "pkg/sub/deeper/d.py": "D = 4\n",
        "pkg/__pycache__/a.cpython-311.pyc": "compiled",
    }
    for name, text in files.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_text(text)
    return root / "pkg"


def _oracle(top: Path) -> str:
    """What the docstring says: the path (relative, '/'-separated), length and bytes of every
    .py file outside __pycache__, in sorted order folder by folder."""
    h = hashlib.sha256()
    for rel in ["__init__.py", "a.py", "b.py", "sub/c.py", "sub/deeper/d.py"]:
        data = (top / rel).read_bytes()
        h.update(f"{rel}\0{len(data)}\0".encode() + data)
    return h.hexdigest()


def test_tree_digest_covers_path_length_and_bytes_of_every_py_file(tmp_path, monkeypatch):
    top = _package(tmp_path / "one")
    assert index.tree_digest(str(top)) == _oracle(top)
    monkeypatch.chdir(tmp_path / "one")
    assert index.tree_digest(str(top)) == _oracle(top)
    other = _package(tmp_path / "two" / "deeper")
    assert index.tree_digest(str(other)) == index.tree_digest(str(top))  # where it lies: no matter
    (other / "sub" / "deeper" / "d.py").write_text("D = 5\n")
    assert index.tree_digest(str(other)) != index.tree_digest(str(top))


def test_tree_digest_changes_with_a_renamed_file(tmp_path):
    top = _package(tmp_path)
    before = index.tree_digest(str(top))
    (top / "sub" / "c.py").rename(top / "sub" / "e.py")  # same bytes and folder, another name
    assert index.tree_digest(str(top)) != before


def test_code_digest_is_the_digest_of_the_running_package():
    import hcdf_trust

    assert index.code_digest() == index.tree_digest(os.path.dirname(hcdf_trust.__file__))
