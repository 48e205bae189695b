"""``ip macsec`` script per port: ``macsec-<iface>.sh`` (static SAKs, every cipher including XPN).

The script creates ``macsecN`` on the port with the derived SCI, ``protect on``,
``validate strict`` and ``replay on window 0`` (``validate check`` for ``should-secure``),
``encrypt off`` for ``integrity-only``, one TX SA per live generation (the sending one is
``encodingsa``) and an RX channel with the same SAs for every other member port. XPN ciphers
get ``xpn``, ``salt`` and ``ssci`` on every SA. After a rotation's activation time, switch
with ``ip link set macsecN type macsec encodingsa AN`` or re-run the new export.
"""

from __future__ import annotations

from ...errors import Notice
from ..plan import is_xpn
from . import ExportError, Key, PortKeys, check_static, header, offset_notice, sci


def _sa(pk: PortKeys, key: Key, ssci: int, *, xpn: bool) -> str:
    """``sa AN pn 1 on key ID SAK``; XPN: ``sa AN xpn 1 on salt SALT ssci N key ID SAK``."""
    kid = f"{key.generation.generation % 256:02x}"
    sak = pk.static_sak(key).hex()
    if xpn:
        return f"sa {key.an} xpn 1 on salt {pk.xpn_salt(key).hex()} ssci {ssci} key {kid} {sak}"
    return f"sa {key.an} pn 1 on key {kid} {sak}"


def render(ports: list[PortKeys], *, notices: list[Notice]) -> dict[str, bytes]:
    files: dict[str, bytes] = {}
    for n, pk in enumerate(ports):
        policy = pk.ca.policy
        assert policy is not None
        if pk.eap_tls:
            raise ExportError(
                f"{pk.ca.id}: eap-tls needs MKA; static ip macsec keys cannot carry it (use --format wpa_supplicant)",
                file=pk.ca.file,
                line=pk.ca.line,
            )
        check_static(pk, notices, fmt="iproute2")
        offset_notice(pk, notices, fmt="iproute2")
        dev = f"macsec{n}"
        xpn = is_xpn(policy.cipher)
        sending = next(k for k in pk.keys if k.sending)
        validate = "check" if policy.policy == "should-secure" else "strict"
        encrypt = "off" if policy.policy == "integrity-only" else "on"

        lines = ["#!/bin/sh", *header(pk), "set -eu", ""]
        lines.append(
            f"ip link add link {pk.iface} {dev} type macsec sci {sci(pk.ca.id, pk.device, pk.port)} "
            f"cipher {policy.cipher} icvlen 16 encrypt {encrypt} protect on replay on window 0 "
            f"validate {validate} encodingsa {sending.an}"
        )
        for key in pk.keys:
            lines.append(f"ip macsec add {dev} tx {_sa(pk, key, pk.index, xpn=xpn)}")
        for peer_device, peer_port, index in pk.peers:
            peer = sci(pk.ca.id, peer_device, peer_port)
            lines.append(f"ip macsec add {dev} rx sci {peer} on")
            for key in pk.keys:
                lines.append(f"ip macsec add {dev} rx sci {peer} {_sa(pk, key, index, xpn=xpn)}")
        lines += [f"ip link set {dev} up", ""]
        files[f"macsec-{pk.iface}.sh"] = "\n".join(lines).encode()
    return files
