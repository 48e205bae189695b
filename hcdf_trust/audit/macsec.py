"""MACsec: control traffic left unprotected, file key stores, weak ciphers, endpoints that
lack the cipher, and (given a key store) keys past their rekey interval.

Built on :func:`hcdf_trust.macsec.plan.plan_resolution` (effective policy of every link and
chain, capability warnings) and :func:`hcdf_trust.macsec.rotation.status`; the only thing read
here from the documents is what the plan does not keep: VLAN priorities and ``<key-store>``.
"""

from __future__ import annotations

from datetime import datetime
from typing import Any

from ..errors import AmbiguousError, HcdfTrustError, at_line
from ..include.flatten import SEPARATOR
from ..include.resolver import Resolution
from ..macsec.plan import Element, Plan, plan_resolution
from ..xml import sourceline
from .policy import CIPHER_ORDER, cipher_rank
from .report import Report

CONTROL_PCP = 5  # IEEE 802.1Q priorities 5-7: motion, safety, time sync


def plan_of(report: Report, res: Resolution) -> Plan | None:
    """The tree's MACsec plan, or None (the plan's errors recorded) when it cannot be made."""
    try:
        return plan_resolution(res.documents, res.includes, res.root_location.url)
    except HcdfTrustError as exc:
        if any(isinstance(e, AmbiguousError) for e in getattr(exc, "errors", None) or [exc]):
            raise  # an element the planner reads written twice: refused as every verb refuses it (exit 3)
        report.add_error(exc)
        return None


def check(report: Report, res: Resolution, plan: Plan) -> None:
    control = _control_networks(res)
    for ca in plan.associations.values():
        policy = ca.policy
        if policy is None:
            continue  # a mesh network key
        for el in ca.elements:
            why = control.get((el.file, _written(el)))
            if why and policy.policy != "must-secure":
                report.add(
                    "macsec-control-traffic",
                    f"{el.label}: network {el.network} carries control traffic ({why}) but its policy is "
                    f"{policy.policy}, not must-secure",
                    file=el.file,
                    line=el.line,
                )
        if ca.keyed and cipher_rank(policy.cipher) < cipher_rank(report.policy.minimum_cipher):
            labels = ", ".join(e.label for e in ca.elements)
            report.add(
                "macsec-weak-cipher",
                f"{ca.id} ({labels}) uses {policy.cipher}, weaker than the policy's minimum "
                f"{report.policy.minimum_cipher} (order: {' < '.join(CIPHER_ORDER)})",
                file=ca.file,
                line=ca.line,
            )
    for el in plan.unprotected:
        why = control.get((el.file, _written(el)))
        if why and el.kind != "mesh":
            report.add(
                "macsec-control-traffic",
                f"{el.label}: network {el.network} carries control traffic ({why}) but it has no MACsec",
                file=el.file,
                line=el.line,
            )
    for notice in plan.warnings:
        if notice.code == "macsec-capability":
            report.add_notice("macsec-capability", notice)
    for doc in res.documents.values():
        _new_model_file_stores(report, doc)
        for store in doc.root.iterfind("network/macsec/key-store"):
            if (store.get("type") or "").strip() == "file":
                ref = store.get("ref")
                report.add(
                    "macsec-file-key-store",
                    f'<key-store type="file"{f" ref={ref!r}" if ref else ""}> keeps keys in a file: '
                    "development only (HCDF schema); use secure-element, hsm or tpm",
                    file=doc.source,
                    line=sourceline(store),
                )


def _new_model_networks(doc: Any) -> list[Any]:
    """The top-level networks of upstream's newer connectivity model in ``doc``."""
    from ..macsec.plan import NETWORK_KINDS

    return list(doc.root.iterchildren(*NETWORK_KINDS))


def _new_model_file_stores(report: Report, doc: Any) -> None:
    """A ``<policy credential-store-ref>`` of the newer model that names a file store."""
    from ..macsec.connectivity import store_kind

    for net in _new_model_networks(doc):
        for policy in net.iterfind("configuration/macsec/policy"):
            ref = (policy.get("credential-store-ref") or "").strip()
            if ref and store_kind(ref) == "file":
                report.add(
                    "macsec-file-key-store",
                    f"<policy credential-store-ref={ref!r}> keeps keys in a file: development only "
                    "(HCDF schema); use secure-element, hsm or tpm",
                    file=doc.source,
                    line=sourceline(policy),
                )


def _written(el: Element) -> str:
    """The network's name as written in its document (the plan prefixes included ones)."""
    prefix = el.scope + SEPARATOR if el.scope else ""
    return el.network[len(prefix) :] if prefix and el.network.startswith(prefix) else el.network


def _control_networks(res: Resolution) -> dict[tuple[str, str], str]:
    """(document, network name) -> why it carries control traffic: a chain, or a VLAN pcp >= 5;
    in the newer model a top-level ``<chain>``, or a ``<traffic-class>`` of pcp >= 5."""
    out: dict[tuple[str, str], str] = {}
    for doc in res.documents.values():
        for net in _new_model_networks(doc):
            name = (net.get("name") or "").strip()
            why = f"chain {name!r}" if net.tag == "chain" else None
            for pcp_el in net.iterfind("configuration/traffic-class/pcp"):
                pcp = (pcp_el.get("value") or "").strip()
                if pcp.isdigit() and int(pcp) >= CONTROL_PCP:
                    tc = pcp_el.getparent()
                    name_tc = tc.get("name") if tc is not None else "?"
                    why = f"traffic class {name_tc!r} pcp {pcp} at {at_line(sourceline(pcp_el))}"
                    break
            if why:
                out[(doc.source, name)] = why
        for net in doc.root.iterfind("network"):
            name = (net.get("name") or "").strip()
            why = None
            chain = net.find("chain")
            if chain is not None:
                why = f"chain {chain.get('name')!r}"
            for vlan in net.iter("vlan"):
                pcp = (vlan.get("pcp") or "").strip()
                if pcp.isdigit() and int(pcp) >= CONTROL_PCP:
                    why = f"VLAN {vlan.get('id')} pcp {pcp} at {at_line(sourceline(vlan))}"
                    break
            if why:
                out[(doc.source, name)] = why
    return out


def check_store(report: Report, plan: Plan, store_dir: str, wrapper: Any, *, now: datetime) -> None:
    """Keys past their rekey interval, read through the store's own status (its passphrase needed).

    Raises:
        InputError / IntegrityError: the store cannot be opened (wrong passphrase, tampered).
    """
    from ..macsec.rotation import status
    from ..macsec.store import KeyStore

    store = KeyStore.open(store_dir, wrapper)
    cas = plan.associations
    for row in status(store, plan, now=now).rows:
        if not row["due"]:
            continue
        ca = cas.get(row["id"])
        report.add(
            "macsec-rekey-due",
            f"{row['id']}: generation {row['active_generation']} is {row['age_sec']} s old, past its "
            f"rekey interval of {row['rekey_interval_sec']} s (run macsec rotate)",
            file=ca.file if ca else row["source"]["file"],
            line=ca.line if ca else row["source"]["line"],
        )
