"""``hcdf-trust bundle``: resolve and verify a tree, then write it as one ``.hcdfz`` (hcdf_trust.bundle)."""

from __future__ import annotations

from typing import Any

import click

from . import emit_json, handle_errors, say, tree_options


@click.command()
@click.argument("doc", type=click.Path(dir_okay=False))
@click.argument("out", type=click.Path(dir_okay=False))
@tree_options
@click.option(
    "--max-elements",
    type=click.IntRange(1, 1_000_000_000),
    default=250_000,
    show_default=True,
    help="Most elements the bundled document may have once every include is expanded.",
)
@click.option(
    "--ca-bundle",
    type=click.Path(dir_okay=False),
    envvar="HCDF_TRUST_CA_BUNDLE",
    help="PEM CA certificates for https (--online) [env: HCDF_TRUST_CA_BUNDLE].",
)
@click.option(
    "--json", "as_json", is_flag=True, help="Print one JSON object on stdout: ok, bundle, sha256, size, entries, wrote."
)
@handle_errors
def bundle(doc: str, out: str, tree: Any, max_elements: int, ca_bundle: str | None, as_json: bool) -> None:
    """Write DOC's verified tree as OUT, one self-contained .hcdfz (upstream's format).

    The tree is verified first, under its lock (offline unless --online, which fetches what the
    cache lacks: remote files are carried in the bundle); every reference must be pinned, by the
    document (a full sha256) or the lock. The includes are flattened into one document, the first entry; each
    referenced file follows as assets/<name>_<sha>.<ext> with its full sha256 pin. Every entry is
    stored, the same tree gives the same bytes, and nothing is written unless all of it verified.
    `verify OUT` (and resolve, validate, audit, sbom, macsec, ota build) read it without extracting.
    """
    import os

    from ..bundle import build, is_bundle, unpinned
    from ..errors import ErrorGroup, display_path
    from ..include.lockfile import default_path
    from ..include.resolver import resolve
    from ..outputs import BUNDLE, ORDINARY, OutputPlan, protect_inputs

    if not is_bundle(out):
        raise click.BadParameter(f"{out}: a bundle's name ends in .hcdfz", param_hint="OUT")

    # Under the lock when there is one; a tree whose document pins everything needs none.
    locked = tree.lock_path is not None or os.path.lexists(default_path(os.path.abspath(doc)))
    options = tree.resolve_options(locked=locked, ca_bundle=ca_bundle)
    res = resolve(doc, options)
    if not as_json:
        for w in res.warnings:
            say(f"warning: {w}", always=True)
    errors: list[Any] = res.errors or unpinned(res)
    if errors:
        raise ErrorGroup(errors)
    plan = OutputPlan()
    protect_inputs(plan, res, doc=doc, options=options)
    plan.protect(res.lock_path, what="the lock file")
    replaces = (ORDINARY, BUNDLE)  # the previous bundle; never a document, key or store
    plan.check(out, flag="OUT", replaces=replaces)  # an input is named as such before the bundle is built
    data = build(
        res,
        root=options.root,
        base=options.base,
        mirrors=options.mirrors,
        cache_dir=options.cache_dir,
        max_elements=max_elements,
    )
    import hashlib

    from ..bundle import check_structure

    entries = check_structure(memoryview(data), shown=out)  # it reads back under our own rules, or is not written
    plan.add(out, data, flag="OUT", if_changed=True, replaces=replaces)
    wrote = [display_path(p) for p in plan.commit()]
    sha = hashlib.sha256(data).hexdigest()
    if as_json:
        emit_json(
            {
                "ok": True,
                "bundle": display_path(out),
                "sha256": sha,
                "size": len(data),
                "entries": [{"name": e.name, "size": e.size} for e in entries],
                "wrote": wrote,
                "unchanged": [display_path(p) for p in plan.unchanged],
                "errors": [],
            }
        )
        return
    state = "wrote" if wrote else "unchanged"
    say(f"{state} {display_path(out)}: {len(entries)} entries, {len(data)} bytes, sha256 {sha}")
