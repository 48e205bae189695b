"""A resolve of content in a read-only checkout (someone else's tree, a read-only mount) never
writes its lock into that tree: a lock that would change needs --lock (exit 2 naming it)."""

from __future__ import annotations

import os
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "robot"


@pytest.fixture
def checkout(tmp_path) -> Iterator[Path]:
    """A copy of the example robot without its lock, in a folder this process cannot write:
    mode 0555, or ``chattr +i`` when running as root (root ignores mode bits; the way
    tests/test_outputs.py and tests/test_cache_tmp.py make a folder read-only for root)."""
    robot = tmp_path / "robot"
    shutil.copytree(EXAMPLE, robot)
    (robot / "robot.hcdf.lock").unlink()
    immutable = os.geteuid() == 0
    if immutable:
        chattr = shutil.which("chattr")
        if chattr is None or subprocess.run([chattr, "+i", robot], capture_output=True).returncode != 0:
            pytest.skip("running as root and chattr +i is not available here (root ignores mode 0555)")
    else:
        robot.chmod(0o555)
    try:
        yield robot
    finally:
        if immutable:
            subprocess.run(["chattr", "-i", robot], check=True)
        robot.chmod(0o755)


def test_a_lock_that_would_be_written_into_a_read_only_checkout_needs_lock(cli, checkout, tmp_path):
    doc = checkout / "robot.hcdf"
    before = sorted(os.listdir(checkout))
    r = cli("resolve", doc)
    assert r.exit_code == 2, r.stderr
    assert "is not writable (a read-only checkout?)" in r.stderr and "--lock" in r.stderr, r.stderr
    assert sorted(os.listdir(checkout)) == before
    mine = tmp_path / "mine.lock"
    assert cli("resolve", doc, "--lock", mine).exit_code == 0 and mine.is_file()  # the named fix
    assert cli("resolve", doc, "--no-lock").exit_code == 0
    assert cli("verify", doc, "--lock", mine).exit_code == 0
    assert sorted(os.listdir(checkout)) == before


def test_a_read_only_checkout_with_its_lock_up_to_date_resolves(cli, tmp_path):
    robot = tmp_path / "robot"
    shutil.copytree(EXAMPLE, robot)  # with the lock it ships, which matches the tree
    immutable = os.geteuid() == 0
    if immutable and subprocess.run(["chattr", "+i", robot], capture_output=True).returncode != 0:
        pytest.skip("running as root and chattr +i is not available here (root ignores mode 0555)")
    if not immutable:
        robot.chmod(0o555)
    try:
        r = cli("resolve", robot / "robot.hcdf")
        assert r.exit_code == 0, r.stderr
        assert "unchanged" in r.stderr
    finally:
        if immutable:
            subprocess.run(["chattr", "-i", robot], check=True)
        robot.chmod(0o755)
