"""The MACsec reader of HCDF's connectivity model as upstream writes it since April 2026.

Upstream (CogniPilot/hcdformat, ``rust/hcdformat-rs/src/model/connectivity.rs``) keeps
``version="1.0"`` and moved networks to the top level: ``<link>``, ``<bus>``, ``<chain>``,
``<star>``, ``<ring>``, ``<mesh>``, ``<tree>``, each with ``<participant name><endpoint>
<port-ref component port/>`` (or ``<channel-ref>``), ``<hop>``s and ``<leg>``s, and a
``<configuration><macsec>`` holding named ``<policy>``s, a ``<default-policy>`` and
``<override>``s. :func:`plan_networks` turns that into the same
:class:`~hcdf_trust.macsec.plan.Association`\\ s the 1.0 reader makes, so store, rotation and
export work unchanged.

Rules this module defines:

Associations (one CAK each), from the topology
    ``link:NET``          a ``<link>``: its two participants
    ``bus:NET``           a ``<bus>`` (a shared medium): every participant
    ``mesh:NET``          a ``<mesh>`` without legs: every participant
    ``star:NET``          a ``<star>`` without legs (one coordinator port and its peers): every participant
    ``leg:NET/LEG``       each ``<leg>`` of a chain, ring, tree, star or mesh: its from and to
    ``NET`` is the network's name scoped like every name of an included file (flatten's prefix).

Policy of a segment
    an ``<override>`` whose ``<target>`` is its ``<leg-ref>``, else one whose target is the
    network's ``<network-ref>``, else ``<default-policy>``; a segment with none is listed as
    unprotected. ``<macsec-policy-ref network policy>`` names a ``<policy>`` of a network of
    the same document instance. ``enforcement`` is 1.0's ``policy`` (``must-secure``,
    ``should-secure``, ``integrity-only``, ``disabled``: listed, no key).

Identifiers
    ``cipher``: ``gcm-aes-128|256``, ``gcm-aes-xpn-128|256``, bare (1.0) or qualified by
    ``ieee8021ae:`` or ``ieee:``. ``key-agreement``: ``psk`` qualified by ``local:``,
    ``vendor:`` or ``ieee:``, or bare; ``ieee:mka`` (MKA with a pre-shared CAK, which is
    what the store holds and what the wpa_supplicant export runs) is ``psk``; ``eap-tls``
    bare or qualified by ``ieee:``/``ieee8021x:``. ``rekey-interval-ns`` becomes 1.0's
    ``rekey-interval-sec`` (whole seconds, rounded down: rotation is due no later).
    ``credential-store-ref`` is the key store reference; its kind, for the plan's
    ``key_store.type``: ``tpm``/``tpm0``/``tpm:…`` → tpm, ``se05x``/``se050``/``se051``/
    ``se:…``/``secure-element:…`` → secure-element, ``hsm…``/``pkcs11:…`` → hsm,
    ``file:…`` or a path (``keys/main``) → file, ``runtime:…`` → runtime; any other name
    (``keystore:control-bus``) is kept as the reference with no kind.

Fail closed (exit 3, element and line)
    an unknown child of ``<macsec>`` or attribute of ``<policy>``, a missing or unknown
    ``enforcement``/``cipher``/``key-agreement``/``confidentiality-offset``/``rekey-interval-ns``,
    two policies of one name, a policy reference or override target that resolves to
    nothing, a ``<macsec>`` that gives no segment a policy, MACsec on a network that is not
    wired Ethernet (``selected`` purpose other than communication, carrier other than
    electrical or guided-optical, a non-Ethernet profile), a secured segment whose
    participant, component or port does not exist, one with fewer than two member ports,
    a link with more than two, and a rate that cannot be read.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from lxml import etree

from ..document import single
from ..errors import counted
from ..units import UnitError, bit_rate
from ..xml import sourceline
from .plan import CIPHERS, NETWORK_KINDS, OFFSETS, POLICIES, Association, Element, MacsecPlanError, Policy

if TYPE_CHECKING:
    from ..document import Document
    from .plan import _Instance, _Planner

CIPHER_AUTHORITIES = ("ieee8021ae", "ieee")
KEY_AGREEMENT_IDS = {
    "psk": "psk",
    "local:psk": "psk",
    "vendor:psk": "psk",
    "ieee:psk": "psk",
    "mka": "psk",
    "ieee:mka": "psk",
    "eap-tls": "eap-tls",
    "ieee:eap-tls": "eap-tls",
    "ieee8021x:eap-tls": "eap-tls",
}
POLICY_ATTRIBUTES = frozenset(
    ("name", "enforcement", "cipher", "key-agreement", "confidentiality-offset", "rekey-interval-ns",
     "credential-store-ref")
)  # fmt: skip
WIRED_CARRIERS = ("electrical", "guided-optical")
_ETHERNET_PROFILE = re.compile(r"ethernet|802\.?3|\d+g?base-", re.IGNORECASE)
_STORE_KINDS = (
    (re.compile(r"tpm\d*|tpm:.*"), "tpm"),
    (re.compile(r"se05\w|se:.*|secure-element:.*"), "secure-element"),
    (re.compile(r"hsm.*|pkcs11:.*"), "hsm"),
    (re.compile(r"file:.*|[^:]*/.*"), "file"),
    (re.compile(r"runtime:.*"), "runtime"),
)


def local(el: etree._Element) -> str:
    return etree.QName(el).localname


def one(el: etree._Element | None, tag: str, source: str) -> etree._Element | None:
    """The one ``<tag>`` child (any namespace) of ``el`` through the shared accessor
    (:func:`hcdf_trust.document.single`): two are refused (exit 3, both lines)."""
    return None if el is None else single(el, "{*}" + tag, source=source)


def kids(el: etree._Element, tag: str) -> list[etree._Element]:
    return list(el.iterchildren("{*}" + tag))


def store_kind(ref: str) -> str | None:
    """The key store kind a ``credential-store-ref`` names (see the module docstring), or None."""
    for pattern, kind in _STORE_KINDS:
        if pattern.fullmatch(ref):
            return kind
    return None


def cipher_id(value: str) -> str | None:
    """A cipher id in any upstream spelling, as 1.0 writes it; None when unknown."""
    authority, sep, name = value.rpartition(":")
    if sep and authority not in CIPHER_AUTHORITIES:
        return None
    return name if name in CIPHERS else None


@dataclass
class _Network:
    """One top-level network of one document instance, and its MACsec configuration."""

    el: etree._Element
    kind: str
    name: str  # as written
    scoped: str
    macsec: etree._Element | None
    policies: dict[str, Policy | None] = field(default_factory=dict)  # None: the policy was malformed
    policy_lines: dict[str, int | None] = field(default_factory=dict)


class _Reader:
    """Plans one document instance's top-level networks into ``planner.plan``."""

    def __init__(self, planner: _Planner, inst: _Instance, doc: Document) -> None:
        self.p = planner
        self.inst = inst
        self.doc = doc
        self.networks: dict[str, _Network] = {}

    def error(self, message: str, el: etree._Element | None, *, line: int | None = None, **kw: str) -> None:
        where = sourceline(el) if el is not None else line
        self.p.errors.append(MacsecPlanError(message, file=self.doc.source, line=where, **kw))

    def run(self) -> None:
        for el in self.doc.root.iterchildren(etree.Element):
            kind = local(el)
            if kind not in NETWORK_KINDS:
                continue
            name = (el.get("name") or "").strip()
            src = self.doc.source
            config = one(one(el, "configuration", src), "macsec", src)
            net = _Network(el, kind, name, self.p._scoped(self.inst, name), config)
            if name in self.networks:
                self.error(f"two networks are named {name!r}", el)
                continue
            self.networks[name] = net
            if net.macsec is not None:
                self.p._consumed.add(net.macsec)
                self.read_policies(net)
        for net in self.networks.values():
            self.plan(net)

    # -- policies ----------------------------------------------------------------------

    def read_policies(self, net: _Network) -> None:
        assert net.macsec is not None
        for child in net.macsec.iterchildren(etree.Element):
            if local(child) not in ("policy", "default-policy", "override"):
                self.error(
                    f"<macsec> of {net.kind} {net.name!r} has an unknown child <{local(child)}>",
                    child,
                    expected="policy | default-policy | override",
                    actual=local(child),
                )
        for el in kids(net.macsec, "policy"):
            name = (el.get("name") or "").strip()
            if not name:
                self.error("<policy> has no name", el)
                continue
            if name in net.policies:
                self.error(f"two MACsec policies of {net.kind} {net.name!r} are named {name!r}", el)
                continue
            net.policies[name] = self.policy(el)
            net.policy_lines[name] = sourceline(el)

    def policy(self, el: etree._Element) -> Policy | None:
        errors = len(self.p.errors)
        for attr in map(str, el.attrib):
            if attr not in POLICY_ATTRIBUTES:
                self.error(
                    f"<policy> has an attribute this planner does not know: {attr}",
                    el,
                    expected=" | ".join(sorted(POLICY_ATTRIBUTES)),
                    actual=attr,
                )
        enforcement = (el.get("enforcement") or "").strip()
        if enforcement not in POLICIES:
            self.error(
                "<policy enforcement> is missing or unknown",
                el,
                expected=" | ".join(POLICIES),
                actual=enforcement or "(missing)",
            )
        raw_cipher = (el.get("cipher") or "gcm-aes-128").strip()
        cipher = cipher_id(raw_cipher)
        if cipher is None:
            self.error(
                "<policy cipher> is not a MACsec cipher suite this planner knows",
                el,
                expected="[ieee8021ae:|ieee:]" + "|".join(CIPHERS),
                actual=raw_cipher,
            )
        raw_agreement = (el.get("key-agreement") or "psk").strip()
        agreement = KEY_AGREEMENT_IDS.get(raw_agreement)
        if agreement is None:
            self.error(
                "<policy key-agreement> is not a key agreement this planner knows",
                el,
                expected=" | ".join(KEY_AGREEMENT_IDS),
                actual=raw_agreement,
            )
        offset_text = (el.get("confidentiality-offset") or "0").strip()
        if offset_text not in {str(o) for o in OFFSETS}:
            self.error(
                "<policy confidentiality-offset> is not 0, 30 or 50", el, expected="0 | 30 | 50", actual=offset_text
            )
        rekey = None
        rekey_text = el.get("rekey-interval-ns")
        if rekey_text is not None:
            text = rekey_text.strip()
            if not text.isdigit() or int(text) > 2**64 - 1:
                self.error("<policy rekey-interval-ns> is not an unsigned 64-bit integer", el, actual=text[:40])
            else:
                ns = int(text)
                rekey = 0 if ns == 0 else max(1, ns // 1_000_000_000)
        ref = (el.get("credential-store-ref") or "").strip() or None
        if len(self.p.errors) != errors or cipher is None or agreement is None:
            return None
        return Policy(enforcement, cipher, agreement, int(offset_text), rekey, store_kind(ref) if ref else None, ref)

    def resolve(self, ref: etree._Element | None, where: str) -> tuple[Policy | None, bool]:
        """The policy a ``<macsec-policy-ref>`` names: (policy, ok). ok is False after an error."""
        if ref is None:
            self.error(f"{where} has no <macsec-policy-ref>", None)
            return None, False
        network, name = (ref.get("network") or "").strip(), (ref.get("policy") or "").strip()
        target = self.networks.get(network)
        if target is None or name not in target.policies:
            known = sorted(f"{n}/{p}" for n, t in self.networks.items() for p in t.policies)
            self.error(
                f"{where}: <macsec-policy-ref network={network!r} policy={name!r}> names no MACsec policy",
                ref,
                expected=", ".join(known)[:300] or "a <policy> in some network's <macsec>",
                actual=f"{network}/{name}",
            )
            return None, False
        policy = target.policies[name]
        return policy, policy is not None

    # -- topology ----------------------------------------------------------------------

    def plan(self, net: _Network) -> None:
        segments = self.segments(net)
        if net.macsec is None:
            for element, _members in segments:
                if self.communication(net):
                    self.p.plan.unprotected.append(element)
                else:
                    self.p.plan.skipped.append((element, "not a communication network"))
            return
        if not self.secured_medium(net):
            return
        default, ok = None, True
        src = self.doc.source
        defaults = one(net.macsec, "default-policy", src)
        if defaults is not None:
            default, ok = self.resolve(one(defaults, "macsec-policy-ref", src), "<default-policy>")
        by_target: dict[str, tuple[Policy | None, etree._Element]] = {}
        legs = {(leg.get("name") or "").strip() for leg in kids(net.el, "leg")}
        for override in kids(net.macsec, "override"):
            target_el = one(override, "target", src)
            targets = list(target_el.iterchildren(etree.Element)) if target_el is not None else []
            policy, good = self.resolve(one(override, "macsec-policy-ref", src), "<override>")
            ok = ok and good
            if len(targets) != 1:
                self.error("<override> needs exactly one <target> with one <network-ref> or <leg-ref>", override)
                ok = False
                continue
            target = targets[0]
            kind, network = local(target), (target.get("network") or "").strip()
            if network != net.name:
                self.error(
                    f"<override> of {net.kind} {net.name!r} targets another network",
                    target,
                    expected=net.name,
                    actual=network,
                )
                ok = False
                continue
            if kind == "network-ref":
                key = ""
            elif kind == "leg-ref" and (target.get("leg") or "").strip() in legs:
                key = (target.get("leg") or "").strip()
            else:
                self.error(
                    f"<override> target <{kind}> names no leg of {net.kind} {net.name!r}",
                    target,
                    expected="<network-ref> | <leg-ref> of one of: " + ", ".join(sorted(legs))[:200],
                    actual=kind if kind != "leg-ref" else f"leg {target.get('leg')!r}",
                )
                ok = False
                continue
            if key in by_target:
                self.error(f"two <override>s target {'leg ' + key if key else 'the network'}", target)
                ok = False
                continue
            by_target[key] = (policy, target)
        if not ok:
            return
        whole = by_target.get("", (default, None))[0]
        assigned = 0
        for element, members in segments:
            policy = by_target.get(element.name if element.kind == "leg" else "\0", (whole, None))[0]
            if policy is None:
                self.p.plan.unprotected.append(element)
                continue
            assigned += 1
            self.associate(net, element, policy, members)
        if not assigned:
            self.error(
                f"<macsec> of {net.kind} {net.name!r} gives no segment a policy (no <default-policy> and no "
                f"<override> that applies): it would key nothing",
                net.macsec,
            )

    def communication(self, net: _Network) -> bool:
        selected = one(net.el, "selected", self.doc.source)
        return selected is None or (selected.get("purpose") or "communication").strip() == "communication"

    def secured_medium(self, net: _Network) -> bool:
        """Whether MACsec can run on the network (wired Ethernet); an error naming why not."""
        assert net.macsec is not None
        selected = one(net.el, "selected", self.doc.source)
        purpose = (selected.get("purpose") or "").strip() if selected is not None else ""
        carrier = (selected.get("carrier") or "").strip() if selected is not None else ""
        profiles = [(p.get("id") or "").strip() for p in kids(selected, "profile")] if selected is not None else []
        why = None
        if purpose and purpose != "communication":
            why = f"its purpose is {purpose}"
        elif carrier and carrier not in WIRED_CARRIERS:
            why = f"its carrier is {carrier} (MACsec needs wired Ethernet: {' or '.join(WIRED_CARRIERS)})"
        elif bad := [p for p in profiles if not _ETHERNET_PROFILE.search(p)]:
            why = f"it selects the non-Ethernet profile {bad[0]}"
        if why is not None:
            self.error(f"{net.kind} {net.name!r} has a MACsec policy, but {why}", net.macsec)
            return False
        return True

    def segments(self, net: _Network) -> list[tuple[Element, list[etree._Element]]]:
        """Each segment of ``net`` and the ``<participant>`` elements it joins (None when unresolved)."""
        participants: dict[str, etree._Element] = {}
        for part in kids(net.el, "participant"):
            name = (part.get("name") or "").strip()
            if name in participants and net.macsec is not None:
                self.error(f"{net.kind} {net.name!r} has two participants named {name!r}", part)
            participants.setdefault(name, part)

        def element(kind: str, name: str, el: etree._Element) -> Element:
            return Element(kind, net.scoped, name, self.doc.source, sourceline(el), self.inst.scope)

        def participant(ref: etree._Element | None, where: etree._Element) -> etree._Element:
            name = (ref.get("participant") or "").strip() if ref is not None else ""
            found = participants.get(name)
            if ref is None or found is None or (ref.get("network") or "").strip() != net.name:
                if net.macsec is not None:
                    self.error(
                        f"{net.kind} {net.name!r}: a <participant-ref> names no participant of this network",
                        ref if ref is not None else where,
                        expected=f"network {net.name!r}, one of: " + ", ".join(participants)[:200],
                        actual=f"network {ref.get('network')!r} participant {name!r}" if ref is not None else "(none)",
                    )
                return where  # no member: the segment then has too few
            return found

        legs = kids(net.el, "leg")
        if legs:
            hops = {(h.get("name") or "").strip() for h in kids(net.el, "hop")}
            out = []
            for leg in legs:
                ends = []
                for side in ("from", "to"):
                    end = one(leg, side, self.doc.source)
                    hop = one(end, "hop-ref", self.doc.source)
                    if net.macsec is not None and (hop is None or (hop.get("hop") or "").strip() not in hops):
                        self.error(
                            f"leg {leg.get('name')!r}: its <{side}> names no <hop> of {net.name!r}",
                            end if end is not None else leg,
                        )
                    ref = one(end, "participant-ref", self.doc.source)
                    ends.append(participant(ref, leg))
                out.append((element("leg", (leg.get("name") or "").strip(), leg), ends))
            return out
        if net.kind in ("chain", "ring", "tree"):
            if net.macsec is not None:
                self.error(f"{net.kind} {net.name!r} has a MACsec policy and no <leg>: no segment to key", net.el)
            return []
        if net.kind == "star":  # a coordinator port and its peers: one shared segment, like a bus
            ref = one(one(net.el, "coordinator", self.doc.source), "participant-ref", self.doc.source)
            participant(ref, net.el)  # must resolve when secured
        return [(element(net.kind, "", net.el), list(participants.values()))]  # the whole network

    def associate(self, net: _Network, element: Element, policy: Policy, members: list[etree._Element]) -> None:
        if element.kind == "leg":
            ca_id = f"{element.kind}:{net.scoped}/{element.name}"
        else:
            ca_id = f"{net.kind}:{net.scoped}"
        if ca_id in self.p.plan.associations:
            self.error(f"two segments have the association id {ca_id}", net.el)
            return
        ca = self.p.plan.associations[ca_id] = Association(ca_id, "macsec", None, policy)
        ca.elements.append(element)
        rate = self.selected_rate(net, keyed=policy.policy != "disabled")
        ports = 0
        for part in members:
            if local(part) != "participant":
                continue  # an unresolved reference, already an error
            endpoint = one(part, "endpoint", self.doc.source)
            refs = list(endpoint.iterchildren(etree.Element)) if endpoint is not None else []
            ref = refs[0] if len(refs) == 1 else None
            if ref is None or local(ref) not in ("port-ref", "channel-ref"):
                self.error(f"participant {part.get('name')!r} has no <endpoint><port-ref>", part)
                continue
            component, port = (ref.get("component") or "").strip(), (ref.get("port") or "").strip()
            comp = self.p._find_comp(self.inst, component)
            port_ref = self.p._port(comp, port)
            if comp is None or port_ref is None:
                what = f"component {component!r}" if comp is None else f"port {component}/{port}"
                self.error(f"{ca_id}: participant {part.get('name')!r} names {what}, which is not defined", ref)
                continue
            device = self.p._device(self.inst, component)
            self.p._endpoint(ca, element, device, port, port_ref, capabilities=False)
            if rate is not None:
                ca.port_speeds_mbps[f"{device}/{port}"] = rate
            ports += 1
        if policy.policy == "disabled":
            return
        if ports < 2 or (net.kind == "link" and ports > 2):
            self.error(
                f"{ca_id} is secured but joins {counted(ports, 'port')}: "
                + ("a link joins exactly two" if net.kind == "link" else "a secured segment needs at least two"),
                None,
                line=element.line,
            )

    def selected_rate(self, net: _Network, *, keyed: bool) -> float | None:
        """The network's ``<selected><rate><nominal value unit>`` in Mb/s (the rate it runs at), if given."""
        src = self.doc.source
        nominal = one(one(one(net.el, "selected", src), "rate", src), "nominal", src)
        if nominal is None:
            return None
        try:
            return bit_rate(nominal.get("value"), nominal.get("unit"), default_unit="bit/s") / 1e6
        except UnitError as exc:
            if keyed:
                self.error(f"{net.kind} {net.name!r}: the selected rate cannot be read ({exc})", nominal)
            return None


def plan_networks(planner: _Planner, inst: _Instance, doc: Document) -> None:
    """Add the associations of ``doc``'s top-level networks (in instance ``inst``) to the plan."""
    _Reader(planner, inst, doc).run()
