"""localfile.py: regular files only, confined on the descriptor, bounded (mutation-testing killers)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from hcdf_trust.errors import InputError, NotFoundError, PathEscapeError
from hcdf_trust.localfile import (
    hash_local,
    open_checked,
    open_local,
    open_regular,
    read_bounded,
    read_chunks,
    read_input,
    stream_bounded,
)

from ._kill import hcdf, model, sha


def _close(pair: tuple[int, os.stat_result]) -> os.stat_result:
    os.close(pair[0])
    return pair[1]


# -- the descriptor check: a sibling whose name starts with the root's is outside ------


@pytest.mark.parametrize("sibling", ["robot-evil", "robotx"])
def test_a_link_into_a_sibling_sharing_the_roots_prefix_is_refused_on_the_descriptor(tmp_path, sibling):
    root, evil = tmp_path / "robot", tmp_path / sibling
    root.mkdir()
    evil.mkdir()
    (evil / "s.glb").write_bytes(b"outside")
    (root / "s.glb").symlink_to(evil / "s.glb")
    for target in (root / "s.glb", evil / "s.glb"):
        with pytest.raises(PathEscapeError) as info:
            open_checked(target, root, file="robot.hcdf", line=5)
        err = info.value
        assert err.file == "robot.hcdf" and err.line == 5
        assert err.actual == str(evil / "s.glb") and str(root) in err.expected
    with pytest.raises(PathEscapeError):
        hash_local(root / "s.glb", root)


def test_resolve_refuses_a_link_into_a_sibling_sharing_the_roots_prefix(cli, tmp_path):
    root, evil = tmp_path / "robot", tmp_path / "robot-evil"
    root.mkdir()
    evil.mkdir()
    (evil / "s.glb").write_bytes(b"outside")
    (root / "s.glb").symlink_to("../robot-evil/s.glb")
    doc = root / "robot.hcdf"
    doc.write_text(hcdf(model("s.glb", sha(b"outside"))))
    r = cli("resolve", doc, "--json", "--no-lock", "--cache-dir", tmp_path / "c")
    assert r.exit_code == 3, r.stdout
    [e] = r.json["errors"]
    assert e["code"] == "path-escape" and e["line"] == 3


def test_files_inside_the_root_and_links_that_stay_inside_are_accepted(tmp_path):
    root = tmp_path / "robot"
    (root / "m").mkdir(parents=True)
    (root / "m" / "a.glb").write_bytes(b"inside")
    (root / "link.glb").symlink_to("m/a.glb")
    for path in (root / "m" / "a.glb", root / "link.glb"):
        st = _close(open_checked(path, root))
        assert st.st_size == 6
    # the root given through a symlink is compared by its real path
    (tmp_path / "alias").symlink_to(root)
    assert _close(open_checked(tmp_path / "alias" / "m" / "a.glb", tmp_path / "alias")).st_size == 6
    assert _close(open_checked(root / "m" / "a.glb", str(root) + "/")).st_size == 6
    got = hash_local(root / "link.glb", root)
    assert (got.sha256, got.size) == (sha(b"inside"), 6)


def test_a_root_that_is_the_file_itself(tmp_path):
    f = tmp_path / "f"
    f.write_bytes(b"x")
    assert _close(open_checked(f, f)).st_size == 1


def test_open_checked_closes_its_descriptor_on_refusal(tmp_path):
    root, evil = tmp_path / "robot", tmp_path / "robot-evil"
    root.mkdir()
    evil.mkdir()
    (evil / "s").write_bytes(b"x")
    (root / "d").mkdir()
    before = len(os.listdir("/proc/self/fd"))
    for _ in range(20):
        with pytest.raises(PathEscapeError):
            open_checked(evil / "s", root)
        with pytest.raises(InputError):
            open_checked(root / "d", root)
        with pytest.raises(InputError):
            open_regular(root / "d")
    assert len(os.listdir("/proc/self/fd")) == before


# -- open_regular: what is refused, and how it is named --------------------------------


def test_missing_file_is_not_found_naming_it(tmp_path):
    missing = tmp_path / "nope.glb"
    with pytest.raises(NotFoundError) as info:
        open_regular(missing, file="d.hcdf", line=3, what="model")
    err = info.value
    assert err.file == "d.hcdf" and err.line == 3 and err.url == str(missing)
    assert f"{missing}: no such model" in str(err)
    with pytest.raises(NotFoundError, match="no such file"):
        open_checked(missing, tmp_path)


def test_a_directory_is_refused(tmp_path):
    with pytest.raises(InputError, match="is a directory") as info:
        open_regular(tmp_path, file="d.hcdf", line=2)
    assert info.value.file == "d.hcdf" and info.value.line == 2


def test_a_fifo_is_refused_at_once(tmp_path):
    fifo = tmp_path / "p"
    os.mkfifo(fifo)
    with pytest.raises(InputError, match=r"not a regular file \(a FIFO\)") as info:
        open_regular(fifo, file="d.hcdf", line=9)
    assert info.value.file == "d.hcdf" and info.value.line == 9
    with pytest.raises(InputError, match="a FIFO"):
        open_checked(fifo, tmp_path)


def test_a_device_is_refused(tmp_path):
    (tmp_path / "z").symlink_to("/dev/zero")
    with pytest.raises(InputError, match=r"not a regular file \(a device\)"):
        open_regular(tmp_path / "z")
    with pytest.raises(InputError, match="a device"):
        read_input(tmp_path / "z", limit=10)


def test_a_socket_is_refused_as_special(tmp_path):
    import socket

    path = tmp_path / "s"
    sock = socket.socket(socket.AF_UNIX)
    try:
        sock.bind(str(path))
        with pytest.raises(InputError):  # open() itself fails (ENXIO): still an input error
            open_regular(path)
    finally:
        sock.close()


def test_unopenable_paths_are_input_errors(tmp_path):
    (tmp_path / "loop").symlink_to("loop")
    (tmp_path / "f").write_bytes(b"x")
    for path in (tmp_path / "loop", tmp_path / "f" / "under"):
        with pytest.raises(InputError, match="cannot open") as info:
            open_regular(path, file="d.hcdf", line=1)
        assert not isinstance(info.value, NotFoundError) and info.value.line == 1


def test_open_regular_follows_links_and_returns_the_targets_stat(tmp_path):
    (tmp_path / "t").write_bytes(b"12345")
    (tmp_path / "l").symlink_to("t")
    fd, st = open_regular(tmp_path / "l")
    try:
        assert st.st_size == 5 and os.read(fd, 10) == b"12345"
        assert os.get_inheritable(fd) is False
    finally:
        os.close(fd)


def test_open_local_yields_a_descriptor_and_closes_it(tmp_path):
    (tmp_path / "f").write_bytes(b"abc")
    with open_local(tmp_path / "f", tmp_path) as fd:
        assert os.read(fd, 10) == b"abc"
    with pytest.raises(OSError):
        os.fstat(fd)


# -- bounded reads ---------------------------------------------------------------------


@pytest.mark.parametrize("size", [0, 1, 64 << 10, (64 << 10) + 1, (2 << 20) + 5])
def test_read_chunks_and_read_bounded_return_everything(tmp_path, size):
    data = os.urandom(size)
    (tmp_path / "f").write_bytes(data)
    fd = os.open(tmp_path / "f", os.O_RDONLY)
    try:
        assert b"".join(read_chunks(fd)) == data
        os.lseek(fd, 0, os.SEEK_SET)
        assert read_bounded(fd, size, source="f") == data
    finally:
        os.close(fd)


def test_read_bounded_refuses_one_byte_over_the_limit_naming_it(tmp_path):
    (tmp_path / "f").write_bytes(b"x" * 101)
    fd = os.open(tmp_path / "f", os.O_RDONLY)
    try:
        with pytest.raises(InputError) as info:
            read_bounded(fd, 100, source="lock.json", what="lock file")
        assert info.value.file == "lock.json" and "lock file is over the 100-byte limit" in str(info.value)
    finally:
        os.close(fd)


def test_read_bounded_refuses_a_file_that_grew_past_the_limit_while_read(tmp_path, monkeypatch):
    """The size is checked again after the read: fstat said small, the read found more."""
    (tmp_path / "f").write_bytes(b"x" * 50)
    fd = os.open(tmp_path / "f", os.O_RDONLY)
    _first_fstat_says_10_bytes(monkeypatch)
    try:
        with pytest.raises(InputError) as info:
            read_bounded(fd, 20, source="f")
        assert (info.value.message, info.value.file) == ("document is over the 20-byte limit", "f")  # the default
    finally:
        monkeypatch.undo()
        os.close(fd)


def test_stream_bounded_refuses_before_reading_naming_a_document_by_default(tmp_path):
    """Nothing is yielded for a file already over the limit (an image is never half-hashed)."""
    (tmp_path / "f").write_bytes(b"x" * 101)
    fd = os.open(tmp_path / "f", os.O_RDONLY)
    try:
        chunks = stream_bounded(fd, 100, source="f")
        with pytest.raises(InputError) as info:
            next(chunks)
        assert (info.value.message, info.value.file) == ("document is over the 100-byte limit", "f")
        assert b"".join(stream_bounded(fd, 101, source="f", what="image")) == b"x" * 101
    finally:
        os.close(fd)


def test_stream_bounded_refuses_a_file_that_grew_past_the_limit_across_chunks(tmp_path, monkeypatch):
    """fstat said small; the file is two 1 MiB reads and a byte, each read under the limit, the
    sum over it: refused once the sum passes it, after no more than the limit was yielded."""
    (tmp_path / "f").write_bytes(b"x" * ((2 << 20) + 1))
    fd = os.open(tmp_path / "f", os.O_RDONLY)
    _first_fstat_says_10_bytes(monkeypatch)
    yielded = 0
    try:
        with pytest.raises(InputError) as info:
            for chunk in stream_bounded(fd, (1 << 20) + 1, source="image.bin", what="image"):
                yielded += len(chunk)
        assert (info.value.message, info.value.file) == (f"image is over the {(1 << 20) + 1}-byte limit", "image.bin")
        assert yielded == 1 << 20
    finally:
        monkeypatch.undo()
        os.close(fd)


def test_read_input_reads_a_regular_file_and_names_errors_by_source(tmp_path):
    p = tmp_path / "k.pem"
    p.write_bytes(b"key")
    assert read_input(p, limit=3) == b"key"
    with pytest.raises(InputError) as info:
        read_input(p, limit=2, what="key", source="KEY")
    assert info.value.file == "KEY" and "key is over the 2-byte limit" in str(info.value)
    with pytest.raises(InputError) as info:
        read_input(p, limit=2)
    assert info.value.file == str(p)
    with pytest.raises(NotFoundError) as info:
        read_input(tmp_path / "none", limit=5, what="key", source="KEY")
    assert info.value.file == "KEY" and "no such key" in str(info.value)


def test_read_input_of_a_directory_fifo_or_device_is_refused_at_once(tmp_path):
    os.mkfifo(tmp_path / "fifo")
    for path in (tmp_path, tmp_path / "fifo", Path("/dev/zero")):
        with pytest.raises(InputError):
            read_input(path, limit=1 << 20)


def test_read_input_closes_its_descriptor_on_success_and_refusal(tmp_path):
    p = tmp_path / "f"
    p.write_bytes(b"x")
    before = len(os.listdir("/proc/self/fd"))
    for _ in range(10):
        read_input(p, limit=1)
        with pytest.raises(InputError):
            read_input(p, limit=0)
    assert len(os.listdir("/proc/self/fd")) == before


def test_a_read_error_after_open_is_an_input_error_naming_the_input():
    """/proc/self/mem is a regular file whose first read fails (EIO): a read error, not a crash."""
    with pytest.raises(InputError) as info:
        read_input("/proc/self/mem", limit=10, what="key", source="KEY")
    assert info.value.file == "KEY" and "KEY: cannot read key: Input/output error" in str(info.value)


def test_default_words_name_a_file(tmp_path):
    with pytest.raises(NotFoundError, match="no such file"):
        open_regular(tmp_path / "none")
    with pytest.raises(NotFoundError, match="no such file"):
        read_input(tmp_path / "none", limit=1)
    with pytest.raises(InputError, match=f"{tmp_path} is a directory"):
        open_regular(tmp_path)
    with pytest.raises(InputError, match=f"{tmp_path} is a directory"):
        open_checked(tmp_path, tmp_path)


def test_absolute_resolves_link_dotdot_as_the_kernel_does(tmp_path):
    from hcdf_trust.localfile import absolute

    (tmp_path / "real" / "deep").mkdir(parents=True)
    (tmp_path / "real" / "x.hcdf").write_text("x")
    (tmp_path / "link").symlink_to(tmp_path / "real" / "deep")
    given = str(tmp_path / "link" / ".." / "x.hcdf")
    fd = os.open(given, os.O_RDONLY)  # the kernel's answer
    try:
        kernel = os.readlink(f"/proc/self/fd/{fd}")
    finally:
        os.close(fd)
    assert absolute(given) == kernel == str(tmp_path / "real" / "x.hcdf")
    assert os.path.abspath(given) != kernel  # the lexical answer names another file


def _first_fstat_says_10_bytes(monkeypatch):
    """localfile's first fstat reports a 10-byte file (the file grows after it was checked)."""
    import hcdf_trust.localfile as localfile

    real_fstat = os.fstat
    calls = []

    def small_first(n):
        st = real_fstat(n)
        calls.append(n)
        if len(calls) == 1:
            return os.stat_result((st.st_mode, st.st_ino, st.st_dev, 1, 0, 0, 10, 0, 0, 0))
        return st

    monkeypatch.setattr(localfile.os, "fstat", small_first)
