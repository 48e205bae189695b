"""``hcdf-trust ota``: keygen, build, verify. Parses, calls :mod:`hcdf_trust.ota`, renders.

imgtool, cbor2 and the COSE library are imported inside the commands only.
"""

from __future__ import annotations

from typing import Any

import click

from . import emit_json, handle_errors, say, tree_options
from .params import source_date_epoch_option

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
@click.option(
    "--key", "key", required=True, help="Signing key: a PEM file, or a PKCS#11 URI (pkcs11:token=…;object=…)."
)
@click.option(
    "--passphrase-file",
    type=click.Path(dir_okay=False),
    help="Passphrase of an encrypted key file (mode 0600) [default: $HCDF_TRUST_PASSPHRASE].",
)
@click.option(
    "--pin-file",
    type=click.Path(dir_okay=False),
    help="PKCS#11 user PIN [default: the URI's pin-source, else $HCDF_TRUST_PKCS11_PIN]; never on the command line.",
)
@click.option(
    "-o", "--out", "out_dir", required=True, type=click.Path(file_okay=False), help="Release folder to write."
)
@click.option("--base-url", help="URL prefix of the release folder, for latest.json and the manifest.")
@click.option(
    "--previous", help="The previous release (folder or https URL): history, sequence number, security counters."
)
@click.option(
    "--ca-bundle",
    type=click.Path(dir_okay=False, exists=True),
    envvar="HCDF_TRUST_CA_BUNDLE",
    help="PEM CA certificates for https (--previous, --online) [env: HCDF_TRUST_CA_BUNDLE].",
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
    previous: str | None,
    ca_bundle: str | None,
    config: str | None,
    changelog: str | None,
    update_hcdf: bool,
    tree: Any,
    jobs: int,
    source_date: Any,
    as_json: bool,
) -> None:
    """Build a signed release from DOC's verified tree: one MCUboot image per <comp> with
    <software>, latest.json per device, and one signed SUIT manifest over all of them.

    Nothing is written unless every step succeeds.
    """
    from ..ota.release import BuildOptions, build_release, format_date

    signer, inputs = _signer(key, passphrase_file, pin_file)
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
                ca_bundle=ca_bundle,
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
    for n in report.notices:
        say(f"warning: {n}")
    for ch in report.hcdf_changes:
        say(f"{ch['file']}:{ch['line']}: comp {ch['comp']!r}: <hash> {ch['old']} -> {ch['new']}")
    for c in report.release.components:
        say(f"{c.board}/{c.app} {c.version} ({c.type}): mcuboot_hash {c.mcuboot_hash or '-'}")
    say(
        f"release {report.release.sequence_number}: {len(report.release.components)} image(s), "
        f"{len(report.wrote)} file(s) written to {out_dir}"
    )


@ota.command(name="verify")
@click.argument("release_dir", type=click.Path(file_okay=False))
@click.option("--key", "key", required=True, type=click.Path(dir_okay=False), help="Public key (PEM).")
@click.option(
    "--previous", help="The previous release (folder or https URL): sequence number and counters must not go back."
)
@click.option(
    "--ca-bundle",
    type=click.Path(dir_okay=False, exists=True),
    envvar="HCDF_TRUST_CA_BUNDLE",
    help="PEM CA certificates for an https --previous [env: HCDF_TRUST_CA_BUNDLE].",
)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout.")
@handle_errors
def verify_cmd(release_dir: str, key: str, previous: str | None, ca_bundle: str | None, as_json: bool) -> None:
    """Check every signature, digest and latest.json of RELEASE_DIR against its signed manifest."""
    from ..ota.keys import load_public
    from ..ota.release import previous_manifest, read_release
    from ..ota.verify import check_release
    from . import fail

    public = load_public(key)
    release, files = read_release(release_dir, public)
    before = previous_manifest(previous, public, ca_bundle=ca_bundle) if previous is not None else None
    errors = check_release(release, files, public, previous=before)
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
            f"release {release.sequence_number}: {len(release.components)} component(s) verified "
            f"(signatures, digests, latest.json{', rollback' if before else ''})"
        )


def _signer(key: str, passphrase_file: str | None, pin_file: str | None) -> tuple[Any, tuple[tuple[str, str], ...]]:
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
