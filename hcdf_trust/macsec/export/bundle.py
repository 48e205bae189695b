"""JSON key bundle for a device agent: ``<device>.macsec.json``.

``{"format": "hcdf-trust-macsec-bundle", "version": 1, "device", "associations": [{"id",
"policy", "cipher", "key_agreement", "confidentiality_offset", "ports": [{"port", "iface",
"sci"}], "peers": [{"device", "port", "sci"}], "generations": [{"generation", "an", "ckn",
"cak", "activation", "expiry", "sending", "kcv"}]}], "mesh_keys": [{"id", "nodes",
"generations": [{"generation", "key", "activation", "expiry", "sending"}]}]}`` — hex strings, UTC times.

With ``--age-recipient age1…`` (the device's X25519 public key) the bundle is written only
as ``<device>.macsec.json.age``, encrypted with age (pyrage); the plaintext never touches disk.
"""

from __future__ import annotations

import json
from typing import Any

from ..kdf import key_check_value
from ..store import fmt_time
from . import ExportError, MeshKeys, PortKeys, sci

BUNDLE_FORMAT = "hcdf-trust-macsec-bundle"


def encrypt_to(recipient: str, data: bytes) -> bytes:
    """``data`` encrypted with age to an X25519 recipient (``age1…``).

    Raises:
        ExportError: the recipient is not an age X25519 public key.
    """
    import pyrage

    try:
        to = pyrage.x25519.Recipient.from_str(recipient.strip())
    except Exception as exc:  # pyrage raises its own RecipientError
        raise ExportError(
            f"--age-recipient is not an age X25519 public key: {exc}", expected="age1…", actual=recipient[:80]
        ) from None
    return bytes(pyrage.encrypt(data, [to]))


def render(
    ports: list[PortKeys], *, device: str, age_recipient: str | None = None, mesh: list[MeshKeys] | None = None
) -> dict[str, bytes]:
    by_ca: dict[str, dict[str, Any]] = {}
    for pk in ports:
        policy = pk.ca.policy
        assert policy is not None
        item = by_ca.get(pk.ca.id)
        if item is None:
            item = by_ca[pk.ca.id] = {
                "id": pk.ca.id,
                "policy": policy.policy,
                "cipher": policy.cipher,
                "key_agreement": policy.key_agreement,
                "confidentiality_offset": policy.confidentiality_offset,
                "ports": [],
                "peers": [],
                "generations": [
                    {
                        "generation": k.generation.generation,
                        "an": k.an,
                        "ckn": k.generation.ckn.hex(),
                        "cak": k.cak.hex(),
                        "activation": fmt_time(k.generation.activation),
                        "expiry": fmt_time(k.generation.expiry) if k.generation.expiry else None,
                        "sending": k.sending,
                        "kcv": key_check_value(k.cak, k.generation.ckn),
                    }
                    for k in pk.keys
                ],
            }
        if pk.eap is not None:
            item["eap_tls"] = {
                "network": pk.eap.network,
                "ca_cert": pk.eap.ca_cert.decode(),
                "cert": pk.eap.cert.decode(),
                "key": pk.eap.key.decode(),
            }
        item["ports"].append({"port": pk.port, "iface": pk.iface, "sci": sci(pk.ca.id, pk.device, pk.port)})
        for d, p, _ in pk.peers:
            peer = {"device": d, "port": p, "sci": sci(pk.ca.id, d, p)}
            if d != device and peer not in item["peers"]:
                item["peers"].append(peer)
    meshes = [
        {
            "id": m.ca.id,
            "nodes": sorted(m.ca.members),
            "generations": [
                {
                    "generation": k.generation.generation,
                    "key": k.cak.hex(),
                    "activation": fmt_time(k.generation.activation),
                    "expiry": fmt_time(k.generation.expiry) if k.generation.expiry else None,
                    "sending": k.sending,
                }
                for k in m.keys
            ],
        }
        for m in mesh or []
    ]
    doc = {
        "format": BUNDLE_FORMAT,
        "version": 1,
        "device": device,
        "associations": list(by_ca.values()),
        "mesh_keys": meshes,
    }
    data = (json.dumps(doc, indent=1, sort_keys=True) + "\n").encode()
    if age_recipient is not None:
        return {f"{device}.macsec.json.age": encrypt_to(age_recipient, data)}
    return {f"{device}.macsec.json": data}
