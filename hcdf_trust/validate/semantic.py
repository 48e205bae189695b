"""HCDF rules the schema documents but XSD 1.0 cannot check.

Pure: a parsed ``<hcdf>`` tree, plus what the I/O layer found along its include
chain (:class:`IncludeEdge`: the included documents and their frames), in;
findings out. Every finding has its own code, the file and the line. All
problems are collected; nothing stops at the first. The codes are listed in
:data:`RULES`; how the ambiguous rules are read is in each ``rule_*`` docstring.

Names an included file defines count as defined, under the prefix flattening
gives them (``<include name="left_arm">`` + comp ``shoulder`` = ``left_arm_shoulder``).

Paths follow hcdf.xsd 1.0: ``hcdf/comp[/switch]/port``, ``hcdf/network/link/wired/port``
and so on. Content inside ``<extension>`` is never looked at.
"""

from __future__ import annotations

import re
from collections import Counter, defaultdict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

from lxml import etree

from ..document import single
from ..errors import at_line
from ..include.flatten import SEPARATOR
from ..include.locate import redact
from ..xml import sourceline
from .findings import Finding, Severity

#: code -> what the rule checks (also the documentation of the codes)
RULES: dict[str, str] = {
    "unresolved-comp": "a comp named by a joint parent/child, loop predecessor/successor, "
    "group tip-comp or self-collision pair exists",
    "unresolved-device": "a device named by a bus participant, PLCA coordinator, chain hop, spur, "
    "gPTP clock, mesh node, DC reference clock or tunnel hop exists",
    "unresolved-port": "a port reference resolves: link ports and schedule-assignment ports "
    "('comp/port' or 'comp.port'), and port names on a device (hop, spur, participant, clock)",
    "unresolved-antenna": "a wireless link antenna ('comp/antenna' or 'comp.antenna') or a mesh "
    "node antenna exists on its comp",
    "unresolved-joint": "a joint named by a mimic, state joint-position, group or transmission exists",
    "unresolved-motor": "a transmission motor or spring actuator ('comp.motor' or a unique motor name) exists",
    "unresolved-group": "a sub-group named by a group exists",
    "unresolved-schedule": "a schedule-assignment names a schedule of the same network",
    "unresolved-chain": "a schedule-assignment names a chain of the same network; a tunnel names an existing chain",
    "duplicate-name": "names that references use are unique (comps, joints, groups; ports, "
    "antennas, motors per comp; schedules, chains per network)",
    "port-ref-form-mixed": "a document writes port/antenna references in one form (warning)",
    "schedule-cycle-mismatch": "the gate durations of a schedule sum to its cycle-time-us",
    "t1-phy-roles": "a T1 link (or T1 chain segment) has one PHY master and one PHY slave",
    "t1-phy-role-missing": "both ends of a T1 link declare a PHY role",
    "joint-limit-order": "limit upper >= lower (all joint types but continuous)",
    "joint-requires": "revolute/prismatic/cylindrical have axis + limit, continuous has axis, "
    "universal has axis + axis2, screw has axis + thread_pitch",
    "joint-forbids": "fixed and free joints have no axis, axis2 or limit",
    "joint-ignored": "axis2 only on universal joints, thread_pitch only on screw joints (warning)",
    "macsec-key-ref-conflict": "one key-ref is not used with different ciphers or policies",
    "macsec-cipher-unsupported": "a link's or chain's MACsec cipher is among the ciphers its ports declare (warning)",
    "unresolved-participant": "in upstream's newer connectivity model (top-level link, bus, chain, star, ring, "
    "mesh, tree): a participant-ref or hop-ref names one of its network, a macsec-policy-ref a policy",
    "frame-convention-mismatch": "body-frame and world-frame agree across the include chain",
    "include-unchecked": "an include could not be read (remote, missing, cycle, too deep): its names "
    "and frames were not checked (warning)",
    "include-refused": "an include escapes its root, is not a regular file, or is malformed or hostile XML",
}

#: how flattening joins an include's name to the names it brings
INCLUDE_SEPARATOR = SEPARATOR

#: macsec@cipher's default in hcdf.xsd (macsec_policy and macsec_config)
DEFAULT_CIPHER = "gcm-aes-128"

#: Single-pair Ethernet, where PHY master/slave applies: nBASE-T1 and nBASE-T1L
#: (10BASE-T1S is multidrop with PLCA, no master/slave) and 802.3dm (asymmetric).
T1_STANDARD = re.compile(r"base-t1(?!s)|802\.3dm", re.IGNORECASE)

#: The T1 standards for which hcdf.xsd (phy_config) says the role is *required*.
#: For other T1 speeds (2.5G/5G/10GBASE-T1) a missing role is a warning: the
#: upstream humanoid example leaves it out on its 2.5GBASE-T1 links.
PHY_ROLE_REQUIRED = re.compile(r"^\s*(100base-t1|1000base-t1|802\.3dm)\s*$", re.IGNORECASE)

_JOINT_REQUIRES: dict[str, tuple[str, ...]] = {
    "revolute": ("axis", "limit"),
    "prismatic": ("axis", "limit"),
    "cylindrical": ("axis", "limit"),
    "continuous": ("axis",),
    "universal": ("axis", "axis2"),
    "screw": ("axis", "@thread_pitch"),
}
_JOINT_FORBIDS: dict[str, tuple[str, ...]] = {
    "fixed": ("axis", "axis2", "limit"),
    "free": ("axis", "axis2", "limit"),
}
_FORMS = {"/": "comp/port", ".": "comp.port"}


@dataclass(frozen=True)
class IncludeEdge:
    """One ``<include>`` as the I/O layer found it.

    ``prefix`` is what flattening puts before the included file's names
    (``left_arm_``; empty for an include without ``name``). ``child`` and
    ``document`` are None when the included file was not read; ``skipped`` says why.
    """

    parent: str  # how findings name the including document
    line: int | None  # of the <include> element in ``parent``
    uri: str
    prefix: str = ""
    child: str | None = None
    body_frame: str | None = None
    world_frame: str | None = None
    skipped: str | None = None
    refused: bool = False  # skipped because it is hostile or unusable, not merely absent
    document: etree._Element | None = field(default=None, compare=False, repr=False)


@dataclass
class SemanticResult:
    findings: list[Finding] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)


def check(root: etree._Element, *, source: str, includes: Sequence[IncludeEdge] = ()) -> SemanticResult:
    """Run every rule on one ``<hcdf>`` tree. Never raises for content problems.

    Without ``includes`` (a tree with no path), the tree's ``<include>`` elements
    count as unread: names they could bring are warnings, not errors.
    """
    checker = _Checker(root, source, list(includes))
    checker.run()
    return SemanticResult(findings=checker.findings, notes=checker.notes)


# --- helpers -------------------------------------------------------------------------


def _text(el: etree._Element | None) -> str | None:
    if el is None or el.text is None:
        return None
    return el.text.strip() or None


def _uint(value: str | None) -> int | None:
    if value is None:
        return None
    try:
        number = int(value.strip())
    except ValueError:
        return None
    return number if number >= 0 else None


def _float(value: str | None, default: float) -> float | None:
    if value is None:
        return default
    try:
        return float(value.strip())
    except ValueError:
        return None


def _phy_role(port: etree._Element) -> str | None:
    phy = port.find("capabilities/phy")
    return phy.get("role") if phy is not None else None


def _port_standard(port: etree._Element) -> str | None:
    return _text(port.find("capabilities/standard"))


def _declared_ciphers(port: etree._Element) -> list[str]:
    """The port's own ``<macsec><cipher>`` list; if it has none, its switch's."""
    own = [t for c in port.findall("capabilities/macsec/cipher") if (t := _text(c))]
    if own:
        return own
    parent = port.getparent()
    if parent is not None and parent.tag == "switch":
        return [t for c in parent.findall("macsec/cipher") if (t := _text(c))]
    return []


def _first(found: dict[str, _Port | None], keys: tuple[str, ...]) -> _Port | None:
    return next((el for k in keys if (el := found.get(k)) is not None), None)


def _listing(names: Iterable[str], limit: int = 10) -> str:
    items = sorted(n for n in names if n)
    if not items:
        return "it has none"
    shown = ", ".join(items[:limit])
    return f"it has: {shown}" + (f" and {len(items) - limit} more" if len(items) > limit else "")


class _Port(NamedTuple):
    """A resolved port and the name the reference gave it (``comp/port``, with the include
    prefix: one included file's port element can stand for several instances)."""

    el: etree._Element
    label: str


@dataclass
class _Link:
    network: etree._Element
    link: etree._Element
    wired: etree._Element
    ports: list[_Port | None]


@dataclass
class _Chain:
    network: etree._Element
    chain: etree._Element
    ports: list[_Port] = field(default_factory=list)
    # (upstream-side port, downstream-side port, element to report at, label)
    segments: list[tuple[_Port | None, _Port | None, etree._Element, str]] = field(default_factory=list)


class _Checker:
    def __init__(self, root: etree._Element, source: str, edges: list[IncludeEdge]) -> None:
        self.root = root
        self.source = source
        self.edges = edges
        self.findings: list[Finding] = []
        self.notes: list[str] = []
        self.comps: dict[str, etree._Element] = {}
        self.ports: dict[str, dict[str, etree._Element]] = {}
        self.antennas: dict[str, dict[str, etree._Element]] = {}
        self.motors: dict[str, dict[str, etree._Element]] = {}
        self.joints: dict[str, etree._Element] = {}
        self.groups: dict[str, etree._Element] = {}
        self.chains: dict[str, etree._Element] = {}
        self.local_chains: set[str] = set()
        # includes that were not read, with the prefix their names would carry
        self.unread: list[tuple[str, str, str, int | None]] = [  # (prefix, uri, file, line)
            (e.prefix, e.uri, e.parent, e.line) for e in edges if e.document is None
        ]
        if not edges:  # a Document given without a path: its includes were not read
            self.unread = [
                (
                    f"{n}{INCLUDE_SEPARATOR}" if (n := (el.get("name") or "").strip()) else "",
                    redact(el.get("uri") or ""),
                    source,
                    sourceline(el),
                )
                for el in root.findall("include")
            ]
        self.links: list[_Link] = []
        self.chain_info: list[_Chain] = []
        self.forms: Counter[str] = Counter()
        self.first_of_form: dict[str, etree._Element] = {}

    def add(self, code: str, severity: Severity, message: str, el: etree._Element | None = None) -> None:
        line = sourceline(el) if el is not None else None
        self.findings.append(Finding(code, severity, message, file=self.source, line=line))

    def run(self) -> None:
        self.index()
        self.rule_references()
        self.rule_port_ref_forms()
        self.rule_schedules()
        self.rule_t1()
        self.rule_joints()
        self.rule_key_refs()
        self.rule_macsec_ciphers()
        self.rule_connectivity()
        self.rule_frames()

    # --- index and duplicate names ---------------------------------------------------

    def _unique(self, elements: Iterable[etree._Element], what: str) -> dict[str, etree._Element]:
        table: dict[str, etree._Element] = {}
        for el in elements:
            name = el.get("name")
            if name is None:
                continue  # the XSD reports the missing attribute
            if name in table:
                self.add(
                    "duplicate-name",
                    "error",
                    f"{what} {name!r} is defined twice (first at {at_line(sourceline(table[name]))}); "
                    "references to it are ambiguous",
                    el,
                )
                continue
            table[name] = el
        return table

    def index(self) -> None:
        """Names this document defines, then those its readable includes bring, prefixed
        as flattening prefixes them (the first definition of a name wins)."""
        root = self.root
        self.comps = self._unique(root.findall("comp"), "comp")
        for name, comp in self.comps.items():
            self._index_comp(name, comp, check=True)
        self.joints = self._unique(root.findall("joint"), "joint")
        self.groups = self._unique(root.findall("group"), "group")
        for net in root.findall("network"):
            label = f"network {net.get('name')!r}:"
            self._unique(net.findall("schedule"), f"{label} schedule")
            self._unique(net.findall("chain"), f"{label} chain")
            for chain in net.findall("chain"):
                self.chains.setdefault(chain.get("name", ""), chain)
        self.local_chains = set(self.chains)  # hop devices of included chains are not prefixed
        for edge in self.edges:
            if edge.document is None:
                continue
            for comp in edge.document.findall("comp"):
                if comp.get("name") and (full := edge.prefix + comp.get("name", "")) not in self.comps:
                    self.comps[full] = comp
                    self._index_comp(full, comp, check=False)
            for table, tag in ((self.joints, "joint"), (self.groups, "group")):
                for el in edge.document.findall(tag):
                    if el.get("name"):
                        table.setdefault(edge.prefix + el.get("name", ""), el)
            for chain in edge.document.findall("network/chain"):
                self.chains.setdefault(edge.prefix + chain.get("name", ""), chain)

    def _index_comp(self, name: str, comp: etree._Element, *, check: bool) -> None:
        def table(elements: list[etree._Element], what: str) -> dict[str, etree._Element]:
            if check:
                return self._unique(elements, f"comp {name!r}: {what}")
            return {n: el for el in reversed(elements) if (n := el.get("name"))}

        self.ports[name] = table(comp.findall("port") + comp.findall("switch/port"), "port")
        self.antennas[name] = table(comp.findall("antenna"), "antenna")
        self.motors[name] = table(comp.findall("motor"), "motor")

    # --- name lookups ----------------------------------------------------------------

    def _missing(self, code: str, name: str, message: str, el: etree._Element) -> None:
        """A name is not defined here nor in a readable include: an error, unless an include
        that could not be read would bring it (its prefix, as flattening forms it, starts the name)."""
        unread = next((u for u in self.unread if name.startswith(u[0])), None)
        if unread is None:
            self.add(code, "error", message, el)
            return
        _, uri, file, line = unread
        where = at_line(line) if file == self.source else f"{file}:{line}"
        self.add(
            code,
            "warning",
            f"{message}; it may come from the include of {uri!r} ({where}), which could not be read",
            el,
        )

    def _comp(self, name: str | None, *, code: str, what: str, el: etree._Element) -> etree._Element | None:
        if name is None:
            return None  # a required attribute: the XSD reports it
        comp = self.comps.get(name)
        if comp is None:
            self._missing(code, name, f"{what} {name!r}: no comp of that name", el)
        return comp

    def _port(self, comp: str, name: str | None, *, what: str, el: etree._Element) -> _Port | None:
        if name is None or comp not in self.comps:
            return None
        port = self.ports[comp].get(name)
        if port is None:
            self.add(
                "unresolved-port",
                "error",
                f"{what}: comp {comp!r} has no port {name!r} ({_listing(self.ports[comp])})",
                el,
            )
            return None
        return _Port(port, f"{comp}/{name}")

    def _named(
        self, table: dict[str, etree._Element], name: str | None, *, code: str, what: str, el: etree._Element
    ) -> etree._Element | None:
        if name is None:
            return None
        found = table.get(name)
        if found is None:
            self._missing(code, name, f"{what} {name!r}: not defined", el)
        return found

    def _item_ref(self, text: str | None, el: etree._Element, kind: str) -> _Port | None:
        """Resolve 'comp/item' or 'comp.item' (kind: port or antenna); record the form used."""
        table = self.ports if kind == "port" else self.antennas
        code = f"unresolved-{kind}"
        ref = (text or "").strip()
        if not ref:
            self.add(code, "error", f"empty {kind} reference", el)
            return None
        sep = "/" if "/" in ref else "." if "." in ref else None
        if sep is None:
            self.add(
                code,
                "error",
                f"{kind} reference {ref!r} names no comp: write 'comp/{kind}' or 'comp.{kind}'",
                el,
            )
            return None
        form = _FORMS[sep].replace("port", kind)
        self.forms[sep] += 1
        self.first_of_form.setdefault(sep, el)
        splits = [(ref[:i], ref[i + 1 :]) for i, ch in enumerate(ref) if ch == sep]
        comp, item = next(
            ((c, i) for c, i in splits if c in self.comps and i in table[c]),
            next(((c, i) for c, i in splits if c in self.comps), splits[0]),
        )
        if comp not in self.comps:
            self._missing(code, comp, f"{kind} reference {ref!r} ({form} form): no comp {comp!r}", el)
            return None
        found = table[comp].get(item)
        if found is None:
            self.add(
                code,
                "error",
                f"{kind} reference {ref!r} ({form} form): comp {comp!r} has no {kind} {item!r} "
                f"({_listing(table[comp])})",
                el,
            )
            return None
        return _Port(found, f"{comp}/{item}")

    def _motor(self, ref: str | None, el: etree._Element, what: str) -> None:
        if ref is None:
            return
        ref = ref.strip()
        for sep in ("/", "."):
            for i, ch in enumerate(ref):
                if ch == sep and ref[:i] in self.comps:
                    comp, name = ref[:i], ref[i + 1 :]
                    if name not in self.motors[comp]:
                        self.add(
                            "unresolved-motor",
                            "error",
                            f"{what} {ref!r}: comp {comp!r} has no motor {name!r} ({_listing(self.motors[comp])})",
                            el,
                        )
                    return
        owners = [c for c, motors in self.motors.items() if ref in motors]
        if not owners:
            self._missing("unresolved-motor", ref, f"{what} {ref!r}: no motor of that name", el)
        elif len(owners) > 1:
            self.add(
                "unresolved-motor",
                "warning",
                f"{what} {ref!r} is ambiguous: comps {', '.join(sorted(owners))} each have a motor "
                f"of that name; write 'comp.{ref}'",
                el,
            )

    # --- rule: references ------------------------------------------------------------

    def rule_references(self) -> None:
        """Every comp, device, port, antenna, joint, motor, group, schedule and chain named resolves.

        A comp-level name that is missing but could come from an ``<include>``
        (one without a name prefix, or whose prefix starts the name) is a
        warning, not an error: validate checks one document and does not merge
        includes (the prefix convention belongs to flattening).
        """
        root = self.root
        for joint in root.findall("joint"):
            jname = joint.get("name")
            for tag in ("parent", "child"):
                sub = joint.find(tag)
                if sub is not None:
                    self._comp(sub.get("comp"), code="unresolved-comp", what=f"joint {jname!r} {tag}", el=sub)
            mimic = joint.find("mimic")
            if mimic is not None:
                self._named(
                    self.joints,
                    mimic.get("joint"),
                    code="unresolved-joint",
                    what=f"joint {jname!r} mimics joint",
                    el=mimic,
                )
            for tag in ("loop/predecessor", "loop/successor"):
                sub = joint.find(tag)
                if sub is not None:
                    self._comp(_text(sub), code="unresolved-comp", what=f"joint {jname!r} {tag}", el=sub)
        for state in root.findall("state"):
            for pos in state.findall("joint-position"):
                self._named(
                    self.joints,
                    pos.get("joint"),
                    code="unresolved-joint",
                    what=f"state {state.get('name')!r} sets joint",
                    el=pos,
                )
        for group in root.findall("group"):
            gname = group.get("name")
            for j in group.findall("joint"):
                self._named(self.joints, j.get("ref"), code="unresolved-joint", what=f"group {gname!r} joint", el=j)
            for g in group.findall("group"):
                self._named(self.groups, g.get("ref"), code="unresolved-group", what=f"group {gname!r} sub-group", el=g)
            self._comp(group.get("tip-comp"), code="unresolved-comp", what=f"group {gname!r} tip-comp", el=group)
        for pair in root.findall("self-collision-disable/pair"):
            for attr in ("comp1", "comp2"):
                self._comp(pair.get(attr), code="unresolved-comp", what=f"self-collision pair {attr}", el=pair)
        for tr in root.findall("transmission"):
            tname = tr.get("name")
            motor = tr.find("motor")
            if motor is not None:
                self._motor(motor.get("ref"), motor, f"transmission {tname!r} motor")
            tr_joint = tr.find("joint")
            if tr_joint is not None:
                self._named(
                    self.joints,
                    tr_joint.get("ref"),
                    code="unresolved-joint",
                    what=f"transmission {tname!r} joint",
                    el=tr_joint,
                )
            for spring in tr.findall("spring"):
                for attr in ("equilibrium-actuator", "stiffness-actuator"):
                    self._motor(spring.get(attr), spring, f"transmission {tname!r} spring {attr}")
        for net in root.findall("network"):
            self._network(net)

    def _device_port(self, el: etree._Element, what: str) -> _Port | None:
        device = el.get("device")
        if self._comp(device, code="unresolved-device", what=f"{what} device", el=el) is None:
            return None
        assert device is not None
        return self._port(device, el.get("port"), what=f"{what} device {device!r}", el=el)

    def _network(self, net: etree._Element) -> None:
        nname = net.get("name")
        where = f"network {nname!r}"
        schedules = {s.get("name") for s in net.findall("schedule")}
        chains_here = {c.get("name") for c in net.findall("chain")}
        for link in net.findall("link"):
            wired = single(link, "wired", source=self.source)
            if wired is not None:
                ports = [self._item_ref(p.text, p, "port") for p in wired.findall("port")]
                self.links.append(_Link(net, link, wired, ports))
            wireless = single(link, "wireless", source=self.source)
            if wireless is not None:
                for ant in wireless.findall("antenna"):
                    self._item_ref(ant.text, ant, "antenna")
        for bus in net.findall("bus"):
            bname = bus.get("name")
            for part in bus.findall("participant"):
                self._device_port(part, f"bus {bname!r} participant")
            for coord in bus.findall("plca/coordinator"):
                self._device_port(coord, f"bus {bname!r} PLCA coordinator")
        for chain in net.findall("chain"):
            self._chain(net, chain)
        for mesh in net.findall("mesh"):
            mname = mesh.get("name")
            for node in mesh.findall("node"):
                device = node.get("device")
                comp = self._comp(device, code="unresolved-device", what=f"mesh {mname!r} node device", el=node)
                antenna = node.get("antenna")
                if comp is not None and antenna is not None and antenna not in self.antennas[device or ""]:
                    self.add(
                        "unresolved-antenna",
                        "error",
                        f"mesh {mname!r} node: comp {device!r} has no antenna {antenna!r} "
                        f"({_listing(self.antennas[device or ''])})",
                        node,
                    )
        for clock in net.findall("gptp/clock"):
            self._device_port(clock, f"{where} gPTP clock")
        for assign in net.findall("schedule-assignment/assign"):
            sched = assign.get("schedule")
            if sched is not None and sched not in schedules:
                elsewhere = [
                    n.get("name")
                    for n in self.root.findall("network")
                    if n is not net and any(s.get("name") == sched for s in n.findall("schedule"))
                ]
                hint = f" (it is defined in network {elsewhere[0]!r})" if elsewhere else ""
                self.add(
                    "unresolved-schedule",
                    "error",
                    f"schedule-assignment in {where} names schedule {sched!r}, which this network "
                    f"does not define{hint}",
                    assign,
                )
            for ref in (assign.get("ports") or "").split():
                self._item_ref(ref, assign, "port")
            for cname in (assign.get("chains") or "").split():
                if cname not in chains_here:
                    self.add(
                        "unresolved-chain",
                        "error",
                        f"schedule-assignment in {where} names chain {cname!r}, which this network does not define",
                        assign,
                    )

    def _chain(self, net: etree._Element, chain: etree._Element) -> None:
        cname = chain.get("name")
        info = _Chain(net, chain)
        self.chain_info.append(info)
        sides: list[tuple[etree._Element, _Port | None, _Port | None]] = []
        for hop in chain.findall("hop"):
            device = hop.get("device")
            what = f"chain {cname!r} hop"
            comp = self._comp(device, code="unresolved-device", what=f"{what} device", el=hop)
            resolved: dict[str, _Port | None] = {}
            if comp is not None and device is not None:
                for attr in ("port", "port-primary", "port-secondary", "ingress", "egress"):
                    if hop.get(attr) is not None:
                        port = self._port(device, hop.get(attr), what=f"{what} {device!r} {attr}", el=hop)
                        resolved[attr] = port
                        if port is not None:
                            info.ports.append(port)
            up = _first(resolved, ("ingress", "port-primary", "port"))
            down = _first(resolved, ("egress", "port-secondary", "port"))
            sides.append((hop, up, down))
            for spur in hop.findall("spur"):
                sdev = spur.get("device")
                scomp = self._comp(sdev, code="unresolved-device", what=f"chain {cname!r} spur device", el=spur)
                sport = via = None
                if scomp is not None and sdev is not None:
                    sport = self._port(sdev, spur.get("port"), what=f"chain {cname!r} spur {sdev!r} port", el=spur)
                if comp is not None and device is not None:
                    via = self._port(device, spur.get("via"), what=f"chain {cname!r} spur via {device!r}", el=spur)
                info.ports.extend(p for p in (via, sport) if p is not None)
                info.segments.append((via, sport, spur, f"chain {cname!r} spur {device}→{sdev}"))
        for (hop_a, _, down), (hop_b, up, _) in zip(sides, sides[1:], strict=False):
            label = f"chain {cname!r} segment {hop_a.get('device')}→{hop_b.get('device')}"
            info.segments.append((down, up, hop_b, label))
        dc = chain.find("dc")
        if dc is not None:
            self._comp(
                dc.get("reference-clock"), code="unresolved-device", what=f"chain {cname!r} DC reference-clock", el=dc
            )
        tunnel = chain.find("tunnel")
        if tunnel is not None:
            outer_name = tunnel.get("chain")
            outer = self.chains.get(outer_name or "")
            if outer_name is not None and outer is None:
                self.add(
                    "unresolved-chain",
                    "error",
                    f"chain {cname!r} tunnels over chain {outer_name!r}, which is not defined",
                    tunnel,
                )
            hop_dev = tunnel.get("hop")
            if self._comp(hop_dev, code="unresolved-device", what=f"chain {cname!r} tunnel hop", el=tunnel) is not None:
                if (
                    outer is not None
                    and outer_name in self.local_chains
                    and hop_dev not in {h.get("device") for h in outer.findall("hop")}
                ):
                    self.add(
                        "unresolved-device",
                        "error",
                        f"chain {cname!r} tunnel hop {hop_dev!r} is not a hop of chain {outer_name!r}",
                        tunnel,
                    )

    def rule_port_ref_forms(self) -> None:
        """Both 'comp/port' and 'comp.port' are accepted; say which is used, warn when mixed."""
        slash, dot = self.forms["/"], self.forms["."]
        if slash or dot:
            self.notes.append(
                f"{self.source}: port/antenna references: {slash} written comp/port, {dot} written "
                "comp.port (both accepted; hcdf.xsd documents comp.port, the published examples "
                "write comp/port)"
            )
        if slash and dot:
            minority = "." if dot <= slash else "/"
            self.add(
                "port-ref-form-mixed",
                "warning",
                f"this document writes port references both as comp/port ({slash}) and comp.port "
                f"({dot}); both are accepted, one form is easier to read and grep",
                self.first_of_form[minority],
            )

    # --- rule: schedules -------------------------------------------------------------

    def rule_schedules(self) -> None:
        """Gate durations sum to cycle-time-us (values the XSD rejects are skipped)."""
        for net in self.root.findall("network"):
            for sched in net.findall("schedule"):
                cycle = _uint(sched.get("cycle-time-us"))
                durations = [_uint(g.get("duration-us")) for g in sched.findall("gate")]
                if cycle is None or not durations or any(d is None for d in durations):
                    continue
                total = sum(d for d in durations if d is not None)
                if total != cycle:
                    terms = " + ".join(str(d) for d in durations)
                    self.add(
                        "schedule-cycle-mismatch",
                        "error",
                        f"schedule {sched.get('name')!r} in network {net.get('name')!r}: gate "
                        f"durations sum to {total} us ({terms}) but cycle-time-us is {cycle}",
                        sched,
                    )

    # --- rule: T1 master/slave -------------------------------------------------------

    def rule_t1(self) -> None:
        """One PHY master and one PHY slave per T1 link and per T1 chain segment.

        A link is T1 when its ``wired@standard`` names single-pair Ethernet
        (:data:`T1_STANDARD`); a chain when its ``type`` does. Chain segments are
        hop *i*'s downstream port to hop *i+1*'s upstream port, and a hop's ``via``
        port to its spur's port; segments whose ports are not named are skipped.
        """
        for link in self.links:
            standard = link.wired.get("standard") or ""
            a, b = (link.ports + [None, None])[:2]
            if not standard and a is not None and b is not None:
                standard = _port_standard(a.el) or _port_standard(b.el) or ""
            if not T1_STANDARD.search(standard) or a is None or b is None:
                continue
            self._t1_pair(a, b, standard, link.wired, f"link {link.link.get('name')!r} ({standard})")
        for info in self.chain_info:
            ctype = info.chain.get("type") or ""
            if not T1_STANDARD.search(ctype):
                continue
            for a, b, el, label in info.segments:
                if a is not None and b is not None:
                    self._t1_pair(a, b, ctype, el, f"{label} ({ctype})")

    def _t1_pair(self, a: _Port, b: _Port, standard: str, el: etree._Element, label: str) -> None:
        ra, rb = _phy_role(a.el), _phy_role(b.el)
        ends = f"{a.label} is {ra or 'unset'}, {b.label} is {rb or 'unset'}"
        if ra is None or rb is None:
            required = bool(PHY_ROLE_REQUIRED.match(standard))
            self.add(
                "t1-phy-role-missing",
                "error" if required else "warning",
                f"{label}: a T1 link needs one PHY master and one PHY slave, but {ends}"
                + ("" if required else " (hcdf.xsd requires <phy role> only for 100BASE-T1, 1000BASE-T1 and 802.3dm)"),
                el,
            )
        elif ra == rb and ra in ("master", "slave"):
            self.add(
                "t1-phy-roles",
                "error",
                f"{label}: both ends are PHY {ra} ({ends}); a T1 link needs one master and one slave",
                el,
            )
        elif "auto" in (ra, rb):
            self.add(
                "t1-phy-roles",
                "warning",
                f"{label}: {ends}; 'auto' negotiates at link-up, so one master and one slave "
                "cannot be confirmed (and is not recommended for deterministic systems)",
                el,
            )

    # --- rule: joints ----------------------------------------------------------------

    def rule_joints(self) -> None:
        """Axis/limit requirements per joint type (hcdf.xsd header and joint docs) and limit order."""
        for joint in self.root.findall("joint"):
            jtype = joint.get("type") or ""
            name = joint.get("name")

            def has(item: str, joint: etree._Element = joint) -> bool:
                return joint.get(item[1:]) is not None if item.startswith("@") else joint.find(item) is not None

            def shown(item: str) -> str:
                return f"attribute {item[1:]}" if item.startswith("@") else f"<{item}>"

            for item in _JOINT_REQUIRES.get(jtype, ()):
                if not has(item):
                    self.add(
                        "joint-requires",
                        "error",
                        f"{jtype} joint {name!r} has no {shown(item)}; {jtype} joints require "
                        + " and ".join(shown(i) for i in _JOINT_REQUIRES[jtype]),
                        joint,
                    )
            for item in _JOINT_FORBIDS.get(jtype, ()):
                if has(item):
                    el = joint.find(item)
                    self.add(
                        "joint-forbids",
                        "error",
                        f"{jtype} joint {name!r} has {shown(item)}, which {jtype} joints forbid",
                        el if el is not None else joint,
                    )
            if jtype not in _JOINT_FORBIDS:
                if jtype != "universal" and joint.find("axis2") is not None:
                    self.add(
                        "joint-ignored",
                        "warning",
                        f"{jtype} joint {name!r} has <axis2>, which only universal joints use",
                        joint.find("axis2"),
                    )
                if jtype != "screw" and joint.get("thread_pitch") is not None:
                    self.add(
                        "joint-ignored",
                        "warning",
                        f"{jtype} joint {name!r} has thread_pitch, which only screw joints use",
                        joint,
                    )
            limit = joint.find("limit")
            if limit is not None and jtype != "continuous":
                lower, upper = _float(limit.get("lower"), 0.0), _float(limit.get("upper"), 0.0)
                if lower is not None and upper is not None and upper < lower:
                    self.add(
                        "joint-limit-order",
                        "error",
                        f"joint {name!r}: limit upper {upper:g} is below lower {lower:g}",
                        limit,
                    )

    # --- rules: MACsec ---------------------------------------------------------------

    def rule_key_refs(self) -> None:
        """One key-ref, one (cipher, policy): a key cannot serve two ciphers or two policies.

        A ``<macsec>`` without ``cipher`` uses the schema default, gcm-aes-128.
        """
        uses: dict[str, list[etree._Element]] = defaultdict(list)
        for net in self.root.findall("network"):
            for m in net.findall("link/wired/macsec") + net.findall("chain/macsec"):
                ref = m.get("key-ref")
                if ref:
                    uses[ref].append(m)
        for ref, elements in uses.items():
            first = elements[0]
            first_cipher, first_policy = first.get("cipher", DEFAULT_CIPHER), first.get("policy")
            for m in elements[1:]:
                cipher, policy = m.get("cipher", DEFAULT_CIPHER), m.get("policy")
                diffs = []
                if cipher != first_cipher:
                    diffs.append(f"cipher {cipher} here, {first_cipher} at {at_line(sourceline(first))}")
                if policy != first_policy:
                    diffs.append(f"policy {policy} here, {first_policy} at {at_line(sourceline(first))}")
                if diffs:
                    self.add(
                        "macsec-key-ref-conflict",
                        "error",
                        f"key-ref {ref!r} is used with different settings ({'; '.join(diffs)}); "
                        "one key cannot serve both",
                        m,
                    )

    def rule_macsec_ciphers(self) -> None:
        """Warn when a link's or chain's MACsec cipher is not among the ciphers its ports declare.

        The policy is the link's/chain's own ``<macsec>``, else the network's.
        A port's ciphers are its own ``<macsec><cipher>`` list, else its switch's;
        ports that declare none are not judged. Policy ``disabled`` is skipped.
        """
        # (scope element, its network, label, ports it uses)
        scopes: list[tuple[etree._Element, etree._Element, str, list[_Port]]] = [
            (link.wired, link.network, f"link {link.link.get('name')!r}", [p for p in link.ports if p is not None])
            for link in self.links
        ] + [(info.chain, info.network, f"chain {info.chain.get('name')!r}", info.ports) for info in self.chain_info]
        for at, net, label, ports in scopes:
            # Both read as the planner reads them: one each, or the document is refused.
            own, default = single(at, "macsec", source=self.source), single(net, "macsec", source=self.source)
            policy = own if own is not None else default
            whose = "" if own is not None else f"network {net.get('name')!r} default "
            if policy is None or policy.get("policy") == "disabled":
                continue
            cipher = policy.get("cipher", DEFAULT_CIPHER)
            seen: set[str] = set()
            for port in ports:
                declared = _declared_ciphers(port.el)
                if port.label in seen or not declared or cipher in declared:
                    continue
                seen.add(port.label)
                self.add(
                    "macsec-cipher-unsupported",
                    "warning",
                    f"{label}: {whose}MACsec policy ({policy.get('policy')}) uses {cipher}, but port "
                    f"{port.label} declares only {', '.join(declared)}",
                    policy if not whose else at,
                )

    # --- rule: frames across includes -------------------------------------------------

    def rule_connectivity(self) -> None:
        """Upstream's newer connectivity model (hcdformat 05d27b58, still ``version="1.0"``):
        every participant's ``<endpoint><port-ref|channel-ref component port>`` resolves
        (``unresolved-comp``, ``unresolved-port``, as a 1.0 link port), and every
        ``<participant-ref network participant>``, ``<hop-ref network hop>`` and
        ``<macsec-policy-ref network policy>`` inside a network names one of the document's
        networks and, in it, a participant, hop or MACsec policy (``unresolved-participant``)."""
        kinds = ("link", "bus", "chain", "star", "ring", "mesh", "tree")
        networks = {(n.get("name") or "").strip(): n for n in self.root if isinstance(n.tag, str) and n.tag in kinds}
        names = {
            net: {
                "participant": {(p.get("name") or "").strip() for p in el.findall("participant")},
                "hop": {(h.get("name") or "").strip() for h in el.findall("hop")},
                "policy": {(p.get("name") or "").strip() for p in el.findall("configuration/macsec/policy")},
            }
            for net, el in networks.items()
        }
        for net, el in networks.items():
            where = f"{el.tag} {net!r}"
            for part in el.findall("participant"):
                for ref in part.findall("endpoint/*"):
                    if ref.tag not in ("port-ref", "channel-ref"):
                        continue
                    what = f"{where} participant {part.get('name')!r}"
                    comp = (ref.get("component") or "").strip() or None
                    if self._comp(comp, code="unresolved-comp", what=what, el=ref) is not None and comp:
                        self._port(comp, (ref.get("port") or "").strip() or None, what=what, el=ref)
            for tag, attr in (("participant-ref", "participant"), ("hop-ref", "hop"), ("macsec-policy-ref", "policy")):
                for ref in el.iter(tag):
                    target, name = (ref.get("network") or "").strip(), (ref.get(attr) or "").strip()
                    known = names.get(target, {}).get(attr)
                    if known is None or name not in known:
                        self.add(
                            "unresolved-participant",
                            "error",
                            f"{where}: <{tag} network={target!r} {attr}={name!r}> names no {attr} of "
                            + (f"network {target!r} ({_listing(known)})" if known is not None else "any network here"),
                            ref,
                        )

    def rule_frames(self) -> None:
        """body-frame and world-frame agree across the include chain.

        The same rule as flattening (:mod:`hcdf_trust.include.flatten`): the
        chain's value is the first one declared, root first, then the includes
        depth first in document order; a file that declares another value is an
        error at the ``<include>`` that brings it in; a file that omits one
        inherits it. Includes that could not be read are warnings.
        """
        # One per <include> (a document included twice is walked twice); two on one line stay two.
        edges = list({(e.parent, e.line, e.uri): e for e in self.edges}.values())
        for edge in edges:
            if edge.child is None and edge.refused:
                self.findings.append(
                    Finding(
                        "include-refused",
                        "error",
                        f"include {edge.uri!r} is refused ({edge.skipped})",
                        file=edge.parent,
                        line=edge.line,
                    )
                )
            elif edge.child is None:
                self.findings.append(
                    Finding(
                        "include-unchecked",
                        "warning",
                        f"include {edge.uri!r} was not read ({edge.skipped}); its names and frame "
                        "conventions were not checked",
                        file=edge.parent,
                        line=edge.line,
                    )
                )
        for attr, key in (("body-frame", "body_frame"), ("world-frame", "world_frame")):
            value = self.root.get(attr)
            first = (value.strip(), self.source) if value else None
            for e in edges:
                declared = getattr(e, key)
                if e.child is None or not declared:
                    continue
                declared = declared.strip()
                if first is None:
                    first = (declared, e.child)
                elif declared != first[0]:
                    self.findings.append(
                        Finding(
                            "frame-convention-mismatch",
                            "error",
                            f"included {e.child} declares {attr}={declared}, but {first[1]} declares "
                            f"{attr}={first[0]}; all files in an include chain must agree",
                            file=e.parent,
                            line=e.line,
                        )
                    )
