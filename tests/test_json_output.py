"""`--json` is one JSON object: compact into a pipe (json's C encoder, fast on large plans),
indented on a terminal for a person reading it."""

from __future__ import annotations

import json
import os
import pty
import subprocess
import sys
from pathlib import Path

PROJECT = Path(__file__).resolve().parent.parent
DOC = PROJECT / "examples" / "robot" / "robot.hcdf"


def _verify(stdout: int) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "hcdf_trust.cli", "verify", str(DOC), "--json"], stdout=stdout, stderr=subprocess.DEVNULL
    )


def test_json_into_a_pipe_is_one_compact_line():
    proc = _verify(subprocess.PIPE)
    out, _ = proc.communicate(timeout=120)
    assert proc.returncode == 0, out
    assert out.count(b"\n") == 1 and out.endswith(b"\n")
    assert json.loads(out)["ok"] is True


def test_json_on_a_terminal_is_indented():
    leader, follower = pty.openpty()
    proc = _verify(follower)
    os.close(follower)
    chunks = []
    while True:
        try:
            data = os.read(leader, 65536)
        except OSError:  # EIO: the child closed the terminal
            break
        if not data:
            break
        chunks.append(data)
    os.close(leader)
    assert proc.wait(timeout=120) == 0
    text = b"".join(chunks).decode().replace("\r\n", "\n")
    assert '\n  "ok": true' in text
    assert json.loads(text)["ok"] is True
