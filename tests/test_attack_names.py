"""Attack: file names that are not UTF-8 (a hostile checkout or tarball can hold any bytes).

Each verb must refuse such a path with a clear input error (exit 3) naming it, not
die with UnicodeEncodeError: the lock file and ``--json`` are UTF-8 and cannot name it.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

DOC = b'<?xml version="1.0"?>\n<hcdf version="1.0" name="r"><comp name="c"/></hcdf>\n'


def _run(cwd: Path, *args: str | bytes) -> subprocess.CompletedProcess[str]:
    exe = [sys.executable, "-m", "hcdf_trust.cli"]
    return subprocess.run([*exe, *args], cwd=cwd, capture_output=True, text=True, timeout=60, check=False)


@pytest.mark.parametrize("verb", ["resolve", "verify", "pin", "validate"])
@pytest.mark.parametrize("where", ["file", "folder"])
def test_a_document_whose_path_is_not_utf8_is_an_input_error(tmp_path, verb, where):
    name = b"\xff.hcdf" if where == "file" else b"d\xfe/robot.hcdf"
    path = os.path.join(os.fsencode(tmp_path), name)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "wb") as f:
        f.write(DOC)
    r = _run(tmp_path, verb, name, "--json")
    assert r.returncode == 3, r.stderr
    assert "Traceback" not in r.stderr
    (error,) = json.loads(r.stdout)["errors"]
    assert "not valid UTF-8" in error["message"]


def test_a_flattened_output_whose_path_is_not_utf8_is_an_input_error(tmp_path):
    """Its references are rebased from its folder's URL (a --lock of that name is just written)."""
    (tmp_path / "robot.hcdf").write_bytes(DOC)
    r = _run(tmp_path, "resolve", "robot.hcdf", "--no-lock", "--out", b"\xfe.out", "--json")
    assert r.returncode == 3, r.stderr
    assert "Traceback" not in r.stderr
    assert "not valid UTF-8" in json.loads(r.stdout)["errors"][0]["message"]
    assert sorted(os.listdir(tmp_path)) == ["robot.hcdf"]
