"""localfile.ConfinedFolders: open_checked's result and errors, one folder check per folder."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

import hcdf_trust.localfile as localfile
from hcdf_trust.errors import HcdfTrustError
from hcdf_trust.localfile import ConfinedFolders, hash_local, open_checked

from ._kill import sha


def _outcome(opener, path: Path, root: Path) -> tuple:
    """What opening ``path`` gives: (size, content) or (error class, message, actual)."""
    try:
        fd, st = opener(str(path), root, file="robot.hcdf", line=7)
    except HcdfTrustError as exc:
        assert (exc.file, exc.line) == ("robot.hcdf", 7)
        return type(exc), str(exc), exc.actual
    try:
        return st.st_size, os.read(fd, 100)
    finally:
        os.close(fd)


@pytest.fixture
def tree(tmp_path: Path) -> Path:
    """A root with plain files, links that stay inside and links that leave it."""
    root, outside, sibling = tmp_path / "robot", tmp_path / "secret", tmp_path / "robot-evil"
    for folder in (root / "m", root / "sub" / "deep", outside, sibling):
        folder.mkdir(parents=True)
    (root / "m" / "a.glb").write_bytes(b"inside a")
    (root / "sub" / "deep" / "b.glb").write_bytes(b"inside b")
    (outside / "key").write_bytes(b"secret")
    (sibling / "s.glb").write_bytes(b"sibling")
    (root / "m" / "in-link.glb").symlink_to("../sub/deep/b.glb")
    (root / "m" / "out-link.glb").symlink_to(outside / "key")
    (root / "m" / "sibling.glb").symlink_to("../../robot-evil/s.glb")
    (root / "out-dir").symlink_to(outside)
    (root / "in-dir").symlink_to("sub/deep")
    (root / "m" / "loop").symlink_to("loop")
    (root / "m" / "dir").mkdir()
    os.mkfifo(root / "m" / "fifo")
    (root / "m" / "zero").symlink_to("/dev/zero")
    return root


CASES = [
    "m/a.glb",
    "m/in-link.glb",
    "sub/deep/b.glb",
    "in-dir/b.glb",  # accepted
    "m/out-link.glb",
    "m/sibling.glb",
    "out-dir/key",
    "../secret/key",  # outside the root
    "m/missing.glb",
    "nope/a.glb",
    "m/a.glb/x",
    "m/loop",
    "m/dir",
    "m/fifo",
    "m/zero",
    "m/.",
    "m/..",
]


@pytest.mark.parametrize("rel", CASES)
def test_every_path_opens_or_fails_exactly_as_open_checked(tree, rel):
    """open_checked (one path lookup and one descriptor check per file) is the oracle."""
    path = Path(os.path.normpath(tree / rel)) if rel not in ("m/.", "m/..") else Path(f"{tree}/{rel}")
    folders = ConfinedFolders()
    try:
        for _ in range(2):  # the first open of a folder checks it, the second reuses the check
            assert _outcome(folders.open, path, tree) == _outcome(open_checked, path, tree)
    finally:
        folders.close()


def test_hash_matches_hash_local(tree):
    folders = ConfinedFolders()
    try:
        for rel in ("m/a.glb", "m/in-link.glb"):
            got = folders.hash(str(tree / rel), tree)
            assert got == hash_local(tree / rel, tree)
            assert got.inode == hash_local(tree / rel, tree).inode is not None
        assert folders.hash(str(tree / "m" / "a.glb"), tree).sha256 == sha(b"inside a")
    finally:
        folders.close()


def test_a_folder_is_checked_once_not_each_file(tree, monkeypatch):
    """The point of the class: one readlink per folder, where open_checked makes one per file."""
    for i in range(20):
        (tree / "m" / f"f{i}.glb").write_bytes(b"%d" % i)
    calls = []
    real_readlink = os.readlink
    monkeypatch.setattr(localfile.os, "readlink", lambda p: calls.append(p) or real_readlink(p))
    folders = ConfinedFolders()
    try:
        for i in range(20):
            assert folders.hash(str(tree / "m" / f"f{i}.glb"), tree).sha256 == sha(b"%d" % i)
    finally:
        folders.close()
    assert len(calls) == 1


def test_a_file_swapped_for_a_link_after_its_folder_was_checked_is_refused(tree):
    folders = ConfinedFolders()
    try:
        folders.hash(str(tree / "m" / "a.glb"), tree)
        (tree / "m" / "a.glb").unlink()
        (tree / "m" / "a.glb").symlink_to(tree.parent / "secret" / "key")
        expected = _outcome(open_checked, tree / "m" / "a.glb", tree)
        assert expected[0] is localfile.PathEscapeError
        assert _outcome(folders.open, tree / "m" / "a.glb", tree) == expected
    finally:
        folders.close()


def test_a_folder_swapped_for_a_link_after_its_check_never_leads_outside(tree):
    """The checked folder's descriptor is used, not its name: the link is not followed."""
    folders = ConfinedFolders()
    try:
        folders.hash(str(tree / "m" / "a.glb"), tree)
        (tree / "m").rename(tree / "m-old")
        (tree / "m").symlink_to(tree.parent / "secret")
        (tree.parent / "secret" / "a.glb").write_bytes(b"secret a")
        size, content = _outcome(folders.open, tree / "m" / "a.glb", tree)
        assert content == b"inside a"  # the folder that was checked, wherever it is now
    finally:
        folders.close()


def test_close_closes_every_folder_descriptor(tree):
    before = len(os.listdir("/proc/self/fd"))
    folders = ConfinedFolders()
    for rel in ("m/a.glb", "sub/deep/b.glb", "in-dir/b.glb", "out-dir/key"):
        _outcome(folders.open, tree / rel, tree)
    assert len(os.listdir("/proc/self/fd")) > before
    folders.close()
    assert len(os.listdir("/proc/self/fd")) == before


def test_past_the_folder_limit_files_are_still_checked(tree, monkeypatch):
    monkeypatch.setattr(ConfinedFolders, "MAX_FOLDERS", 1)
    folders = ConfinedFolders()
    try:
        assert _outcome(folders.open, tree / "m" / "a.glb", tree) == (8, b"inside a")
        assert _outcome(folders.open, tree / "sub" / "deep" / "b.glb", tree) == (8, b"inside b")
        assert _outcome(folders.open, tree / "out-dir" / "key", tree)[0] is localfile.PathEscapeError
    finally:
        folders.close()


@pytest.mark.parametrize("rel", CASES)
def test_hash_entry_is_hash_local_or_leaves_the_file_to_it(tree, rel):
    """The resolver's small-file path: hash_local's digest, size and inode for a plain
    entry of a checked folder, None (the general path decides) for everything else:
    never the content of a link, a file outside the root or a special file."""
    path = os.path.normpath(tree / rel) if rel not in ("m/.", "m/..") else f"{tree}/{rel}"
    folders = ConfinedFolders()
    try:
        for _ in range(2):  # the folder's first file, and one after its check
            got = folders.hash_entry(path, tree)
            if rel in ("m/a.glb", "sub/deep/b.glb", "in-dir/b.glb"):  # in-dir: a folder link that stays inside
                want = hash_local(path, tree)
                assert got == (want.sha256, want.size, want.inode)
            else:
                assert got is None
    finally:
        folders.close()


def test_hash_entry_hashes_large_files_and_leaves_other_roots_to_the_general_path(tree):
    (tree / "m" / "big.glb").write_bytes(b"x" * (3 * localfile.SMALL_FILE + 1))  # hash_fd's chunked reads
    (tree / "m" / "limit.glb").write_bytes(b"y" * localfile.SMALL_FILE)  # the one-read size
    folders = ConfinedFolders()
    try:
        for name in ("big.glb", "limit.glb"):
            want = hash_local(tree / "m" / name, tree)
            assert folders.hash_entry(str(tree / "m" / name), tree) == (want.sha256, want.size, want.inode)
        # The same folder under a root it is not inside: the remembered folder is not reused.
        assert folders.hash_entry(str(tree / "m" / "a.glb"), tree / "sub") is None
        assert folders.hash_entry(str(tree / "m" / "a.glb"), tree) is not None
    finally:
        folders.close()
    assert folders.hash_entry(str(tree / "m" / "a.glb"), tree) is not None  # after close: the folder again
    folders.close()


def test_hash_entry_after_its_folder_was_swapped_for_a_link_reads_the_checked_folder(tree):
    folders = ConfinedFolders()
    try:
        first = folders.hash_entry(str(tree / "m" / "a.glb"), tree)
        (tree / "m").rename(tree / "m-old")
        (tree / "m").symlink_to(tree.parent / "secret")
        (tree.parent / "secret" / "a.glb").write_bytes(b"secret a")
        assert folders.hash_entry(str(tree / "m" / "a.glb"), tree) == first
        assert first is not None and first[0] == sha(b"inside a")
    finally:
        folders.close()
