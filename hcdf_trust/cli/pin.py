"""``hcdf-trust pin``: fill in missing and weak sha attributes (hcdf_trust.include.pin)."""

from __future__ import annotations

from typing import Any

import click

from ..errors import counted
from . import emit_json, fail, fetch_options, handle_errors, resolve_options, say, warn


@click.command()
@click.argument("doc", type=click.Path(dir_okay=False))
@resolve_options
@fetch_options
@click.option("--write", is_flag=True, help="Edit the documents in place and update the lock (default: only report).")
@click.option(
    "--update",
    "update",
    multiple=True,
    metavar="URI",
    help="Accept the current content of this file where it disagrees with its sha or its lock entry: the uri "
    "as written in the document, its URL or its path (repeatable).",
)
@click.option("--all", "update_all", is_flag=True, help="Accept the current content of every file (like --update).")
@handle_errors
def pin(doc: str, write: bool, update: tuple[str, ...], update_all: bool, as_json: bool, **kw: Any) -> None:
    """Fill in missing and weak sha attributes across DOC's include tree, and update the lock.

    A missing or weak sha is filled in with the full SHA-256, from the lock's entry
    when it has one: content that differs from its lock entry is refused (exit 1),
    not pinned. A sha that disagrees with the content is replaced only for the
    files named with --update URI, or with --all; otherwise it is a digest
    mismatch (exit 1) and nothing is written. Each change shows the old and new
    digests and whether the lock agreed with the old one.

    Each edit is a minimal text edit of one attribute: comments and formatting are
    kept. --write writes the edited documents and the lock file (exactly what a
    following resolve writes) all together, or nothing. Without --write, nothing is
    written.
    """
    from ..bundle import is_bundle
    from ..errors import InputError
    from ..include.pin import pin_tree
    from ..include.resolver import ResolveOptions

    if is_bundle(doc):
        raise InputError(
            f"{doc}: a bundle: every reference in it is pinned already, and pin edits documents in place"
            " (pin the tree it was made from, then `hcdf-trust bundle` it again)",
            file=doc,
        )

    report = pin_tree(doc, ResolveOptions(**kw), write=write, update=update, update_all=update_all)
    payload = {
        "changes": [c.to_dict() for c in report.changes],
        "lock_changes": [c.to_dict() for c in report.lock_changes],
        "planned": report.planned,
        "wrote": report.written,
        "warnings": [w.to_dict() for w in report.warnings],
    }
    if report.errors:
        if not as_json:
            warn(report.warnings)
        fail(report.errors, as_json=as_json, payload=payload)
    if as_json:
        emit_json({"ok": True, **payload, "errors": []})
        return
    warn(report.warnings)
    verb = "pinned" if write else "would pin"
    for c in report.changes:
        say(f"{c.file}:{c.line}: {verb} {c.uri} ({c.reason}): {c.old or '-'} -> {c.new} [lock: {c.lock}]")
    added = sum(1 for lc in report.lock_changes if lc.old is None)
    for lc in report.lock_changes:
        if lc.old is not None:  # new entries are counted, not listed
            say(f"{'' if write else 'would '}lock {lc.url}: {lc.old} -> {lc.new or '(dropped)'}")
    for path in report.written:
        say(f"wrote {path}")
    tail = "" if write or not report.planned else f" (dry run: --write writes {', '.join(report.planned)})"
    say(
        f"{counted(len(report.changes), 'sha change')}, "
        f"{counted(len(report.lock_changes) - added, 'lock entry', 'lock entries')} changed, "
        f"{added} new{tail}"
    )
