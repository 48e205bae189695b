"""``hcdf-trust --version`` and shell completion (click's mechanism: ``_HCDF_TRUST_COMPLETE``)."""

from __future__ import annotations

import importlib.metadata
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

from hcdf_trust.cli import main

BIN = Path(sys.executable).parent  # the venv's bin, where the console script is installed


def test_version_is_the_installed_package_version(cli):
    r = cli("--version")
    assert r.exit_code == 0
    assert r.stdout == f"hcdf-trust, version {importlib.metadata.version('hcdf-trust')}\n"


@pytest.mark.parametrize("shell", ["bash", "zsh", "fish"])
def test_completion_script_for_each_shell(shell):
    r = CliRunner().invoke(main, [], prog_name="hcdf-trust", env={"_HCDF_TRUST_COMPLETE": f"{shell}_source"})
    assert r.exit_code == 0
    assert "_HCDF_TRUST_COMPLETE" in r.stdout and "hcdf-trust" in r.stdout


def _complete(words: list[str]) -> list[str]:
    env = {"COMP_WORDS": " ".join(words), "COMP_CWORD": str(len(words) - 1), "_HCDF_TRUST_COMPLETE": "bash_complete"}
    r = CliRunner().invoke(main, [], prog_name="hcdf-trust", env=env)
    assert r.exit_code == 0
    return [line.split(",", 1)[1] for line in r.stdout.splitlines()]


def test_completion_names_verbs_groups_and_options_loaded_lazily():
    assert "resolve" in _complete(["hcdf-trust", "res"])
    assert _complete(["hcdf-trust", "macsec", "rot"]) == ["rotate"]  # a group imported only when used
    options = _complete(["hcdf-trust", "verify", "--"])
    assert {"--lock", "--quiet", "--no-project-config", "--json"} <= set(options)  # shared options too


@pytest.mark.skipif(shutil.which("bash") is None, reason="bash is not installed")
def test_the_bash_script_completes_in_a_real_bash():
    """What docs/completion.md tells a user to put in ~/.bashrc, run by bash itself against the
    installed console script."""
    if not (BIN / "hcdf-trust").exists():
        pytest.skip(f"the console script is not installed in {BIN}")
    script = (
        'eval "$(_HCDF_TRUST_COMPLETE=bash_source hcdf-trust)"\n'
        "COMP_WORDS=(hcdf-trust ota bu); COMP_CWORD=2; _hcdf_trust_completion hcdf-trust\n"
        'echo "${COMPREPLY[@]}"; complete -p hcdf-trust\n'
    )
    env = {**os.environ, "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}"}
    r = subprocess.run(["bash", "-c", script], capture_output=True, text=True, env=env, timeout=60)
    assert r.returncode == 0, r.stderr
    assert r.stdout.splitlines() == ["build", "complete -o nosort -F _hcdf_trust_completion hcdf-trust"]
