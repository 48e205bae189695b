"""Export one device's keys for its consumer: wpa_supplicant, systemd-networkd, iproute2, JSON.

Least privilege: :func:`collect` returns only the associations the device is a member of,
and within them only the device's own ports. Every generation that is not retired at
``now`` is exported (the rotation overlap: devices hold the next key before it sends).

Conventions shared by the static-key formats (networkd, iproute2), which have no MKA:

* One SAK per association and generation, the same for every member, derived from the CAK:
  ``KDF(CAK, "IEEE8021 SAK", "hcdf-trust static SAK" ‖ CKN[0:16] ‖ generation (4 octets), |CAK|)``.
  Members differ by SCI, so their GCM IVs (SCI ‖ PN) never collide.
* The SCI of a member port is a locally administered unicast MAC derived from
  ``SHA-256("hcdf-trust sci" ‖ CA id ‖ device ‖ port)``, with SCI port 1; every export
  derives the peer's SCI the same way, so no MAC address needs to be known in advance
  (the MACsec interface is given that address).
* Association number AN = (generation - 1) mod 4; the newest active generation encodes.
* XPN ciphers: salt = ``KDF(CAK, "hcdf-trust XPN salt", CKN[0:16] ‖ generation, 96)``, SSCI = the
  member's 1-based position in the association.
* Packet-number exhaustion: a static non-XPN key is refused on a port of 10 Gb/s or more
  (a 32-bit PN lasts under 7 minutes there); below, a notice states the PN lifetime when
  the rekey interval is missing or exceeds half of it.
* ``must-secure`` has no wpa_supplicant flag: it is enforced by the exported network setup
  (addresses only on the MACsec interface, the parent left without any; ``protect on``,
  ``validate strict`` for static keys), as each file's header says.
"""

from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass
from datetime import datetime

from ...errors import InputError, Notice
from ..kdf import kdf
from ..plan import PN_WARN_MBPS, Association, Plan, is_xpn, pn_lifetime_seconds
from ..store import Entry, Generation, KeyStore

FORMATS = ("wpa_supplicant", "networkd", "iproute2", "json")
# Interface and device names become file names and shell words: refuse anything else.
_IFACE = re.compile(r"[A-Za-z0-9_.:@-]{1,15}")
DEVICE_NAME = re.compile(r"[A-Za-z0-9_.@-]{1,200}")


def clean(text: str) -> str:
    """Text from the description, safe inside a comment line (no control characters)."""
    return "".join(c if c.isprintable() else "?" for c in text)


def check_name(value: str, pattern: re.Pattern[str], *, what: str, ca: Association) -> str:
    if not pattern.fullmatch(value) or value in (".", ".."):
        raise ExportError(
            f"{what} {clean(value)!r} cannot be used as a file name or shell word",
            file=ca.file,
            line=ca.line,
            expected=pattern.pattern,
            actual=clean(value)[:80],
        )
    return value


class ExportError(InputError):
    """What the chosen consumer cannot express, or a device the description does not key."""

    code = "macsec-export"


@dataclass
class Key:
    generation: Generation
    cak: bytes
    sending: bool  # the newest active generation

    @property
    def an(self) -> int:
        return (self.generation.generation - 1) % 4


@dataclass(frozen=True)
class Eap:
    """A device's EAP-TLS material for one network: the CA certificate, its key and certificate (PEM)."""

    network: str
    ca_cert: bytes
    key: bytes
    cert: bytes


@dataclass
class PortKeys:
    """One port of the exported device in one association, with the keys it needs."""

    ca: Association
    entry: Entry
    device: str
    port: str
    iface: str
    index: int  # position of this port among the association's member ports (1-based): SSCI, priority
    peers: list[tuple[str, str, int]]  # (device, port, index) of every other member port
    keys: list[Key]
    eap: Eap | None = None  # key-agreement eap-tls: certificates instead of a CAK

    @property
    def eap_tls(self) -> bool:
        return self.eap is not None

    def static_sak(self, key: Key) -> bytes:
        context = b"hcdf-trust static SAK" + key.generation.ckn[:16] + key.generation.generation.to_bytes(4, "big")
        return kdf(key.cak, b"IEEE8021 SAK", context, len(key.cak) * 8)

    def xpn_salt(self, key: Key) -> bytes:
        context = key.generation.ckn[:16] + key.generation.generation.to_bytes(4, "big")
        return kdf(key.cak, b"hcdf-trust XPN salt", context, 96)


def member_mac(ca_id: str, device: str, port: str) -> str:
    """The locally administered unicast MAC (and so SCI) of a member port."""
    digest = bytearray(
        hashlib.sha256(b"\0".join([b"hcdf-trust sci", ca_id.encode(), device.encode(), port.encode()])).digest()[:6]
    )
    digest[0] = (digest[0] & 0xFC) | 0x02
    return ":".join(f"{b:02x}" for b in digest)


def sci(ca_id: str, device: str, port: str) -> str:
    """SCI as 16 hex digits: the member MAC followed by port 0001."""
    return member_mac(ca_id, device, port).replace(":", "") + "0001"


def collect(plan: Plan, store: KeyStore, device: str, *, now: datetime) -> tuple[list[PortKeys], list[Notice]]:
    """The device's ports in every keyed association it belongs to, with their live keys.

    Raises:
        KeyStoreRobotError: the store was generated for another robot.
        ExportError: the device is in no keyed association, or one of them has no key yet.
    """
    store.bind(plan.robot, document=plan.document)
    cas = [ca for ca in plan.for_device(device) if ca.kind == "macsec"]
    if not plan.for_device(device):
        known = sorted({d for ca in plan.keyed() for d in ca.members})
        raise ExportError(
            f"device {device!r} is a member of no keyed MACsec association",
            file=plan.document,
            expected="one of: " + ", ".join(known)[:400] if known else "a device on a MACsec link or chain",
            actual=device,
        )
    out: list[PortKeys] = []
    notices: list[Notice] = []
    seen_ports: dict[str, str] = {}
    for ca in cas:
        assert ca.policy is not None
        eap = None
        if ca.policy.key_agreement == "eap-tls":
            from .. import eaptls  # cryptography.x509: only for eap-tls associations

            eap = _eap(store, ca, device, now)
            entry, keys = store.entries[eaptls.cert_id(eap.network, device)], []
        else:
            found = store.entries.get(ca.id)
            current = found.current(now) if found is not None else None
            if found is None or current is None:
                raise ExportError(
                    f"{ca.id} has no active key in the store: run `macsec generate`", file=ca.file, line=ca.line
                )
            entry = found
            keys = [Key(g, store.key(entry, g), g is current) for g in entry.live(now)]
        member_ports = [(m.device, p) for m in ca.members.values() for p in m.ports]
        for port in ca.members[device].ports:
            if port in seen_ports:
                raise ExportError(
                    f"port {device}/{port} is in two associations ({seen_ports[port]} and {ca.id}): "
                    f"one port, one connectivity association",
                    file=ca.file,
                    line=ca.line,
                )
            seen_ports[port] = ca.id
            index = member_ports.index((device, port)) + 1
            peers = [(d, p, i + 1) for i, (d, p) in enumerate(member_ports) if (d, p) != (device, port)]
            iface = check_name(ca.ifaces.get(f"{device}/{port}", port), _IFACE, what="interface", ca=ca)
            check_name(device, DEVICE_NAME, what="device", ca=ca)
            out.append(PortKeys(ca, entry, device, port, iface, index, peers, keys, eap))
    return out, notices


@dataclass
class MeshKeys:
    """A mesh network key the device holds as a mesh node."""

    ca: Association
    keys: list[Key]


def mesh_keys(plan: Plan, store: KeyStore, device: str, *, now: datetime) -> list[MeshKeys]:
    """The mesh network keys of every mesh the device is a node of.

    Raises:
        ExportError: one of them has no key in the store yet.
    """
    out = []
    for ca in plan.for_device(device):
        if ca.kind != "mesh-key":
            continue
        entry = store.entries.get(ca.id)
        current = entry.current(now) if entry is not None else None
        if entry is None or current is None:
            raise ExportError(f"{ca.id} has no key in the store: run `macsec generate`", file=ca.file, line=ca.line)
        out.append(MeshKeys(ca, [Key(g, store.key(entry, g), g is current) for g in entry.live(now)]))
    return out


def _eap(store: KeyStore, ca: Association, device: str, now: datetime) -> Eap:
    from .. import eaptls

    network = ca.elements[0].network
    parts = []
    for entry_id in (eaptls.ca_id(network), eaptls.cert_id(network, device)):
        entry = store.entries.get(entry_id)
        current = entry.current(now) if entry is not None else None
        if entry is None or current is None:
            raise ExportError(
                f"{ca.id}: {entry_id} is not in the store: run `macsec generate`", file=ca.file, line=ca.line
            )
        parts.append(eaptls.split(store.key(entry, current)))
    return Eap(network, ca_cert=parts[0][1], key=parts[1][0], cert=parts[1][1])


def check_static(pk: PortKeys, notices: list[Notice], *, fmt: str) -> None:
    """Packet-number exhaustion rule for static SAKs (no MKA to rekey on PN)."""
    policy = pk.ca.policy
    assert policy is not None
    speed = pk.ca.max_speed_mbps
    if speed is None or is_xpn(policy.cipher):
        return
    life = pn_lifetime_seconds(speed)
    if speed >= PN_WARN_MBPS:
        raise ExportError(
            f"{pk.ca.id}: {fmt} uses static keys without MKA, and at {speed:g} Mb/s a 32-bit packet number "
            f"lasts {life:.0f} s: refusing a non-XPN static key at 10 Gb/s or more (use an XPN cipher "
            f"or --format wpa_supplicant)",
            file=pk.ca.file,
            line=pk.ca.line,
            expected="gcm-aes-xpn-128 | gcm-aes-xpn-256",
            actual=policy.cipher,
        )
    rekey = policy.rekey_interval_sec
    if rekey is None or rekey > life / 2:
        notices.append(
            Notice(
                "macsec-pn-lifetime",
                f"{pk.ca.id}: with static keys at {speed:g} Mb/s a 32-bit packet number lasts {life:.0f} s "
                f"with minimum-size frames; rotate at least every {life / 2:.0f} s "
                f"(rekey-interval-sec is {rekey if rekey is not None else 'not set'})",
                file=pk.ca.file,
                line=pk.ca.line,
            )
        )


def offset_notice(pk: PortKeys, notices: list[Notice], *, fmt: str) -> None:
    policy = pk.ca.policy
    if policy is not None and policy.confidentiality_offset:
        notices.append(
            Notice(
                "macsec-offset",
                f"{pk.ca.id}: {fmt} cannot set confidentiality offset {policy.confidentiality_offset}; "
                f"{pk.device}/{pk.port} will use offset 0",
                file=pk.ca.file,
                line=pk.ca.line,
            )
        )


def header(pk: PortKeys, comment: str = "#") -> list[str]:
    policy = pk.ca.policy
    assert policy is not None
    lines = [
        f"{comment} Generated by hcdf-trust macsec export: device {pk.device}, port {clean(pk.port)} ({pk.iface}).",
        f"{comment} Connectivity association {clean(pk.ca.id)}: {policy.policy} {policy.cipher} "
        f"({clean(pk.ca.file)}:{pk.ca.line}). Secret: install as root, mode 0600.",
    ]
    if policy.policy == "must-secure":
        lines.append(
            f"{comment} must-secure: configure addresses, bridges and routes only on the MACsec interface, "
            f"never on {pk.iface}, so no traffic leaves unprotected."
        )
    for key in pk.keys:
        g = key.generation
        role = "sends" if key.sending else "accepted, sends from " + g.activation.strftime("%Y-%m-%dT%H:%M:%SZ")
        until = f", accepted until {g.expiry.strftime('%Y-%m-%dT%H:%M:%SZ')}" if g.expiry else ""
        lines.append(f"{comment} generation {g.generation}: {role}{until}")
    return lines


def render(
    fmt: str,
    ports: list[PortKeys],
    *,
    device: str,
    wpa_version: tuple[int, int],
    notices: list[Notice],
    age_recipient: str | None = None,
    mesh: list[MeshKeys] | None = None,
) -> dict[str, bytes]:
    """File name -> content for ``fmt`` (one of :data:`FORMATS`); ``age_recipient`` encrypts the JSON bundle.

    Raises:
        ExportError: the consumer cannot express an association (cipher, version, PN rule).
    """
    if age_recipient is not None and fmt != "json":
        raise ExportError("--age-recipient encrypts the JSON bundle: use it with --format json")
    if fmt != "json":
        if not ports:
            raise ExportError(f"device {device!r} holds only mesh network keys: export them with --format json")
        for m in mesh or []:
            notices.append(
                Notice("macsec-mesh-key", f"{m.ca.id}: a mesh network key is exported only by --format json")
            )
    if fmt == "wpa_supplicant":
        from . import wpa_supplicant

        return wpa_supplicant.render(ports, version=wpa_version, notices=notices)
    if fmt == "networkd":
        from . import networkd

        return networkd.render(ports, notices=notices)
    if fmt == "iproute2":
        from . import iproute2

        return iproute2.render(ports, notices=notices)
    from . import bundle

    return bundle.render(ports, device=device, age_recipient=age_recipient, mesh=mesh or [])
