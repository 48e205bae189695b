"""A new user's install: `make demo` needs only Python (no Debian packages, no native extras),
says how to run the installed command; `--help` works where fcntl does not exist; a LICENSE."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

from .conftest import PROJECT


def _make_dry_run(target: str) -> str:
    """The commands `make TARGET` would run from scratch (-B: as if nothing were installed)."""
    # Under `make test` (CI) this make is a sub-make: MAKELEVEL/MAKEFLAGS would make it print
    # "Entering/Leaving directory" lines; --no-print-directory keeps its output the commands only.
    r = subprocess.run(
        ["make", "--no-print-directory", "-n", "-B", target], cwd=PROJECT, capture_output=True, text=True, check=True
    )
    return r.stdout


def test_make_demo_installs_no_system_packages_and_no_test_extras():
    demo = _make_dry_run("demo")
    assert "install-system-deps" not in demo and "apt-get" not in demo
    installs = [line for line in demo.splitlines() if " install " in line and "pip" in line]
    assert any(line.rstrip().endswith("install --quiet -e .") for line in installs), installs
    assert not any("[test]" in line for line in installs), installs
    last = demo.strip().splitlines()[-2:]  # what the user reads at the end: how to run the command
    assert "hcdf-trust --help" in last[0] and "export PATH=" in last[1], last


def test_make_test_installs_the_system_packages_and_the_test_extras():
    test = _make_dry_run("test")
    assert "install-system-deps" in test
    assert "-e '.[test]'" in test


def _script_with_packages(tmp_path, packages: str):
    ci = tmp_path / ".ci"
    ci.mkdir()
    shutil.copy(PROJECT / ".ci" / "install-system-deps", ci)
    (ci / "apt-packages").write_text(packages)
    for path, mode in ((ci, 0o755), (ci / "apt-packages", 0o644), (ci / "install-system-deps", 0o755)):
        path.chmod(mode)  # readable by the unprivileged user of the non-root test, whatever the umask
    return ci / "install-system-deps"


def test_system_deps_as_non_root_names_the_missing_packages_and_root():
    with tempfile.TemporaryDirectory(dir="/tmp") as folder:  # pytest's tmp_path is private to root
        os.chmod(folder, 0o755)
        script = _script_with_packages(Path(folder), "# a comment\nhcdf-trust-no-such-package\n")
        r = subprocess.run(
            ["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups", "bash", str(script)],
            capture_output=True,
            text=True,
        )
    assert r.returncode == 1
    assert "needs root" in r.stderr and "apt-get install hcdf-trust-no-such-package" in r.stderr, r.stderr


def test_system_deps_without_dpkg_says_so(tmp_path):
    script = _script_with_packages(tmp_path, "cmake\n")
    bin_dir = tmp_path / "bin"  # a PATH with bash and the coreutils it uses, but no dpkg-query
    bin_dir.mkdir()
    for tool in ("bash", "grep", "dirname", "id"):
        os.symlink(shutil.which(tool), bin_dir / tool)
    r = subprocess.run([bin_dir / "bash", script], capture_output=True, text=True, env={"PATH": str(bin_dir)})
    assert r.returncode == 1
    assert "not a Debian-based system" in r.stderr and "cmake" in r.stderr, r.stderr


def _without_fcntl(code: str) -> subprocess.CompletedProcess[str]:
    """Run ``code`` in a Python where ``import fcntl`` fails, as on Windows."""
    prelude = "import sys\nsys.modules['fcntl'] = None\n"
    return subprocess.run(
        [sys.executable, "-c", prelude + textwrap.dedent(code)], capture_output=True, text=True, cwd=PROJECT
    )


def test_help_of_every_verb_works_without_fcntl():
    r = _without_fcntl(
        """
        import click
        from click.testing import CliRunner
        from hcdf_trust.cli import main
        def walk(group, path):
            yield path
            if isinstance(group, click.Group):
                for name, sub in group.commands.items():
                    yield from walk(sub, [*path, name])
        for path in walk(main, []):
            result = CliRunner().invoke(main, [*path, "--help"])
            assert result.exit_code == 0, (path, result.output, result.exception)
        print("ok")
        """
    )
    assert r.returncode == 0 and r.stdout.strip() == "ok", r.stderr


def test_a_verb_that_writes_says_the_platform_lacks_flock(tmp_path):
    shutil.copytree(PROJECT / "examples" / "robot", tmp_path / "robot")
    (tmp_path / "robot" / "robot.hcdf.lock").unlink()
    r = _without_fcntl(
        f"""
        from click.testing import CliRunner
        from hcdf_trust.cli import main
        result = CliRunner().invoke(main, ["resolve", {str(tmp_path / "robot" / "robot.hcdf")!r}])
        print(result.exit_code)
        print(result.output)
        """
    )
    assert r.returncode == 0, r.stderr
    code, _, output = r.stdout.partition("\n")
    assert code == "3", r.stdout
    assert "flock" in output and "platform" in output and "Traceback" not in output, output
    assert not (tmp_path / "robot" / "robot.hcdf.lock").exists()


def test_license_file_is_apache_2_and_packaged():
    text = (PROJECT / "LICENSE").read_text()
    assert "Apache License" in text and "Version 2.0, January 2004" in text
    pyproject = (PROJECT / "pyproject.toml").read_text()
    assert 'license = "Apache-2.0"' in pyproject and 'license-files = ["LICENSE"]' in pyproject


def _demo_commands() -> list[str]:
    """The demo's own commands (after the install), as `make -n demo` prints them."""
    lines = _make_dry_run("demo").splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("rm -rf examples/out"))
    return [line for line in lines[start:] if line and not line.startswith("echo")]


def test_make_demo_reads_nothing_outside_the_checkout():
    """A fresh clone runs the demo with only Python: no ../shared/corpus, no other folder."""
    for line in _demo_commands():
        assert "shared/corpus" not in line and "CORPUS" not in line and " ../" not in line, line


def test_the_demo_says_each_warning_once(cli, tmp_path, monkeypatch):
    """Issue 20's Done-when: run every command of `make demo` (in-process, on a copy of examples/)
    and count the warning lines about each file: a lock-covered fact is said by the run that wrote
    the lock, a fact about a file referenced twice is one line."""
    from .test_flatten_root import demo_lines

    shutil.copytree(PROJECT / "examples", tmp_path / "examples", ignore=shutil.ignore_patterns("out"))
    monkeypatch.chdir(tmp_path)
    warnings: list[str] = []
    for args in demo_lines(Path("/nonexistent/corpus")):  # the demo needs none
        if isinstance(args, str):  # the shell line making the throwaway passphrase files
            subprocess.run(["bash", "-c", args], check=True)
            continue
        r = cli(*args)
        assert r.exit_code == 0, (args, r.stderr)
        warnings += [w for w in r.stderr.splitlines() if w.startswith("warning: ")]
    for name in ("chassis-hull.stl", "arm-ctrl.latest.json", "gripper.glb", "key-ref:arm-links"):
        said = [w for w in warnings if name in w]
        assert len(said) == 1, (name, said)
    assert len(warnings) == len(set(warnings)), warnings
