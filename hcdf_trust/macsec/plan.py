"""Plan: from HCDF MACsec policy to connectivity associations (CAs).

:func:`plan` resolves and verifies the whole include tree first (locked, offline, no cache
writes: a key is never provisioned for a description that fails its pins), then reads the
parsed documents of that :class:`~hcdf_trust.include.resolver.Resolution`; it parses nothing
itself. :func:`plan_resolution` is the pure part.

Rules this module defines (HCDF 1.0 states the intent, not these details):

Effective policy
    A ``<network><macsec>`` sets the network's default for every Ethernet link and chain in
    it. A link's ``<wired><macsec>`` or a chain's ``<macsec>`` overrides it attribute by
    attribute: an attribute the override leaves out keeps the network's value (so an
    override never silently weakens the network's cipher), and only without either falls
    back to the schema default (``gcm-aes-128``, ``psk``, offset 0). ``rekey-interval-sec``
    and ``<key-store>`` exist only network-wide. A link or chain with neither element is
    listed as unprotected. ``policy="disabled"`` is listed and gets no key.

Which elements
    Wired links whose two ports are of type ``ethernet`` (or not found, which is also a
    warning), and every chain. Wireless links, buses and non-Ethernet wired links
    (SIGNAL, POWER, CAN) have no MACsec and are listed as skipped. A ``<mesh
    network-key-ref>`` is its own entry: a 128-bit mesh network key (no MACsec policy).

Connectivity association ids (stable; the key store is indexed by them)
    ``key-ref:<key-ref>``             every link and chain naming that ``key-ref`` (one CAK)
    ``link:<network>/<link>``         a link without ``key-ref``
    ``chain:<network>/<chain>``       a chain without ``key-ref``
    ``mesh-key:<network-key-ref>``    a mesh network key

Include instances
    Names are scoped exactly as :mod:`hcdf_trust.include.flatten` prefixes them: an
    include's ``name`` joined with ``_``, outermost first. Networks, links, chains,
    ``key-ref`` and ``network-key-ref`` written in an included file are always prefixed
    (so an arm included as ``left_arm`` and ``right_arm`` gets two CAKs); a device
    reference is prefixed when the included file (with its own includes) defines that
    comp. Two include instances that end up with the same key-ref (an include without
    ``name``, included twice) are an error: they would share a CAK.

Conflicts and warnings
    One CA has one cipher, policy, key agreement, confidentiality offset, rekey interval
    and key store: members that disagree are an error naming both places. Warnings
    (:class:`~hcdf_trust.errors.Notice`): an endpoint port whose declared MACsec
    capabilities lack the CA's cipher (or declare none); a non-XPN cipher on a port of
    10 Gb/s or more (32-bit packet numbers last minutes there); a confidentiality offset
    no Linux tool can set; a port the description does not define.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple, cast

from lxml import etree

from ..document import Document, only
from ..errors import ErrorGroup, HcdfTrustError, InputError, Notice
from ..units import UnitError, bit_rate
from ..xml import sourceline

if TYPE_CHECKING:
    from ..include.resolver import TreeOptions

# The include prefix separator, as hcdf_trust.include.flatten.SEPARATOR (a test checks they agree);
# not imported from there, so that planning does not load the flattener.
SEPARATOR = "_"
POLICIES = ("must-secure", "should-secure", "integrity-only", "disabled")
CIPHERS = ("gcm-aes-128", "gcm-aes-256", "gcm-aes-xpn-128", "gcm-aes-xpn-256")
KEY_AGREEMENTS = ("psk", "eap-tls")
OFFSETS = (0, 30, 50)
KEY_STORE_TYPES = ("secure-element", "hsm", "tpm", "file", "runtime")
MESH_KEY_BYTES = 16
MAX_INSTANCES = 10_000
# IEEE 802.1AE: 32-bit packet numbers; minimum frames of 64 B + 20 B preamble/IFG + 32 B SecTAG/ICV.
PN_SPACE = 2**32 - 1
MIN_FRAME_BITS = 116 * 8
PN_WARN_MBPS = 10_000


# The public API (docs/api.md); everything else here is internal.
__all__ = ["Association", "Plan", "plan"]


class MacsecPlanError(InputError):
    """The description's MACsec policy is malformed or contradicts itself."""

    code = "macsec-plan"


def cak_length(cipher: str) -> int:
    """CAK length in bytes for a cipher suite: 16 for the 128-bit suites, 32 for the 256-bit ones."""
    return 32 if cipher.endswith("256") else 16


def is_xpn(cipher: str) -> bool:
    return "-xpn-" in cipher


def pn_lifetime_seconds(mbps: float) -> float:
    """How long a 32-bit packet number lasts at ``mbps`` with minimum-size MACsec frames."""
    return PN_SPACE * MIN_FRAME_BITS / (mbps * 1e6)


@dataclass(frozen=True)
class Policy:
    policy: str
    cipher: str
    key_agreement: str
    confidentiality_offset: int
    rekey_interval_sec: int | None
    key_store_type: str | None
    key_store_ref: str | None

    def conflicts(self, other: Policy) -> list[tuple[str, str, str]]:
        out = []
        for name in self.__dataclass_fields__:
            a, b = getattr(self, name), getattr(other, name)
            if a != b:
                out.append((name.replace("_", "-"), str(a), str(b)))
        return out


@dataclass(slots=True)
class Member:
    device: str
    ports: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return {"device": self.device, "ports": self.ports}


@dataclass(slots=True)
class Element:
    """One link, chain or mesh that belongs to an association."""

    kind: str  # link | chain | mesh
    network: str  # scoped
    name: str  # scoped
    file: str
    line: int | None
    scope: str  # include instance ("" for the root document)

    @property
    def label(self) -> str:
        """``kind:network/name``; ``kind:network`` for a whole network (the new model's link, bus, mesh)."""
        return f"{self.kind}:{self.network}/{self.name}" if self.name else f"{self.kind}:{self.network}"

    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "network": self.network,
            "name": self.name,
            "file": self.file,
            "line": self.line,
            "scope": self.scope,
        }


@dataclass(slots=True)
class Association:
    """A connectivity association: one CAK (or one mesh network key) and who holds it.

    ``id`` is stable (``key-ref:R``, ``link:NET/LINK``, ``leg:NET/LEG``…, docs/macsec.md);
    ``members`` maps each device to its ports; ``policy`` holds the cipher and enforcement.

    Example:
        >>> from hcdf_trust.macsec.plan import plan
        >>> ca = plan("examples/robot/robot.hcdf").associations["key-ref:head-link"]
        >>> ca.kind, sorted(ca.members), ca.policy.cipher, ca.key_bytes
        ('macsec', ['compute', 'head_camera'], 'gcm-aes-128', 16)
    """

    id: str
    kind: str  # macsec | mesh-key
    key_ref: str | None  # scoped
    policy: Policy | None  # None for a mesh key
    elements: list[Element] = field(default_factory=list)
    members: dict[str, Member] = field(default_factory=dict)
    port_speeds_mbps: dict[str, float] = field(default_factory=dict)  # "device/port" -> Mb/s
    ifaces: dict[str, str] = field(default_factory=dict)  # "device/port" -> OS interface (``iface``, else port)
    warned: set[str] = field(default_factory=set, repr=False)  # warnings already given (one per port)

    @property
    def keyed(self) -> bool:
        return self.policy is None or self.policy.policy != "disabled"

    @property
    def shared(self) -> bool:
        """The same CAK is used on more than one link or chain."""
        return len(self.elements) > 1

    @property
    def file(self) -> str:
        return self.elements[0].file

    @property
    def line(self) -> int | None:
        return self.elements[0].line

    @property
    def key_bytes(self) -> int:
        return MESH_KEY_BYTES if self.policy is None else cak_length(self.policy.cipher)

    @property
    def max_speed_mbps(self) -> float | None:
        return max(self.port_speeds_mbps.values(), default=None)

    def add_member(self, device: str, port: str | None) -> None:
        member = self.members.get(device)
        if member is None:
            member = self.members[device] = Member(device)
        if port and port not in member.ports:
            member.ports.append(port)

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "id": self.id,
            "kind": self.kind,
            "key_ref": self.key_ref,
            "keyed": self.keyed,
            "key_bytes": self.key_bytes if self.keyed else 0,
            "shared": self.shared,
            "elements": [e.to_dict() for e in self.elements],
            "members": [m.to_dict() for m in self.members.values()],
            "max_speed_mbps": self.max_speed_mbps,
        }
        if self.policy is not None:
            p = self.policy
            out.update(
                policy=p.policy,
                cipher=p.cipher,
                key_agreement=p.key_agreement,
                confidentiality_offset=p.confidentiality_offset,
                rekey_interval_sec=p.rekey_interval_sec,
                key_store={"type": p.key_store_type, "ref": p.key_store_ref},
            )
        return out


@dataclass
class Plan:
    """What ``macsec plan`` shows: the connectivity associations a description's MACsec policy
    asks for (``associations``, by id), the networks left unprotected or skipped, warnings,
    and the verified tree it was planned from (``resolution``).

    Example:
        >>> from hcdf_trust.macsec.plan import plan
        >>> p = plan("examples/robot/robot.hcdf")
        >>> p.robot, sorted(p.associations)
        ('scout2', ['key-ref:arm-links', 'key-ref:head-link'])
        >>> [ca.id for ca in p.for_device("head_camera")]
        ['key-ref:head-link']
    """

    document: str
    robot: str = ""  # the root document's <hcdf name>: the identity a key store is bound to
    associations: dict[str, Association] = field(default_factory=dict)
    unprotected: list[Element] = field(default_factory=list)
    skipped: list[tuple[Element, str]] = field(default_factory=list)
    warnings: list[Notice] = field(default_factory=list)
    resolution: Any = None  # the verified tree it was planned from (its inputs are never an output)

    def keyed(self) -> list[Association]:
        return [ca for ca in self.associations.values() if ca.keyed]

    def for_device(self, device: str) -> list[Association]:
        """The keyed associations ``device`` is a member of (least privilege for exports)."""
        return [ca for ca in self.keyed() if device in ca.members]

    def to_dict(self) -> dict[str, Any]:
        return {
            "document": self.document,
            "robot": self.robot,
            "associations": [ca.to_dict() for ca in self.associations.values()],
            "unprotected": [e.to_dict() for e in self.unprotected],
            "skipped": [dict(e.to_dict(), reason=r) for e, r in self.skipped],
            "warnings": [w.to_dict() for w in self.warnings],
        }


def plan(doc_path: str | Path, *, device: str | None = None, tree: TreeOptions | None = None) -> Plan:
    """Resolve and verify ``doc_path`` (locked; offline unless ``tree`` says otherwise, where
    ``tree`` holds resolve's --base, --mirror, --root, --cache-dir, --lock), then plan its associations.

    Example:
        >>> from hcdf_trust.macsec.plan import plan
        >>> [(ca.id, ca.policy.cipher) for ca in plan("examples/robot/robot.hcdf").keyed()]
        [('key-ref:head-link', 'gcm-aes-128'), ('key-ref:arm-links', 'gcm-aes-256')]

    With ``device``, only the networks that can hold that device's associations are planned
    (see :func:`plan_resolution`); when the device is in none of them, the whole description
    is planned, so the caller's "no such device" message lists every device.

    Raises:
        ErrorGroup / HcdfTrustError: the tree fails to resolve or verify (a missing or
            drifted lock included), or its MACsec policy is malformed or contradictory.
    """
    from ..include.resolver import TreeOptions, resolve

    res = resolve(doc_path, (tree or TreeOptions()).resolve_options(locked=True))
    if res.errors:
        raise ErrorGroup(list(res.errors))
    result = plan_resolution(res.documents, res.includes, res.root_location.url, device=device)
    if device is not None and not result.for_device(device):
        result = plan_resolution(res.documents, res.includes, res.root_location.url)
    result.warnings[:0] = res.warnings  # already Notice objects
    result.resolution = res
    return result


# --- the pure part -----------------------------------------------------------------------


@dataclass(frozen=True)
class _Instance:
    url: str
    names: tuple[str, ...]  # include names from the root down to this instance ("" = no prefix)
    chain: tuple[str, ...]  # document urls from the root down to this instance
    sites: tuple[int, ...] = ()  # which <include> of its parent each level is: tells unnamed copies apart

    @functools.cached_property
    def scope(self) -> str:
        """The include names joined (flatten's prefix), "" for the root document."""
        return SEPARATOR.join(n for n in self.names if n)

    @functools.cached_property
    def identity(self) -> str:
        """Tells two include instances apart, even two copies of one file included without a name."""
        return repr((self.chain, self.sites))


def _written_forms(device: str, names: tuple[str, ...]) -> set[str]:
    """How a reference to scoped comp ``device`` can be written in an instance with include
    ``names``: the name with any of those prefixes (outermost first) taken off its front."""
    forms = {device}
    for name in names:
        if name:
            head = name + SEPARATOR
            forms |= {f[len(head) :] for f in forms if f.startswith(head)}
    return forms


def _may_share_ids(network: str, names: set[str]) -> bool:
    """Whether a link or chain of ``network`` can have the id (``kind:NETWORK/NAME``) of one in ``names``."""
    return any(network == n or network.startswith(n + "/") or n.startswith(network + "/") for n in names)


def _network_of(el: etree._Element, root: etree._Element) -> etree._Element:
    """The ``<network>`` (a child of ``root``) that holds ``el``."""
    while (parent := el.getparent()) is not None and parent is not root:
        el = parent
    return el


@dataclass(frozen=True)
class _Queries:
    naming: etree.XPath  # networks whose text, or an attribute outside their links, contains $w
    refs: etree.XPath  # the key-ref and network-key-ref values a network writes (relative to it)
    all_refs: tuple[etree.XPath, ...]  # the same for every network of a document (from its root)


@functools.cache
def _compile(plain: bool) -> _Queries:
    """The queries with plain name tests, or with ``local-name()`` tests (any namespace)."""
    net, link, wired, macsec, chain, mesh = (
        t if plain else f"*[local-name()='{t}']" for t in ("network", "link", "wired", "macsec", "chain", "mesh")
    )
    not_link = "*[not(self::link)]" if plain else "*[local-name()!='link']"
    refs = (f"{link}/{wired}/{macsec}/@key-ref", f"{chain}/{macsec}/@key-ref", f"{mesh}/@network-key-ref")
    return _Queries(
        # ``X/descendant-or-self::*/@*`` is ``X//@*`` (only elements have attributes), without the text nodes
        naming=etree.XPath(f"{net}[contains(., $w) or {not_link}/descendant-or-self::*/@*[contains(., $w)]]"),
        refs=etree.XPath(" | ".join(refs)),
        all_refs=tuple(etree.XPath(f"{net}/{r}") for r in refs),  # three queries: a union sorts 5,000 nodes
    )


_ASCII_COMPATIBLE = frozenset(("UTF-8", "ASCII", "US-ASCII"))


def _queries(doc: Document) -> _Queries:
    """Plain name tests (several times faster in libxml2) when no element of ``doc`` can be in
    a namespace: its bytes read as ASCII and declare none (no ``xmlns``, no ``xml:``; most
    documents hold "xml" only in ``<?xml``). Otherwise ``local-name()`` tests, since the
    planner takes its elements in any namespace."""
    data = doc.data
    if data.find(b"xml", 6) == -1 and data.startswith(b"<?xml") and b"\x00" not in data:
        return _compile(True)
    ascii_like = (doc.tree.docinfo.encoding or "").upper() in _ASCII_COMPATIBLE and b"\x00" not in data
    return _compile(ascii_like and b"xmlns" not in data and b"xml:" not in data)


def _children(el: etree._Element, tag: str) -> list[etree._Element]:
    """Child elements named ``tag`` in any namespace or none (matched by lxml, in C)."""
    return list(el.iterchildren("{*}" + tag))


# Upstream's top-level network elements since 2026 (read by hcdf_trust.macsec.connectivity).
NETWORK_KINDS = ("link", "bus", "chain", "star", "ring", "mesh", "tree")
_NEW_NETWORK_TAGS = tuple("{*}" + k for k in NETWORK_KINDS)
# Every <macsec> outside a 1.0 <network> that is not a capability declaration (see _Planner._unread_macsec),
# with plain name tests (3x faster in libxml2) for a document that can hold no namespace, else local-name() tests.
_POLICY_MACSEC = {
    True: etree.XPath(
        "*[not(self::network)]/descendant-or-self::macsec[not(ancestor::capabilities)]"
        "[@* or not(*) or *[not(self::cipher)]]"
    ),
    False: etree.XPath(
        "*[local-name()!='network']/descendant-or-self::*[local-name()='macsec']"
        "[not(ancestor::*[local-name()='capabilities'])][@* or not(*) or *[local-name()!='cipher']]"
    ),
}


def _by_tag(el: etree._Element) -> dict[str, list[etree._Element]]:
    """Child elements grouped by local name, in one pass."""
    out: dict[str, list[etree._Element]] = {}
    for child in el:
        tag = child.tag
        if isinstance(tag, str):
            out.setdefault(tag[tag.rfind("}") + 1 :], []).append(child)
    return out


def plan_resolution(
    documents: dict[str, Document],
    includes: dict[str, list[tuple[Any, str]]],
    root_url: str,
    *,
    device: str | None = None,
) -> Plan:
    """Plan the associations of a resolved tree (``Resolution.documents`` / ``.includes``).

    ``device`` (a scoped comp name) plans only the networks a reference to that device can
    be written in, plus every network that writes one of their key-refs or network-key-refs
    or has their name (so a CA's consistency checks see all its members): the device's
    associations come out exactly as in the whole plan, other networks are not checked.

    Raises:
        ErrorGroup: malformed MACsec attributes or contradictory associations.
    """
    return _Planner(documents, includes, root_url, device=device).run()


class _Planner:
    def __init__(
        self,
        documents: dict[str, Document],
        includes: dict[str, list[tuple[Any, str]]],
        root: str,
        *,
        device: str | None = None,
    ) -> None:
        self.docs = documents
        self.device = device
        self.includes = includes
        self.root = root
        self.errors: list[HcdfTrustError] = []
        self.plan = Plan(document=documents[root].source, robot=(documents[root].root.get("name") or "").strip())
        self._defined: dict[str, frozenset[str]] = {}
        self._comps: dict[str, dict[str, etree._Element]] = {}
        self._query_set: dict[str, _Queries] = {}
        # scoped key-ref -> (instance identity, file, element) where it was first written
        self._key_scope: dict[str, tuple[str, str, etree._Element]] = {}
        self._ports: dict[etree._Element, dict[str, _PortInfo]] = {}
        self._override_cache: dict[tuple[tuple[Any, ...], ...], Policy] = {}  # this network's overrides
        self._consumed: set[etree._Element] = set()  # <macsec> elements outside <network> a reader understood

    def run(self) -> Plan:
        instances = self._instances()
        networks = [_children(self.docs[inst.url].root, "network") for inst in instances]
        if self.device is not None:
            networks = self._restrict(instances, networks, self.device)
        for inst, nets in zip(instances, networks, strict=True):
            doc = self.docs[inst.url]
            for net in nets:
                self._network(inst, doc, net)
        self._connectivity(instances)
        self._unread_macsec(instances)
        if self.errors:
            raise ErrorGroup(self.errors)
        for ca in self.plan.keyed():
            self._pn_warning(ca)
        return self.plan

    def _connectivity(self, instances: list[_Instance]) -> None:
        """The top-level networks of upstream's newer connectivity model, in every instance
        that has one (:mod:`hcdf_trust.macsec.connectivity`, imported only then)."""
        for inst in instances:
            doc = self.docs[inst.url]
            if next(doc.root.iterchildren(*_NEW_NETWORK_TAGS), None) is not None:
                from .connectivity import plan_networks

                plan_networks(self, inst, doc)

    def _unread_macsec(self, instances: list[_Instance]) -> None:
        """Fail closed: every ``<macsec>`` outside a 1.0 ``<network>`` (whose rules are
        :meth:`_network`'s) that is not a capability declaration must have been read by a
        reader; one that was not is an error naming it, so a description whose MACsec policy
        this code does not understand is never "0 associations to key". A capability
        declaration is a ``<macsec>`` inside a port's ``<capabilities>``, or 1.0's switch-level
        form: no attributes, only ``<cipher>`` children. (One XPath per document, in libxml2.)"""
        for url in dict.fromkeys(inst.url for inst in instances):
            doc = self.docs[url]
            query = _POLICY_MACSEC[self._queries(url) is _compile(True)]
            for el in cast("list[etree._Element]", query(doc.root)):
                if el in self._consumed:
                    continue
                parent = el.getparent()
                top = el
                while top.getparent() is not None and top.getparent() is not doc.root:
                    top = top.getparent()  # type: ignore[assignment]
                where = etree.QName(parent).localname if parent is not None else "?"
                self.errors.append(
                    MacsecPlanError(
                        f"<macsec> in <{where}> (under <{etree.QName(top).localname} name={top.get('name', '')!r}>) "
                        f"is not read by this planner: refusing to plan a description whose MACsec policy would "
                        f"be ignored",
                        file=doc.source,
                        line=sourceline(el),
                    )
                )

    def _pn_warning(self, ca: Association) -> None:
        speeds = ca.port_speeds_mbps
        if not speeds or max(speeds.values()) < PN_WARN_MBPS or ca.policy is None or is_xpn(ca.policy.cipher):
            return
        fast = sorted(p for p, mbps in ca.port_speeds_mbps.items() if mbps >= PN_WARN_MBPS)
        if not fast:
            return
        speed = max(ca.port_speeds_mbps[p] for p in fast)
        self.plan.warnings.append(
            Notice(
                "macsec-pn-exhaustion",
                f"{ca.id}: {', '.join(fast)} run at up to {speed:g} Mb/s, where a 32-bit packet number lasts "
                f"{pn_lifetime_seconds(speed):.0f} s with minimum-size frames; {ca.policy.cipher} needs MKA "
                f"rekeying on packet number (static keys are refused at export); prefer an XPN cipher",
                file=ca.file,
                line=ca.line,
            )
        )

    # -- restriction to one device ----------------------------------------------------------

    def _restrict(
        self, instances: list[_Instance], networks: list[list[etree._Element]], device: str
    ) -> list[list[etree._Element]]:
        """The networks (per instance, in document order) that can hold ``device``'s associations.

        A device becomes a member only through the text of a link's ``<port>`` and the
        attributes of a chain's or mesh's elements, written in the form the instance's file
        uses (:meth:`_device` prefixes it level by level): a network none of whose text holds
        any written form of the name, nor any attribute outside its links, cannot name it.
        Matching is by substring (``contains``, evaluated by libxml2): it may keep a network
        that does not name the device, never the reverse. Then every network that writes one
        of the kept networks' scoped key-refs or network-key-refs, or whose scoped name could
        give one of their link or chain ids, is kept too.
        """
        keep: list[set[etree._Element]] = []
        refs: set[str] = set()
        names: set[str] = set()
        naming: dict[tuple[str, str], list[etree._Element]] = {}  # a file included many times is searched once
        for inst in instances:
            doc = self.docs[inst.url]
            query = self._queries(inst.url)
            hits: set[etree._Element] = set()
            for written in _written_forms(device, inst.names):
                if (inst.url, written) not in naming:
                    naming[inst.url, written] = cast("list[etree._Element]", query.naming(doc.root, w=written))
                hits.update(naming[inst.url, written])
            keep.append(hits)
            for net in hits:
                names.add(self._scoped(inst, net.get("name", "").strip()))
                for ref in cast("list[str]", query.refs(net)):
                    if ref.strip():
                        refs.add(self._scoped(inst, ref.strip()))
        written_refs: dict[str, list[Any]] = {}
        for k, inst in enumerate(instances):
            doc = self.docs[inst.url]
            if refs:
                if inst.url not in written_refs:
                    written_refs[inst.url] = [
                        a for q in self._queries(inst.url).all_refs for a in cast("list[Any]", q(doc.root))
                    ]
                for attr in written_refs[inst.url]:
                    if attr.strip() and self._scoped(inst, attr.strip()) in refs:
                        keep[k].add(_network_of(attr.getparent(), doc.root))
            for net in networks[k]:
                if net not in keep[k] and _may_share_ids(self._scoped(inst, net.get("name", "").strip()), names):
                    keep[k].add(net)
        return [[net for net in nets if net in kept] for nets, kept in zip(networks, keep, strict=True)]

    # -- include instances and name scoping ---------------------------------------------

    def _instances(self) -> list[_Instance]:
        out: list[_Instance] = []
        stack = [_Instance(self.root, (), (self.root,))]
        while stack:
            inst = stack.pop()
            out.append(inst)
            if len(out) > MAX_INSTANCES:
                raise MacsecPlanError(
                    f"the include tree expands to more than {MAX_INSTANCES} instances",
                    file=self.docs[self.root].source,
                )
            for index, (ref, child) in reversed(list(enumerate(self.includes.get(inst.url, [])))):
                if child in self.docs and child not in inst.chain:
                    stack.append(
                        _Instance(
                            child,
                            (*inst.names, (ref.name or "").strip()),
                            (*inst.chain, child),
                            (*inst.sites, index),
                        )
                    )
        return out

    def _defined_comps(self, url: str, seen: tuple[str, ...] = ()) -> frozenset[str]:
        """Comp names the expansion of ``url`` defines, as they stand at that level (flatten's rule)."""
        if url in self._defined:
            return self._defined[url]
        names = set(self._own_comps(url))
        for ref, child in self.includes.get(url, []):
            if child in self.docs and child not in seen:
                prefix = (ref.name or "").strip()
                inner = self._defined_comps(child, (*seen, url))
                names.update(f"{prefix}{SEPARATOR}{n}" if prefix else n for n in inner)
        self._defined[url] = frozenset(names)
        return self._defined[url]

    def _queries(self, url: str) -> _Queries:
        if url not in self._query_set:
            self._query_set[url] = _queries(self.docs[url])
        return self._query_set[url]

    def _own_comps(self, url: str) -> dict[str, etree._Element]:
        if url not in self._comps:
            root = self.docs[url].root
            self._comps[url] = {name: c for c in root.iterchildren("{*}comp") if (name := c.get("name"))}
        return self._comps[url]

    @staticmethod
    def _scoped(inst: _Instance, name: str) -> str:
        """A name the instance's own file defines: every include name, outermost first."""
        scope = inst.scope
        return f"{scope}{SEPARATOR}{name}" if scope else name

    def _device(self, inst: _Instance, name: str) -> str:
        """A comp reference written in the instance's file, renamed level by level as flatten does."""
        value = name.strip()
        for level in range(len(inst.chain) - 1, 0, -1):
            prefix = inst.names[level - 1]
            if prefix and value in self._defined_comps(inst.chain[level]):
                value = f"{prefix}{SEPARATOR}{value}"
        return value

    def _find_comp(self, inst: _Instance, written: str) -> tuple[etree._Element, str] | None:
        """The comp element a device reference names, searched from the instance outwards."""
        value = written.strip()
        own = self._own_comps(inst.url).get(value)
        if own is not None:  # the first place the loop below looks
            return own, self.docs[inst.url].source
        for level in range(len(inst.chain) - 1, -1, -1):
            url = inst.chain[level]
            comp = self._own_comps(url).get(value)
            if comp is not None:
                return comp, self.docs[url].source
            for ref, child in self.includes.get(url, []):
                prefix = (ref.name or "").strip()
                if prefix and value.startswith(prefix + SEPARATOR) and child in self.docs:
                    found = self._find_in(child, value[len(prefix) + 1 :], depth=0)
                    if found is not None:
                        return found
            if level:
                prefix = inst.names[level - 1]
                if prefix and value in self._defined_comps(url):
                    value = f"{prefix}{SEPARATOR}{value}"
        return None

    def _find_in(self, url: str, name: str, *, depth: int) -> tuple[etree._Element, str] | None:
        comp = self._own_comps(url).get(name)
        if comp is not None:
            return comp, self.docs[url].source
        if depth > 64:
            return None
        for ref, child in self.includes.get(url, []):
            prefix = (ref.name or "").strip()
            if child not in self.docs:
                continue
            if not prefix:
                found = self._find_in(child, name, depth=depth + 1)
            elif name.startswith(prefix + SEPARATOR):
                found = self._find_in(child, name[len(prefix) + 1 :], depth=depth + 1)
            else:
                continue
            if found is not None:
                return found
        return None

    def _port(self, comp: tuple[etree._Element, str] | None, name: str) -> _PortRef:
        if comp is None:
            return None
        ports = self._ports.get(comp[0])
        if ports is None:
            ports = self._ports[comp[0]] = _read_ports(*comp)
        return ports.get(name)

    # -- networks ------------------------------------------------------------------------

    def _network(self, inst: _Instance, doc: Document, net: etree._Element) -> None:
        net_name = self._scoped(inst, net.get("name", "").strip())
        default = None
        self._override_cache = {}
        parts = _by_tag(net)
        cfg = self._once(doc, parts.get("macsec", []))
        if cfg is not None:
            default = self._policy(doc, cfg, None, network_level=True)
        for link in parts.get("link", ()):
            self._link(inst, doc, net_name, link, default)
        for chain in parts.get("chain", ()):
            self._chain(inst, doc, net_name, chain, default)
        for mesh in parts.get("mesh", ()):
            self._mesh(inst, doc, net_name, mesh)
        for bus in parts.get("bus", ()):
            el = self._element(inst, doc, "bus", net_name, bus)
            self.plan.skipped.append((el, "a bus has no MACsec"))

    def _once(self, doc: Document, found: list[etree._Element]) -> etree._Element | None:
        """:func:`hcdf_trust.document.only` (the one reading of an element the schema allows
        once); a second one is recorded as an error naming both lines, and planning goes on
        with the first so that every other error is reported too."""
        try:
            return only(found, source=doc.source)
        except HcdfTrustError as exc:
            self.errors.append(exc)
            return found[0]

    def _element(self, inst: _Instance, doc: Document, kind: str, net: str, el: etree._Element) -> Element:
        name = self._scoped(inst, el.get("name", "").strip())
        return Element(kind, net, name, doc.source, sourceline(el), inst.scope)

    def _policy(self, doc: Document, el: etree._Element, base: Policy | None, *, network_level: bool) -> Policy | None:
        line = sourceline(el)

        def pick(attr: str, allowed: tuple[str, ...], inherited: str | None, default: str) -> str:
            value = el.get(attr)
            if value is None:
                return inherited if inherited is not None else default
            value = value.strip()
            if value not in allowed:
                self.errors.append(
                    MacsecPlanError(
                        f"<macsec {attr}> is not one of {', '.join(allowed)}",
                        file=doc.source,
                        line=line,
                        expected=" | ".join(allowed),
                        actual=value,
                    )
                )
            return value

        if el.get("policy") is None:
            self.errors.append(
                MacsecPlanError(
                    "<macsec> has no policy attribute (it is required)",
                    file=doc.source,
                    line=line,
                    expected=" | ".join(POLICIES),
                    actual="(missing)",
                )
            )
            return None
        policy = pick("policy", POLICIES, None, "")
        cipher = pick("cipher", CIPHERS, base.cipher if base else None, "gcm-aes-128")
        agreement = pick("key-agreement", KEY_AGREEMENTS, base.key_agreement if base else None, "psk")
        offset_text = pick("confidentiality-offset", tuple(str(o) for o in OFFSETS), None, "0")
        offset = int(offset_text) if offset_text.isdigit() else 0
        rekey = base.rekey_interval_sec if base else None
        store_type = base.key_store_type if base else None
        store_ref = base.key_store_ref if base else None
        if network_level:
            text = el.get("rekey-interval-sec")
            if text is not None:
                if not text.strip().isdigit() or int(text) > 2**32 - 1:
                    self.errors.append(
                        MacsecPlanError(
                            "<macsec rekey-interval-sec> is not an unsigned 32-bit integer",
                            file=doc.source,
                            line=line,
                            expected="0..4294967295",
                            actual=text,
                        )
                    )
                else:
                    rekey = int(text)
            store = self._once(doc, _children(el, "key-store"))
            if store is not None:
                store_type = store.get("type", "").strip()
                store_ref = (store.get("ref") or "").strip() or None
                if store_type not in KEY_STORE_TYPES:
                    self.errors.append(
                        MacsecPlanError(
                            "<key-store type> is not a known key store",
                            file=doc.source,
                            line=sourceline(store),
                            expected=" | ".join(KEY_STORE_TYPES),
                            actual=store_type or "(missing)",
                        )
                    )
        return Policy(policy, cipher, agreement, offset, rekey, store_type, store_ref)

    def _override(
        self, doc: Document, el: etree._Element | None, default: Policy | None
    ) -> tuple[Policy | None, str | None]:
        if el is None:
            return default, None
        # Overrides repeat (every link of a network written alike): parse each distinct one once.
        # The cache holds one network's overrides (:meth:`_network` empties it), so ``default`` is fixed.
        attrs = tuple(kv for kv in el.items() if kv[0] != "key-ref")
        policy = self._override_cache.get(attrs)
        if policy is None:
            errors = len(self.errors)
            policy = self._policy(doc, el, default, network_level=False)
            if policy is not None and len(self.errors) == errors:
                self._override_cache[attrs] = policy
        ref = el.get("key-ref")
        return policy, (ref.strip() or None) if ref is not None else None

    def _link(self, inst: _Instance, doc: Document, net: str, link: etree._Element, default: Policy | None) -> None:
        element = self._element(inst, doc, "link", net, link)
        # The one <wired>, its <port>s and its one <macsec> (in any namespace), read in plain
        # loops with tag tests: cheaper in lxml than three filtered iterators, for 10,000 links.
        wired = self._once(
            doc, [c for c in link if c.tag == "wired" or (type(c.tag) is str and c.tag.endswith("}wired"))]
        )
        if wired is None:
            self.plan.skipped.append((element, "a wireless link has no MACsec"))
            return
        endpoints: list[tuple[str, str, _PortRef]] = []
        override = None
        for el in wired:
            tag = el.tag
            if type(tag) is not str:
                continue
            local = tag[tag.rfind("}") + 1 :]
            if local == "port":
                device, _, port = (el.text or "").strip().partition("/")
                endpoints.append((self._device(inst, device), port, self._port(self._find_comp(inst, device), port)))
            elif local == "macsec":
                override = el if override is None else self._once(doc, [override, el])
        types = {p.type for *_, p in endpoints if p is not None}
        if types and types != {"ethernet"}:
            self.plan.skipped.append((element, f"not an Ethernet link (port type {', '.join(sorted(types))})"))
            return
        policy, key_ref = self._override(doc, override, default)
        if policy is None:
            self.plan.unprotected.append(element)
            return
        ca = self._association(inst, doc, element, policy, key_ref, link if override is None else override)
        if ca is None:
            return
        for device, port, port_ref in endpoints:
            self._endpoint(ca, element, device, port, port_ref)

    def _chain(self, inst: _Instance, doc: Document, net: str, chain: etree._Element, default: Policy | None) -> None:
        element = self._element(inst, doc, "chain", net, chain)
        override = self._once(doc, _children(chain, "macsec"))
        policy, key_ref = self._override(doc, override, default)
        if policy is None:
            self.plan.unprotected.append(element)
            return
        ca = self._association(inst, doc, element, policy, key_ref, override if override is not None else chain)
        if ca is None:
            return
        for hop in _children(chain, "hop"):
            device = hop.get("device", "").strip()
            comp = self._find_comp(inst, device)
            scoped = self._device(inst, device)
            hop_ports = [hop.get(a, "").strip() for a in ("port", "port-secondary", "ingress", "egress")]
            for spur in _children(hop, "spur"):
                via = spur.get("via", "").strip()
                hop_ports.append(via)
                spur_device = spur.get("device", "").strip()
                spur_port = spur.get("port", "").strip()
                self._endpoint(
                    ca,
                    element,
                    self._device(inst, spur_device),
                    spur_port,
                    self._port(self._find_comp(inst, spur_device), spur_port),
                )
            if not any(hop_ports):
                ca.add_member(scoped, None)
            for port in hop_ports:
                if port:
                    self._endpoint(ca, element, scoped, port, self._port(comp, port))

    def _mesh(self, inst: _Instance, doc: Document, net: str, mesh: etree._Element) -> None:
        element = self._element(inst, doc, "mesh", net, mesh)
        ref = (mesh.get("network-key-ref") or "").strip()
        if not ref:
            self.plan.unprotected.append(element)
            return
        scoped = self._scoped(inst, ref)
        ca_id = f"mesh-key:{scoped}"
        ca = self.plan.associations.get(ca_id)
        if ca is None:
            ca = self.plan.associations[ca_id] = Association(ca_id, "mesh-key", scoped, None)
        ca.elements.append(element)
        for node in _children(mesh, "node"):
            ca.add_member(self._device(inst, node.get("device", "")), node.get("antenna", "").strip() or None)

    def _association(
        self,
        inst: _Instance,
        doc: Document,
        element: Element,
        policy: Policy,
        key_ref: str | None,
        where: etree._Element,
    ) -> Association | None:
        if key_ref is None:
            ca_id = element.label
            if ca_id in self.plan.associations:
                self.errors.append(
                    MacsecPlanError(
                        f"two {element.kind}s are named {element.network}/{element.name}",
                        file=doc.source,
                        line=element.line,
                    )
                )
                return None
            ca = self.plan.associations[ca_id] = Association(ca_id, "macsec", None, policy)
            ca.elements.append(element)
            return ca
        scoped = self._scoped(inst, key_ref)
        first = self._key_scope.setdefault(scoped, (inst.identity, doc.source, where))
        if first[0] != inst.identity:
            here = f"{doc.source}:{sourceline(where)}"
            self.errors.append(
                MacsecPlanError(
                    f"key-ref {scoped!r} is written by two include instances ({first[1]}:{sourceline(first[2])} "
                    f"and {here}): they would share a CAK; give each <include> a name",
                    file=doc.source,
                    line=sourceline(where),
                )
            )
            return None
        ca_id = f"key-ref:{scoped}"
        existing = self.plan.associations.get(ca_id)
        if existing is None:
            ca = self.plan.associations[ca_id] = Association(ca_id, "macsec", scoped, policy)
        else:
            ca = existing
            assert ca.policy is not None
            for attr, want, got in ca.policy.conflicts(policy):
                self.errors.append(
                    MacsecPlanError(
                        f"key-ref {scoped!r} is used with two different {attr} values "
                        f"({ca.elements[0].label} at {ca.file}:{ca.line} and {element.label}): one CAK, one {attr}",
                        file=doc.source,
                        line=sourceline(where),
                        expected=want,
                        actual=got,
                    )
                )
        ca.elements.append(element)
        return ca

    def _endpoint(
        self,
        ca: Association,
        element: Element,
        device: str,
        port: str,
        port_ref: _PortRef,
        *,
        capabilities: bool = True,
    ) -> None:
        """Add a member port to ``ca`` and give the port's warnings and speed errors; without
        ``capabilities`` (the new connectivity model, whose ports declare no ciphers) the
        port's MACsec capability is not compared with the cipher."""
        ca.add_member(device, port or None)
        if not port:
            return
        label = f"{device}/{port}"
        if port_ref is None:
            self.plan.warnings.append(
                Notice(
                    "macsec-port",
                    f"{element.label}: port {label} is not defined in the description; "
                    f"its MACsec capabilities cannot be checked",
                    file=element.file,
                    line=element.line,
                )
            )
            return
        ca.ifaces[label] = port_ref.iface
        speed = port_ref.speed_mbps
        if speed is not None:
            ca.port_speeds_mbps[label] = speed
        policy = ca.policy
        if policy is None or policy.policy == "disabled":
            return
        if port_ref.bad_speed is not None:
            # The packet-number rules need the speed: one we cannot read is never "unknown, no check".
            self.errors.append(
                MacsecPlanError(
                    f"{ca.id}: the speed of port {label} cannot be read ({port_ref.bad_speed[1]}); "
                    'write it as e.g. <speed unit="Gb/s">10</speed> or <rate nominal="10000000000" unit="bit/s"/>',
                    file=port_ref.file,
                    line=port_ref.bad_speed[0],
                )
            )
        ciphers = port_ref.ciphers
        if capabilities and policy.cipher not in ciphers:
            what = f"declares only {', '.join(ciphers)}" if ciphers else "declares no MACsec capability"
            self.plan.warnings.append(
                Notice(
                    "macsec-capability",
                    f"{ca.id}: device {device} port {port} {what}; the association needs {policy.cipher}",
                    file=port_ref.file,
                    line=port_ref.line,
                )
            )
        if policy.confidentiality_offset and f"offset {device}" not in ca.warned:
            ca.warned.add(f"offset {device}")
            self.plan.warnings.append(
                Notice(
                    "macsec-offset",
                    f"{ca.id}: confidentiality offset {policy.confidentiality_offset} cannot be set by "
                    f"wpa_supplicant, iproute2 or systemd-networkd on {device}",
                    file=element.file,
                    line=element.line,
                )
            )


class _PortInfo(NamedTuple):
    """What the plan needs of one ``<port>`` definition, read once (a tuple: 20,000 ports are made fast)."""

    file: str
    line: int | None
    type: str
    iface: str
    speed_mbps: float | None
    ciphers: tuple[str, ...]
    bad_speed: tuple[int | None, str] | None = None  # (line, why) of a speed that could not be read


_PortRef = _PortInfo | None


_SPEEDS = frozenset(("speed", "speed-tx", "speed-rx"))
_RATE_ATTRIBUTES = ("nominal", "max")  # upstream's <rate min max nominal unit>: nominal, else max
_ONCE_IN_CAPABILITIES = _SPEEDS | {"macsec", "rate"}  # hcdf.xsd port_capabilities (and upstream's rate): once


def _read_ports(comp: etree._Element, file: str) -> dict[str, _PortInfo]:
    """Every ``<port name>`` defined anywhere inside a comp (switch ports included), read in one pass:
    the first definition of a name wins; ``<capabilities>`` children of the port give its speed
    (the highest of 1.0's ``speed``, ``speed-tx``, ``speed-rx`` and of upstream's ``<rate nominal
    max unit>``, all read by :func:`hcdf_trust.units.bit_rate`) and the ``<cipher>``s of its
    ``<macsec>``. A speed that cannot be read is kept as ``bad_speed``: an error once the port
    is a member of a keyed association. Tags match in no namespace or any, tested inline
    (20,000 ports make ~100,000 tests)."""
    out: dict[str, _PortInfo] = {}
    for el in comp.iter("{*}port"):
        name = el.get("name")
        if name is None or name in out:
            continue
        ciphers: list[str] = []
        speed: float | None = None
        bad: tuple[int | None, str] | None = None
        seen: dict[str, etree._Element] = {}  # <capabilities>, <macsec>, <speed>...: each allowed once
        for caps in el:  # plain iteration and tag tests: faster in lxml than filtered iterators
            tag = caps.tag
            if tag != "capabilities" and not (type(tag) is str and tag.endswith("}capabilities")):
                continue
            if "capabilities" in seen:
                only([seen["capabilities"], caps], source=file)  # raises AmbiguousError, both lines
            seen["capabilities"] = caps
            for item in caps:
                tag = item.tag
                if type(tag) is not str:
                    continue
                local = tag[tag.rfind("}") + 1 :]
                if local in _ONCE_IN_CAPABILITIES:
                    if local in seen:
                        only([seen[local], item], source=file)  # raises AmbiguousError, both lines
                    seen[local] = item
                if local == "macsec":
                    for c in item:
                        tag = c.tag
                        if tag == "cipher" or (type(tag) is str and tag.endswith("}cipher")):
                            ciphers.append((c.text or "").strip())
                    continue
                if local in _SPEEDS:
                    values = [(item.text, item.get("unit"), "Mb/s", f"<{local}>")]
                elif local == "rate":
                    attr = next((a for a in _RATE_ATTRIBUTES if item.get(a) is not None), None)
                    if attr is None:
                        continue
                    values = [(item.get(attr), item.get("unit"), "bit/s", f"<rate {attr}>")]
                else:
                    continue
                for text, unit, default, what in values:
                    try:
                        mbps = bit_rate(text, unit, default_unit=default) / 1e6
                    except UnitError as exc:
                        bad = bad or (sourceline(item), f"{what}: {exc}")
                        continue
                    speed = mbps if speed is None or mbps > speed else speed
        out[name] = _PortInfo(
            file,
            sourceline(el),
            (el.get("type") or "").strip().lower(),
            (el.get("iface") or "").strip() or name,
            speed,
            tuple(ciphers),
            bad,
        )
    return out
