"""``hcdf-trust bundle``: resolve and verify a tree, then write it as one ``.hcdfz`` (hcdf_trust.bundle);
``bundle push`` / ``bundle pull``: a bundle through an OCI registry (hcdf_trust.oci.bundle).

``bundle DOC OUT`` stays the writer: ``bundle`` is a group whose first argument, unless it is
``push``, ``pull`` or ``write``, is the writer's (a document named ``push`` is written ``./push``). The
registry verbs are ``ota push``/``ota pull``'s: the same reference grammar, credentials,
``--ca-bundle`` and ``--insecure-registry``.
"""

from __future__ import annotations

from typing import Any

import click

from . import CA_BUNDLE_OPTION, INSECURE_REGISTRY_OPTION, emit_json, handle_errors, say, tree_options
from .ota import signing_key_options
from .params import load_provenance_keys, provenance_key_options, sbom_referrers_option, source_date_epoch_option


class _WriterByDefault(click.Group):
    """A group whose arguments, when they do not start with a subcommand's name, go to ``write``."""

    default_command = "write"  # (tests/test_docs.py's command checker reads it too)

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        if args and args[0] not in self.commands and args[0] not in ctx.help_option_names:
            args = [self.default_command, *args]
        return super().parse_args(ctx, args)

    def format_usage(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        formatter.write_usage(ctx.command_path, "DOC OUT.hcdfz [OPTIONS] | push ... | pull ...")


@click.group(cls=_WriterByDefault)
def bundle() -> None:
    """Write a verified tree as one .hcdfz (`bundle DOC OUT.hcdfz`, short for `bundle write DOC
    OUT.hcdfz`), or push / pull a bundle through an OCI registry, verified on every pull."""


@bundle.command("write")
@click.argument("doc", type=click.Path(dir_okay=False))
@click.argument("out", type=click.Path(dir_okay=False))
@tree_options
@click.option(
    "--max-elements",
    # At most xml.MAX_DOCUMENT_ELEMENTS (not imported: lxml stays out of start-up), so that
    # what is written can be read again; tests/test_bounds.py checks the two agree.
    type=click.IntRange(1, 1_000_000),
    default=250_000,
    show_default=True,
    help="Most elements the bundled document may have once every include is expanded.",
)
@click.option(
    "--provenance",
    is_flag=True,
    help="Also write OUT.intoto.json (in-toto/SLSA, DSSE, signed with --key): the bundle and what it was built from.",
)
@signing_key_options(required=False)
@click.option("--builder-id", help="The provenance's runDetails.builder.id [default: the CI workflow, else ours].")
@source_date_epoch_option
@click.option(
    "--json", "as_json", is_flag=True, help="Print one JSON object on stdout: ok, bundle, sha256, size, entries, wrote."
)
@handle_errors
def write(
    doc: str,
    out: str,
    tree: Any,
    max_elements: int,
    provenance: bool,
    key: str | None,
    passphrase_file: str | None,
    pin_file: str | None,
    builder_id: str | None,
    source_date: Any,
    as_json: bool,
) -> None:
    """Write DOC's verified tree as OUT, one self-contained .hcdfz (upstream's format).

    The tree is verified first, under its lock (offline unless --online, which fetches what the
    cache lacks: remote files are carried in the bundle); every reference must be pinned, by the
    document (a full sha256) or the lock. The includes are flattened into one document, the first entry; each
    referenced file follows as assets/<name>_<sha>.<ext> with its full sha256 pin. Every entry is
    stored, the same tree gives the same bytes, and nothing is written unless all of it verified.
    --provenance also writes OUT.intoto.json beside it, signed with --key (`verify OUT
    --provenance` checks it); both are written, or neither.
    `verify OUT` (and resolve, validate, audit, sbom, macsec, ota build) read it without extracting.
    `hcdf-trust bundle DOC OUT` is short for `hcdf-trust bundle write DOC OUT`.
    """
    import os
    import time

    from ..bundle import build, is_bundle, unpinned
    from ..errors import ErrorGroup, display_path
    from ..include.lockfile import default_path
    from ..include.resolver import resolve
    from ..outputs import BUNDLE, ORDINARY, OutputPlan, protect_inputs

    if not is_bundle(out):
        raise click.BadParameter(f"{out}: a bundle's name ends in .hcdfz", param_hint="OUT")
    if is_bundle(doc):  # its assets are entries, not files: flatten/build read a tree
        raise click.BadParameter(
            f"{doc} is already a bundle: check it with `hcdf-trust verify {doc}`, or copy it as it is",
            param_hint="DOC",
        )
    if provenance and key is None:
        raise click.UsageError("--provenance needs --key (the key that signs it)")
    if not provenance and (key or passphrase_file or pin_file or builder_id):
        raise click.UsageError("--key, --passphrase-file, --pin-file and --builder-id need --provenance")

    # Under the lock when there is one; a tree whose document pins everything needs none.
    locked = tree.lock_path is not None or os.path.lexists(default_path(os.path.abspath(doc)))
    options = tree.resolve_options(locked=locked)
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
    if provenance:
        assert key is not None
        from ..ota.release import format_date
        from ..provenance.bundle import bundle_provenance, envelope_path
        from .ota import open_signer

        signer, inputs = open_signer(key, passphrase_file, pin_file)
        try:
            for path, what in inputs:
                plan.protect(path, what=what)
            date = format_date(source_date.timestamp() if source_date is not None else time.time())
            envelope = bundle_provenance(res, bundle=out, data=data, date=date, signers=[signer], builder_id=builder_id)
        finally:
            signer.close()
        plan.add(envelope_path(out), envelope, flag="--provenance", if_changed=True, replaces=(ORDINARY,))
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


@bundle.command()
@click.argument("path", metavar="X.hcdfz", type=click.Path(dir_okay=False))
@click.argument("target", metavar="oci://HOST[:PORT]/REPO:TAG")
@sbom_referrers_option("bundle", "`hcdf-trust sbom X.hcdfz`")
@provenance_key_options(besides_key=False)
@CA_BUNDLE_OPTION
@INSECURE_REGISTRY_OPTION
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout.")
@handle_errors
def push(
    path: str,
    target: str,
    sboms: tuple[str, ...],
    provenance_keys: tuple[str, ...],
    threshold: int,
    ca_bundle: str | None,
    insecure_registries: tuple[str, ...],
    as_json: bool,
) -> None:
    """Verify X.hcdfz as `verify` does, then push it to an OCI registry as one artifact (the
    bundle as its one layer), with its provenance (X.hcdfz.intoto.json, if any; verified first
    with --provenance-key) and each --sbom attached as referrers.
    Credentials: $HCDF_TRUST_OCI_USERNAME/PASSWORD or the Docker config."""
    from ..bundle import is_bundle
    from ..oci.bundle import push_bundle
    from ..oci.client import connect
    from ..oci.release import read_sbom

    if not is_bundle(path):
        raise click.BadParameter(f"{path}: a bundle's name ends in .hcdfz", param_hint="X.hcdfz")
    if threshold != 1 and not provenance_keys:
        raise click.UsageError("--threshold needs --provenance-key")
    keys = load_provenance_keys(provenance_keys, threshold) if provenance_keys else None
    attached = [read_sbom(p) for p in sboms]  # refused before anything is sent
    ref, client = connect(
        target, ca_bundle=ca_bundle, insecure_registries=insecure_registries, push=True, need_tag=True
    )
    with client:
        result = push_bundle(path, ref, client, sboms=attached, provenance_keys=keys, threshold=threshold)
    warnings = result.pop("warnings")
    if as_json:
        emit_json(
            {
                "ok": True,
                "reference": str(ref),
                **result,
                "warnings": [n.to_dict() for n in warnings],
                "errors": [],
            }
        )
        return
    for n in warnings:
        say(f"warning: {n}", always=True)
    say(f"pushed {path} ({result['size']} bytes, sha256 {result['sha256']}) to {ref} ({result['digest']})")
    for r in result["referrers"]:
        say(f"attached {r['artifactType']} ({r['digest']})")
    say(f"pull it with: hcdf-trust bundle pull {ref.with_digest(result['digest'])} --out X.hcdfz")


@bundle.command()
@click.argument("source", metavar="oci://HOST[:PORT]/REPO:TAG|@sha256:HEX")
@click.option("-o", "--out", required=True, type=click.Path(dir_okay=False), help="The bundle to write (*.hcdfz).")
@click.option(
    "--cache-dir",
    type=click.Path(file_okay=False),
    help="Content store of verified blobs [default: $XDG_CACHE_HOME/hcdf-trust].",
)
@click.option(
    "--require-provenance",
    is_flag=True,
    help="Fail unless a provenance referrer of this bundle is listed (it is verified whenever one is "
    "and --provenance-key is given; needs --provenance-key).",
)
@provenance_key_options(besides_key=False)
@click.option(
    "--trust-tag",
    is_flag=True,
    help="Pull by tag without a provenance to check: take whatever bundle the tag names today "
    "(a digest reference needs no flag).",
)
@CA_BUNDLE_OPTION
@INSECURE_REGISTRY_OPTION
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout.")
@handle_errors
def pull(
    source: str,
    out: str,
    cache_dir: str | None,
    require_provenance: bool,
    provenance_keys: tuple[str, ...],
    threshold: int,
    trust_tag: bool,
    ca_bundle: str | None,
    insecure_registries: tuple[str, ...],
    as_json: bool,
) -> None:
    """Pull a bundle from an OCI registry: the manifest pinned by its body's hash, the blob hashed
    while it streams, then verified as `verify X.hcdfz` verifies it (and its provenance referrer
    as `verify X.hcdfz` checks a provenance, given --provenance-key) in a staging folder, and only then
    written to --out (the verified provenance beside it, as OUT.intoto.json).

    A tag names whatever the registry says today: pulling by tag needs --provenance-key (and a
    provenance that verifies) or --trust-tag; a digest (@sha256:) needs neither."""
    from ..bundle import is_bundle
    from ..errors import display_path
    from ..oci.bundle import pull_bundle
    from ..oci.client import connect
    from ..oci.reference import parse_reference
    from ..store import default_cache_dir

    if not is_bundle(out):
        raise click.BadParameter(f"{out}: a bundle's name ends in .hcdfz", param_hint="--out")
    if (require_provenance or threshold != 1) and not provenance_keys:
        raise click.UsageError("--require-provenance and --threshold need --provenance-key")
    ref = parse_reference(source)
    if ref.digest is None and not provenance_keys and not trust_tag:
        raise click.UsageError(
            f"{source} names a tag, which is whatever the registry says today: pull by digest "
            "(oci://…@sha256:…, as `bundle push` prints it), give --provenance-key to have the bundle's "
            "provenance verify what the tag names, or --trust-tag to take it as it is"
        )
    keys = load_provenance_keys(provenance_keys, threshold) if provenance_keys else None
    ref, client = connect(ref, ca_bundle=ca_bundle, insecure_registries=insecure_registries)
    with client:
        report = pull_bundle(
            ref,
            client,
            out=out,
            cache_dir=cache_dir or str(default_cache_dir()),
            provenance_keys=keys,
            threshold=threshold,
            require_provenance=require_provenance,
            trust_tag=trust_tag,
        )
    checked = report.checked
    if as_json:
        emit_json(
            {
                "ok": True,
                "reference": report.reference,
                "digest": report.digest,
                "sha256": checked.sha256,
                "size": checked.size,
                "root": checked.root,
                "from_cache": report.from_cache,
                "provenance": report.provenance,
                "sboms": report.sboms,
                "warnings": [n.to_dict() for n in report.notices],
                "wrote": [display_path(p) for p in report.wrote],
                "errors": [],
            }
        )
        return
    for n in report.notices:
        say(f"warning: {n}", always=True)
    say(
        f"bundle {checked.root} from {report.reference} ({report.digest}): {checked.size} bytes verified"
        f"{' (from the cache)' if report.from_cache else ''}{', provenance verified' if report.provenance else ''}"
        f", written to {display_path(out)}"
    )
