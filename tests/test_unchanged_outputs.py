"""A rebuild over an unchanged tree touches no file: resolve leaves a lock (and an --out) that
already holds exactly its bytes alone (OutputPlan.add(if_changed=True)), and rewrites it as
before whenever anything differs. Also store.create_temp, the temporary file every write uses."""

from __future__ import annotations

import json
import os
import stat

import pytest
from click.testing import CliRunner

import hcdf_trust.store as store_module
from hcdf_trust.cli import main
from hcdf_trust.outputs import OutputError, OutputPlan

from ._kill import hcdf, model, sha


def _tree(tmp_path):
    (tmp_path / "m.glb").write_bytes(b"model")
    (tmp_path / "n.glb").write_bytes(b"unpinned")
    doc = tmp_path / "robot.hcdf"
    doc.write_text(hcdf(model("m.glb", sha(b"model"), name="a") + model("n.glb", name="b")))
    return doc


def _resolve(doc, *args):
    r = CliRunner().invoke(
        main, ["resolve", str(doc), "--cache-dir", str(doc.parent / "c"), *map(str, args)], catch_exceptions=False
    )
    return r


def _identity(path):
    st = os.lstat(path)
    return st.st_ino, st.st_mtime_ns, st.st_ctime_ns


def _listing(folder):
    return sorted(p.name for p in folder.iterdir())


def test_a_second_resolve_leaves_the_lock_untouched(tmp_path):
    doc = _tree(tmp_path)
    lock = tmp_path / "robot.hcdf.lock"
    first = _resolve(doc)
    assert first.exit_code == 0, first.output
    assert f"wrote {lock}" in first.stderr
    before, names = _identity(lock), _listing(tmp_path)
    again = _resolve(doc)
    assert again.exit_code == 0, again.output
    assert _identity(lock) == before  # same inode, not even a rename of identical bytes
    assert _listing(tmp_path) == names  # no temporary file or backup left either
    assert f"unchanged {lock}" in again.stderr and "wrote" not in again.stderr
    out = json.loads(_resolve(doc, "--json").stdout)
    assert out["ok"] and out["wrote"] == [] and out["unchanged"] == [str(lock)]


def test_a_lock_that_would_change_is_rewritten(tmp_path):
    doc = _tree(tmp_path)
    lock = tmp_path / "robot.hcdf.lock"
    assert _resolve(doc).exit_code == 0
    old = lock.read_bytes()
    (tmp_path / "o.glb").write_bytes(b"new model")  # a new reference: a new lock entry
    doc.write_text(hcdf(model("m.glb", sha(b"model"), name="a") + model("n.glb", name="b") + model("o.glb", name="c")))
    before = _identity(lock)
    r = _resolve(doc)
    assert r.exit_code == 0, r.output
    assert f"wrote {lock}" in r.stderr
    assert _identity(lock)[0] != before[0] and lock.read_bytes() != old
    assert "o.glb" in lock.read_text()


@pytest.mark.parametrize(
    "damage",
    [
        pytest.param(lambda lock: lock.write_bytes(lock.read_bytes().replace(b'"size": 5', b'"size":5')), id="bytes"),
        pytest.param(lambda lock: lock.write_bytes(lock.read_bytes() + b"\n"), id="longer"),
        pytest.param(lambda lock: lock.chmod(0o600), id="mode"),
    ],
)
def test_a_lock_that_differs_in_any_byte_or_its_mode_is_rewritten(tmp_path, damage):
    """Same entries, other bytes (a json-equivalent spelling, a trailing newline) or another mode:
    what resolve writes is the canonical lock, so it writes it."""
    doc = _tree(tmp_path)
    lock = tmp_path / "robot.hcdf.lock"
    assert _resolve(doc).exit_code == 0
    canonical = lock.read_bytes()
    damage(lock)
    before = _identity(lock)
    r = _resolve(doc)
    assert r.exit_code == 0, r.output
    assert f"wrote {lock}" in r.stderr
    assert _identity(lock)[0] != before[0]
    assert lock.read_bytes() == canonical and stat.S_IMODE(lock.stat().st_mode) == 0o644


def test_a_symlinked_lock_with_the_same_bytes_is_still_replaced_by_a_file(tmp_path):
    """A destination that is a symlink is replaced, never written through nor kept: as before."""
    doc = _tree(tmp_path)
    lock = tmp_path / "robot.hcdf.lock"
    assert _resolve(doc).exit_code == 0
    elsewhere = tmp_path / "elsewhere.lock"
    os.rename(lock, elsewhere)
    lock.symlink_to(elsewhere.name)
    r = _resolve(doc)
    assert r.exit_code == 0, r.output
    assert f"wrote {lock}" in r.stderr
    assert not lock.is_symlink() and lock.read_bytes() == elsewhere.read_bytes()


def test_drift_is_still_reported_and_the_lock_left_as_it_was(tmp_path):
    doc = _tree(tmp_path)
    lock = tmp_path / "robot.hcdf.lock"
    assert _resolve(doc).exit_code == 0
    old, before = lock.read_bytes(), _identity(lock)
    (tmp_path / "n.glb").write_bytes(b"changed")
    r = _resolve(doc)
    assert r.exit_code == 1
    assert "changed since it was locked" in r.stderr and sha(b"changed") in r.stderr
    assert lock.read_bytes() == old and _identity(lock) == before
    r = _resolve(doc, "--update", "n.glb")
    assert r.exit_code == 0 and f"wrote {lock}" in r.stderr and sha(b"changed") in lock.read_text()


def test_an_unchanged_out_document_is_left_untouched_too(tmp_path):
    doc = _tree(tmp_path)
    flat = tmp_path / "robot.flat.hcdf"
    assert _resolve(doc, "--out", flat).exit_code == 0
    before = _identity(flat)
    r = _resolve(doc, "--out", flat)
    assert r.exit_code == 0, r.output
    assert _identity(flat) == before and f"unchanged {flat}" in r.stderr


def test_a_destination_that_is_an_input_is_refused_even_with_the_same_bytes(tmp_path):
    """if_changed never gets around the input check: the refusal comes first."""
    (tmp_path / "in.bin").write_bytes(b"same")
    plan = OutputPlan()
    plan.protect(tmp_path / "in.bin", what="the root document")
    with pytest.raises(OutputError, match="is the root document"):
        plan.add(tmp_path / "in.bin", b"same", flag="--lock", if_changed=True)


def test_only_outputs_added_with_if_changed_are_skipped(tmp_path):
    (tmp_path / "a").write_bytes(b"A")
    (tmp_path / "b").write_bytes(b"B")
    (tmp_path / "a").chmod(0o644)
    (tmp_path / "b").chmod(0o644)
    a, b = _identity(tmp_path / "a"), _identity(tmp_path / "b")
    plan = OutputPlan()
    plan.add(tmp_path / "a", b"A", flag="--a", if_changed=True)
    plan.add(tmp_path / "b", b"B", flag="--b")
    plan.add(tmp_path / "c", b"C", flag="--c", if_changed=True)  # new: written
    assert plan.commit() == [tmp_path / "b", tmp_path / "c"]
    assert plan.unchanged == [tmp_path / "a"]
    assert _identity(tmp_path / "a") == a and _identity(tmp_path / "b")[0] != b[0]
    assert (tmp_path / "c").read_bytes() == b"C"


# -- store.create_temp: tempfile.mkstemp's guarantees, without importing tempfile --------------


def _fixed_names(monkeypatch, *values: bytes):
    """os.urandom returns ``values`` in turn (then random bytes): the names create_temp tries."""
    queue = list(values)
    real = os.urandom
    monkeypatch.setattr(store_module.os, "urandom", lambda n: queue.pop(0) if queue else real(n))


def test_create_temp_makes_a_new_private_file(tmp_path):
    fd, path = store_module.create_temp(tmp_path, ".x.", ".tmp")
    try:
        st = os.fstat(fd)
        assert stat.S_ISREG(st.st_mode) and stat.S_IMODE(st.st_mode) == 0o600 and st.st_size == 0
        assert os.path.isabs(path) and os.path.dirname(path) == str(tmp_path)
        name = os.path.basename(path)
        assert name.startswith(".x.") and name.endswith(".tmp") and len(name) == len(".x..tmp") + 12
        assert os.get_inheritable(fd) is False
        os.write(fd, b"data")
    finally:
        os.close(fd)
    assert open(path, "rb").read() == b"data"


def test_create_temp_never_opens_an_existing_file_or_follows_a_planted_link(tmp_path, monkeypatch):
    taken = tmp_path / ".x.000000000000"
    taken.write_bytes(b"someone else's")
    target = tmp_path / "target"
    (tmp_path / ".x.111111111111").symlink_to(target)  # a link planted at the next name, to a new file
    _fixed_names(monkeypatch, bytes(6), b"\x11" * 6, b"\x22" * 6)
    fd, path = store_module.create_temp(tmp_path, ".x.")
    os.close(fd)
    assert path == str(tmp_path / ".x.222222222222")
    assert taken.read_bytes() == b"someone else's" and not target.exists()


def test_create_temp_gives_up_after_a_hundred_names_taken(tmp_path, monkeypatch):
    (tmp_path / ".x.000000000000").write_bytes(b"")
    monkeypatch.setattr(store_module.os, "urandom", lambda n: bytes(n))
    with pytest.raises(FileExistsError):
        store_module.create_temp(tmp_path, ".x.")


def test_create_temp_in_a_missing_folder_is_file_not_found(tmp_path):
    with pytest.raises(FileNotFoundError):
        store_module.create_temp(tmp_path / "none", ".x.")
