"""macsec plan: effective policy, connectivity associations, include scoping, conflicts, warnings."""

from __future__ import annotations

from pathlib import Path

import pytest

from hcdf_trust.errors import ErrorGroup
from hcdf_trust.macsec.plan import plan

from ._macsec import comp, hcdf, humanoid, link, port, tree

PROJECT = Path(__file__).resolve().parents[1]
ROBOT = PROJECT / "examples" / "robot" / "robot.hcdf"


def _members(ca) -> dict[str, list[str]]:
    return {m.device: sorted(m.ports) for m in ca.members.values()}


# --- the humanoid example: expectation written by reading the file -----------------------

SE = ("secure-element", "se051")
HUMANOID_CAS = {
    # backbone: network-wide must-secure gcm-aes-256, tpm key store, links without key-ref
    "link:backbone/s32n79_to_thor_p0": ("gcm-aes-256", ("tpm", "tpm0"), {"s32n79": ["e810_p0"], "agx-thor": ["mgbe0"]}),
    "link:backbone/s32n79_to_thor_p1": ("gcm-aes-256", ("tpm", "tpm0"), {"s32n79": ["e810_p1"], "agx-thor": ["mgbe1"]}),
    # arm chains: per-chain key-ref; hops' ingress/egress, the spur's port and the hop's via port
    "key-ref:arm-left-keys": (
        "gcm-aes-128",
        SE,
        {
            "s32n79": ["xfi_left"],
            "mcn1-l": ["eth0", "eth1"],
            "mcn2-l": ["eth0", "eth1"],
            "mcn3-l": ["eth0", "eth1", "eth2"],
            "cam-l": ["eth0"],
            "mcn4-l": ["eth0"],
        },
    ),
    "key-ref:arm-right-keys": (
        "gcm-aes-128",
        SE,
        {
            "s32n79": ["xfi_right"],
            "mcn1-r": ["eth0", "eth1"],
            "mcn2-r": ["eth0", "eth1"],
            "mcn3-r": ["eth0", "eth1", "eth2"],
            "cam-r": ["eth0"],
            "mcn4-r": ["eth0"],
        },
    ),
    **{
        f"key-ref:link-n79-j100-{i}": ("gcm-aes-128", SE, {"s32n79": [f"qxgmii_p{i}"], "s32j100": [f"eth_up{i}"]})
        for i in range(4)
    },
    # base: Ethernet links without key-ref take the network default
    "link:base/j100_to_head": ("gcm-aes-128", SE, {"s32j100": ["eth_head"], "head": ["eth0"]}),
    "link:base/j100_to_lidar_f": ("gcm-aes-128", SE, {"s32j100": ["eth_lidar_front"], "lidar-front": ["eth0"]}),
    "link:base/j100_to_lidar_r": ("gcm-aes-128", SE, {"s32j100": ["eth_lidar_rear"], "lidar-rear": ["eth0"]}),
    "link:base/j100_to_radar": ("gcm-aes-128", SE, {"s32j100": ["eth_radar"], "radar-4d": ["eth0"]}),
}


def test_humanoid_associations(tmp_path):
    p = plan(humanoid(tmp_path))
    assert set(p.associations) == set(HUMANOID_CAS)
    for ca_id, (cipher, store, members) in HUMANOID_CAS.items():
        ca = p.associations[ca_id]
        assert ca.policy is not None
        assert (ca.policy.policy, ca.policy.cipher, ca.policy.key_agreement) == ("must-secure", cipher, "psk")
        assert (ca.policy.key_store_type, ca.policy.key_store_ref) == store
        assert ca.policy.confidentiality_offset == 0 and ca.policy.rekey_interval_sec is None
        assert _members(ca) == members, ca_id
        assert ca.key_bytes == (32 if cipher == "gcm-aes-256" else 16)
        assert not ca.shared
    # SIGNAL links and buses carry no MACsec; the power network declares none and has only a bus
    assert sorted(e.label for e, _ in p.skipped) == sorted(
        [f"link:base/zlac_to_wheel_{s}_{k}" for s in ("left", "right") for k in ("sig", "phase")]
        + ["bus:base/base_can", "bus:power/power_bus"]
    )
    assert p.unprotected == []


def test_humanoid_warnings(tmp_path):
    p = plan(humanoid(tmp_path))
    capability = {
        w.message.split(": ", 1)[1].split(" declares")[0] for w in p.warnings if w.code == "macsec-capability"
    }
    # ports without a <macsec> capability that the plan still puts in an association
    assert capability == {
        f"device {d} port {pt}"
        for d, pt in [
            ("agx-thor", "mgbe0"),
            ("agx-thor", "mgbe1"),
            ("cam-l", "eth0"),
            ("mcn3-l", "eth2"),
            ("cam-r", "eth0"),
            ("mcn3-r", "eth2"),
            ("s32j100", "eth_head"),
            ("s32j100", "eth_lidar_front"),
            ("s32j100", "eth_lidar_rear"),
            ("s32j100", "eth_radar"),
            ("head", "eth0"),
            ("lidar-front", "eth0"),
            ("lidar-rear", "eth0"),
            ("radar-4d", "eth0"),
        ]
    }
    agx = next(w for w in p.warnings if "agx-thor port mgbe0" in w.message)
    assert agx.line == 28 and agx.file.endswith("humanoid-mobile-base.hcdf")
    # 25G backbone and 10G arm uplinks with non-XPN ciphers
    pn = {":".join(w.message.split(":")[:2]) for w in p.warnings if w.code == "macsec-pn-exhaustion"}
    assert pn == {
        "link:backbone/s32n79_to_thor_p0",
        "link:backbone/s32n79_to_thor_p1",
        "key-ref:arm-left-keys",
        "key-ref:arm-right-keys",
    }


def test_humanoid_cli_json(tmp_path, cli):
    doc = humanoid(tmp_path)
    r = cli("macsec", "plan", doc, "--json")
    assert r.exit_code == 0, r.stderr
    out = r.json
    assert out["ok"] is True
    assert len(out["associations"]) == 12
    assert all(isinstance(w, dict) and {"code", "message", "file", "line"} <= set(w) for w in out["warnings"])


# --- the example robot: a key-ref shared by two links -------------------------------------


def test_robot_shared_key_ref():
    p = plan(ROBOT)
    assert set(p.associations) == {"key-ref:head-link", "key-ref:arm-links"}
    arms = p.associations["key-ref:arm-links"]
    assert arms.shared and [e.name for e in arms.elements] == ["compute_to_left_arm", "compute_to_right_arm"]
    assert _members(arms) == {
        "compute": ["eth1", "eth2"],
        "left_arm_shoulder": ["eth0"],
        "right_arm_shoulder": ["eth0"],
    }
    assert arms.policy is not None and arms.policy.cipher == "gcm-aes-256" and arms.key_bytes == 32
    head = p.associations["key-ref:head-link"]
    assert _members(head) == {"compute": ["eth0"], "head_camera": ["eth0"]}
    assert not head.shared
    # every endpoint declares the cipher its association uses: no capability warning
    assert not [w for w in p.warnings if w.code == "macsec-capability"]


def test_robot_cli_shows_sharing(cli):
    r = cli("macsec", "plan", ROBOT)
    assert r.exit_code == 0, r.stderr
    assert "shared: one CAK on 2 links" in r.stdout


# --- include instances ---------------------------------------------------------------------

ARM = hcdf(
    comp("ctrl", port("eth0", "gcm-aes-128"), port("eth1", "gcm-aes-128")),
    comp("hand", port("eth0", "gcm-aes-128")),
    '<network name="arm-net">',
    link("ctrl_to_hand", "ctrl/eth1", "hand/eth0", '<macsec policy="must-secure" key-ref="hand-key"/>'),
    link("ctrl_to_body", "ctrl/eth0", "body/eth0"),
    '<macsec policy="should-secure" cipher="gcm-aes-128"/>',
    "</network>",
)


def _two_arms(tmp: Path, names: tuple[str, str] = ("left_arm", "right_arm")) -> Path:
    includes = "".join(f'<include uri="arm.hcdf" name="{n}"/>' for n in names)
    return tree(tmp, {"arm.hcdf": ARM, "robot.hcdf": hcdf(comp("body", port("eth0", "gcm-aes-128")), includes)})


def test_included_twice_gets_two_caks(tmp_path):
    p = plan(_two_arms(tmp_path))
    assert set(p.associations) == {
        "key-ref:left_arm_hand-key",
        "key-ref:right_arm_hand-key",
        "link:left_arm_arm-net/left_arm_ctrl_to_body",
        "link:right_arm_arm-net/right_arm_ctrl_to_body",
    }
    left = p.associations["key-ref:left_arm_hand-key"]
    assert _members(left) == {"left_arm_ctrl": ["eth1"], "left_arm_hand": ["eth0"]}
    assert left.elements[0].scope == "left_arm" and left.elements[0].file.endswith("arm.hcdf")
    # a device the included file does not define keeps its name (flatten's rule): the includer's body
    body = p.associations["link:right_arm_arm-net/right_arm_ctrl_to_body"]
    assert _members(body) == {"right_arm_ctrl": ["eth0"], "body": ["eth0"]}
    assert body.policy is not None and body.policy.policy == "should-secure"
    assert not [w for w in p.warnings if w.code == "macsec-port"]


def test_unnamed_double_include_would_share_a_cak(tmp_path):
    doc = tree(
        tmp_path,
        {
            "arm.hcdf": ARM,
            "robot.hcdf": hcdf(comp("body", port("eth0")), '<include uri="arm.hcdf"/><include uri="./arm.hcdf"/>'),
        },
    )
    with pytest.raises(ErrorGroup) as info:
        plan(doc)
    assert any("two include instances" in e.message for e in info.value.errors)


# --- effective policy, conflicts, warnings -------------------------------------------------


def _net(*body: str, devices: str = "") -> str:
    two = (port("p0", "gcm-aes-128"), port("p1", "gcm-aes-128"))
    devs = devices or comp("a", *two) + comp("b", *two)
    return hcdf(devs, '<network name="n">', *body, "</network>")


def test_override_inherits_unstated_attributes(tmp_path):
    doc = tree(
        tmp_path,
        {
            "robot.hcdf": _net(
                link("l0", "a/p0", "b/p0", '<macsec policy="integrity-only" key-ref="k" confidentiality-offset="30"/>'),
                link("l1", "a/p1", "b/p1", '<macsec policy="disabled"/>'),
                '<macsec policy="must-secure" cipher="gcm-aes-256" key-agreement="psk" rekey-interval-sec="3600">'
                '<key-store type="hsm" ref="h1"/></macsec>',
            )
        },
    )
    p = plan(doc)
    k = p.associations["key-ref:k"].policy
    assert k is not None
    assert (k.policy, k.cipher, k.confidentiality_offset, k.rekey_interval_sec, k.key_store_type) == (
        "integrity-only",
        "gcm-aes-256",
        30,
        3600,
        "hsm",
    )
    disabled = p.associations["link:n/l1"]
    assert not disabled.keyed and disabled not in p.keyed()
    codes = [w.code for w in p.warnings]
    assert "macsec-offset" in codes
    # the 256-bit CA on ports that declare only gcm-aes-128
    assert codes.count("macsec-capability") == 2


def test_same_key_ref_two_ciphers_is_an_error(tmp_path, cli):
    doc = tree(
        tmp_path,
        {
            "robot.hcdf": _net(
                link("l0", "a/p0", "b/p0", '<macsec policy="must-secure" cipher="gcm-aes-128" key-ref="k"/>'),
                link("l1", "a/p1", "b/p1", '<macsec policy="must-secure" cipher="gcm-aes-256" key-ref="k"/>'),
            )
        },
    )
    r = cli("macsec", "plan", doc, "--json")
    assert r.exit_code == 3
    (err,) = r.json["errors"]
    assert "two different cipher values" in err["message"]
    assert (err["expected"], err["actual"], err["line"]) == ("gcm-aes-128", "gcm-aes-256", 6)


def test_bad_attribute_values_are_errors(tmp_path, cli):
    doc = tree(tmp_path, {"robot.hcdf": _net(link("l0", "a/p0", "b/p0", '<macsec policy="maybe" cipher="rot13"/>'))})
    r = cli("macsec", "plan", doc, "--json")
    assert r.exit_code == 3
    assert {(e["actual"]) for e in r.json["errors"]} == {"maybe", "rot13"}


def test_unprotected_and_mesh_key(tmp_path):
    doc = tree(
        tmp_path,
        {
            "robot.hcdf": _net(
                link("l0", "a/p0", "b/p0"),
                '<mesh name="skin" standard="802.15.4" network-key-ref="thread-key">'
                '<node device="a" antenna="ant0"/><node device="b" antenna="ant0"/></mesh>',
            )
        },
    )
    p = plan(doc)
    assert [e.label for e in p.unprotected] == ["link:n/l0"]
    mesh = p.associations["mesh-key:thread-key"]
    assert mesh.kind == "mesh-key" and mesh.key_bytes == 16 and set(mesh.members) == {"a", "b"}


def test_unknown_port_is_a_warning(tmp_path):
    doc = tree(tmp_path, {"robot.hcdf": _net(link("l0", "a/p0", "ghost/eth9", '<macsec policy="must-secure"/>'))})
    p = plan(doc)
    assert [w.code for w in p.warnings] == ["macsec-port"]


# --- the tree is verified first ------------------------------------------------------------


def test_refuses_a_tree_that_fails_its_pins(tmp_path, cli):
    doc = _two_arms(tmp_path)
    (tmp_path / "arm.hcdf").write_text(ARM.replace("hand-key", "evil-key"))
    r = cli("macsec", "plan", doc, "--json")
    assert r.exit_code == 1
    assert "associations" not in r.json


def test_refuses_without_a_lock(tmp_path, cli):
    doc = tmp_path / "robot.hcdf"
    doc.write_text(_net(link("l0", "a/p0", "b/p0", '<macsec policy="must-secure"/>')))
    r = cli("macsec", "plan", doc)
    assert r.exit_code == 3
    assert "lock" in r.stderr


def _reference_ports(comp_el, file: str) -> dict[str, tuple[object, ...]] | None:
    """The port rule of macsec.plan written plainly with lxml's filtered iterators and QName;
    None when a port read has two <capabilities>, or two <speed> (<speed-tx>, <speed-rx>,
    <macsec>) in one: the schema allows each once, and the planner refuses it."""
    from collections import Counter

    from lxml import etree

    from hcdf_trust.units import UnitError, bit_rate

    out: dict[str, tuple[object, ...]] = {}
    for el in comp_el.iter("{*}port"):
        name = el.get("name")
        if name is None or name in out:
            continue
        ciphers: list[str] = []
        speeds: list[float] = []
        bad = None
        if len(list(el.iterchildren("{*}capabilities"))) > 1:
            return None
        for caps in el.iterchildren("{*}capabilities"):
            once = Counter(etree.QName(i).localname for i in caps.iterchildren(etree.Element))
            if any(once[t] > 1 for t in ("speed", "speed-tx", "speed-rx", "macsec")):
                return None
            for item in caps.iterchildren(etree.Element):
                local = etree.QName(item).localname
                if local == "macsec":
                    ciphers += [(c.text or "").strip() for c in item.iterchildren("{*}cipher")]
                elif local in ("speed", "speed-tx", "speed-rx"):
                    try:
                        speeds.append(bit_rate(item.text, item.get("unit"), default_unit="Mb/s") / 1e6)
                    except UnitError as exc:  # unreadable: kept, an error on a secured link (issue 16 §6)
                        bad = bad or (item.sourceline, f"<{local}>: {exc}")
        kind = (el.get("type") or "").strip().lower()
        iface = (el.get("iface") or "").strip() or name
        out[name] = (file, el.sourceline, kind, iface, max(speeds, default=None), tuple(ciphers), bad)
    return out


@pytest.mark.parametrize("seed", range(40))
def test_port_reading_matches_a_plain_reference(seed):
    # _read_ports tests tags inline for speed; the same ports read the plain way give the same result
    import random

    from hcdf_trust.macsec.plan import _read_ports
    from hcdf_trust.xml import parse_bytes

    r = random.Random(seed)

    def tag(local: str) -> str:
        return r.choice([local, local, f"x:{local}", f"y:{local}"])

    def capabilities() -> str:
        items = []
        for _ in range(r.randrange(6)):
            pick = r.random()
            if pick < 0.4:
                ciphers = "".join(
                    f"<{t}> {r.choice(['gcm-aes-128', 'gcm-aes-256', ''])}<!--c--></{t}>"
                    for t in (tag(r.choice(["cipher", "cipher", "ciphers"])) for _ in range(r.randrange(3)))
                )
                t = tag(r.choice(["macsec", "macsec", "macsecs"]))
                items.append(f"<{t}>{ciphers}<?pi x?></{t}>")
            elif pick < 0.8:
                t = tag(r.choice(["speed", "speed-tx", "speed-rx", "speeds"]))
                unit = r.choice(["", ' unit="Gbps"', ' unit="kbps"', ' unit="x"'])
                items.append(f"<{t}{unit}>{r.choice(['1000', ' 2.5 ', '100', '10000', 'fast', '-1'])}</{t}>")
            else:
                items.append("<!-- note -->")
        t = tag(r.choice(["capabilities", "capabilities", "capability"]))
        return f"<{t}>{''.join(items)}</{t}>"

    def port_xml(depth: int = 0) -> str:
        name = r.choice([' name="p0"', ' name="p1"', ' name="p2"', ""])
        attrs = name + r.choice(["", ' type=" Ethernet "', ' type="can"']) + r.choice(["", ' iface="e0"', ' iface=" "'])
        inner = "".join(capabilities() for _ in range(r.randrange(3)))
        if depth < 2 and r.random() < 0.2:
            inner += port_xml(depth + 1)
        t = tag("port")
        return f"<{t}{attrs}>{inner}</{t}>"

    body = "\n".join(port_xml() for _ in range(r.randrange(1, 8)))
    if r.random() < 0.5:
        body = f"<switch>{body}</switch>"
    text = f'<hcdf xmlns:x="urn:x" xmlns:y="urn:y"><comp name="c">\n{body}\n</comp></hcdf>'
    comp_el = parse_bytes(text.encode(), source="t.hcdf").getroot()[0]
    expected = _reference_ports(comp_el, "t.hcdf")
    if expected is None:
        from hcdf_trust.errors import AmbiguousError

        with pytest.raises(AmbiguousError, match="the schema allows one"):
            _read_ports(comp_el, "t.hcdf")
    else:
        assert _read_ports(comp_el, "t.hcdf") == expected


def test_link_children_are_read_in_any_namespace():
    # _link reads the one <wired>, all its <port>s and its one <macsec> in one loop of tag tests
    from hcdf_trust.document import Document
    from hcdf_trust.macsec.plan import plan_resolution
    from hcdf_trust.xml import parse_bytes

    wired = (
        '<x:wired xmlns:x="urn:x"><!-- a comment --><x:port>a/p0</x:port><?pi?><ports>c/p0</ports>'
        '<port> b/p0</port><x:macsec policy="must-secure" key-ref="k"/></x:wired>'
    )
    text = hcdf(
        comp("a", port("p0", "gcm-aes-128")),
        comp("b", port("p0", "gcm-aes-128")),
        comp("c", port("p0", "gcm-aes-128")),
        f'<network name="n"><link name="l">{wired}</link></network>',
    )
    doc = Document(source="t.hcdf", tree=parse_bytes(text.encode(), source="t.hcdf"), data=text.encode())
    p = plan_resolution({"u": doc}, {}, "u")
    assert list(p.associations) == ["key-ref:k"]
    ca = p.associations["key-ref:k"]
    assert ca.policy is not None and ca.policy.policy == "must-secure"
    assert _members(ca) == {"a": ["p0"], "b": ["p0"]}


@pytest.mark.parametrize(
    ("wired", "tag"),
    [
        (
            '<wired><port>a/p0</port><port>b/p0</port><macsec policy="must-secure"/>'
            '<x:macsec xmlns:x="urn:x" policy="disabled"/></wired>',
            "macsec",
        ),
        (
            '<wired><port>a/p0</port><port>b/p0</port><macsec policy="must-secure"/></wired>'
            '<wired><port>c/p0</port><macsec policy="disabled"/></wired>',
            "wired",
        ),
    ],
)
def test_link_with_two_macsec_or_two_wired_is_refused(wired, tag):
    # First-one-wins used to secure the link with the first <macsec> while another reader took the
    # second (disabled): the schema allows one, so two are refused, naming both lines.
    from hcdf_trust.document import Document
    from hcdf_trust.errors import AmbiguousError, ErrorGroup
    from hcdf_trust.macsec.plan import plan_resolution
    from hcdf_trust.xml import parse_bytes

    text = hcdf(
        comp("a", port("p0", "gcm-aes-128")),
        comp("b", port("p0", "gcm-aes-128")),
        comp("c", port("p0", "gcm-aes-128")),
        f'<network name="n"><link name="l">\n{wired}\n</link></network>',
    )
    doc = Document(source="t.hcdf", tree=parse_bytes(text.encode(), source="t.hcdf"), data=text.encode())
    with pytest.raises(ErrorGroup) as info:
        plan_resolution({"u": doc}, {}, "u")
    (error,) = [e for e in info.value.errors if isinstance(e, AmbiguousError)]
    assert error.code == "ambiguous" and f"2 <{tag}> elements" in error.message
