"""Shared fixtures: the corpus location, an isolated cache, and a CLI runner."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import pytest
from click.testing import CliRunner

from hcdf_trust.cli import main

pytest_plugins = ["tests.servers", "tests._fleet"]  # loopback HTTP(S) servers; fleet robots and SMP devices

PROJECT = Path(__file__).resolve().parents[1]
CORPUS = Path(os.environ.get("HCDF_CORPUS", PROJECT.parent / "shared" / "corpus")).resolve()
MODELS = CORPUS / "hcdf_models"
HCDFORMAT = CORPUS / "hcdformat"


@pytest.fixture(autouse=True)
def _isolated_cache(tmp_path_factory, monkeypatch):
    """No test reads or writes the user's real cache."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path_factory.mktemp("xdg-cache")))


@pytest.fixture(autouse=True, scope="session")
def _private_umask():
    """Files the tests write are their owner's only, as a key handler's are: key, passphrase and
    PIN files are refused when others can read them (tests of that check chmod explicitly)."""
    old = os.umask(0o077)
    yield
    os.umask(old)


@dataclass
class CliResult:
    exit_code: int
    stdout: str
    stderr: str

    @property
    def json(self):
        return json.loads(self.stdout)


@pytest.fixture
def cli():
    """Run ``hcdf-trust ARGS...`` in-process; returns exit code, stdout and stderr."""

    def run(*args: str | os.PathLike[str]) -> CliResult:
        result = CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)
        return CliResult(result.exit_code, result.stdout, result.stderr)

    return run
