"""``hcdf-trust sbom``: parses, calls :mod:`hcdf_trust.sbom`, writes through one OutputPlan.

The SBOM libraries are imported inside the command only (start-up stays light).
"""

from __future__ import annotations

from datetime import datetime
from typing import Any

import click

from . import emit_json, handle_errors, say, tree_options, warn
from .params import source_date_epoch_option


@click.command()
@click.argument("doc", type=click.Path(dir_okay=False))
@click.option(
    "--format", "fmt", required=True, type=click.Choice(["cyclonedx", "spdx"]), help="CycloneDX 1.6 or SPDX 3.0.1 JSON."
)
@click.option("-o", "--out", type=click.Path(dir_okay=False), help="Write the SBOM here [default: stdout, also -].")
@click.option(
    "--release",
    "release_dir",
    type=click.Path(file_okay=False),
    help="A release folder (ota build) of this tree: each firmware gets its signer, file digest and counter.",
)
@click.option(
    "--key", type=click.Path(dir_okay=False), help="Public key (PEM) the --release must verify with (required with it)."
)
@tree_options
@click.option(
    "--json",
    "as_json",
    is_flag=True,
    help="Print one JSON object on stdout: ok, format, warnings, wrote, and the SBOM itself (as `sbom`) without -o.",
)
@source_date_epoch_option
@handle_errors
def sbom(
    doc: str,
    fmt: str,
    out: str | None,
    release_dir: str | None,
    key: str | None,
    tree: Any,
    source_date: datetime | None,
    as_json: bool,
) -> None:
    """Write a bill of materials of DOC's verified tree: sub-assemblies with their author and
    license, comps (devices) with their board, firmware, drivers, every file with its SHA-256,
    and the dependency graph.

    The tree is verified first, under its lock (offline unless --online, as `verify` does); any error stops
    the run with nothing written. The same inputs give byte-identical output: the serial
    number comes from the lock's, root document's (and release's) digests, the time from
    SOURCE_DATE_EPOCH (else 1970-01-01T00:00:00Z).
    """
    from ..errors import ErrorGroup
    from ..include.resolver import resolve
    from ..outputs import OutputPlan, protect_inputs
    from ..sbom.model import collect, read_release

    if (release_dir is None) != (key is None):
        raise click.UsageError("--release and --key go together: a release's signer is only named once verified")
    options = tree.resolve_options(locked=True)
    res = resolve(doc, options)
    if not as_json:
        warn(res.warnings)
    if not res.ok:
        raise ErrorGroup(res.errors)
    release = read_release(release_dir, key) if release_dir is not None and key is not None else None
    facts = collect(res, release=release, fmt=fmt, created=source_date)
    if fmt == "cyclonedx":
        from ..sbom.cyclonedx import render
    else:
        from ..sbom.spdx import render
    data = render(facts)
    warnings = [*res.warnings, *facts.notices]
    if not as_json:
        warn(facts.notices)
    if out is None or out == "-":
        if as_json:
            import json

            emit_json(_payload(fmt, warnings, wrote=[], document=json.loads(data)))
            return
        from ..outputs import write_stdout

        write_stdout(data)  # a full or closed stdout: exit 3, with a message
        return
    plan = OutputPlan()
    protect_inputs(plan, res, doc=doc, options=options)
    plan.protect(res.lock_path, what="the lock file")
    if release_dir is not None and key is not None:
        plan.protect_tree(release_dir, what="the release folder")
        plan.protect(key, what="the public key")
    plan.add(out, data, flag="--out")
    from ..errors import display_path

    wrote = [display_path(path) for path in plan.commit()]
    if as_json:
        emit_json(_payload(fmt, warnings, wrote=wrote))
        return
    for path in wrote:
        say(f"wrote {path}")


def _payload(fmt: str, warnings: list[Any], *, wrote: list[str], document: Any = None) -> dict[str, Any]:
    out: dict[str, Any] = {"ok": True, "format": fmt, "warnings": [w.to_dict() for w in warnings], "wrote": wrote}
    if document is not None:
        out["sbom"] = document
    out["errors"] = []
    return out
