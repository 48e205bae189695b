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
# machine-readable parts of the specifications our outputs follow (see its README): SPDX 3.0.1, SUIT draft-34
SPECS = Path(os.environ.get("HCDF_SPECS", PROJECT.parent / "shared" / "specs")).resolve()


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
        argv = [str(a) for a in args]
        result = CliRunner().invoke(main, argv, catch_exceptions=False)
        if result.exit_code == 0 and argv[:2] == ["ota", "build"]:
            from tests._dendrite import check_cli_run

            check_cli_run(tuple(argv))  # every latest.json a build writes is one the fleet daemon reads
        if result.exit_code == 0 and argv[:1] == ["sbom"] and "spdx" in argv:
            from tests._spdx3 import check_cli_run as check_spdx

            check_spdx(argv, result.stdout)  # the official SPDX 3 validator accepts every SPDX document
        if result.exit_code == 0 and argv[:2] == ["macsec", "export"]:
            from tests._consumers import check_export

            check_export(argv)  # wpa_supplicant, systemd-networkd and iproute2 read what was exported
        return CliResult(result.exit_code, result.stdout, result.stderr)

    return run
