"""``hcdf-trust ota``: keygen, build, verify, sign-provenance. Parses, calls :mod:`hcdf_trust.ota`, renders.

imgtool, cbor2 and the COSE library are imported inside the commands only.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import click

from ..errors import counted
from . import CA_BUNDLE_OPTION, INSECURE_REGISTRY_OPTION, emit_json, handle_errors, say, tree_options, warn
from .params import load_provenance_keys, provenance_key_options, sbom_referrers_option, source_date_epoch_option


def signing_key_options(*, required: bool) -> Callable[[Any], Any]:
    """``--key``, ``--passphrase-file`` and ``--pin-file``: the same for every verb that signs
    (ota build, ota sign-provenance, bundle --provenance)."""

    def apply(func: Any) -> Any:
        func = click.option(
            "--pin-file",
            type=click.Path(dir_okay=False),
            help="PKCS#11 user PIN [default: the URI's pin-source, else $HCDF_TRUST_PKCS11_PIN]; "
            "never on the command line.",
        )(func)
        func = click.option(
            "--passphrase-file",
            type=click.Path(dir_okay=False),
            help="Passphrase of an encrypted key file (mode 0600) [default: $HCDF_TRUST_PASSPHRASE].",
        )(func)
        return click.option(
            "--key",
            "key",
            required=required,
            help="Signing key: a PEM file, or a PKCS#11 URI (pkcs11:token=…;object=…).",
        )(func)

    return apply


KEY_TYPES = ("ecdsa-p256", "ed25519", "rsa-2048", "rsa-3072")  # == ota.keys.KEY_TYPES (not imported: --help stays fast)


@click.group()
def ota() -> None:
    """MCUboot-signed images, latest.json and a signed SUIT release manifest from the HCDF."""


@ota.command()
@click.option("--type", "kind", type=click.Choice(KEY_TYPES), default="ecdsa-p256", show_default=True)
@click.option("-o", "--out", required=True, type=click.Path(dir_okay=False), help="Private key file (PEM, mode 0600).")
@click.option(
    "--passphrase-file",
    type=click.Path(dir_okay=False),
    help="Encrypt the private key with this passphrase (the file minus one final newline, mode 0600) "
    "[default: $HCDF_TRUST_PASSPHRASE, else not encrypted].",
)
@click.option("--force", is_flag=True, help="Replace an existing key file.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout.")
@handle_errors
def keygen(kind: str, out: str, passphrase_file: str | None, force: bool, as_json: bool) -> None:
    """Generate a signing key with imgtool; the public key goes beside it (KEY.pub.pem)."""
    from ..ota.keys import generate, key_type, private_pem, public_path, public_pem
    from ..outputs import NEW_ONLY, PRIVATE_KEY, PUBLIC_KEY, OutputPlan
    from ..passphrase import read_passphrase

    pub = public_path(out)
    plan = OutputPlan()
    if passphrase_file:
        plan.protect(passphrase_file, what="the passphrase file")
    passphrase = read_passphrase(passphrase_file, required=False)
    # an existing key is replaced only with --force, and only by a key: never a document, never a passphrase file
    plan.check(out, flag="--out", replaces=(PRIVATE_KEY,) if force else NEW_ONLY)
    plan.check(pub, flag="public key", replaces=(PUBLIC_KEY,) if force else NEW_ONLY)
    key = generate(kind)
    plan.add(
        out, private_pem(key, passphrase), flag="--out", mode=0o600, replaces=(PRIVATE_KEY,) if force else NEW_ONLY
    )
    plan.add(pub, public_pem(key), flag="public key", replaces=(PUBLIC_KEY,) if force else NEW_ONLY)
    plan.commit()
    result = {"type": key_type(key), "private": out, "public": str(pub), "encrypted": passphrase is not None}
    if as_json:
        emit_json({"ok": True, **result, "errors": []})
    else:
        say(f"wrote {out} ({kind}, {'encrypted' if passphrase else 'not encrypted'}, mode 0600)")
        say(f"wrote {pub}")


@ota.command()
@click.argument("doc", type=click.Path(dir_okay=False))
@click.option("--firmware-dir", required=True, type=click.Path(file_okay=False), help="Where the binaries are.")
@signing_key_options(required=True)
@click.option(
    "-o", "--out", "out_dir", required=True, type=click.Path(file_okay=False), help="Release folder to write."
)
@click.option(
    "--base-url", help="https:// URL prefix of the release folder, for latest.json and the manifest (no credentials)."
)
@click.option("--allow-http", is_flag=True, help="Allow a plain http:// --base-url (or ota.toml base_url).")
@click.option(
    "--previous", help="The previous release (folder or https URL): history, sequence number, security counters."
)
@click.option(
    "--import-unsigned-history",
    is_flag=True,
    help="Accept a --previous without a signed manifest; its latest.json history is taken on your word.",
)
@click.option("--config", type=click.Path(dir_okay=False), help="ota.toml [default: ota.toml beside DOC, if any].")
@click.option("--changelog", help="Changelog for images whose ota.toml entry has none.")
@click.option(
    "--update-hcdf",
    is_flag=True,
    help="Write each image's hash into a <software><hash> that differs (minimal edits; includers and lock follow).",
)
@tree_options
@click.option("--jobs", "-j", type=click.IntRange(0, 64), default=0, help="Parallel signing [default: one per core].")
@source_date_epoch_option
@click.option(
    "--provenance", is_flag=True, help="Also write provenance.intoto.json (in-toto/SLSA, DSSE, the release key)."
)
@click.option("--builder-id", help="The provenance's runDetails.builder.id [default: the CI workflow, else ours].")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout.")
@handle_errors
def build(
    doc: str,
    firmware_dir: str,
    key: str,
    passphrase_file: str | None,
    pin_file: str | None,
    out_dir: str,
    base_url: str | None,
    allow_http: bool,
    previous: str | None,
    import_unsigned_history: bool,
    config: str | None,
    changelog: str | None,
    update_hcdf: bool,
    tree: Any,
    jobs: int,
    source_date: Any,
    provenance: bool,
    builder_id: str | None,
    as_json: bool,
) -> None:
    """Build a signed release from DOC's verified tree: one MCUboot image per <comp> with
    <software>, latest.json per device, and one signed SUIT manifest over all of them.

    Nothing is written unless every step succeeds.
    """
    from ..ota.release import BuildOptions, build_release, format_date

    signer, inputs = open_signer(key, passphrase_file, pin_file)
    try:
        report = build_release(
            doc,
            BuildOptions(
                firmware_dir=firmware_dir,
                out_dir=out_dir,
                signer=signer,
                inputs=inputs,
                base_url=base_url,
                previous=previous,
                config=config,
                changelog=changelog,
                update_hcdf=update_hcdf,
                date=format_date(source_date.timestamp()) if source_date is not None else None,
                tree=tree,
                jobs=jobs,
                ca_bundle=tree.ca_bundle,  # tree_options' --ca-bundle: --previous and --online alike
                allow_http=allow_http,
                import_unsigned_history=import_unsigned_history,
                provenance=provenance,
                builder_id=builder_id,
            ),
        )
    finally:
        signer.close()
    if as_json:
        emit_json(
            {
                "ok": True,
                "sequence_number": report.release.sequence_number,
                "lock_sha256": report.release.lock_sha256,
                "images": [c.to_json() for c in report.release.components],
                "excluded": report.excluded,
                "hcdf_changes": report.hcdf_changes,
                "warnings": [n.to_dict() for n in report.notices],
                "wrote": report.wrote,
                "errors": [],
            }
        )
        return
    warn(report.notices)
    for ch in report.hcdf_changes:
        say(f"{ch['file']}:{ch['line']}: comp {ch['comp']!r}: <hash> {ch['old']} -> {ch['new']}")
    for c in report.release.components:
        say(f"{c.board}/{c.app} {c.version} ({c.type}): mcuboot_hash {c.mcuboot_hash or '-'}")
    say(
        f"release {report.release.sequence_number}: {counted(len(report.release.components), 'image')}, "
        f"{counted(len(report.wrote), 'file')} written to {out_dir}"
    )


@ota.command(name="verify")
@click.argument("release_dir", type=click.Path(file_okay=False))
@click.option("--key", "key", required=True, type=click.Path(dir_okay=False), help="Public key (PEM).")
@click.option(
    "--previous",
    help="The previous release (folder or https URL): sequence number and counters must not go back; "
    "its signed history vouches for previous[] entries.",
)
@click.option(
    "--import-unsigned-history",
    is_flag=True,
    help="Accept a --previous without a signed manifest; its latest.json entries are taken on your word.",
)
@CA_BUNDLE_OPTION
@click.option(
    "--provenance", is_flag=True, help="Also verify provenance.intoto.json (signed by --key and --provenance-key)."
)
@provenance_key_options(besides_key=True)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout.")
@handle_errors
def verify_cmd(
    release_dir: str,
    key: str,
    previous: str | None,
    import_unsigned_history: bool,
    ca_bundle: str | None,
    provenance: bool,
    provenance_keys: tuple[str, ...],
    threshold: int,
    as_json: bool,
) -> None:
    """Check every signature, digest and latest.json of RELEASE_DIR against its signed manifest."""
    from ..ota.keys import load_public
    from ..ota.release import read_release
    from ..ota.verify import check_release
    from . import fail

    public = load_public(key)
    if not provenance and (provenance_keys or threshold != 1):
        raise click.UsageError("--provenance-key and --threshold need --provenance")
    keys = load_provenance_keys(provenance_keys, threshold, key=public)
    release, files = read_release(
        release_dir, public, previous=previous, ca_bundle=ca_bundle, import_unsigned=import_unsigned_history
    )
    before = files.previous
    errors = check_release(release, files, public)
    if provenance:
        from ..provenance.verify import verify_provenance

        errors += verify_provenance(release_dir, release, keys, threshold=threshold)
    payload = {
        "sequence_number": release.sequence_number,
        "lock_sha256": release.lock_sha256,
        "components": [c.to_json() for c in release.components],
    }
    if errors:
        fail(errors, as_json=as_json, payload=payload)
    if as_json:
        emit_json({"ok": True, **payload, "errors": []})
    else:
        say(
            f"release {release.sequence_number}: {counted(len(release.components), 'component')} verified "
            f"(signatures, digests, latest.json{', rollback' if before else ''}{', provenance' if provenance else ''})"
        )


@ota.command(name="sign-provenance")
@click.argument("release_dir", type=click.Path(file_okay=False))
@signing_key_options(required=True)
@click.option(
    "--release-key",
    required=True,
    type=click.Path(dir_okay=False),
    help="The release's public key (PEM): the release and its provenance must verify with it first.",
)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout.")
@handle_errors
def sign_provenance_cmd(
    release_dir: str, key: str, passphrase_file: str | None, pin_file: str | None, release_key: str, as_json: bool
) -> None:
    """Co-sign RELEASE_DIR's provenance.intoto.json: add this key's signature over the same
    statement bytes, for a verifier's threshold.

    The release and its provenance are verified with --release-key first (as `ota verify`
    verifies a provenance); a key that already signed is refused. Nothing is written on any error.
    """
    import os

    from ..ota.keys import load_public
    from ..ota.release import read_release
    from ..ota.verify import check_release
    from ..outputs import OutputPlan
    from ..provenance import FILE_NAME, dsse
    from ..provenance.errors import ProvenanceError
    from ..provenance.verify import read_envelope, verify_provenance
    from . import fail

    public = load_public(release_key)
    signer, inputs = open_signer(key, passphrase_file, pin_file)
    try:
        release, files = read_release(release_dir, public)
        errors = check_release(release, files, public)
        data = read_envelope(release_dir)
        if data is None:
            raise ProvenanceError(
                "the release has no provenance to co-sign", file=FILE_NAME, expected=FILE_NAME, actual="none"
            )
        errors += verify_provenance(release_dir, release, [public], data=data)
        if errors:
            fail(errors, as_json=as_json)
        signed = dsse.cosign(data, signer, source=FILE_NAME)
    finally:
        signer.close()
    plan = OutputPlan()
    for path, what in (*inputs, (release_key, "the release key")):
        plan.protect(path, what=what)
    out = os.path.join(release_dir, FILE_NAME)
    plan.add(out, signed, flag="RELEASE_DIR", under=release_dir)
    plan.commit()
    keyids = sorted(dsse.parse(signed, source=FILE_NAME).signatures)
    if as_json:
        emit_json({"ok": True, "signatures": keyids, "wrote": [out], "errors": []})
    else:
        say(f"{out}: {counted(len(keyids), 'signature')} ({', '.join(keyids)})")


def open_signer(key: str, passphrase_file: str | None, pin_file: str | None) -> tuple[Any, tuple[tuple[str, str], ...]]:
    """The signer of ``--key`` and the inputs it read (to protect from being overwritten)."""
    from ..ota.keys import load_private
    from ..ota.signer import FileSigner
    from ..passphrase import read_passphrase

    if key.startswith("pkcs11:"):
        from ..ota.hsm import HsmSigner, parse_uri, read_pin

        uri = parse_uri(key)
        pin_inputs = ((pin_file, "the PIN file"),) if pin_file else ()
        return HsmSigner(uri, read_pin(uri, pin_file)), pin_inputs
    inputs = [(key, "the signing key")]
    passphrase = None
    if passphrase_file:
        inputs.append((passphrase_file, "the passphrase file"))
        passphrase = read_passphrase(passphrase_file)
    return FileSigner(load_private(key, passphrase)), tuple(inputs)


def _registry_options(func: Any) -> Any:
    """``--ca-bundle`` and ``--insecure-registry``, the same for every verb that talks to a registry."""
    return CA_BUNDLE_OPTION(INSECURE_REGISTRY_OPTION(func))


@ota.command()
@click.argument("release_dir", type=click.Path(file_okay=False))
@click.argument("target", metavar="oci://HOST[:PORT]/REPO:TAG")
@click.option(
    "--key",
    type=click.Path(dir_okay=False),
    help="Public key: verify the release (and its provenance.intoto.json) before pushing.",
)
@sbom_referrers_option("release", "from `hcdf-trust sbom`")
@_registry_options
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout.")
@handle_errors
def push(
    release_dir: str,
    target: str,
    key: str | None,
    sboms: tuple[str, ...],
    ca_bundle: str | None,
    insecure_registries: tuple[str, ...],
    as_json: bool,
) -> None:
    """Push RELEASE_DIR to an OCI registry as one artifact (one layer per file) and attach its
    SUIT envelope, its provenance.intoto.json (if any) and each --sbom as referrers.
    Credentials: $HCDF_TRUST_OCI_USERNAME/PASSWORD or the Docker config."""
    from ..oci.release import push_release, read_sbom
    from ..ota.release import MANIFEST_NAME
    from . import fail

    attached = [read_sbom(path) for path in sboms]  # refused before anything is sent
    from ..oci.client import connect

    ref, client = connect(
        target, ca_bundle=ca_bundle, insecure_registries=insecure_registries, push=True, need_tag=True
    )
    with client:
        if key is not None:
            from ..oci.release import read_provenance
            from ..ota.keys import load_public
            from ..ota.release import read_release
            from ..ota.verify import check_release

            public = load_public(key)
            release, files = read_release(release_dir, public)
            errors = check_release(release, files, public)
            if not errors and read_provenance(release_dir) is not None:
                from ..provenance.verify import verify_provenance

                errors = verify_provenance(release_dir, release, [public])
            if errors:
                fail(errors, as_json=as_json)
        else:
            import os

            from ..localfile import read_input
            from ..ota import suit

            path = os.path.join(release_dir, MANIFEST_NAME)
            data = read_input(path, limit=suit.MAX_MANIFEST_BYTES, what="release manifest")
            release = suit.parse_release(suit.parse_envelope(data, source=path), source=path)
        result = push_release(release_dir, ref, client, release, sboms=attached)
    warnings = []
    if key is None:
        from ..errors import Notice

        warnings.append(
            Notice("unverified-push", "pushed without --key: the release was not verified first (every pull verifies)")
        )
    if as_json:
        emit_json(
            {
                "ok": True,
                "reference": str(ref),
                "verified": key is not None,
                **result,
                "warnings": [n.to_dict() for n in warnings],
                "errors": [],
            }
        )
    else:
        warn(warnings)
        say(f"pushed {counted(len(result['layers']), 'file')} to {ref} ({result['digest']})")
        say(f"pull it with: hcdf-trust ota pull {ref.with_digest(result['digest'])} --key PUB --out DIR")


@ota.command()
@click.argument("source", metavar="oci://HOST[:PORT]/REPO:TAG|@sha256:HEX")
@click.option("--key", required=True, type=click.Path(dir_okay=False), help="Public key (PEM).")
@click.option(
    "-o", "--out", "out_dir", required=True, type=click.Path(file_okay=False), help="Release folder to write."
)
@click.option(
    "--previous", help="The previous release (folder or https URL): sequence number and counters must not go back."
)
@click.option(
    "--cache-dir",
    type=click.Path(file_okay=False),
    help="Content store of verified blobs (a resumed pull fetches only what is missing) "
    "[default: $XDG_CACHE_HOME/hcdf-trust].",
)
@click.option(
    "--require-provenance",
    is_flag=True,
    help="Fail unless a provenance referrer of this release is listed (it is verified whenever one is).",
)
@provenance_key_options(besides_key=True)
@_registry_options
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout.")
@handle_errors
def pull(
    source: str,
    key: str,
    out_dir: str,
    previous: str | None,
    cache_dir: str | None,
    require_provenance: bool,
    provenance_keys: tuple[str, ...],
    threshold: int,
    ca_bundle: str | None,
    insecure_registries: tuple[str, ...],
    as_json: bool,
) -> None:
    """Pull a release from an OCI registry: every blob hashed against the manifest, `ota verify`
    run on the result in a staging folder (and its provenance referrer, when listed, verified as
    `ota verify` verifies a provenance), and only then written to --out (all or nothing)."""
    from ..oci.release import pull_release
    from ..ota.keys import load_public
    from ..store import default_cache_dir

    public = load_public(key)
    others = tuple(load_provenance_keys(provenance_keys, threshold, key=public)[1:])
    before = None
    if previous is not None:
        from ..ota.release import previous_manifest  # the build module: only for --previous

        before = previous_manifest(previous, public, ca_bundle=ca_bundle)
    from ..oci.client import connect

    ref, client = connect(source, ca_bundle=ca_bundle, insecure_registries=insecure_registries)
    with client:
        report = pull_release(
            ref,
            client,
            public_key=public,
            out_dir=out_dir,
            cache_dir=cache_dir or str(default_cache_dir()),
            key_path=key,
            previous=before,
            provenance_keys=others,
            threshold=threshold,
            require_provenance=require_provenance,
        )
    release = report.release
    if as_json:
        emit_json(
            {
                "ok": True,
                "reference": report.reference,
                "digest": report.digest,
                "sequence_number": release.sequence_number,
                "files": report.files,
                "from_cache": report.from_cache,
                "referrers": report.referrers,
                "provenance": report.provenance,
                "sboms": report.sboms,
                "warnings": [n.to_dict() for n in report.notices],
                "wrote": report.wrote,
                "errors": [],
            }
        )
        return
    warn(report.notices)
    say(
        f"release {release.sequence_number} from {report.reference} ({report.digest}): "
        f"{counted(len(report.files), 'file')} verified ({report.from_cache} from the cache)"
        f"{', provenance verified' if report.provenance else ''}, written to {out_dir}"
    )
