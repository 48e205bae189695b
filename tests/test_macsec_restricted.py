"""macsec export plans only the networks that can hold the device: same files as from the whole plan.

Oracle: for every keyed device of three robots (the corpus humanoid, the example robot with its
arm included twice, a generated multi-network robot with includes, shared key-refs, chains,
meshes and eap-tls), the CLI export (restricted plan) writes byte-identical files to an export
rendered from the whole plan, and every format gives the same files or the same refusal.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from hcdf_trust.errors import ErrorGroup
from hcdf_trust.macsec.backends import PassphraseWrapper
from hcdf_trust.macsec.export import FORMATS, ExportError, collect, mesh_keys, render
from hcdf_trust.macsec.plan import Plan, plan, plan_resolution
from hcdf_trust.macsec.store import KeyStore, parse_time

from ._macsec import comp, generate, hcdf, humanoid, link, lock, port, tree

PROJECT = Path(__file__).resolve().parents[1]
PASS = b"restricted export passphrase"
T0 = "2026-01-01T00:00:00Z"
T1 = "2026-01-01T00:30:00Z"  # inside the overlap of the rotation made at T0: two generations exported
C = "gcm-aes-128"

SUB = hcdf(
    comp("ctrl", port("eth0", C), port("eth1", C), port("eth2", C)),
    comp("hand", port("eth0", C)),
    comp("d1", port("eth0", C)),  # scoped left_d1 / right_d1: not the root's d1
    '<network name="arm-net">',
    link("ctrl_to_hand", "ctrl/eth1", "hand/eth0", '<macsec policy="must-secure" key-ref="hand-key"/>'),
    '<chain name="uplink"><hop device="ctrl" port="eth0"/><hop device="hub"/></chain>',  # the includer's hub
    link("ctrl_to_d1", "ctrl/eth2", " d1 /eth0", '<macsec policy="must-secure" key-ref="hand-key"/>'),
    '<macsec policy="should-secure" cipher="gcm-aes-128"/>',
    "</network>",
)


def _generated_robot(tmp: Path) -> Path:
    hub = comp("hub", *(port(f"p{i}", C, "gcm-aes-256") for i in range(10)))
    devices = [comp(d, port("eth0", C, "gcm-aes-256"), port("eth1", C)) for d in ("d1", "d10", "d2", "d3", "d4", "d5")]
    chain = (
        '<chain name="ring"><macsec policy="must-secure" key-ref="ring-key"/>'
        '<hop device="d2" port="eth1"/><hop device="d3" port="eth1"><spur device="d4" port="eth1" via="eth1"/></hop>'
        "</chain>"
    )
    body = [
        hub,
        *devices,
        '<network name="net0">',
        link("l0", "hub/p0", "d1/eth0", '<macsec policy="must-secure" key-ref="shared"/>'),
        link("l1", "hub/p1", "d10/eth0", '<macsec policy="must-secure" cipher="gcm-aes-256"/>'),
        '<macsec policy="must-secure"/>',
        "</network>",
        '<network name="net1">',  # names no d1, but shares its key-ref: planned for d1 too
        link("l2", "hub/p2", "d2/eth0", '<macsec policy="must-secure" key-ref="shared"/>'),
        chain,
        '<macsec policy="must-secure"/>',
        "</network>",
        '<network name="net2">',
        '<mesh name="skin" standard="802.15.4" network-key-ref="thread"><node device="d1" antenna="x"/>'
        '<node device="d3" antenna="x"/></mesh>',
        link("off", "hub/p3", "d3/eth0", '<macsec policy="disabled"/>'),
        '<link name="air"><wireless/></link>',
        '<bus name="can"/>',
        "</network>",
        '<network name="net3">',
        '<mesh name="skin2" standard="802.15.4" network-key-ref="thread"><node device="d4" antenna="x"/></mesh>',
        "</network>",
        '<network name="net0">',  # a second network of that name: its link ids could collide with net0's
        link("l9", "hub/p4", "d4/eth0", '<macsec policy="must-secure"/>'),
        "</network>",
        '<network name="eap">',
        link("l5", "hub/p5", "d5/eth0"),
        '<macsec policy="must-secure" key-agreement="eap-tls"/>',
        "</network>",
        '<include uri="arm.hcdf" name="left"/><include uri="arm.hcdf" name="right"/>',
    ]
    return tree(tmp, {"arm.hcdf": SUB, "robot.hcdf": hcdf(*body)})


def _example_robot(tmp: Path) -> Path:
    shutil.copytree(PROJECT / "examples" / "robot", tmp / "robot")
    return lock(tmp / "robot" / "robot.hcdf")


def _humanoid(tmp: Path) -> Path:
    (tmp / "doc").mkdir()
    return humanoid(tmp / "doc")


def _outcome(p: Plan, store: KeyStore, device: str, fmt: str) -> object:
    """What an export of ``device`` in ``fmt`` from plan ``p`` writes (or why it refuses)."""
    now = parse_time(T1, what="now", source="test")
    try:
        ports, notices = collect(p, store, device, now=now)
        mesh = mesh_keys(p, store, device, now=now)
        files = render(fmt, ports, device=device, wpa_version=(2, 10), notices=notices, mesh=mesh)
    except ExportError as exc:
        return ("refused", str(exc))
    return files, [n.to_dict() for n in notices]


@pytest.mark.parametrize("robot", [_humanoid, _example_robot, _generated_robot])
def test_restricted_export_equals_export_from_the_whole_plan(tmp_path, cli, robot):
    doc = robot(tmp_path)
    pp = tmp_path / "pass"
    pp.write_bytes(PASS)
    base = ["--store", tmp_path / "keys", "--passphrase-file", pp]
    assert cli("macsec", "generate", doc, *base, "--now", T0).exit_code == 0
    full = plan(doc)
    some_ref = next(ca.key_ref for ca in full.keyed() if ca.key_ref and ca.kind == "macsec")
    assert cli("macsec", "rotate", doc, *base, "--key-ref", some_ref, "--now", T0).exit_code == 0
    store = KeyStore.open(tmp_path / "keys", PassphraseWrapper(PASS))
    devices = sorted({d for ca in full.keyed() for d in ca.members})
    assert len(devices) >= 4
    restricted_somewhere = False
    res = full.resolution
    for device in devices:
        # the restricted plan itself (plan(doc, device=) falls back to the whole plan for a device it misses)
        part = plan_resolution(res.documents, res.includes, res.root_location.url, device=device)
        assert part.for_device(device), device
        restricted_somewhere |= len(part.associations) < len(full.associations)
        assert [ca.to_dict() for ca in part.for_device(device)] == [ca.to_dict() for ca in full.for_device(device)]
        for fmt in FORMATS:
            assert _outcome(part, store, device, fmt) == _outcome(full, store, device, fmt), (device, fmt)
        # the CLI's files, byte for byte
        want = _outcome(full, store, device, "json")
        out = tmp_path / "out" / device
        r = cli("macsec", "export", doc, *base, "--device", device, "--format", "json", "--out", out, "--now", T1)
        assert isinstance(want, tuple)
        if want[0] == "refused":
            assert r.exit_code == 3 and str(want[1]) in r.stderr and not out.exists()
        else:
            assert r.exit_code == 0, r.stderr
            assert {f.name: f.read_bytes() for f in out.iterdir()} == want[0]
    networks = {e.network for ca in full.associations.values() for e in ca.elements}
    assert restricted_somewhere or len(networks) == 1  # the example robot has one network


def test_generated_robot_plans_what_the_device_needs(tmp_path):
    doc = _generated_robot(tmp_path)
    networks = {e.network for ca in plan(doc, device="d1").associations.values() for e in ca.elements}
    # net0 and net2 name d1; net1 shares its key-ref, net3 its mesh key; the second net0 could share ids;
    # the arm copies write "d1" (their own d1) and are kept by the substring match
    assert networks == {"net0", "net1", "net2", "net3", "left_arm-net", "right_arm-net"}
    networks = {e.network for ca in plan(doc, device="d5").associations.values() for e in ca.elements}
    assert networks == {"eap"}
    arm = plan(doc, device="left_hand")
    assert {e.network for ca in arm.associations.values() for e in ca.elements} == {"left_arm-net"}
    assert set(arm.associations["key-ref:left_hand-key"].members) == {"left_ctrl", "left_hand", "left_d1"}
    assert {e.network for ca in plan(doc, device="hub").associations.values() for e in ca.elements} >= {
        "left_arm-net",
        "right_arm-net",
        "net0",
    }


def _two_networks(tmp: Path, other_macsec: str) -> Path:
    devs = [comp(d, port("p0", C, "gcm-aes-256")) for d in ("a", "b", "c", "d")]
    body = [
        *devs,
        '<network name="mine">',
        link("l", "a/p0", "b/p0", '<macsec policy="must-secure" key-ref="k"/>'),
        "</network>",
        '<network name="other">',
        link("l", "c/p0", "d/p0", other_macsec),
        "</network>",
    ]
    return tree(tmp, {"robot.hcdf": hcdf(*body)})


def test_export_checks_the_device_associations_not_unrelated_networks(tmp_path, cli):
    doc = _two_networks(tmp_path, '<macsec policy="must-secure" key-ref="k2"/>')
    base = generate(cli, tmp_path, doc, PASS)
    # a mistake in a network the device is not on: plan refuses, the device's export does not
    text = doc.read_text().replace('key-ref="k2"', 'key-ref="k2" cipher="gcm-aes-999"')
    doc.write_text(text)
    lock(doc)
    assert cli("macsec", "plan", doc).exit_code == 3
    r = cli("macsec", "export", doc, *base, "--device", "a", "--format", "json", "--out", tmp_path / "o")
    assert r.exit_code == 0, r.stderr
    r = cli("macsec", "export", doc, *base, "--device", "c", "--format", "json", "--out", tmp_path / "o2")
    assert r.exit_code == 3 and "gcm-aes-999" in r.stderr


def test_a_conflict_written_in_another_network_still_refuses_the_export(tmp_path, cli):
    # the other network does not name the device, but writes its key-ref with another cipher
    doc = _two_networks(tmp_path, '<macsec policy="must-secure" cipher="gcm-aes-256" key-ref="k"/>')
    with pytest.raises(ErrorGroup) as info:
        plan(doc, device="a")
    assert any("two different cipher values" in e.message for e in info.value.errors)


@pytest.mark.parametrize(
    ("first", "second"),
    [(("mine", "l"), ("mine", "l")), (("a", "b/c"), ("a/b", "c")), (("a/b", "c"), ("a", "b/c"))],
)
def test_a_duplicate_link_id_in_another_network_still_refuses_the_export(tmp_path, first, second):
    devs = [comp(d, port("p0", C)) for d in ("a", "b", "c", "d")]
    body = [*devs]
    for (net, name), ends in ((first, ("a/p0", "b/p0")), (second, ("c/p0", "d/p0"))):
        body += [f'<network name="{net}">', link(name, *ends, '<macsec policy="must-secure"/>'), "</network>"]
    doc = tree(tmp_path, {"robot.hcdf": hcdf(*body)})
    for device in ("a", "c"):
        with pytest.raises(ErrorGroup) as info:
            plan(doc, device=device)
        assert [e.message for e in info.value.errors] == [
            "two links are named a/b/c" if "/" in first[1] + second[1] else "two links are named mine/l"
        ]


def test_an_unknown_device_lists_every_device(tmp_path, cli):
    doc = _two_networks(tmp_path, '<macsec policy="must-secure" key-ref="k2"/>')
    base = generate(cli, tmp_path, doc, PASS)
    r = cli("macsec", "export", doc, *base, "--device", "zz", "--format", "json", "--out", tmp_path / "o")
    assert r.exit_code == 3 and "one of: a, b, c, d" in r.stderr


def test_a_namespaced_document_is_matched_in_any_namespace(tmp_path):
    # the planner takes a <network> in any namespace; so does the restriction (resolve refuses
    # such a document, plan_resolution alone does not)
    from hcdf_trust.document import Document
    from hcdf_trust.xml import parse_bytes

    text = hcdf(
        comp("a", port("p0", C)),
        comp("b", port("p0", C)),
        comp("c", port("p0", C)),
        '<x:network xmlns:x="urn:x" name="n">',
        link("l", "a/p0", "b/p0", '<macsec policy="must-secure" key-ref="k"/>'),
        "</x:network>",
        '<network name="m">',
        link("l2", "c/p0", "b/p0", '<macsec policy="must-secure" key-ref="k"/>'),
        "</network>",
    )
    doc = Document(source="t.hcdf", tree=parse_bytes(text.encode(), source="t.hcdf"), data=text.encode())
    full = plan_resolution({"u": doc}, {}, "u")
    part = plan_resolution({"u": doc}, {}, "u", device="a")
    assert part.associations["key-ref:k"].to_dict() == full.associations["key-ref:k"].to_dict()
    assert set(part.associations["key-ref:k"].members) == {"a", "b", "c"}


def test_the_plan_scopes_names_with_the_flattener_separator():
    from hcdf_trust.include import flatten
    from hcdf_trust.macsec import plan as planner

    assert planner.SEPARATOR == flatten.SEPARATOR
