"""``hcdf-trust fleet``: what the robot's MCUs report over SMP, checked against the signed
release and the description. Parses, calls :mod:`hcdf_trust.fleet`, renders.

smpclient, smp and pyserial are imported inside the commands only.
"""

from __future__ import annotations

import functools
import sys
from typing import Any

import click

from . import emit_json, handle_errors, tree_options

DEFAULT_JOBS = 16  # == fleet.status.DEFAULT_JOBS (not imported: --help stays fast)
DEFAULT_TIMEOUT = 5.0


@click.group()
def fleet() -> None:
    """Device-reported image state (MCUmgr/SMP) against the signed release: status, update, confirm."""


def device_options(func: Any) -> Any:
    """The options every fleet verb shares: the release, the devices, the bounds."""
    options: list[Any] = [
        click.option(
            "--release",
            "release_dir",
            required=True,
            type=click.Path(file_okay=False),
            help="Signed OTA release folder.",
        ),
        click.option(
            "--key", "key", required=True, type=click.Path(dir_okay=False), help="The release's public key (PEM)."
        ),
        click.option(
            "--device",
            "devices",
            multiple=True,
            metavar="COMP=URI",
            help="Where COMP's SMP server is: udp://HOST[:PORT] (default port 1337), serial:///dev/NAME?baud=N, "
            "socket://HOST:PORT. Default: the comp's <discovered><ip>/<port> over UDP.",
        ),
        click.option(
            "--jobs",
            type=click.IntRange(1, 256),
            default=DEFAULT_JOBS,
            show_default=True,
            help="Devices asked at once.",
        ),
        click.option(
            "--timeout",
            type=click.FloatRange(0.1, 600),
            default=DEFAULT_TIMEOUT,
            show_default=True,
            help="Seconds to wait for each answer of a device.",
        ),
        tree_options,
        click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout."),
    ]
    for option in reversed(options):
        func = option(func)
    return func


def _devices(pairs: tuple[str, ...]) -> dict[str, str]:
    out: dict[str, str] = {}
    for text in pairs:
        comp, sep, uri = text.partition("=")
        if not sep or not comp or not uri:
            raise click.UsageError(f"--device {text!r}: expected COMP=URI")
        if comp in out:
            raise click.UsageError(f"--device names comp {comp!r} twice")
        out[comp] = uri
    return out


def _verified_release(release_dir: str, key: str, previous: tuple[str, ...]) -> tuple[Any, list[Any]]:
    """The release, verified exactly as ``ota verify`` does (exit 1 on any error), and the
    manifests of the ``--previous`` releases, each verified with the same key."""
    from ..errors import ErrorGroup
    from ..ota.keys import load_public
    from ..ota.release import previous_manifest, read_release
    from ..ota.verify import check_release

    public = load_public(key)
    release, files = read_release(release_dir, public)
    errors = check_release(release, files, public)
    if errors:
        raise ErrorGroup(errors)
    return release, [previous_manifest(p, public) for p in previous]


@fleet.command(name="status")
@click.argument("doc", type=click.Path(dir_okay=False))
@device_options
@click.option(
    "--previous",
    multiple=True,
    help="An earlier release (folder or https URL) signed by the same key: a device running it is "
    "'outdated' rather than 'unknown-image'. Repeatable.",
)
@click.option(
    "--skip-description",
    is_flag=True,
    help="Do not ask the HCDF group (100) which description the firmware was built for.",
)
@handle_errors
def status_cmd(
    doc: str,
    release_dir: str,
    key: str,
    devices: tuple[str, ...],
    jobs: int,
    timeout: float,
    tree: Any,
    as_json: bool,
    previous: tuple[str, ...],
    skip_description: bool,
) -> None:
    """Ask each comp's MCU what it runs and judge it against the signed release.

    Verdicts: current, outdated, pending, unconfirmed, unknown-image, wrong-description,
    no-hcdf-group, unreachable, malformed-answer. Exit 0 only when every comp is current;
    1 for an unknown image or a release that does not verify (and any other verdict), 3
    when a device is unreachable or its answer malformed (and nothing worse was seen).
    SMP answers are unauthenticated: this reports what devices claim.
    """
    from ..fleet.status import run_status

    release, before = _verified_release(release_dir, key, previous)
    report = run_status(
        doc,
        tree,
        release,
        before,
        _devices(devices),
        jobs=jobs,
        timeout=timeout,
        check_description=not skip_description,
    )
    errors = [e for e in (d.error() for d in report.devices) if e is not None]
    if as_json:
        emit_json(
            {
                "ok": report.exit_code == 0,
                "release": {"sequence_number": release.sequence_number, "lock_sha256": release.lock_sha256},
                "devices": [d.to_json() for d in report.devices],
                "notices": [
                    {"code": n.code, "message": n.message, "file": n.file, "line": n.line} for n in report.notices
                ],
                "errors": [e.to_dict() for e in errors],
            }
        )
    else:
        _table(report)
    sys.exit(report.exit_code)


def _table(report: Any) -> None:
    rows = [("COMP", "DEVICE", "VERDICT", "RUNS", "RELEASE", "WHY")]
    for d in report.devices:
        active = next((s for s in d.slots if s.active), None)
        runs = f"{active.version} {active.hash[:12]}" if active else "-"
        want = f"{d.target.component.version} {(d.target.component.mcuboot_hash or '')[:12]}"
        uri = d.target.endpoint.uri if d.target.endpoint else "-"
        rows.append((_shown(d.target.comp), _shown(uri), d.verdict, _shown(runs), want, _shown(d.reason)))
    widths = [max(len(r[i]) for r in rows) for i in range(5)]
    echo = functools.partial(click.echo, err=True)
    for n in report.notices:
        echo(f"note: {n}")
    for r in rows:
        echo("  ".join(cell.ljust(w) for cell, w in zip(r[:5], widths, strict=True)) + "  " + r[5])
    counts: dict[str, int] = {}
    for d in report.devices:
        counts[d.verdict] = counts.get(d.verdict, 0) + 1
    summary = ", ".join(f"{n} {v}" for v, n in sorted(counts.items())) or "no devices"
    echo(f"fleet: {summary} (release {report.release.sequence_number}; SMP answers are unauthenticated)")


def _shown(text: str) -> str:
    """A device-supplied or description text as one printable cell (control characters
    escaped: a device must not be able to rewrite the terminal)."""
    return text if text.isprintable() else text.encode("unicode_escape").decode("ascii")
