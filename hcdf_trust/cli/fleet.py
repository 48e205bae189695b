"""``hcdf-trust fleet``: what the robot's MCUs report over SMP, checked against the signed
release and the description. Parses, calls :mod:`hcdf_trust.fleet`, renders.

smpclient, smp and pyserial are imported inside the commands only.
"""

from __future__ import annotations

import functools
import sys
from typing import Any

import click

from . import emit_json, handle_errors, say, tree_options

DEFAULT_JOBS = 16  # == fleet.status.DEFAULT_JOBS (not imported: --help stays fast)
DEFAULT_TIMEOUT = 5.0


@click.group()
def fleet() -> None:
    """Device-reported image state (MCUmgr/SMP) against the signed release: status, update, confirm."""


def device_options(func: Any, *, jobs: int = DEFAULT_JOBS, timeout: float = DEFAULT_TIMEOUT) -> Any:
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
            default=jobs,
            show_default=True,
            help="Devices talked to at once.",
        ),
        click.option(
            "--timeout",
            type=click.FloatRange(0.1, 600),
            default=timeout,
            show_default=True,
            help="Seconds to wait for each answer of a device (each upload chunk's, for update).",
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


def _verified_release(release_dir: str, key: str, previous: tuple[str, ...]) -> tuple[Any, list[Any], Any]:
    """The release, verified exactly as ``ota verify`` does (exit 1 on any error), the
    manifests of the ``--previous`` releases, each verified with the same key, and the
    release's files (the images ``update`` sends are these verified bytes)."""
    from ..errors import ErrorGroup, InputError
    from ..ota.keys import load_public

    try:
        import serial  # noqa: F401
        import smp  # noqa: F401
        import smpclient  # noqa: F401
    except ImportError as exc:
        raise InputError(
            f"fleet needs the 'fleet' extra ({exc.name} is missing): pip install 'hcdf-trust[fleet]'"
        ) from None
    from ..ota.release import previous_manifest, read_release
    from ..ota.verify import check_release

    public = load_public(key)
    release, files = read_release(release_dir, public)
    errors = check_release(release, files, public)
    if errors:
        raise ErrorGroup(errors)
    return release, [previous_manifest(p, public) for p in previous], files


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
@click.option(
    "-o",
    "--out",
    type=click.Path(dir_okay=False),
    help="Write a version report signed with --host-key here (host-attested, not device attestation).",
)
@click.option(
    "--host-key",
    help="The host's private key that signs --out: a PEM file, or a PKCS#11 URI (pkcs11:token=…;object=…).",
)
@click.option(
    "--pin-file",
    type=click.Path(dir_okay=False),
    help="PKCS#11 user PIN [default: the URI's pin-source, else $HCDF_TRUST_PKCS11_PIN]; never on the command line.",
)
@click.option(
    "--passphrase-file",
    type=click.Path(dir_okay=False),
    help="Passphrase of an encrypted --host-key (mode 0600) [default: $HCDF_TRUST_PASSPHRASE].",
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
    out: str | None,
    host_key: str | None,
    pin_file: str | None,
    passphrase_file: str | None,
) -> None:
    """Ask each comp's MCU what it runs and judge it against the signed release.

    Verdicts: current, outdated, pending, unconfirmed, unknown-image, wrong-description,
    no-hcdf-group, unreachable, malformed-answer. Exit 0 only when every comp is current;
    1 for an unknown image or a release that does not verify (and any other verdict), 3
    when a device is unreachable or its answer malformed (and nothing worse was seen).
    SMP answers are unauthenticated: this reports what devices claim.
    """
    from ..fleet.status import run_status

    if (out is None) != (host_key is None):
        raise click.UsageError("--out and --host-key go together: the report is signed by the host")
    if passphrase_file is not None and host_key is None:
        raise click.UsageError("--passphrase-file needs --host-key")
    signer = None
    if host_key is not None and host_key.startswith("pkcs11:"):
        from ..fleet.report import token_signer
        from ..ota.hsm import HsmSigner, parse_uri, read_pin

        uri = parse_uri(host_key)
        hsm = HsmSigner(uri, read_pin(uri, pin_file))  # a wrong PIN stops here, before any device
        signer = token_signer(hsm)
    elif host_key is not None:
        from ..fleet.report import host_signer
        from ..ota.keys import load_private
        from ..passphrase import read_passphrase

        secret = read_passphrase(passphrase_file, required=False)
        signer = host_signer(load_private(host_key, secret))  # a wrong passphrase stops here, before any device
    release, before, _files = _verified_release(release_dir, key, previous)
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
    wrote: list[str] = []
    if out is not None:
        wrote = _write_report(
            report, out, signer, doc=doc, tree=tree, inputs=(release_dir, key, host_key, passphrase_file or pin_file)
        )
    if as_json:
        emit_json(
            {
                "ok": report.exit_code == 0,
                "release": {"sequence_number": release.sequence_number, "lock_sha256": release.lock_sha256},
                "devices": [d.to_json() for d in report.devices],
                "notices": [
                    {"code": n.code, "message": n.message, "file": n.file, "line": n.line} for n in report.notices
                ],
                "wrote": wrote,
                "errors": [e.to_dict() for e in errors],
            }
        )
    else:
        _table(report)
        for path in wrote:
            say(f"wrote {path} (host-attested version report)")
    sys.exit(report.exit_code)


def _write_report(
    report: Any, out: str, signer: Any, *, doc: str, tree: Any, inputs: tuple[str | None, ...]
) -> list[str]:
    """Sign and write the report through the one output plan (never onto an input)."""
    from ..errors import display_path
    from ..fleet import report as fleet_report
    from ..fleet.status import root_sha256
    from ..outputs import OutputPlan, protect_inputs

    release_dir, key, host_key, passphrase_file = inputs
    assert release_dir is not None and key is not None and host_key is not None
    plan = OutputPlan()
    res = report.resolution
    protect_inputs(plan, res, doc=doc, options=tree.resolve_options(locked=True))
    plan.protect(res.lock_path, what="the lock file")
    plan.protect_tree(release_dir, what="the release folder")
    plan.protect(key, what="the public key")
    if not host_key.startswith("pkcs11:"):
        plan.protect(host_key, what="the host key")
    if passphrase_file is not None:
        plan.protect(passphrase_file, what="the passphrase or PIN file")
    statement = fleet_report.payload(
        report, release_dir=release_dir, root_sha256=root_sha256(res), host_keyid=signer.public_key.keyid
    )
    plan.add(out, fleet_report.sign(statement, signer), flag="--out")
    return [display_path(p) for p in plan.commit()]


def _table(report: Any) -> None:
    rows = [("COMP", "DEVICE", "VERDICT", "RUNS", "RELEASE", "WHY")]
    for d in report.devices:
        active = next((s for s in d.slots if s.active), None)
        runs = f"{active.version} {active.hash[:12]}" if active else "-"
        want = f"{d.target.component.version} {(d.target.component.mcuboot_hash or '')[:12]}"
        uri = d.target.endpoint.uri if d.target.endpoint else "-"
        rows.append((_shown(d.target.comp), _shown(uri), d.verdict, _shown(runs), want, _shown(d.reason)))
    widths = [max(len(r[i]) for r in rows) for i in range(5)]
    echo = say
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
    """A device-supplied or description text as one table cell, its control characters
    escaped before the columns are measured (a device must not rewrite the terminal)."""
    from ..scrub import escape_controls

    return escape_controls(text)


UPLOAD_JOBS = 4  # == fleet.update.DEFAULT_UPLOAD_JOBS
UPLOAD_TIMEOUT = 30.0  # emulated and busy devices can take many seconds for one chunk


def _targets(doc: str, tree: Any, release: Any, devices: tuple[str, ...], only: tuple[str, ...]) -> list[Any]:
    from ..fleet.status import resolve_tree, targets

    todo, notices = targets(resolve_tree(doc, tree), release, _devices(devices), check_description=False)
    for n in notices:
        say(f"note: {n}")
    unknown = sorted(set(only) - {t.comp for t in todo})
    if unknown:
        raise click.UsageError(f"--only names comps with no released MCUboot image: {', '.join(unknown)}")
    return [t for t in todo if not only or t.comp in only]


def _render(outcomes: list[Any], verb: str, as_json: bool, release: Any) -> None:
    from ..fleet.update import exit_code

    code = exit_code(outcomes)
    errors = [o.error for o in outcomes if o.error is not None]
    if as_json:
        emit_json(
            {
                "ok": code == 0,
                "release": {"sequence_number": release.sequence_number, "lock_sha256": release.lock_sha256},
                "devices": [o.to_json() for o in outcomes],
                "errors": [e.to_dict() for e in errors],
            }
        )
    else:
        for o in outcomes:
            uri = o.target.endpoint.uri if o.target.endpoint else "-"
            say(f"{_shown(o.target.comp)} ({_shown(uri)}): {o.result}: {_shown(o.detail)}")
        for e in errors:
            say(f"error: {e}")
        counts: dict[str, int] = {}
        for o in outcomes:
            counts[o.result] = counts.get(o.result, 0) + 1
        say(f"fleet {verb}: " + (", ".join(f"{n} {r}" for r, n in sorted(counts.items())) or "no devices"))
    sys.exit(code)


@fleet.command(name="update")
@click.argument("doc", type=click.Path(dir_okay=False))
@functools.partial(device_options, jobs=UPLOAD_JOBS, timeout=UPLOAD_TIMEOUT)
@click.option("--only", multiple=True, metavar="COMP", help="Update only this comp (repeatable).")
@click.option("--confirm", is_flag=True, help="Mark the new image permanent instead of for test (no revert).")
@click.option("--dry-run", is_flag=True, help="Read each device's state and say what would happen; send nothing.")
@handle_errors
def update_cmd(
    doc: str,
    release_dir: str,
    key: str,
    devices: tuple[str, ...],
    jobs: int,
    timeout: float,
    tree: Any,
    as_json: bool,
    only: tuple[str, ...],
    confirm: bool,
    dry_run: bool,
) -> None:
    """Upload each comp's image of the verified release to its device's slot 1, check the
    device reports the release's hash, and mark it for test (--confirm: permanent).

    Resumes an interrupted upload where the device says it stopped. After the devices are
    reset, `fleet status` shows them unconfirmed until the application confirms (or
    `fleet confirm`). Exit 0 when every device got the image (or runs it), 1 when a device
    reports another image after the upload, 3 when one is unreachable or malformed.
    """
    import asyncio

    from ..fleet.update import update_one
    from ..ota.verify import image_path

    release, _, files = _verified_release(release_dir, key, ())
    todo = _targets(doc, tree, release, devices, only)
    with _progress(as_json or dry_run) as progress:
        work = [
            functools.partial(
                update_one,
                t,
                files.images[image_path(t.component)],
                confirm=confirm,
                dry_run=dry_run,
                timeout=timeout,
                progress=progress,
            )
            for t in todo
        ]
        from ..fleet.update import run_all

        outcomes = asyncio.run(run_all(jobs, work))
    _render(outcomes, "update", as_json, release)


@fleet.command(name="confirm")
@click.argument("doc", type=click.Path(dir_okay=False))
@device_options
@click.option("--only", multiple=True, metavar="COMP", help="Confirm only this comp (repeatable).")
@handle_errors
def confirm_cmd(
    doc: str,
    release_dir: str,
    key: str,
    devices: tuple[str, ...],
    jobs: int,
    timeout: float,
    tree: Any,
    as_json: bool,
    only: tuple[str, ...],
) -> None:
    """Confirm the running image on each device that runs the release's image (so it does
    not revert on the next reset); a device running anything else is left alone (exit 1)."""
    import asyncio

    from ..fleet.update import confirm_one, run_all

    release, _, _files = _verified_release(release_dir, key, ())
    todo = _targets(doc, tree, release, devices, only)
    work = [functools.partial(confirm_one, t, timeout=timeout) for t in todo]
    outcomes = asyncio.run(run_all(jobs, work))
    _render(outcomes, "confirm", as_json, release)


class _progress:
    """A progress bar per device on a terminal (rich); nothing otherwise."""

    def __init__(self, quiet: bool) -> None:
        self.enabled = not quiet and sys.stderr.isatty()
        self.bar: Any = None
        self.tasks: dict[str, Any] = {}

    def __enter__(self) -> Any:
        if not self.enabled:
            return None
        from rich.console import Console
        from rich.progress import Progress

        self.bar = Progress(console=Console(stderr=True), transient=False)
        self.bar.start()
        return self.update

    def update(self, target: Any, off: int, total: int) -> None:
        task = self.tasks.get(target.comp)
        if task is None:
            task = self.tasks[target.comp] = self.bar.add_task(_shown(target.comp), total=total)
        self.bar.update(task, completed=off)

    def __exit__(self, *exc: object) -> None:
        if self.bar is not None:
            self.bar.stop()
