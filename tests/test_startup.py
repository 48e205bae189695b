"""Start-up cost: a run imports only what it needs (no ssl/httpx without a remote fetch)."""

from __future__ import annotations

import json
import subprocess
import sys

from .conftest import PROJECT

# The modules a local run must not pay for: TLS and HTTP (fetch.py), the progress bar
# without a terminal, and the thread pool when every file is small.
HEAVY = ("ssl", "_ssl", "httpx", "httpcore", "hcdf_trust.include.fetch", "rich")

PROBE = """
import json, sys
from hcdf_trust.cli import main
try:
    main(sys.argv[1:])
except SystemExit as exc:
    code = exc.code
print(json.dumps({"code": code, "modules": sorted(sys.modules)}), file=sys.stderr)
"""


def _modules_after(*args: str) -> tuple[int, set[str]]:
    proc = subprocess.run([sys.executable, "-c", PROBE, *args], capture_output=True, text=True, cwd=PROJECT, timeout=60)
    report = json.loads(proc.stderr.strip().splitlines()[-1])
    return report["code"], set(report["modules"])


def test_local_resolve_imports_neither_ssl_nor_httpx(tmp_path):
    # not --offline: a tree with no remote reference must not load the fetcher either
    lock = tmp_path / "robot.hcdf.lock"
    code, modules = _modules_after(
        "resolve", "examples/robot/robot.hcdf", "--lock", str(lock), "--cache-dir", str(tmp_path / "c")
    )
    assert code == 0 and lock.exists()
    assert "click" in modules and "hcdf_trust.include.resolver" in modules  # the probe ran the verb
    assert not modules & set(HEAVY), sorted(modules & set(HEAVY))
    code, modules = _modules_after("verify", "examples/robot/robot.hcdf", "--lock", str(lock))
    assert code == 0
    assert not modules & set(HEAVY), sorted(modules & set(HEAVY))


def test_importing_the_cli_loads_no_network_code():
    code, modules = _modules_after("--version")
    assert code == 0
    assert not modules & {*HEAVY, "lxml", "hcdf_trust.include.resolver"}


def test_resolver_defaults_are_the_fetchers():
    """resolver.py repeats fetch.py's defaults so that it need not import it."""
    from hcdf_trust.include import fetch, resolver

    assert (resolver.DEFAULT_MAX_BYTES, resolver.DEFAULT_TIMEOUT) == (fetch.DEFAULT_MAX_BYTES, fetch.DEFAULT_TIMEOUT)


def test_hashing_threads_import_no_thread_pool(tmp_path):
    """Files large enough for the hashing threads (resolver.PARALLEL_MIN_BYTES) are hashed on
    plain threads: concurrent.futures would import logging on every such run."""
    import hashlib

    from hcdf_trust.include.resolver import PARALLEL_MIN_BYTES

    refs = []
    for i in range(3):
        data = bytes([i]) * PARALLEL_MIN_BYTES
        (tmp_path / f"m{i}.glb").write_bytes(data)
        refs.append(f'<model uri="m{i}.glb" sha="{hashlib.sha256(data).hexdigest()}"/>')
    doc = tmp_path / "robot.hcdf"
    doc.write_text(f'<hcdf version="1.0"><comp name="c">{"".join(refs)}</comp></hcdf>')
    code, modules = _modules_after("resolve", str(doc), "--cache-dir", str(tmp_path / "c"))
    assert code == 0 and (tmp_path / "robot.hcdf.lock").exists()
    assert not modules & {"concurrent.futures", "logging"}, sorted(modules & {"concurrent.futures", "logging"})


def test_a_resolve_writing_its_lock_imports_neither_tempfile_nor_secrets(tmp_path):
    """Temporary files come from store.create_temp: tempfile would bring shutil, random, bz2 and
    lzma (and secrets base64 and hmac) into every run's start-up."""
    lock = tmp_path / "robot.hcdf.lock"
    code, modules = _modules_after(
        "resolve", "examples/robot/robot.hcdf", "--lock", str(lock), "--cache-dir", str(tmp_path / "c")
    )
    assert code == 0 and lock.exists()  # written: the commit's temporary file was made
    unwanted = {"tempfile", "shutil", "random", "secrets", "bz2", "lzma"}
    assert not modules & unwanted, sorted(modules & unwanted)


def test_an_xml_run_never_imports_the_json_form(tmp_path):
    """xmlschema (~150 ms to import, ~0.3 s to build hcdf.xsd) is paid only when a JSON document
    is read: not by an XML run, even with --schema given."""
    from .conftest import CORPUS

    xsd = CORPUS / "hcdformat" / "hcdf.xsd"
    code, modules = _modules_after("validate", "examples/robot/robot.hcdf", "--schema", str(xsd))
    assert code == 0 and "hcdf_trust.validate" in modules
    assert "xmlschema" not in modules
    code, modules = _modules_after("verify", "examples/robot/robot.hcdf")
    assert code == 0 and not modules & {"xmlschema", "hcdf_trust.jsonform"}
    # the control: a JSON document does import it
    doc = tmp_path / "r.json"
    doc.write_text('{"hcdf": {"version": 1.0, "name": "r"}}')
    code, modules = _modules_after("validate", str(doc), "--schema", str(xsd))
    assert code == 0 and "xmlschema" in modules
