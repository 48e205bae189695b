"""`-q/--quiet` on every verb: nothing on stderr but errors and warnings; results on stdout stay."""

from __future__ import annotations

import shutil

import click

from hcdf_trust.cli import main

from .conftest import PROJECT


def _leaves():
    def walk(group, path, ctx):
        for name in group.list_commands(ctx):
            command = group.get_command(ctx, name)
            if isinstance(command, click.Group):
                yield from walk(command, [*path, name], click.Context(command, parent=ctx, info_name=name))
            else:
                yield [*path, name]

    return list(walk(main, [], click.Context(main, info_name="hcdf-trust")))


def test_every_verb_has_quiet(cli):
    leaves = _leaves()
    assert len(leaves) > 20  # every verb of every group, not only resolve and verify
    for path in leaves:
        r = cli(*path, "--help")
        assert "-q, --quiet" in r.stdout, path


def test_quiet_keeps_warnings_and_errors_only(cli, tmp_path):
    shutil.copytree(PROJECT / "examples" / "robot", tmp_path / "robot")
    doc = tmp_path / "robot" / "robot.hcdf"
    # a lock of its own that does not exist yet, never written: the warnings are not ones an
    # earlier run said when it wrote the lock (docs/config.md#warnings), so every run says them
    fresh = ("--lock", tmp_path / "fresh.lock", "--no-lock")
    loud = cli("resolve", doc, *fresh)
    assert loud.exit_code == 0 and "references to" in loud.stderr
    quiet = cli("resolve", doc, *fresh, "--quiet")
    assert quiet.exit_code == 0
    warnings = [line for line in loud.stderr.splitlines() if line.startswith("warning: ")]
    assert warnings and quiet.stderr.splitlines() == warnings  # the example has a weak pin: still said
    model = tmp_path / "robot" / "models" / "chassis.glb"
    model.write_bytes(model.read_bytes() + b"x")
    failed = cli("verify", "-q", doc)
    assert failed.exit_code == 1 and "error: " in failed.stderr and "chassis.glb" in failed.stderr


def test_quiet_keeps_results_on_stdout(cli):
    doc = PROJECT / "examples" / "robot" / "robot.hcdf"
    loud, quiet = cli("macsec", "plan", doc), cli("macsec", "plan", doc, "-q")
    assert loud.exit_code == quiet.exit_code == 0
    assert quiet.stdout == loud.stdout and quiet.stdout
    warnings = [line for line in loud.stderr.splitlines() if line.startswith("warning: ")]
    assert quiet.stderr.splitlines() == warnings != loud.stderr.splitlines()  # the summary line went
