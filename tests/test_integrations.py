"""The integrations docs/integrations.md offers, run for real: the CMake snippet built with CMake and
Ninja, the pre-commit hook's command and the GitHub Actions example's commands. Each must
re-check after a model changes: a tampered GLB fails them."""

from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import yaml

from hcdf_trust.store import default_cache_dir

from .conftest import PROJECT

INTEGRATIONS = (PROJECT / "docs" / "integrations.md").read_text()
BIN = Path(sys.executable).parent  # the venv running the tests holds the hcdf-trust command


def _env(tmp_path: Path) -> dict[str, str]:
    return {**os.environ, "PATH": f"{BIN}{os.pathsep}{os.environ['PATH']}", "XDG_CACHE_HOME": str(tmp_path / "cache")}


def _flip(path: Path) -> None:
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x01
    path.write_bytes(bytes(data))


def _source_tree(tmp_path: Path) -> Path:
    src = tmp_path / "src"
    shutil.copytree(PROJECT / "examples" / "robot", src / "robot")
    return src


def test_cmake_snippet_rebuilds_when_a_model_the_lock_names_changes(tmp_path):
    snippet = re.search(r"```cmake\n(.*?)```", INTEGRATIONS, re.S).group(1)
    src = _source_tree(tmp_path)
    (src / "CMakeLists.txt").write_text(f"cmake_minimum_required(VERSION 3.19)\nproject(robot NONE)\n{snippet}")
    build = src / "build"
    env = _env(tmp_path)

    def run(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(args, cwd=src, env=env, capture_output=True, text=True, timeout=300)

    r = run("cmake", "-G", "Ninja", "-S", str(src), "-B", str(build))
    assert r.returncode == 0, r.stdout + r.stderr
    r = run("cmake", "--build", str(build))
    assert r.returncode == 0, r.stdout + r.stderr
    assert (build / "robot.flat.hcdf").is_file()
    assert "no work to do" in run("cmake", "--build", str(build)).stdout

    # a model reached only through an include (assemblies/arm.hcdf -> ../models/gripper.glb)
    gripper = src / "robot" / "models" / "gripper.glb"
    _flip(gripper)
    r = run("cmake", "--build", str(build))
    assert r.returncode != 0, r.stdout + r.stderr
    assert "gripper.glb" in r.stdout + r.stderr
    assert "no work to do" not in r.stdout
    _flip(gripper)
    r = run("cmake", "--build", str(build))
    assert r.returncode == 0, r.stdout + r.stderr

    # a changed lock re-runs CMake itself, which reads the list of files again
    lock = src / "robot" / "robot.hcdf.lock"
    lock.write_text(lock.read_text().replace("models/gripper.glb", "models/gripper-v2.glb"))
    (src / "robot" / "models" / "gripper-v2.glb").write_bytes(gripper.read_bytes())
    r = run("cmake", "--build", str(build))  # the lock no longer matches the tree: fails
    assert "Re-running CMake" in r.stdout, r.stdout
    assert "gripper-v2.glb" in (build / "build.ninja").read_text()


def test_pre_commit_hook_runs_verify_and_fails_on_a_tampered_model(tmp_path):
    (hook,) = yaml.safe_load((PROJECT / ".pre-commit-hooks.yaml").read_text())
    assert hook["id"] == "hcdf-trust-verify"
    assert hook["pass_filenames"] is False and hook["always_run"] is True  # a model may be the only change
    src = _source_tree(tmp_path)
    command = [*shlex.split(hook["entry"]), "robot/robot.hcdf"]  # what pre-commit runs, with `args`
    env = _env(tmp_path)
    subprocess.run(["hcdf-trust", "resolve", "robot/robot.hcdf", "--locked"], cwd=src, env=env, check=True)
    assert subprocess.run(command, cwd=src, env=env, capture_output=True).returncode == 0
    _flip(src / "robot" / "models" / "chassis.glb")
    r = subprocess.run(command, cwd=src, env=env, capture_output=True, text=True)
    assert r.returncode == 1, r.stderr
    assert "chassis.glb" in r.stderr


def test_github_actions_example_caches_the_store_and_fails_on_a_tampered_model(tmp_path, monkeypatch):
    workflow = yaml.safe_load((PROJECT / "examples" / "ci" / "github-actions.yml").read_text())
    steps = workflow["jobs"]["verify"]["steps"]
    (cache,) = [s for s in steps if s.get("uses", "").startswith("actions/cache@")]
    monkeypatch.delenv("XDG_CACHE_HOME", raising=False)  # as on a GitHub runner
    monkeypatch.setenv("HOME", str(tmp_path / "runner"))
    assert Path(os.path.expanduser(cache["with"]["path"])) == default_cache_dir()  # it caches the store
    runs = [s for s in steps if "run" in s]
    install, checks = runs[0], runs[1:]
    assert re.match(r"python -m pip install .*hcdf-trust", install["run"])  # not run here: the project is installed
    src = _source_tree(tmp_path)
    home = tmp_path / "home"
    env = {**_env(tmp_path), "HOME": str(home)}
    del env["XDG_CACHE_HOME"]

    def run_checks() -> subprocess.CompletedProcess[str]:
        script = "set -e\n" + "\n".join(s["run"] for s in checks)
        return subprocess.run(["bash", "-c", script], cwd=src, env=env, capture_output=True, text=True)

    r = run_checks()
    assert r.returncode == 0, r.stderr
    _flip(src / "robot" / "models" / "chassis.glb")
    r = run_checks()
    assert r.returncode == 1, r.stderr
    assert "chassis.glb" in r.stderr
