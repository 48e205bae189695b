"""Issue 6 item 8: what a build step costs, pinned where a test can see it (bench/run.py measures it)."""

from __future__ import annotations

import gc
import json
import subprocess
import sys

from click.testing import CliRunner

import hcdf_trust.include.resolver as resolver_module
from hcdf_trust.cli import main

from ._kill import hcdf, model, sha


def test_the_cyclic_collector_is_off_during_a_command_and_back_on_after(tmp_path, monkeypatch):
    (tmp_path / "m.glb").write_bytes(b"m")
    doc = tmp_path / "robot.hcdf"
    doc.write_text(hcdf(model("m.glb", sha(b"m"))))
    seen = []
    real = resolver_module.resolve

    def spy(*args, **kwargs):
        seen.append(gc.isenabled())
        return real(*args, **kwargs)

    monkeypatch.setattr(resolver_module, "resolve", spy)
    assert gc.isenabled()
    for args in (["resolve", doc, "--cache-dir", tmp_path / "c"], ["verify", doc, "--cache-dir", tmp_path / "c"]):
        r = CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)
        assert r.exit_code == 0, r.output
        assert gc.isenabled()
    r = CliRunner().invoke(main, ["verify", str(tmp_path / "none.hcdf")])  # a failing command restores it too
    assert r.exit_code == 3 and gc.isenabled()
    assert seen == [False, False, False]


def test_the_collector_stays_on_for_the_verbs_driving_tuf_and_imgtool(monkeypatch):
    calls = []
    monkeypatch.setattr(gc, "disable", lambda: calls.append("off"))
    for verb in ("ota", "registry"):
        r = CliRunner().invoke(main, [verb, "--help"], catch_exceptions=False)
        assert r.exit_code == 0, r.output
    assert calls == []
    assert CliRunner().invoke(main, ["macsec", "--help"]).exit_code == 0
    assert calls == ["off"]


# -- the console script leaves without tearing the interpreter down -----------------------

_RUN = r"""
import atexit, sys
from hcdf_trust.cli import main

class Witness:  # alive to the end: its __del__ runs only if the interpreter is torn down
    def __del__(self):
        sys.stderr.write("torn down\n")

WITNESS = Witness()
atexit.register(lambda: sys.stderr.write("atexit ran\n"))
sys.argv = ["hcdf-trust", *sys.argv[1:]]
main()
"""


def _console(*args) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-c", _RUN, *map(str, args)], capture_output=True, text=True, timeout=120)


def _tree(tmp_path, count: int):
    (tmp_path / "m").mkdir()
    body = []
    for i in range(count):
        (tmp_path / "m" / f"{i}.glb").write_bytes(b"%d" % i)
        body.append(model(f"m/{i}.glb", sha(b"%d" % i), name=f"c{i}"))
    doc = tmp_path / "robot.hcdf"
    doc.write_text(hcdf("\n".join(body)))
    return doc


def test_a_console_run_ends_with_its_output_flushed_and_atexit_run_but_no_teardown(tmp_path):
    doc = _tree(tmp_path, 300)
    r = _console("resolve", doc, "--json", "--cache-dir", tmp_path / "c")
    assert r.returncode == 0, r.stderr
    payload = json.loads(r.stdout)  # 300 artifacts of JSON on a pipe: every byte arrived
    assert payload["ok"] and len(payload["artifacts"]) == 300
    assert "atexit ran" in r.stderr
    assert "torn down" not in r.stderr
    assert (tmp_path / "robot.hcdf.lock").is_file()


def test_a_console_run_keeps_every_exit_status(tmp_path):
    doc = _tree(tmp_path, 2)
    (tmp_path / "m" / "1.glb").write_bytes(b"changed")
    r = _console("resolve", doc, "--cache-dir", tmp_path / "c")
    assert r.returncode == 1 and "digest mismatch" in r.stderr and "atexit ran" in r.stderr
    r = _console("verify", tmp_path / "none.hcdf")
    assert r.returncode == 3 and "no such" in r.stderr
    r = _console("resolve", doc, "--jobs", "0")
    assert r.returncode == 2 and "--jobs" in r.stderr
    r = _console("--help")
    assert r.returncode == 0 and "resolve" in r.stdout and "torn down" not in r.stderr


def test_in_process_callers_are_not_ended(tmp_path):
    """CliRunner (and any caller of main.main) returns: no os._exit outside the console script."""
    doc = _tree(tmp_path, 2)
    r = CliRunner().invoke(main, ["resolve", str(doc), "--cache-dir", str(tmp_path / "c")], catch_exceptions=False)
    assert r.exit_code == 0
    r = CliRunner().invoke(main, ["verify", str(tmp_path / "none.hcdf")])
    assert r.exit_code == 3


def test_main_called_with_arguments_returns_by_system_exit(tmp_path):
    """An embedder's main([...]) raises SystemExit as click does: only main() ends the process."""
    code = "import sys\nfrom hcdf_trust.cli import main\ntry:\n    main(['--version'])\nexcept SystemExit as e:\n"
    code += "    print('returned', e.code)\n"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and "returned 0" in r.stdout, r


def test_a_resolve_imports_no_other_verb_group(tmp_path):
    doc = _tree(tmp_path, 1)
    code = (
        "import sys\nfrom hcdf_trust.cli import main\ntry:\n    main(sys.argv[1:])\nexcept SystemExit as e:\n"
        "    print(e.code, sorted(m for m in sys.modules if m.startswith('hcdf_trust.cli.')\n"
        "                         and m != 'hcdf_trust.cli.params'))\n"  # the click types every verb shares
    )
    args = ["resolve", str(doc), "--cache-dir", str(tmp_path / "c")]
    r = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=60)
    assert r.stdout.strip() == "0 []", r
    r = subprocess.run([sys.executable, "-c", code, "--help"], capture_output=True, text=True, timeout=60)
    assert "hcdf_trust.cli.ota" in r.stdout and "ota " in r.stdout  # --help lists every group (and loads them)
    for verb in ("pin", "validate"):  # built only when they run or --help lists them
        assert f"hcdf_trust.cli.{verb}" in r.stdout and f"  {verb} " in r.stdout
