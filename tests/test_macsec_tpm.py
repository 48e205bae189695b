"""The TPM 2.0 backend: the store's data key sealed to a software TPM (swtpm) started by the tests."""

from __future__ import annotations

import shutil
import socket
import subprocess
import time
from pathlib import Path

import pytest

from ._macsec import comp, hcdf, link, port, tree

pytest.importorskip("tpm2_pytss")
pytestmark = pytest.mark.skipif(shutil.which("swtpm") is None, reason="swtpm (Debian swtpm) not installed")


def _free_pair() -> int:
    """A free port P with P+1 free too (the swtpm TCTI's control port is the server port + 1)."""
    while True:
        with socket.socket() as a:
            a.bind(("127.0.0.1", 0))
            port = int(a.getsockname()[1])
            with socket.socket() as b:
                try:
                    b.bind(("127.0.0.1", port + 1))
                except OSError:
                    continue
                return port


@pytest.fixture
def swtpm(tmp_path_factory):
    """Start a fresh swtpm on loopback; yields a function giving a TCTI for a new TPM (each its own seed)."""
    procs = []

    def start() -> str:
        state = tmp_path_factory.mktemp("tpmstate")
        for _ in range(5):
            server = _free_pair()
            ctrl = server + 1
            proc = subprocess.Popen(
                [
                    "swtpm", "socket", "--tpm2", "--tpmstate", f"dir={state}",
                    "--server", f"type=tcp,port={server},bindaddr=127.0.0.1",
                    "--ctrl", f"type=tcp,port={ctrl},bindaddr=127.0.0.1",
                    "--flags", "not-need-init,startup-clear",
                ],
                stdout=subprocess.DEVNULL,
                stderr=subprocess.PIPE,
            )  # fmt: skip
            deadline = time.monotonic() + 10
            while time.monotonic() < deadline and proc.poll() is None:
                try:
                    socket.create_connection(("127.0.0.1", server), timeout=0.2).close()
                    procs.append(proc)
                    return f"swtpm:host=127.0.0.1,port={server}"
                except OSError:
                    time.sleep(0.05)
            proc.kill()
            proc.wait()
        pytest.skip("swtpm did not start")

    yield start
    for proc in procs:
        proc.terminate()
        proc.wait(timeout=10)


@pytest.fixture
def doc(tmp_path: Path) -> Path:
    caps = ("gcm-aes-128",)
    body = [comp("a", port("p0", *caps)), comp("b", port("p0", *caps)), '<network name="n">']
    body += [link("l0", "a/p0", "b/p0", '<macsec policy="must-secure" key-ref="k"/>'), "</network>"]
    return tree(tmp_path / "d", {"robot.hcdf": hcdf(*body)})


def test_store_sealed_to_a_tpm(swtpm, doc, tmp_path, cli, monkeypatch):
    monkeypatch.delenv("HCDF_TRUST_PASSPHRASE", raising=False)
    tcti = swtpm()
    store = tmp_path / "keys"
    r = cli("macsec", "generate", doc, "--store", store, "--tpm", tcti, "--json")
    assert r.exit_code == 0, r.stderr
    assert r.json["created"] == ["key-ref:k"]
    assert '"method":"tpm"' in (store / "macsec-keys.json").read_text()
    r = cli("macsec", "status", doc, "--store", store, "--tpm", tcti, "--json")
    assert r.exit_code == 0, r.stderr
    kcv = r.json["associations"][0]["generations"][0]["kcv"]
    before = (store / "macsec-keys.json").read_bytes()
    # another TPM (another seed) cannot unseal it: exit 3, nothing changed
    other = swtpm()
    r = cli("macsec", "rotate", doc, "--store", store, "--tpm", other)
    assert r.exit_code == 3 and "sealed to another TPM" in r.stderr
    assert (store / "macsec-keys.json").read_bytes() == before
    # the same TPM still opens it
    r = cli("macsec", "status", doc, "--store", store, "--tpm", tcti, "--json")
    assert r.json["associations"][0]["generations"][0]["kcv"] == kcv
    r = cli("macsec", "status", doc, "--store", store, "--tpm", "swtpm:host=127.0.0.1,port=1")
    assert r.exit_code == 3 and "cannot reach the TPM" in r.stderr
