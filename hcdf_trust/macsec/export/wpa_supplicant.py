"""wpa_supplicant MKA (PSK) configuration, one file per port: ``wpa_supplicant-wired-<iface>.conf``.

The name is the one Debian's ``wpa_supplicant-wired@<iface>.service`` reads. Only keys the
stated ``--wpa-version`` knows are written, since wpa_supplicant refuses a whole file for
one unknown key: 2.10 (Debian 12) has no ``macsec_csindex`` (so no GCM-AES-256), 2.11 adds
it. No upstream version negotiates XPN. Each live generation is one network block; the
sending one has the highest ``priority``. wpa_supplicant runs one block at a time, so a
rotation is completed by re-exporting (or ``wpa_cli set_network``) at the activation time.
``mka_priority`` is 16 for the association's first member port (the preferred key server)
and 32 for the others.
"""

from __future__ import annotations

from ...errors import Notice
from . import DEVICE_NAME, ExportError, PortKeys, check_name, header, offset_notice

DEFAULT_VERSION = "2.10"  # what a user most likely runs: Debian 12, Ubuntu 22.04 and 24.04 ship 2.10


def target_line(version: tuple[int, int]) -> str:
    """The header line naming the version the file was written for (and how to change it)."""
    return (
        f"# For wpa_supplicant {version[0]}.{version[1]}: only keys it knows are written "
        f"(hcdf-trust macsec export --wpa-version; Debian 12 and Ubuntu 22.04/24.04 ship 2.10)."
    )


CERT_DIR = "/etc/wpa_supplicant/hcdf"


def _eap_block(pk: PortKeys, policy: str, version: tuple[int, int], files: dict[str, bytes]) -> list[str]:
    """An EAP-TLS network block; the CA certificate, device certificate and key as files for CERT_DIR."""
    assert pk.eap is not None and pk.ca.policy is not None
    net = check_name(pk.eap.network, DEVICE_NAME, what="network", ca=pk.ca)
    ca_file, cert_file, key_file = f"hcdf-{net}-ca.pem", f"hcdf-{net}-{pk.device}.pem", f"hcdf-{net}-{pk.device}.key"
    files[ca_file], files[cert_file], files[key_file] = pk.eap.ca_cert, pk.eap.cert, pk.eap.key
    block = [
        f"# EAP-TLS: install {ca_file}, {cert_file} and {key_file} in {CERT_DIR} (root, 0600)",
        "network={",
        "\tkey_mgmt=IEEE8021X",
        "\teap=TLS",
        "\teapol_flags=0",
        "\tmacsec_policy=1",
        f"\tmacsec_integ_only={1 if policy == 'integrity-only' else 0}",
        "\tmacsec_replay_protect=1",
        "\tmacsec_replay_window=0",
        "\tmacsec_port=1",
        f'\tidentity="{pk.device}"',
        f'\tca_cert="{CERT_DIR}/{ca_file}"',
        f'\tclient_cert="{CERT_DIR}/{cert_file}"',
        f'\tprivate_key="{CERT_DIR}/{key_file}"',
    ]
    if version >= (2, 11):
        block.append(f"\tmacsec_csindex={1 if pk.ca.policy.cipher == 'gcm-aes-256' else 0}")
    return [*block, "}"]


def render(ports: list[PortKeys], *, version: tuple[int, int], notices: list[Notice]) -> dict[str, bytes]:
    files: dict[str, bytes] = {}
    for pk in ports:
        policy = pk.ca.policy
        assert policy is not None
        if policy.cipher.startswith("gcm-aes-xpn"):
            raise ExportError(
                f"{pk.ca.id}: wpa_supplicant cannot negotiate {policy.cipher} (no upstream XPN support); "
                f"use --format iproute2 for static XPN keys",
                file=pk.ca.file,
                line=pk.ca.line,
                expected="gcm-aes-128 | gcm-aes-256",
                actual=policy.cipher,
            )
        if policy.cipher == "gcm-aes-256" and version < (2, 11):
            raise ExportError(
                f"{pk.ca.id}: wpa_supplicant {version[0]}.{version[1]} cannot select gcm-aes-256 "
                f"(macsec_csindex needs 2.11 or later; pass --wpa-version 2.11 if the device has it)",
                file=pk.ca.file,
                line=pk.ca.line,
                expected="wpa_supplicant >= 2.11",
                actual=f"{version[0]}.{version[1]}",
            )
        offset_notice(pk, notices, fmt="wpa_supplicant")
        lines = [*header(pk), target_line(version)]
        lines += ["ctrl_interface=/run/wpa_supplicant", "eapol_version=3", "ap_scan=0"]
        if pk.eap is not None:
            lines += _eap_block(pk, policy.policy, version, files)
            files[f"wpa_supplicant-wired-{pk.iface}.conf"] = ("\n".join(lines) + "\n").encode()
            continue
        for n, key in enumerate(sorted(pk.keys, key=lambda k: (k.sending, k.generation.generation))):
            g = key.generation
            block = [
                "network={",
                "\tkey_mgmt=NONE",
                "\teapol_flags=0",
                "\tmacsec_policy=1",
                f"\tmacsec_integ_only={1 if policy.policy == 'integrity-only' else 0}",
                "\tmacsec_replay_protect=1",
                "\tmacsec_replay_window=0",
                "\tmacsec_port=1",
                f"\tmka_cak={key.cak.hex()}",
                f"\tmka_ckn={g.ckn.hex()}",
                f"\tmka_priority={16 if pk.index == 1 else 32}",
                f"\tpriority={n + 1}",
            ]
            if version >= (2, 11):
                block.append(f"\tmacsec_csindex={1 if policy.cipher == 'gcm-aes-256' else 0}")
            lines += [f"# generation {g.generation}", *block, "}"]
        files[f"wpa_supplicant-wired-{pk.iface}.conf"] = ("\n".join(lines) + "\n").encode()
    return files
