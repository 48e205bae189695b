"""The README's commands and examples are run here, so they cannot go stale."""

from __future__ import annotations

import re
import shutil

from .conftest import PROJECT

README = (PROJECT / "README.md").read_text()


def test_readme_opens_with_the_two_commands():
    first_block = re.search(r"```sh\n(.*?)```", README, re.S).group(1)
    commands = [line.split("#")[0].strip() for line in first_block.splitlines() if line.strip()]
    assert commands == ["make demo", "make test"]
    ci = (PROJECT / ".ci" / "run").read_text()
    assert "make test" in ci.splitlines()[-1]


def test_readme_library_example_runs(tmp_path, monkeypatch, capsys):
    shutil.copytree(PROJECT / "examples" / "robot", tmp_path / "examples" / "robot")
    lock = tmp_path / "examples" / "robot" / "robot.hcdf.lock"
    committed = lock.read_bytes()
    lock.unlink()
    monkeypatch.chdir(tmp_path)
    code = re.search(r"```python\n(.*?)```", README, re.S).group(1)
    exec(compile(code, "README.md", "exec"), {})
    assert "9 files verified" in capsys.readouterr().out
    # the lock the example writes is byte-identical to the committed one: deterministic
    assert lock.read_bytes() == committed
