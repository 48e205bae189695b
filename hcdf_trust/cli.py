"""The ``hcdf-trust`` command: parses, calls the library, renders. No logic here.

Heavy modules (httpx, rich) are imported inside the commands that
need them, so ``--help`` and an offline ``verify`` start fast.
"""

from __future__ import annotations

import functools
import json
import sys
from collections.abc import Callable
from typing import Any

import click

from . import __version__
from .errors import ErrorGroup, HcdfTrustError


def emit_json(payload: dict[str, Any]) -> None:
    click.echo(json.dumps(payload, indent=2, sort_keys=True))


def fail(errors: list[HcdfTrustError], *, as_json: bool, payload: dict[str, Any] | None = None) -> None:
    """Report errors (stderr, or JSON on stdout) and exit with the contract's code."""
    group = ErrorGroup(errors)
    if as_json:
        out = dict(payload or {})
        out["ok"] = False
        out["errors"] = [e.to_dict() for e in errors]
        emit_json(out)
    else:
        for e in errors:
            click.echo(f"error: {e}", err=True)
    sys.exit(group.exit_code)


def handle_errors(func: Callable[..., Any]) -> Callable[..., Any]:
    """Turn a library exception into the exit code and message of the CLI contract."""

    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return func(*args, **kwargs)
        except HcdfTrustError as exc:
            errors = exc.errors if isinstance(exc, ErrorGroup) else [exc]
            fail(errors, as_json=bool(kwargs.get("as_json")))

    return wrapper


def _mirror(ctx: click.Context, param: click.Parameter, values: tuple[str, ...]) -> tuple[tuple[str, str], ...]:
    out = []
    for value in values:
        prefix, sep, target = value.partition("=")
        if not sep or not prefix or not target:
            raise click.BadParameter(f"{value!r} is not PREFIX=DIR|URL")
        out.append((prefix, target))
    return tuple(out)


def resolve_options(func: Callable[..., Any]) -> Callable[..., Any]:
    """Options shared by every verb that resolves a document tree."""
    options = [
        click.option(
            "--lock", "lock_path", type=click.Path(dir_okay=False), help="Lock file [default: hcdf.lock beside DOC]."
        ),
        click.option(
            "--cache-dir",
            type=click.Path(file_okay=False),
            help="Content-addressed cache [default: ~/.cache/hcdf-trust].",
        ),
        click.option(
            "--base", help="Folder or URL that relative references resolve against (default: the referencing document)."
        ),
        click.option(
            "--root",
            type=click.Path(file_okay=False),
            help="Folder that local references may not leave [default: --base if a folder, else DOC's folder].",
        ),
        click.option(
            "--mirror",
            "mirrors",
            multiple=True,
            callback=_mirror,
            metavar="PREFIX=DIR|URL",
            help="Rewrite a URL prefix to a local folder or another server (repeatable).",
        ),
        click.option(
            "--ca-bundle",
            type=click.Path(dir_okay=False, exists=True),
            envvar="HCDF_TRUST_CA_BUNDLE",
            help="PEM file of CA certificates to trust for https [env: HCDF_TRUST_CA_BUNDLE].",
        ),
        click.option(
            "--timeout", type=float, default=30.0, show_default=True, help="Seconds without data before a fetch fails."
        ),
        click.option(
            "--max-size",
            "max_bytes",
            type=int,
            default=4 << 30,
            show_default=True,
            help="Largest body accepted from a server, in bytes.",
        ),
        click.option("--max-depth", type=int, default=16, show_default=True, help="Deepest include nesting accepted."),
        click.option("--strict", is_flag=True, help="Refuse weak pins (hex prefixes shorter than 64 digits)."),
        click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout."),
    ]
    for option in reversed(options):
        func = option(func)
    return func


def fetch_options(func: Callable[..., Any]) -> Callable[..., Any]:
    """Options of the verbs that may fetch (resolve, pin); verify never does."""
    options = [
        click.option(
            "--offline", is_flag=True, help="Use only local files, mirrors and the cache; never open a socket."
        ),
        click.option(
            "--allow-http", is_flag=True, help="Allow plain http:// for references pinned with a full SHA-256."
        ),
        click.option(
            "--jobs",
            "-j",
            type=click.IntRange(1, 64),
            default=16,
            show_default=True,
            help="Parallel network fetches (local hashing uses one thread per core).",
        ),
    ]
    for option in reversed(options):
        func = option(func)
    return func


@click.group(context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(__version__, prog_name="hcdf-trust")
def main() -> None:
    """Verify, lock and flatten everything an HCDF robot description references.

    Exit codes: 0 success, 1 integrity failure (digest mismatch, lock drift, bad
    signature), 2 usage error, 3 input error (missing or malformed file, network).
    """


@main.command()
@click.argument("doc", type=click.Path(dir_okay=False))
@resolve_options
@click.option(
    "--locked", is_flag=True, help="Fail (exit 1) if anything differs from the lock file or is missing from it."
)
@fetch_options
@click.option(
    "--out", "out", type=click.Path(dir_okay=False), help="Write one flattened document with every include expanded."
)
@click.option("--no-lock", is_flag=True, help="Do not write the lock file.")
@handle_errors
def resolve(doc: str, out: str | None, no_lock: bool, as_json: bool, **kw: Any) -> None:
    """Fetch every file DOC references, verify its SHA-256, cache it, write the lock file.

    Relative references resolve against the referencing document, or against
    --base. Nothing is written unless every reference verifies.
    """
    from .include.resolver import ResolveOptions

    options = ResolveOptions(**kw)
    res = _run_resolve(doc, options, as_json=as_json)
    flat = None
    if out:
        from .include.flatten import flatten

        flat = flatten(res, out_path=out)
    if flat is not None and out:
        from .store import atomic_write

        atomic_write(out, flat)
    if not no_lock:
        res.write_lock()
    wrote = ([] if no_lock else [str(res.lock_path)]) + ([out] if out else [])
    from .include.locate import display_path

    _report(res, as_json=as_json, wrote=[display_path(p) for p in wrote])


@main.command()
@click.argument("doc", type=click.Path(dir_okay=False))
@resolve_options
@handle_errors
def verify(doc: str, as_json: bool, **kw: Any) -> None:
    """Check DOC's tree against its lock file, offline; write nothing.

    Every file must be present locally, in a mirror or in the cache, and match
    both its pin and the lock.
    """
    from .include.resolver import ResolveOptions

    options = ResolveOptions(locked=True, offline=True, write_cache=False, **kw)
    res = _run_resolve(doc, options, as_json=as_json)
    _report(res, as_json=as_json, wrote=[])


@main.command()
@click.argument("doc", type=click.Path(dir_okay=False))
@resolve_options
@fetch_options
@click.option("--write", is_flag=True, help="Edit the files in place (default: only report what would change).")
@handle_errors
def pin(doc: str, write: bool, as_json: bool, **kw: Any) -> None:
    """Fill in missing and repair outdated sha attributes across DOC's include tree.

    Each edit is a minimal text edit of one attribute: comments and formatting
    are kept. Without --write, only reports what would change.
    """
    from .include.pin import pin_tree
    from .include.resolver import ResolveOptions

    report = pin_tree(doc, ResolveOptions(**kw), write=write)
    if report.errors:
        fail(report.errors, as_json=as_json, payload={"changes": [c.to_dict() for c in report.changes]})
    if as_json:
        emit_json(
            {
                "ok": True,
                "changes": [c.to_dict() for c in report.changes],
                "wrote": report.written,
                "warnings": list(report.warnings),
                "errors": [],
            }
        )
        return
    for w in report.warnings:
        click.echo(f"warning: {w}", err=True)
    verb = "pinned" if write else "would pin"
    for c in report.changes:
        click.echo(f"{c.file}:{c.line}: {verb} {c.uri} ({c.reason}): {c.old or '-'} -> {c.new}", err=True)
    click.echo(f"{len(report.changes)} change(s){'' if write else ' (dry run; use --write)'}", err=True)


@main.command()
@click.argument("doc", type=click.Path(dir_okay=False))
@click.option(
    "--schema", type=click.Path(dir_okay=False), help="XSD to validate against (the official schemas are not shipped)."
)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout.")
@handle_errors
def validate(doc: str, schema: str | None, as_json: bool) -> None:
    """Validate DOC against an XSD and check the HCDF semantic rules the XSD cannot express.

    Exits 1 if any error was found; every finding is listed, not just the first.
    """
    from .validate import validate_document

    report = validate_document(doc, schema=schema)
    if as_json:
        emit_json(
            {
                "ok": report.ok,
                "checked": report.checked,
                "schema": report.schema,
                "notes": list(report.notes),
                "findings": [f.to_dict() for f in report.findings],
                "errors": [f.to_dict() for f in report.findings if f.severity == "error"],
            }
        )
    else:
        for f in report.findings:
            click.echo(str(f), err=True)
        for n in report.notes:
            click.echo(f"note: {n}", err=True)
        if report.schema is None:
            click.echo("note: no --schema given: only the semantic rules were checked", err=True)
        errors = sum(1 for f in report.findings if f.severity == "error")
        click.echo(f"{errors} error(s), {len(report.findings) - errors} warning(s)", err=True)
    sys.exit(0 if report.ok else 1)


def _run_resolve(doc: str, options: Any, *, as_json: bool) -> Any:
    from .include.resolver import resolve as do_resolve

    with _progress(enabled=not as_json) as (on_start, on_progress):
        res = do_resolve(doc, options, on_start=on_start, on_progress=on_progress)
    if not res.ok:
        if not as_json:
            for w in res.warnings:
                click.echo(f"warning: {w}", err=True)
        fail(res.errors, as_json=as_json, payload=_payload(res))
    return res


class _progress:
    """A rich progress bar on stderr when it is a terminal; otherwise nothing."""

    def __init__(self, *, enabled: bool) -> None:
        self.enabled = enabled and sys.stderr.isatty()
        self.bar: Any = None

    def __enter__(self) -> tuple[Callable[[int], None] | None, Callable[[int, int], None] | None]:
        if not self.enabled:
            return None, None
        from rich.console import Console
        from rich.filesize import decimal
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

        self.bar = Progress(
            TextColumn("resolving"),
            BarColumn(),
            TextColumn("{task.completed}/{task.total} files"),
            TextColumn("{task.fields[verified]} hashed"),
            TimeElapsedColumn(),
            console=Console(stderr=True),
            transient=True,
        )
        self.bar.start()
        self.task = self.bar.add_task("resolve", total=0, verified=decimal(0))
        self.bytes = 0

        def on_start(n: int) -> None:
            self.bar.update(self.task, total=(self.bar.tasks[0].total or 0) + n)

        def on_progress(files: int, nbytes: int) -> None:
            self.bytes += nbytes
            self.bar.update(self.task, advance=files, verified=decimal(self.bytes))

        return on_start, on_progress

    def __exit__(self, *exc: Any) -> None:
        if self.bar is not None:
            self.bar.stop()


def _payload(res: Any) -> dict[str, Any]:
    from .document import Kind
    from .include.resolver import display_url, lock_url

    base = res.lock_path.parent
    artifacts = []
    for art in sorted(res.artifacts.values(), key=lambda a: a.url):
        artifacts.append(
            {
                "kind": art.kind.value,
                "uri": art.uri,
                "url": lock_url(art.url, base),
                "sha256": art.sha256,
                "size": art.size,
                "pin": art.pin_status,
                "source": art.source,
                "referenced_from": sorted({f"{u.doc}:{u.ref.line}" for u in art.uses}),
            }
        )
    firmware = [
        {"name": r.name, "version": r.version, "hash": r.sha, "file": src, "line": r.line}
        for src, r in res.others
        if r.kind is Kind.FIRMWARE
    ]
    extensions = [
        {"domain": r.domain, "version": r.version, "file": src, "line": r.line}
        for src, r in res.others
        if r.kind is Kind.EXTENSION
    ]
    return {
        "ok": res.ok,
        "root": display_url(res.root_location.url),
        "artifacts": artifacts,
        "firmware": firmware,
        "extensions": extensions,
        "summary": _summary(res),
        "warnings": list(res.warnings),
        "errors": [e.to_dict() for e in res.errors],
    }


def _summary(res: Any) -> dict[str, int]:
    arts = list(res.artifacts.values())
    return {
        "references": sum(len(a.uses) for a in arts),
        "files": len(arts),
        "pinned": sum(1 for a in arts if a.pin_status == "full"),
        "weak": sum(1 for a in arts if a.pin_status == "weak"),
        "unpinned": sum(1 for a in arts if a.pin_status == "unpinned"),
        "bytes_verified": sum(a.size or 0 for a in arts),
        "from_cache": sum(1 for a in arts if a.source == "cache"),
        "fetched": sum(1 for a in arts if a.source == "network"),
        "local": sum(1 for a in arts if a.source in ("file", "mirror")),
    }


def _report(res: Any, *, as_json: bool, wrote: list[str]) -> None:
    if as_json:
        payload = _payload(res)
        payload["wrote"] = wrote
        emit_json(payload)
        return
    for w in res.warnings:
        click.echo(f"warning: {w}", err=True)
    s = _summary(res)
    click.echo(
        f"{s['references']} references to {s['files']} files: {s['pinned']} pinned, {s['weak']} weak, "
        f"{s['unpinned']} unpinned; {s['bytes_verified']} bytes verified "
        f"({s['local']} local, {s['from_cache']} from cache, {s['fetched']} fetched)",
        err=True,
    )
    for path in wrote:
        click.echo(f"wrote {path}", err=True)


from .cli_ota import ota  # noqa: E402  (the ota verb group; imports nothing heavy)

main.add_command(ota)

if __name__ == "__main__":  # pragma: no cover
    main()
