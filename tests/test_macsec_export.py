"""macsec export: least privilege, per-consumer limits, and the real consumers parsing our files."""

from __future__ import annotations

import json
import os
import shutil
import stat
import subprocess
import uuid
from pathlib import Path

import pytest

from hcdf_trust.macsec.backends import PassphraseWrapper
from hcdf_trust.macsec.plan import plan
from hcdf_trust.macsec.store import KeyStore

from ._macsec import comp, generate, hcdf, humanoid, link, port, tree

PROJECT = Path(__file__).resolve().parents[1]
ROBOT = PROJECT / "examples" / "robot" / "robot.hcdf"
PASS = b"export test passphrase"
T0 = "2026-01-01T00:00:00Z"


@pytest.fixture
def provisioned(tmp_path, cli):
    """The humanoid example, locked, with every key generated; ``export(device, fmt, *args)``."""
    (tmp_path / "doc").mkdir()
    doc = humanoid(tmp_path / "doc")
    pp = tmp_path / "pass"
    pp.write_bytes(PASS)
    store = tmp_path / "keys"
    base = ["--store", store, "--passphrase-file", pp]
    assert cli("macsec", "generate", doc, *base, "--now", T0).exit_code == 0

    def export(device: str, fmt: str, *args: str, out: Path | None = None):
        out = out or tmp_path / f"out-{device}-{fmt}-{uuid.uuid4().hex[:6]}"
        r = cli("macsec", "export", doc, *base, "--device", device, "--format", fmt, "--out", out, *args)
        return r, out

    return doc, store, base, export


def _keys_by_ca(store: Path) -> dict[str, list[str]]:
    ks = KeyStore.open(store, PassphraseWrapper(PASS))
    return {ca: [ks.key(e, g).hex() for g in e.generations] for ca, e in ks.entries.items()}


def _text(out: Path) -> str:
    return "".join(p.read_text() for p in sorted(out.iterdir()))


# --- least privilege -----------------------------------------------------------------------


@pytest.mark.parametrize("fmt", ["json", "wpa_supplicant"])
def test_a_device_gets_only_its_associations(provisioned, fmt):
    doc, store, _base, export = provisioned
    p = plan(doc)
    keys = _keys_by_ca(store)
    for device in ("s32j100", "head", "mcn2-l"):
        r, out = export(device, fmt)
        assert r.exit_code == 0, r.stderr
        mine = {ca.id for ca in p.for_device(device)}
        assert mine
        text = _text(out)
        for ca_id, cas in keys.items():
            for cak in cas:
                assert (cak in text) == (ca_id in mine), (device, ca_id)
        shown = {line.split()[3].rstrip(":") for line in text.splitlines() if "Connectivity association" in line}
        assert fmt == "json" or shown == mine
        if fmt == "json":
            bundle = json.loads((out / f"{device}.macsec.json").read_text())
            assert {a["id"] for a in bundle["associations"]} == mine
        for f in out.iterdir():
            assert stat.S_IMODE(f.stat().st_mode) == 0o600
        assert stat.S_IMODE(out.stat().st_mode) == 0o700


def test_export_json_output_and_errors_hold_no_key(provisioned):
    _doc, store, _base, export = provisioned
    keys = [k for ks in _keys_by_ca(store).values() for k in ks]
    results = [export("s32j100", "json", "--json")[0], export("s32n79", "wpa_supplicant")[0]]
    results.append(export("ghost", "json")[0])
    assert [r.exit_code for r in results] == [0, 3, 3]
    for r in results:
        for k in keys:
            assert k not in r.stdout and k not in r.stderr
    assert results[0].json["files"] and results[0].json["associations"]
    assert "member of no keyed MACsec association" in results[2].stderr


def test_export_never_over_an_input(provisioned, tmp_path):
    doc, _store, _base, export = provisioned
    out = tmp_path / "trap"
    out.mkdir()
    os.symlink(doc, out / "head.macsec.json")
    before = doc.read_bytes()
    r, _ = export("head", "json", out=out)
    assert r.exit_code == 3 and "refusing to overwrite an input" in r.stderr
    assert doc.read_bytes() == before


# --- what each consumer can express ------------------------------------------------------------


def test_wpa_version_gates_gcm_aes_256(provisioned):
    _doc, _store, _base, export = provisioned
    r, _ = export("agx-thor", "wpa_supplicant")
    assert r.exit_code == 3 and "2.11" in r.stderr  # the backbone is gcm-aes-256
    r, out = export("agx-thor", "wpa_supplicant", "--wpa-version", "2.11")
    assert r.exit_code == 0, r.stderr
    conf = (out / "wpa_supplicant-wired-eth0.conf").read_text()
    assert "macsec_csindex=1" in conf and len(conf.split("mka_cak=")[1].split()[0]) == 64
    r, _ = export("agx-thor", "wpa_supplicant", "--wpa-version", "2.9")
    assert r.exit_code == 2


def test_static_keys_refused_at_10g(provisioned):
    _doc, _store, _base, export = provisioned
    for fmt in ("networkd", "iproute2"):
        r, _ = export("mcn1-l", fmt)  # arm chain: 10G uplink, gcm-aes-128
        assert r.exit_code == 3 and "10 Gb/s" in r.stderr, fmt
    r, _ = export("mcn1-l", "wpa_supplicant")  # MKA rekeys on packet number: allowed
    assert r.exit_code == 0, r.stderr
    r, _ = export("agx-thor", "networkd")
    assert r.exit_code == 3 and "only gcm-aes-128" in r.stderr


def _xpn_tree(tmp: Path, iface: str = "eth0") -> Path:
    caps = ("gcm-aes-xpn-256",)
    a = comp("a", port("p0", *caps, mbps=25000).replace('type="ethernet"', f'type="ethernet" iface="{iface}"'))
    body = [a, comp("b", port("p0", *caps, mbps=25000)), '<network name="n">']
    body += [link("l0", "a/p0", "b/p0", '<macsec policy="must-secure" cipher="gcm-aes-xpn-256"/>'), "</network>"]
    return tree(tmp, {"robot.hcdf": hcdf(*body)})


def test_iproute2_xpn_has_salt_and_ssci(tmp_path, cli):
    doc = _xpn_tree(tmp_path)
    base = generate(cli, tmp_path, doc, PASS)
    r = cli("macsec", "export", doc, *base, "--device", "a", "--format", "iproute2", "--out", tmp_path / "o")
    assert r.exit_code == 0, r.stderr
    script = (tmp_path / "o" / "macsec-eth0.sh").read_text()
    assert "cipher gcm-aes-xpn-256" in script
    tx = next(line for line in script.splitlines() if " tx sa " in line).split()
    assert tx[tx.index("salt") + 1].__len__() == 24 and tx[tx.index("ssci") + 1] == "1"
    assert len(tx[-1]) == 64  # a 256-bit SAK
    rx = next(line for line in script.splitlines() if " rx sci " in line and " sa " in line).split()
    assert rx[rx.index("ssci") + 1] == "2"
    r = cli("macsec", "export", doc, *base, "--device", "a", "--format", "wpa_supplicant", "--out", tmp_path / "w")
    assert r.exit_code == 3 and "XPN" in r.stderr


@pytest.mark.parametrize("iface", ["eth0;reboot", "../../x", "eth0&#10;reboot"])
def test_hostile_interface_names_are_refused(tmp_path, cli, iface):
    doc = _xpn_tree(tmp_path, iface=iface)
    base = generate(cli, tmp_path, doc, PASS)
    r = cli("macsec", "export", doc, *base, "--device", "a", "--format", "iproute2", "--out", tmp_path / "o")
    assert r.exit_code == 3 and "cannot be used as a file name" in r.stderr
    assert not (tmp_path / "o").exists()


def test_overlap_exports_both_generations(provisioned, cli):
    doc, _store, base, export = provisioned
    r = cli("macsec", "rotate", doc, *base, "--key-ref", "link-n79-j100-0", "--now", T0, "--overlap", "600")
    assert r.exit_code == 0, r.stderr
    r, out = export("s32j100", "wpa_supplicant", "--now", "2026-01-01T00:05:00Z")
    conf = (out / "wpa_supplicant-wired-swp0.conf").read_text()
    assert conf.count("network={") == 2 and "generation 2: accepted, sends from 2026-01-01T00:10:00Z" in conf
    r, out = export("s32j100", "networkd", "--now", "2026-01-01T00:05:00Z")
    netdev = (out / "50-hcdf-macsec0.netdev").read_text()
    assert netdev.count("[MACsecTransmitAssociation]") == 2 and netdev.count("UseForEncoding=yes") == 1
    assert "KeyId=01\nKey=" in netdev and "KeyId=02" in netdev
    r, out = export("s32j100", "iproute2", "--now", "2026-01-01T00:15:00Z")
    script = (out / "macsec-swp0.sh").read_text()
    assert "encodingsa 1" in script  # generation 2 (AN 1) sends after its activation
    r, out = export("s32j100", "wpa_supplicant", "--now", "2026-01-01T00:25:00Z")
    assert (out / "wpa_supplicant-wired-swp0.conf").read_text().count("network={") == 1


# --- real consumers ----------------------------------------------------------------------------


@pytest.fixture
def netns():
    """A network namespace with a veth pair va/vb (root and iproute2 needed)."""
    if os.geteuid() != 0 or shutil.which("ip") is None:
        pytest.skip("network namespaces need root and iproute2")
    name = f"hcdf-{uuid.uuid4().hex[:8]}"
    if subprocess.run(["ip", "netns", "add", name], capture_output=True).returncode != 0:
        pytest.skip("cannot create a network namespace here")
    try:
        subprocess.run(["ip", "-n", name, "link", "add", "va", "type", "veth", "peer", "name", "vb"], check=True)
        subprocess.run(["ip", "-n", name, "link", "set", "va", "up"], check=True)
        yield name
    finally:
        subprocess.run(["ip", "netns", "del", name], capture_output=True)


def _wpa_log(ns: str, conf: Path) -> str:
    proc = subprocess.run(
        [
            "ip",
            "netns",
            "exec",
            ns,
            "timeout",
            "4",
            "wpa_supplicant",
            "-dd",
            "-D",
            "macsec_linux",
            "-i",
            "va",
            "-c",
            conf,
        ],
        capture_output=True,
        text=True,
    )
    return proc.stdout + proc.stderr  # the exit code is 255 for good and bad files alike: read the log


@pytest.mark.skipif(
    shutil.which("wpa_supplicant") is None, reason="wpa_supplicant (Debian wpasupplicant) not installed"
)
def test_wpa_supplicant_parses_our_configuration(provisioned, netns):
    _doc, _store, _base, export = provisioned
    r, out = export("s32j100", "wpa_supplicant")
    assert r.exit_code == 0, r.stderr
    confs = sorted(out.glob("wpa_supplicant-wired-*.conf"))
    assert len(confs) == 8
    for conf in confs:
        log = _wpa_log(netns, conf)
        assert "MKA-CAK - hexdump(len=16)" in log, log
        assert "Failed to read or parse configuration" not in log and "unknown network field" not in log
    # the oracle tells bad from good: the 2.11 form (macsec_csindex) is refused by this 2.10
    version = subprocess.run(["wpa_supplicant", "-v"], capture_output=True, text=True).stdout
    r, out = export("agx-thor", "wpa_supplicant", "--wpa-version", "2.11")
    log = _wpa_log(netns, out / "wpa_supplicant-wired-eth0.conf")
    if "v2.10" in version:
        assert "unknown network field 'macsec_csindex'" in log
    else:
        assert "Failed to read or parse configuration" not in log


NETWORKD = Path("/lib/systemd/systemd-networkd")


@pytest.mark.skipif(not NETWORKD.exists() or shutil.which("unshare") is None, reason="systemd-networkd not installed")
def test_systemd_networkd_parses_our_netdev(provisioned, netns, tmp_path):
    _doc, _store, _base, export = provisioned
    r, out = export("s32j100", "networkd")
    assert r.exit_code == 0, r.stderr
    # installed as the .netdev header and docs say: root:systemd-network, 0640
    stage = tmp_path / "install"
    shutil.copytree(out, stage)
    for f in stage.iterdir():
        shutil.chown(f, "root", "systemd-network")
        f.chmod(0o640)
    script = (
        "umask 022 && "  # the tests' umask is 077 (conftest): networkd's own user must read the folder
        f"mount -t tmpfs tmpfs /run/systemd && mkdir -p /run/systemd/network && cp -p {stage}/* /run/systemd/network/ "
        f"&& ip netns exec {netns} timeout 3 env SYSTEMD_LOG_LEVEL=debug SYSTEMD_LOG_TARGET=console {NETWORKD}"
    )
    proc = subprocess.run(["unshare", "-m", "sh", "-c", script], capture_output=True, text=True, timeout=30)
    log = proc.stdout + proc.stderr
    if "Operation not permitted" in log and "mount" in log:
        pytest.skip("cannot make a private mount namespace here")
    for n in range(8):
        assert f'macsec{n}: loaded "macsec"' in log, log[-3000:]
    ours = [line for line in log.splitlines() if "50-hcdf-" in line]
    assert not [line for line in ours if any(w in line for w in ("Unknown", "Invalid", "Failed", "ignoring"))], ours


def _kernel_has_macsec(ns: str) -> bool:
    probe = subprocess.run(
        ["ip", "-n", ns, "link", "add", "link", "va", "probe0", "type", "macsec"], capture_output=True, text=True
    )
    subprocess.run(["ip", "-n", ns, "link", "del", "probe0"], capture_output=True)
    return probe.returncode == 0


def test_two_namespaces_exchange_traffic_over_our_iproute2_export(tmp_path, cli, netns):
    if not _kernel_has_macsec(netns):
        pytest.skip(
            "this kernel has no MACsec (CONFIG_MACSEC unset, no macsec module): 'ip link add type macsec' fails"
        )
    doc = ROBOT
    base = generate(cli, tmp_path, doc, PASS)
    a, b = f"{netns}-a", f"{netns}-b"
    try:
        for ns in (a, b):
            subprocess.run(["ip", "netns", "add", ns], check=True)
        subprocess.run(
            ["ip", "link", "add", "eth0", "netns", a, "type", "veth", "peer", "name", "eth0", "netns", b], check=True
        )
        for ns, device, addr in ((a, "compute", "10.99.0.1/24"), (b, "head_camera", "10.99.0.2/24")):
            out = tmp_path / device
            r = cli("macsec", "export", doc, *base, "--device", device, "--format", "iproute2", "--out", out)
            assert r.exit_code == 0, r.stderr
            subprocess.run(["ip", "-n", ns, "link", "set", "eth0", "up"], check=True)
            subprocess.run(["ip", "netns", "exec", ns, "sh", out / "macsec-eth0.sh"], check=True)
            subprocess.run(["ip", "-n", ns, "addr", "add", addr, "dev", "macsec0"], check=True)
        ping = subprocess.run(
            ["ip", "netns", "exec", a, "ping", "-c", "3", "-W", "2", "10.99.0.2"], capture_output=True
        )
        assert ping.returncode == 0, ping.stdout
    finally:
        for ns in (a, b):
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)


def test_bundle_encrypted_to_the_device_age_key(provisioned, tmp_path):
    pyrage = pytest.importorskip("pyrage")
    _doc, store, _base, export = provisioned
    identity = pyrage.x25519.Identity.generate()
    r, out = export("head", "json", "--age-recipient", str(identity.to_public()))
    assert r.exit_code == 0, r.stderr
    assert [p.name for p in out.iterdir()] == ["head.macsec.json.age"]
    sealed = (out / "head.macsec.json.age").read_bytes()
    assert sealed.startswith(b"age-encryption.org/v1\n")
    cak = _keys_by_ca(store)["link:base/j100_to_head"][0]
    assert cak.encode() not in sealed
    if shutil.which("age"):  # the reference implementation, where installed, as the independent reader
        key = tmp_path / "id.txt"
        key.write_text(str(identity) + "\n")
        plain = subprocess.run(["age", "-d", "-i", key], input=sealed, capture_output=True, check=True).stdout
    else:
        plain = pyrage.decrypt(sealed, [identity])
    bundle = json.loads(plain)
    assert [a["id"] for a in bundle["associations"]] == ["link:base/j100_to_head"]
    assert bundle["associations"][0]["generations"][0]["cak"] == cak
    r, _ = export("head", "json", "--age-recipient", "age1notakey")
    assert r.exit_code == 3 and "not an age X25519 public key" in r.stderr
    r, _ = export("head", "wpa_supplicant", "--age-recipient", str(identity.to_public()))
    assert r.exit_code == 3


def test_mesh_network_keys_go_to_mesh_nodes_only(tmp_path, cli):
    caps = ("gcm-aes-128",)
    body = [comp("a", port("p0", *caps)), comp("b", port("p0", *caps)), comp("c"), '<network name="n">']
    body += [link("l0", "a/p0", "b/p0", '<macsec policy="must-secure"/>')]
    body += ['<mesh name="skin" standard="802.15.4" network-key-ref="thread">']
    body += ['<node device="a" antenna="x"/><node device="c" antenna="x"/></mesh>', "</network>"]
    doc = tree(tmp_path / "d", {"robot.hcdf": hcdf(*body)})
    base = generate(cli, tmp_path, doc, PASS)
    ks = KeyStore.open(tmp_path / "keys", PassphraseWrapper(PASS))
    entry = ks.entries["mesh-key:thread"]
    mesh_key = ks.key(entry, entry.generations[0]).hex()
    assert len(mesh_key) == 32

    def bundle(device: str) -> dict:
        out = tmp_path / f"o-{device}"
        r = cli("macsec", "export", doc, *base, "--device", device, "--format", "json", "--out", out)
        assert r.exit_code == 0, r.stderr
        return json.loads((out / f"{device}.macsec.json").read_text())

    assert [m["generations"][0]["key"] for m in bundle("c")["mesh_keys"]] == [mesh_key]
    assert bundle("c")["associations"] == []
    assert [m["id"] for m in bundle("a")["mesh_keys"]] == ["mesh-key:thread"]
    assert bundle("b")["mesh_keys"] == [] and mesh_key not in json.dumps(bundle("b"))
    r = cli("macsec", "export", doc, *base, "--device", "c", "--format", "wpa_supplicant", "--out", tmp_path / "w")
    assert r.exit_code == 3 and "only mesh network keys" in r.stderr


def test_cli_formats_are_the_exporters():
    from hcdf_trust.cli.macsec import export as command
    from hcdf_trust.macsec.export import FORMATS

    option = next(p for p in command.params if p.name == "fmt")
    assert tuple(option.type.choices) == FORMATS


def test_iproute2_scripts_are_valid_shell(provisioned):
    _doc, _store, _base, export = provisioned
    r, out = export("s32j100", "iproute2")
    assert r.exit_code == 0, r.stderr
    scripts = sorted(out.glob("macsec-*.sh"))
    assert len(scripts) == 8
    for script in scripts:
        proc = subprocess.run(["sh", "-n", script], capture_output=True, text=True)
        assert proc.returncode == 0, proc.stderr
        body = script.read_text()
        assert "validate strict" in body and "protect on" in body and "encrypt on" in body  # must-secure
