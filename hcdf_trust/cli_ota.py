"""``hcdf-trust ota``: keygen, build, verify. Parses, calls :mod:`hcdf_trust.ota`, renders.

imgtool, cbor2 and the COSE library are imported inside the commands only.
"""

from __future__ import annotations

from typing import Any

import click

from .cli import emit_json, handle_errors

KEY_TYPES = ("ecdsa-p256", "ed25519", "rsa-2048", "rsa-3072")  # == ota.keys.KEY_TYPES (not imported: --help stays fast)


@click.group()
def ota() -> None:
    """MCUboot-signed images, latest.json and a signed SUIT release manifest from the HCDF."""


@ota.command()
@click.option("--type", "kind", type=click.Choice(KEY_TYPES), default="ecdsa-p256", show_default=True)
@click.option("-o", "--out", required=True, type=click.Path(dir_okay=False), help="Private key file (PEM, mode 0600).")
@click.option(
    "--passphrase-file", type=click.Path(dir_okay=False), help="Encrypt the private key with this file's content."
)
@click.option("--force", is_flag=True, help="Replace an existing key file.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout.")
@handle_errors
def keygen(kind: str, out: str, passphrase_file: str | None, force: bool, as_json: bool) -> None:
    """Generate a signing key with imgtool; the public key goes beside it (KEY.pub.pem)."""
    from .ota.errors import KeyFileError
    from .ota.keys import generate, key_type, private_pem, public_path, public_pem, read_passphrase
    from .outputs import OutputPlan

    pub = public_path(out)
    plan = OutputPlan()
    passphrase = None
    if passphrase_file:
        plan.protect(passphrase_file, what="the passphrase file")
        passphrase = read_passphrase(passphrase_file)
    if not force:
        for path in (out, pub):
            if _exists(path):
                raise KeyFileError("exists: refusing to replace a key (use --force)", file=str(path))
    key = generate(kind)
    plan.add(out, private_pem(key, passphrase), flag="--out", mode=0o600)
    plan.add(pub, public_pem(key), flag="public key")
    plan.commit()
    result = {"type": key_type(key), "private": out, "public": str(pub), "encrypted": passphrase is not None}
    if as_json:
        emit_json({"ok": True, **result, "errors": []})
    else:
        click.echo(f"wrote {out} ({kind}, {'encrypted' if passphrase else 'not encrypted'}, mode 0600)", err=True)
        click.echo(f"wrote {pub}", err=True)


def _exists(path: Any) -> bool:
    import os

    return os.path.lexists(path)
