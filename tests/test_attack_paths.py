"""Attack: command-line paths that climb out of a symlink with ``..``, and messages about the lock.

The shell and the kernel resolve ``link/../x`` by following ``link`` first, then
climbing from its target; ``os.path.abspath`` collapses ``link/..`` lexically and
names another file. Every path given on the command line (DOC, ``--lock``,
``--out``, ``--root``, ``--schema``) must name the file ``ls`` shows.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

from .conftest import PROJECT

EXAMPLE = PROJECT / "examples" / "robot"


@pytest.fixture
def robot(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A copy of the example robot, ``elsewhere/deep/al -> ../../robot/assemblies``, run from tmp_path."""
    shutil.copytree(EXAMPLE, tmp_path / "robot")
    (tmp_path / "robot" / "robot.hcdf.lock").unlink()
    (tmp_path / "elsewhere" / "deep").mkdir(parents=True)
    os.symlink("../../robot/assemblies", tmp_path / "elsewhere" / "deep" / "al")
    monkeypatch.chdir(tmp_path)
    return tmp_path / "robot"


# The kernel reads elsewhere/deep/al/.. as robot/ (al's target's parent); abspath says elsewhere/deep/.
VIA_LINK = "elsewhere/deep/al/.."


@pytest.mark.parametrize("verb", ["resolve", "validate", "pin"])
def test_doc_through_a_symlink_and_dotdot_is_the_file_the_shell_opens(cli, robot: Path, verb: str) -> None:
    doc = f"{VIA_LINK}/robot.hcdf"
    assert Path(doc).resolve() == (robot / "robot.hcdf").resolve()  # the oracle: what the kernel opens
    r = cli(verb, doc)
    assert r.exit_code == 0, r.stderr
    assert "no such file" not in r.stderr


def test_verify_doc_through_a_symlink_and_dotdot(cli, robot: Path) -> None:
    assert cli("resolve", "robot/robot.hcdf").exit_code == 0
    r = cli("verify", f"{VIA_LINK}/robot.hcdf")
    assert r.exit_code == 0, r.stderr


def test_lock_through_a_symlink_and_dotdot_names_files_from_where_it_lands(cli, robot: Path) -> None:
    r = cli("resolve", "robot/robot.hcdf", "--lock", f"{VIA_LINK}/other.lock")
    assert r.exit_code == 0, r.stderr
    assert (robot / "other.lock").is_file() and not (robot.parent / "elsewhere" / "deep" / "other.lock").exists()
    # Written where it landed, its relative paths must hold from there: the same lock read by its real name.
    r = cli("verify", "robot/robot.hcdf", "--lock", "robot/other.lock")
    assert r.exit_code == 0, r.stderr


def test_out_through_a_symlink_and_dotdot_rebases_for_where_it_lands(cli, robot: Path) -> None:
    r = cli("resolve", "robot/robot.hcdf", "--root", ".", "--out", f"{VIA_LINK}/flat.hcdf")
    assert r.exit_code == 0, r.stderr
    flat = robot / "flat.hcdf"
    assert flat.is_file()
    # The flattened document's references hold from its own folder: it resolves again.
    r = cli("resolve", flat, "--no-lock")
    assert r.exit_code == 0, r.stderr


def test_root_through_a_symlink_and_dotdot_is_the_folder_the_shell_names(cli, robot: Path) -> None:
    r = cli("resolve", "robot/robot.hcdf", "--root", VIA_LINK, "--no-lock")
    assert r.exit_code == 0, r.stderr


def test_missing_default_lock_is_named_as_the_user_named_the_document(cli, robot: Path) -> None:
    r = cli("verify", "robot/robot.hcdf")
    assert r.exit_code == 3
    assert "robot/robot.hcdf.lock does not exist" in r.stderr
    assert str(robot) not in r.stderr  # no absolute path where the user gave a relative one
    r = cli("verify", "robot/robot.hcdf", "--json")
    (lock_error,) = [e for e in r.json["errors"] if e["code"] == "lock-file"]
    assert str(robot) not in lock_error["message"]


@pytest.mark.parametrize(
    "args",
    [
        ("--cache-dir", "robot"),  # the default lock robot/robot.hcdf.lock lies in the cache
        ("--lock", "robot/robot.hcdf/x.lock"),  # under a regular file
        ("--lock", "robot/models/chassis.glb"),
    ],
)
def test_output_errors_name_the_destination_relative_as_given(cli, robot: Path, args: tuple[str, str]) -> None:
    r = cli("resolve", "robot/robot.hcdf", *args)
    assert r.exit_code == 3
    (line,) = [ln for ln in r.stderr.splitlines() if ln.startswith("error:")]
    assert "--lock robot/" in line, line
    assert str(robot / "robot.hcdf") not in line, line


@pytest.mark.parametrize(
    ("out", "what"),
    [
        ("robot/assemblies/arm.hcdf", "is an included document"),
        (f"{VIA_LINK}/assemblies/sensor-head.hcdf", "is an included document"),
        ("robot/models/chassis.glb", "is a verified model file"),
    ],
)
def test_out_at_an_input_is_refused_as_an_input_before_flattening(cli, robot: Path, out: str, what: str) -> None:
    """Not as "would reference files outside its folder": the flattening root rule is not the problem."""
    before = (robot / "assemblies" / "arm.hcdf").read_bytes()
    r = cli("resolve", "robot/robot.hcdf", "--out", out)
    assert r.exit_code == 3
    (line,) = [ln for ln in r.stderr.splitlines() if ln.startswith("error:")]
    assert what in line and "refusing to overwrite an input" in line, line
    assert (robot / "assemblies" / "arm.hcdf").read_bytes() == before
