"""``hcdf-trust macsec``: plan, generate, status, rotate, retire, export. Parses, calls, renders.

Library modules (lxml, cryptography, the resolver) are imported inside the commands.
No key material is ever printed: human output and ``--json`` carry ids, CKNs' owners,
times and key check values only.
"""

from __future__ import annotations

from datetime import datetime, timedelta
from typing import Any

import click

from ..errors import counted
from . import emit_json, fail, handle_errors, keep_until_exit, say, tree_options, warn
from .params import UTC_TIME, Duration


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
            if store["type"] or store["ref"]:
                head += f" key-store {store['type'] or 'ref'}" + (f":{store['ref']}" if store["ref"] else "")
            if not ca.keyed:
                head += " (no key)"
        say(head, err=False)
        for el in ca.elements:
            scope = f" scope {el.scope}" if el.scope else ""
            say(f"  {el.kind} {el.label.partition(':')[2]} ({el.file}:{el.line}{scope})", err=False)
        if ca.shared:
            say(f"  shared: one CAK on {len(ca.elements)} {ca.elements[0].kind}s", err=False)
        members = ", ".join(f"{m.device}[{' '.join(m.ports)}]" for m in ca.members.values())
        say(f"  members: {members}", err=False)
    for el in p.unprotected:
        say(f"unprotected: {el.label} ({el.file}:{el.line})", err=False)
    for el, reason in p.skipped:
        say(f"skipped: {el.label}: {reason}", err=False)
    warn(p.warnings)


@macsec.command("plan")
@click.argument("doc", type=click.Path(dir_okay=False))
@tree_options
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout.")
@handle_errors
def plan_cmd(doc: str, tree: Any, as_json: bool) -> None:
    """Show the connectivity associations DOC's MACsec policy asks for.

    The include tree is resolved and verified first (against its lock file, offline unless
    --online); any resolve error refuses the plan.
    """
    from ..macsec.plan import plan

    p = plan(doc, tree=tree)
    keep_until_exit(p)  # a 10,000-link plan and its XML trees are left for the kernel to reclaim
    if as_json:
        payload = {"ok": True, **p.to_dict()}
        keep_until_exit(payload)
        emit_json(payload)
        return
    _plan_lines(p)
    keyed = p.keyed()
    say(f"{counted(len(keyed), 'association')} to key, {len(p.associations) - len(keyed)} disabled")


# --- the key store ---------------------------------------------------------------------------


def store_options(func: Any, *, required: bool = True) -> Any:
    func = click.option(
        "--tpm",
        "tpm_tcti",
        metavar="TCTI",
        help="Seal the store's data key to a TPM 2.0 (e.g. device:/dev/tpmrm0, swtpm:host=127.0.0.1,port=2321).",
    )(func)
    func = click.option(
        "--pin-file",
        type=click.Path(dir_okay=False),
        help="File holding the PKCS#11 user PIN (mode 0600) [default: $HCDF_TRUST_PKCS11_PIN].",
    )(func)
    func = click.option("--token-label", help="PKCS#11 token label (with --pkcs11-module).")(func)
    func = click.option(
        "--pkcs11-module",
        type=click.Path(dir_okay=False),
        help="PKCS#11 library (e.g. /usr/lib/softhsm/libsofthsm2.so) of the token named by --token-label, "
        "whose non-extractable AES key (made on first use) wraps the store's keys; needs hcdf-trust[hsm].",
    )(func)
    func = click.option(
        "--now",
        "now_given",
        type=UTC_TIME,
        metavar="TIME",
        help="Act as if the time were TIME (ISO 8601 UTC), e.g. to plan a rotation or in tests.",
    )(func)
    func = click.option(
        "--passphrase-file",
        type=click.Path(dir_okay=False),
        help="File holding the store passphrase (the whole file minus one final newline, mode 0600) "
        "[default: $HCDF_TRUST_PASSPHRASE]; never an argument.",
    )(func)
    func = click.option(
        "--store", "store_dir", required=required, type=click.Path(file_okay=False), help="Key store folder."
    )(func)
    return func


def _now(given: datetime | None) -> datetime:
    """``--now`` (already checked by its click type), else the clock."""
    from ..macsec.store import now_utc

    return now_utc() if given is None else given


def _is_passphrase(backend: dict[str, Any]) -> bool:
    """Do the store options name the passphrase backend (no token, no TPM)?"""
    return not backend.get("pkcs11_module") and not backend.get("tpm_tcti")


def _wrapper(passphrase_file: str | None, backend: dict[str, Any]) -> Any:
    """The wrapping-key backend the store options name: a passphrase, or a PKCS#11 token."""
    from ..macsec.backends import PassphraseWrapper, Pkcs11Wrapper, TpmWrapper, passphrase_from, pin_from

    module, label, pin_file = backend.get("pkcs11_module"), backend.get("token_label"), backend.get("pin_file")
    tcti = backend.get("tpm_tcti")
    if tcti is not None:
        if module or passphrase_file:
            raise click.UsageError("--tpm, --pkcs11-module and --passphrase-file are different backends: give one")
        return TpmWrapper(tcti)
    if module is None:
        if label or pin_file:
            raise click.UsageError("--token-label and --pin-file need --pkcs11-module")
        return PassphraseWrapper(passphrase_from(passphrase_file))
    if not label:
        raise click.UsageError("--pkcs11-module needs --token-label")
    if passphrase_file:
        raise click.UsageError("--passphrase-file and --pkcs11-module are two different backends: give one")
    return Pkcs11Wrapper(module, label, pin_from(pin_file))


# What opening or creating a passphrase store imports, and the cryptography modules the caller's
# thread imports next (kdf); a token backend's own library is imported by its thread only.
_STORE_THREAD_MODULES = (
    "cryptography.exceptions",
    "cryptography.hazmat.primitives.ciphers.aead",
    "cryptography.hazmat.primitives.ciphers.algorithms",
    "cryptography.hazmat.primitives.cmac",
    "cryptography.hazmat.primitives.kdf.scrypt",
    "hcdf_trust.macsec.backends",
)


def _in_background(fn: Any) -> Any:
    """``Background(fn)`` for a store's open or creation, once the modules it runs are imported
    here: the caller goes on importing the planner (and cryptography) meanwhile, and two threads
    importing the same modules at once can fail on an import cycle between them."""
    import importlib

    from ..macsec.store import Background

    for name in _STORE_THREAD_MODULES:
        importlib.import_module(name)
    return Background(fn)


def _warmed(store_dir: str, passphrase_file: str | None, backend: dict[str, Any]) -> Any:
    """A passphrase wrapper that has opened the store once (its scrypt key kept), or None on any
    error: the caller makes its own wrapper and opens the store again, and then reports it."""
    from ..macsec.store import KeyStore

    try:
        wrapper = _wrapper(passphrase_file, backend)
        KeyStore.open(store_dir, wrapper)
    except Exception:  # noqa: BLE001 -- reported by the open the caller makes under the lock
        return None
    return wrapper


def _output_plan(p: Any, *, passphrase_file: str | None, backend: dict[str, Any]) -> Any:
    """An OutputPlan that refuses every input of this run: the verified tree of plan ``p``
    (documents, artifacts, the cache) and its lock, the passphrase and PIN files."""
    from ..outputs import OutputPlan, protect_inputs

    out = OutputPlan()
    if p is not None and p.resolution is not None:
        protect_inputs(out, p.resolution)
        out.protect(p.resolution.lock_path, what="the lock file")
    if passphrase_file:
        out.protect(passphrase_file, what="the passphrase file")
    if backend.get("pin_file"):
        out.protect(backend["pin_file"], what="the PIN file")
    return out


def _indexed(doc: str, tree: Any) -> str | None:
    """``doc``, whose export index generate and rotate write, when its tree is found where
    resolve finds it by default (the index's fast path assumes so); None otherwise."""
    return doc if tree.finds_tree_by_default() else None


def _save(
    store: Any, now: Any, *, doc: str | None, p: Any, passphrase_file: str | None, backend: dict[str, Any]
) -> None:
    """Write the store if it changed, and the export index of plan ``p`` if it changed,
    through one OutputPlan: 0600 from the first byte, never over an input."""
    import os

    from ..macsec import index

    out = _output_plan(p, passphrase_file=passphrase_file, backend=backend)
    if store.changed:
        store.plan_write(out, now=now)
    rendered = index.render(doc, p, store) if doc is not None else None
    if rendered is not None:
        out.add(index.path_in(store.path.parent), rendered, flag="--store", mode=0o600, if_changed=True)
    if out.paths:
        os.makedirs(store.path.parent, mode=0o700, exist_ok=True)
        out.commit()


@macsec.command()
@click.argument("doc", type=click.Path(dir_okay=False))
@store_options
@tree_options
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout (no key material).")
@handle_errors
def generate(
    doc: str,
    store_dir: str,
    passphrase_file: str | None,
    now_given: datetime | None,
    tree: Any,
    as_json: bool,
    **backend: Any,
) -> None:
    """Create every missing key DOC's associations need (running it again changes nothing)."""
    from ..macsec.store import KeyStore, locked

    now = _now(now_given)
    fresh = None
    if not KeyStore.exists(store_dir) and _is_passphrase(backend):
        # A new store's data key is wrapped (scrypt, a pure computation) while the description
        # is verified; if a store exists once the lock is held, it is opened and this one dropped.
        fresh = _in_background(lambda: KeyStore.create(store_dir, _wrapper(passphrase_file, backend)))
    from ..macsec.plan import plan
    from ..macsec.rotation import generate as run

    p = plan(doc, tree=tree)
    keep_until_exit(p)
    wrapper = _wrapper(passphrase_file, backend)
    with locked(store_dir):
        if KeyStore.exists(store_dir):
            store = KeyStore.open(store_dir, wrapper)
        else:
            store = fresh.result() if fresh is not None else KeyStore.create(store_dir, wrapper)
        keep_until_exit(store)
        created, notices = run(store, p, now=now)
        _save(store, now, doc=_indexed(doc, tree), p=p, passphrase_file=passphrase_file, backend=backend)
    warnings = [*p.warnings, *notices]
    if as_json:
        emit_json(
            {"ok": True, "store": str(store.path), "created": created, "warnings": [w.to_dict() for w in warnings]}
        )
        return
    warn(warnings)
    if created:  # one write for 10,000 lines
        say(*(f"created {ca_id} generation 1" for ca_id in created), err=False)
    say(f"{counted(len(created), 'key')} created in {store.path}" if created else "nothing to do")


@macsec.command()
@click.argument("doc", type=click.Path(dir_okay=False))
@store_options
@tree_options
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout (no key material).")
@handle_errors
def status(
    doc: str,
    store_dir: str,
    passphrase_file: str | None,
    now_given: datetime | None,
    tree: Any,
    as_json: bool,
    **backend: Any,
) -> None:
    """Per association: active generation, age, due under rekey-interval-sec, key check values."""
    from ..macsec.store import KeyStore

    now = _now(now_given)
    opening = _in_background(lambda: KeyStore.open(store_dir, _wrapper(passphrase_file, backend)))
    from ..macsec.plan import plan
    from ..macsec.rotation import status as run

    p = plan(doc, tree=tree)
    keep_until_exit(p)
    store = opening.result()
    keep_until_exit(store)
    st = run(store, p, now=now)
    if as_json:
        if not st.ok:  # an association without a usable key: exit 1, the status beside the errors
            fail(st.problems, as_json=True, payload=st.to_dict())
        emit_json({"ok": True, **st.to_dict()})
        return
    for row in st.rows:
        gens = " ".join(f"g{g['generation']}:{g['state']}:kcv={g['kcv']}" for g in row["generations"])
        age = f" age {row['age_sec']} s" if row["age_sec"] is not None else ""
        flags = (" DUE" if row["due"] else "") + ("" if row["described"] else " (no longer described)")
        active = f"active g{row['active_generation']}" if row["active_generation"] is not None else "NO ACTIVE KEY"
        say(f"{row['id']}: {active}{age}{flags}  {gens}", err=False)
    for ca_id in st.missing:
        say(f"{ca_id}: no key (run generate)", err=False)
    if not st.ok:
        fail(st.problems, as_json=False)


@macsec.command()
@click.argument("doc", type=click.Path(dir_okay=False))
@store_options
@tree_options
@click.option("--network", help="Only associations of this network.")
@click.option("--key-ref", help="Only the association of this key-ref (as scoped in the plan).")
@click.option("--due", is_flag=True, help="Only associations due under rekey-interval-sec.")
@click.option(
    "--overlap",
    type=Duration(),
    default="1h",
    show_default=True,
    help="Time until the new generation sends, and again until the old one stops being accepted "
    "(seconds, or 30m, 12h, 7d, 2w).",
)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout (no key material).")
@handle_errors
def rotate(
    doc: str,
    store_dir: str,
    passphrase_file: str | None,
    now_given: datetime | None,
    tree: Any,
    network: str | None,
    key_ref: str | None,
    due: bool,
    overlap: timedelta,
    as_json: bool,
    **backend: Any,
) -> None:
    """Add generation N+1 (pending, with an activation time) to the selected associations."""
    from ..macsec.store import KeyStore, fmt_time, locked

    now = _now(now_given)
    warm = None
    if _is_passphrase(backend):
        # scrypt runs while the description is verified; the store is read again under the lock
        # (the passphrase wrapper keeps the derived key, so that second open costs no scrypt).
        warm = _in_background(lambda: _warmed(store_dir, passphrase_file, backend))
    from ..macsec.plan import plan
    from ..macsec.rotation import rotate as run
    from ..macsec.rotation import select

    p = plan(doc, tree=tree)
    keep_until_exit(p)
    wrapper = (warm.result() if warm is not None else None) or _wrapper(passphrase_file, backend)
    with locked(store_dir):
        store = KeyStore.open(store_dir, wrapper)
        keep_until_exit(store)
        store.bind(p.robot, document=p.document)
        selected = select(p, network=network, key_ref=key_ref)
        done = run(store, selected, now=now, overlap=int(overlap.total_seconds()), due_only=due)
        _save(store, now, doc=_indexed(doc, tree), p=p, passphrase_file=passphrase_file, backend=backend)
    rows = [{"id": i, "generation": g, "activation": fmt_time(a)} for i, g, a in done]
    if as_json:
        emit_json({"ok": True, "rotated": rows})
        return
    for r in rows:
        say(f"{r['id']}: generation {r['generation']} pending, sends from {r['activation']}", err=False)
    if not rows:
        say("nothing to rotate")


@macsec.command()
@store_options
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout (no key material).")
@handle_errors
def retire(
    store_dir: str, passphrase_file: str | None, now_given: datetime | None, as_json: bool, **backend: Any
) -> None:
    """Remove generations past their overlap (and only those)."""
    from ..macsec.rotation import retire as run
    from ..macsec.store import KeyStore, locked

    now = _now(now_given)
    wrapper = _wrapper(passphrase_file, backend)
    with locked(store_dir):
        store = KeyStore.open(store_dir, wrapper)
        keep_until_exit(store)
        removed = run(store, now=now)
        _save(store, now, doc=None, p=None, passphrase_file=passphrase_file, backend=backend)
    if as_json:
        emit_json({"ok": True, "retired": [{"id": i, "generation": g} for i, g in removed]})
        return
    for ca_id, g in removed:
        say(f"{ca_id}: generation {g} retired", err=False)
    if not removed:
        say("nothing to retire")


def _wpa_version(ctx: click.Context, param: click.Parameter, value: str) -> tuple[int, int]:
    from ..macsec import parse_wpa_version

    try:
        version = parse_wpa_version(value)
    except ValueError as exc:
        raise click.BadParameter(str(exc)) from None
    if version < (2, 10):
        raise click.BadParameter(f"{value}: only wpa_supplicant 2.10 and later are supported")
    return version


@macsec.command()
@click.argument("doc", type=click.Path(dir_okay=False))
@store_options
@tree_options
@click.option("--device", required=True, help="The comp (as named in the plan) whose keys to export.")
@click.option(
    "--format",
    "fmt",
    required=True,
    type=click.Choice(["wpa_supplicant", "networkd", "iproute2", "json"]),
    help="The consumer of the exported files.",
)
@click.option(
    "-o", "--out", "out_dir", required=True, type=click.Path(file_okay=False), help="Folder for the files (mode 0600)."
)
@click.option(
    "--wpa-version",
    default="2.10",
    show_default=True,
    callback=_wpa_version,
    help="wpa_supplicant version on the device (2.10: Debian 12, Ubuntu 22.04/24.04); only its keys are written.",
)
@click.option(
    "--age-recipient",
    metavar="AGE1…",
    help="Encrypt the JSON bundle to the device's age X25519 public key (writes DEVICE.macsec.json.age).",
)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout (file names, no keys).")
@handle_errors
def export(
    doc: str,
    store_dir: str,
    passphrase_file: str | None,
    now_given: datetime | None,
    tree: Any,
    device: str,
    fmt: str,
    out_dir: str,
    wpa_version: tuple[int, int],
    age_recipient: str | None,
    as_json: bool,
    **backend: Any,
) -> None:
    """Write only DEVICE's keys (least privilege), for one consumer, as 0600 files in --out."""
    import os

    from ..macsec.store import KeyStore
    from ..outputs import ORDINARY, kind_of

    now = _now(now_given)
    # The store opens (scrypt, on a second thread) from here on, while the rest is imported and
    # the description verified and planned.
    opening = _in_background(lambda: KeyStore.open(store_dir, _wrapper(passphrase_file, backend)))
    from ..macsec import index
    from ..macsec.export import collect, mesh_keys, render

    # The export index, when it was written for this description as it is now, holds its
    # verified plan: once the store opens, it is checked (MAC, every file's digest) and used.
    # A store that does not open sends us to the description too: its errors come first, and
    # opening.result() then raises the store's error again. Only for a tree found where resolve
    # finds it by default: with --base, --root, --lock... it is planned in full.
    found = index.candidate(doc, store_dir, device) if tree.finds_tree_by_default() else None
    p = None
    if found is not None:
        try:
            store = opening.result()
        except Exception:  # noqa: BLE001 -- reported by the second opening.result() below
            found = None
        else:
            p = found.plan(store)
    if p is None:
        from ..macsec.plan import plan

        p = plan(doc, device=device, tree=tree)  # only the networks that can hold the device's associations
        keep_until_exit(p)
        store = opening.result()
    keep_until_exit(store)
    ports, notices = collect(p, store, device, now=now)
    mesh = mesh_keys(p, store, device, now=now)
    files = render(
        fmt, ports, device=device, wpa_version=wpa_version, notices=notices, age_recipient=age_recipient, mesh=mesh
    )
    out = _output_plan(p, passphrase_file=passphrase_file, backend=backend)
    if p.resolution is None:  # planned from the index
        assert found is not None
        found.protect(out)
    out.protect(store.path, what="the key store")
    out.protect(index.path_in(store_dir), what="the export index")
    out.protect_tree(store.path.parent, what="the key store's folder")
    for name in sorted(files):
        # a re-export replaces the previous one's EAP-TLS device key: key material of the same kind
        kind = kind_of(files[name])
        out.add(
            os.path.join(out_dir, name),
            files[name],
            flag="--out",
            mode=0o600,
            under=out_dir,
            folder_mode=0o700,
            replaces=(ORDINARY, kind),
        )
    written = out.commit()
    target = f"{wpa_version[0]}.{wpa_version[1]}" if fmt == "wpa_supplicant" else None
    if as_json:
        emit_json(
            {
                "ok": True,
                "device": device,
                "format": fmt,
                "planned_from": "description" if p.resolution is not None else "index",
                "associations": sorted({pk.ca.id for pk in ports} | {m.ca.id for m in mesh}),
                "files": [str(w) for w in written],
                "warnings": [n.to_dict() for n in notices],
                **({"wpa_supplicant_version": target} if target else {}),
            }
        )
        return
    warn(notices)
    for w in written:
        say(f"wrote {w}")
    if target:
        say(f"written for wpa_supplicant {target} (--wpa-version)")
