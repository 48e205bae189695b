"""The progress bar: shown on a terminal, absent otherwise (so logs and --json stay clean)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

from .conftest import PROJECT

CLI = Path(sys.executable).parent / "hcdf-trust"


def _run_on_a_pty(args: list[str], cwd: Path) -> tuple[int, bytes]:
    primary, secondary = os.openpty()
    try:
        proc = subprocess.run(
            [str(CLI), *args],
            cwd=cwd,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=secondary,
            env={**os.environ, "COLUMNS": "120", "TERM": "xterm"},
            timeout=60,
        )
    finally:
        os.close(secondary)
    out = b""
    while True:
        try:
            chunk = os.read(primary, 65536)
        except OSError:  # EIO once the other side is closed and drained
            break
        if not chunk:
            break
        out += chunk
    os.close(primary)
    return proc.returncode, out


def test_progress_bar_on_a_terminal_only(tmp_path, cli):
    robot = tmp_path / "robot"
    shutil.copytree(PROJECT / "examples" / "robot", robot)
    code, tty = _run_on_a_pty(["resolve", "robot.hcdf", "--no-lock", "--cache-dir", str(tmp_path / "c")], robot)
    assert code == 0, tty
    assert b"resolving" in tty
    assert b"9/9 files" in tty  # every distinct file counted once
    assert b"7.4 kB hashed" in tty  # 7,368 bytes, the sum of the nine files
    plain = cli("resolve", robot / "robot.hcdf", "--no-lock", "--cache-dir", tmp_path / "c")
    assert plain.exit_code == 0
    assert "resolving" not in plain.stderr
