"""``hcdf-trust macsec``: plan, generate, status, rotate, retire, export. Parses, calls, renders.

Library modules (lxml, cryptography, the resolver) are imported inside the commands.
No key material is ever printed: human output and ``--json`` carry ids, CKNs' owners,
times and key check values only.
"""

from __future__ import annotations

from typing import Any

import click

from .cli import emit_json, handle_errors


@click.group()
def macsec() -> None:
    """Provision MACsec keys for the connectivity associations an HCDF describes."""


def _plan_lines(p: Any) -> None:
    for ca in p.associations.values():
        d = ca.to_dict()
        if ca.kind == "mesh-key":
            head = f"{ca.id}: mesh network key ({ca.key_bytes * 8}-bit)"
        else:
            head = f"{ca.id}: {d['policy']} {d['cipher']} {d['key_agreement']}"
            if d["confidentiality_offset"]:
                head += f" offset {d['confidentiality_offset']}"
            if d["rekey_interval_sec"] is not None:
                head += f" rekey {d['rekey_interval_sec']} s"
            store = d["key_store"]
            if store["type"]:
                head += f" key-store {store['type']}" + (f":{store['ref']}" if store["ref"] else "")
            if not ca.keyed:
                head += " (no key)"
        click.echo(head)
        for el in ca.elements:
            scope = f" scope {el.scope}" if el.scope else ""
            click.echo(f"  {el.kind} {el.network}/{el.name} ({el.file}:{el.line}{scope})")
        if ca.shared:
            click.echo(f"  shared: one CAK on {len(ca.elements)} {ca.elements[0].kind}s")
        members = ", ".join(f"{m.device}[{' '.join(m.ports)}]" for m in ca.members.values())
        click.echo(f"  members: {members}")
    for el in p.unprotected:
        click.echo(f"unprotected: {el.label} ({el.file}:{el.line})")
    for el, reason in p.skipped:
        click.echo(f"skipped: {el.label}: {reason}")
    for w in p.warnings:
        click.echo(f"warning: {w}", err=True)


@macsec.command("plan")
@click.argument("doc", type=click.Path(dir_okay=False))
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout.")
@handle_errors
def plan_cmd(doc: str, as_json: bool) -> None:
    """Show the connectivity associations DOC's MACsec policy asks for.

    The include tree is resolved and verified first (offline, against its lock file);
    any resolve error refuses the plan.
    """
    from .macsec.plan import plan

    p = plan(doc)
    if as_json:
        emit_json({"ok": True, **p.to_dict()})
        return
    _plan_lines(p)
    keyed = p.keyed()
    click.echo(f"{len(keyed)} association(s) to key, {len(p.associations) - len(keyed)} disabled", err=True)
