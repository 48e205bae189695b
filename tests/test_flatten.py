"""resolve --out: includes expanded, names prefixed, poses composed, frames and collisions checked.

Rotations are checked against quaternions (Hamilton product, q = qz(yaw)·qy(pitch)·qx(roll)),
built independently of the rotation matrices in hcdf_trust.include.flatten.
"""

from __future__ import annotations

import hashlib
import math
import shutil
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from lxml import etree

from hcdf_trust.errors import FlattenError
from hcdf_trust.include import ResolveOptions, resolve
from hcdf_trust.include.flatten import SEPARATOR, Pose, flatten, format_pose, parse_pose

from .conftest import HCDFORMAT


def hcdf(body: str, *, name: str = "t", attrs: str = "") -> str:
    return f'<?xml version="1.0"?>\n<hcdf version="1.0" name="{name}"{attrs}>\n{body}\n</hcdf>\n'


def write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
    return path


def line_of(path: Path, needle: str) -> int:
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        if needle in line:
            return number
    raise AssertionError(f"{needle!r} not in {path}")


def flat(cli, doc: Path, tmp_path: Path, *extra) -> tuple[etree._Element, bytes]:
    out = doc.parent / "flat.hcdf"
    r = cli("resolve", doc, "--cache-dir", tmp_path / "cache", "--no-lock", "--out", out, *extra)
    assert r.exit_code == 0, r.stderr
    data = out.read_bytes()
    return etree.fromstring(data), data


def fails(cli, doc: Path, tmp_path: Path) -> tuple[str, Path]:
    """Resolve with --out and expect exit 3; return stderr and the --out path."""
    out = doc.parent / "flat.hcdf"
    r = cli("resolve", doc, "--cache-dir", tmp_path / "cache", "--out", out)
    assert r.exit_code == 3, (r.exit_code, r.stderr)
    return r.stderr, out


# --- a sub-assembly that uses every kind of reference HCDF has ---------------------------

ARM = hcdf(
    """
  <description>two-link arm with a wrist camera</description>
  <author>Arm Works</author>
  <!-- the arm's base -->
  <comp name="base">
    <visual name="shell"><material name="alu"/></visual>
    <collision name="hull"><surface material="rubber"/></collision>
    <frame name="mount" relative-to="base"/>
    <frame name="probe" relative-to="mount"/>
    <switch chip="sw"><port name="eth0" type="ethernet"/><port name="eth1" type="ethernet"/></switch>
    <port name="can0" type="CAN"/>
    <antenna name="ble" type="bluetooth"/>
    <sensor name="enc"><encoder type="absolute"/></sensor>
    <motor name="m1" type="bldc" encoder="enc"/>
    <motor name="eq" type="brushed"/>
  </comp>
  <comp name="link1">
    <port name="eth0" type="ethernet"/><port name="eth1" type="ethernet"/>
    <port name="eth2" type="ethernet"/><port name="can0" type="CAN"/>
    <antenna name="ble" type="bluetooth"/>
    <sensor name="out_enc"><encoder type="absolute"/></sensor>
  </comp>
  <comp name="tool">
    <frame name="tcp" relative-to="tool"/>
    <port name="eth0" type="ethernet"/><port name="can0" type="CAN"/>
  </comp>
  <comp name="cam"><port name="eth0" type="ethernet"/></comp>
  <joint name="shoulder" type="revolute"><parent comp="base"/><child comp="link1"/></joint>
  <joint name="elbow" type="revolute"><parent comp="link1"/><child comp="tool"/></joint>
  <joint name="elbow_twin" type="revolute">
    <parent comp="link1"/><child comp="tool"/><mimic joint="elbow"/>
  </joint>
  <joint name="cam_mount" type="fixed"><parent comp="link1"/><child comp="cam"/></joint>
  <group name="arm" type="end-effector" tip-comp="tool" tip-frame="tcp">
    <joint ref="shoulder"/><joint ref="elbow"/>
  </group>
  <group name="whole"><group ref="arm"/></group>
  <state name="home"><joint-position joint="shoulder" value="0"/></state>
  <self-collision-disable><pair comp1="base" comp2="link1"/></self-collision-disable>
  <network name="arm_net">
    <link name="uplink"><wired standard="802.3dm">
      <port>base/eth1</port><port>link1.eth1</port>
      <macsec policy="must-secure" key-ref="arm-keys"/>
    </wired></link>
    <link name="radio"><wireless standard="bluetooth-5.3">
      <antenna>base.ble</antenna><antenna>link1.ble</antenna>
    </wireless></link>
    <bus name="can" type="CAN">
      <plca><coordinator device="base" port="can0"/></plca>
      <participant device="base" port="can0"/><participant device="tool" port="can0"/>
    </bus>
    <chain name="arm_chain" type="802.3dm">
      <dc reference-clock="link1"/>
      <hop device="base" port="eth0" role="root"/>
      <hop device="link1" ingress="eth0" egress="eth1">
        <spur device="cam" port="eth0" via="eth2"/>
      </hop>
      <hop device="tool" ingress="eth0" role="tail"/>
    </chain>
    <chain name="tunnelled" type="ethercat">
      <tunnel chain="arm_chain" hop="link1"/>
      <hop device="tool" port="eth0"/>
    </chain>
    <mesh name="touch"><node device="base" antenna="ble"/><node device="link1" antenna="ble"/></mesh>
    <gptp domain="0"><clock device="base" port="eth0"/><clock device="link1" port="eth0"/></gptp>
    <schedule name="s1" cycle-time-us="1000"/>
    <schedule-assignment>
      <assign schedule="s1" ports="base/eth0 link1.eth0" chains="arm_chain tunnelled"/>
    </schedule-assignment>
  </network>
  <transmission name="shoulder_tx" encoder="out_enc">
    <motor ref="m1"/><joint ref="shoulder"/>
    <spring placement="parallel" equilibrium-actuator="base.eq"/>
  </transmission>
  <material name="alu"/>
  <material name="rubber"/>
""",
    name="2link-arm",
)
ARM_NAMES = {
    "comp": {"base", "link1", "tool", "cam"},
    "joint": {"shoulder", "elbow", "elbow_twin", "cam_mount"},
    "group": {"arm", "whole"},
    "state": {"home"},
    "network": {"arm_net"},
    "transmission": {"shoulder_tx"},
    "material": {"alu", "rubber"},
}


def check_references(root: etree._Element) -> tuple[list[str], int]:
    """Every reference in a flattened document names something it defines.

    Returns the problems found and how many references were checked.
    """
    problems: list[str] = []
    checked = 0
    comps = {c.get("name"): c for c in root.findall("comp")}
    defined = {k: {e.get("name") for e in root.findall(k)} for k in ("joint", "group", "material")}

    def need(ok: bool, what: str) -> None:
        nonlocal checked
        checked += 1
        if not ok:
            problems.append(what)

    def named(comp: str, tag: str, name: str) -> bool:
        c = comps.get(comp)
        return c is not None and any(e.get("name") == name for e in c.iter(tag))

    def path(value: str, tag: str) -> None:
        """``comp/name`` or ``comp.name``; a bare name must be on exactly one comp."""
        head, sep, tail = value.replace("/", ".").partition(".")
        if sep:
            need(named(head, tag, tail), f"{tag} path {value!r}")
        else:
            need(sum(named(c, tag, value) for c in comps) == 1, f"{tag} {value!r}")

    for j in root.findall("joint"):
        for end in ("parent", "child"):
            need(j.find(end).get("comp") in comps, f"joint {j.get('name')} {end}")
        for m in j.findall("mimic"):
            need(m.get("joint") in defined["joint"], f"mimic {m.get('joint')}")
    for g in root.findall("group"):
        for r in g.findall("joint"):
            need(r.get("ref") in defined["joint"], f"group joint {r.get('ref')}")
        for r in g.findall("group"):
            need(r.get("ref") in defined["group"], f"group group {r.get('ref')}")
        if g.get("tip-comp"):
            need(g.get("tip-comp") in comps, f"tip-comp {g.get('tip-comp')}")
            need(named(g.get("tip-comp"), "frame", g.get("tip-frame")), "tip-frame")
    for jp in root.iter("joint-position"):
        need(jp.get("joint") in defined["joint"], f"joint-position {jp.get('joint')}")
    for p in root.iter("pair"):
        need(p.get("comp1") in comps and p.get("comp2") in comps, f"pair {dict(p.attrib)}")
    for t in root.findall("transmission"):
        for j in t.findall("joint"):
            need(j.get("ref") in defined["joint"], f"transmission joint {j.get('ref')}")
        for m in t.findall("motor"):
            path(m.get("ref"), "motor")
        for s in t.findall("spring"):
            path(s.get("equilibrium-actuator"), "motor")
        if t.get("encoder"):
            path(t.get("encoder"), "sensor")
    for c in comps.values():
        for s in c.iter("surface"):
            if s.get("material"):
                need(s.get("material") in defined["material"], f"surface {s.get('material')}")
        for m in c.findall("visual/material"):
            need(m.get("name") in defined["material"], f"visual material {m.get('name')}")
        for f in c.findall("frame"):
            rel = f.get("relative-to")
            need(rel == c.get("name") or named(c.get("name"), "frame", rel), f"frame {rel}")
    for net in root.findall("network"):
        chains = {e.get("name") for e in net.findall("chain")}
        schedules = {e.get("name") for e in net.findall("schedule")}
        for p in net.iterfind(".//wired/port"):
            path(p.text, "port")
        for a in net.iterfind(".//wireless/antenna"):
            path(a.text, "antenna")
        for tag, port_attrs in (
            ("participant", ("port",)),
            ("coordinator", ("port",)),
            ("hop", ("port", "ingress", "egress")),
            ("spur", ("port",)),
            ("clock", ("port",)),
            ("node", ()),
        ):
            for e in net.iter(tag):
                need(e.get("device") in comps, f"{tag} device {e.get('device')}")
                for attr in port_attrs:
                    if e.get(attr):
                        need(named(e.get("device"), "port", e.get(attr)), f"{tag} {attr}")
        for s in net.iter("spur"):
            hop = s.getparent()
            need(named(hop.get("device"), "port", s.get("via")), "spur via")
        for d in net.iter("dc"):
            if d.get("reference-clock"):
                need(d.get("reference-clock") in comps, "dc reference-clock")
        for t in net.iter("tunnel"):
            need(t.get("chain") in chains and t.get("hop") in comps, f"tunnel {dict(t.attrib)}")
        for a in net.iter("assign"):
            need(a.get("schedule") in schedules, f"assign schedule {a.get('schedule')}")
            for p in (a.get("ports") or "").split():
                path(p, "port")
            for ch in (a.get("chains") or "").split():
                need(ch in chains, f"assign chain {ch}")
    return problems, checked


def test_the_reference_checker_can_fail():
    broken = etree.fromstring(ARM.encode().split(b"?>", 1)[1].replace(b'comp="tool"', b'comp="x"'))
    problems, _ = check_references(broken)
    assert any("child" in p for p in problems)
    problems, checked = check_references(etree.fromstring(ARM.encode().split(b"?>", 1)[1]))
    assert problems == [] and checked >= 40


@pytest.fixture
def two_arms(tmp_path):
    root = tmp_path / "robot"
    write(root / "parts" / "arm.hcdf", ARM)
    doc = write(
        root / "robot.hcdf",
        hcdf(
            """
  <comp name="chassis"/>
  <joint name="mount_left" type="fixed"><parent comp="chassis"/><child comp="left_arm_base"/></joint>
  <include uri="parts/arm.hcdf" name="left_arm" pose="0 0.2 0 0 0 0"/>
  <include uri="parts/arm.hcdf" name="right_arm" pose="0 -0.2 0 0 0 0"/>
""",
            name="robot",
            attrs=' xmlns:xsi="http://www.w3.org/2001/XMLSchema-instance" author-note="kept"',
        ),
    )
    return doc


def test_names_and_every_reference_are_prefixed(cli, tmp_path, two_arms):
    out, _ = flat(cli, two_arms, tmp_path)
    problems, checked = check_references(out)
    assert problems == []
    assert checked >= 80  # both copies' references were all looked at
    assert out.find(".//include") is None
    assert {c.get("name") for c in out.findall("comp")} == {"chassis"} | {
        f"{side}{SEPARATOR}{n}" for side in ("left_arm", "right_arm") for n in ARM_NAMES["comp"]
    }
    net = out.find("network[@name='left_arm_arm_net']")
    assert [p.text for p in net.iterfind(".//wired/port")] == ["left_arm_base/eth1", "left_arm_link1.eth1"]
    assign = net.find(".//assign")
    assert assign.get("ports") == "left_arm_base/eth0 left_arm_link1.eth0"
    assert assign.get("chains") == "left_arm_arm_chain left_arm_tunnelled"
    assert assign.get("schedule") == "left_arm_s1"
    tx = out.find("transmission[@name='right_arm_shoulder_tx']")
    assert tx.find("motor").get("ref") == "right_arm_base.m1"  # bare name qualified with its comp
    assert tx.find("spring").get("equilibrium-actuator") == "right_arm_base.eq"
    assert tx.get("encoder") == "right_arm_link1.out_enc"
    # Names inside a comp are not prefixed; opaque strings are left alone.
    base = out.find("comp[@name='left_arm_base']")
    assert [p.get("name") for p in base.iter("port")] == ["eth0", "eth1", "can0"]
    assert base.find("motor").get("encoder") == "enc"
    assert base.find("frame[@name='probe']").get("relative-to") == "mount"
    assert base.find("frame[@name='mount']").get("relative-to") == "left_arm_base"
    assert net.find(".//macsec").get("key-ref") == "arm-keys"
    # The root's own attributes, namespaces and references are kept.
    assert out.get("name") == "robot" and out.get("version") == "1.0"
    assert out.get("author-note") == "kept"
    assert out.nsmap == {"xsi": "http://www.w3.org/2001/XMLSchema-instance"}
    assert out.find("joint[@name='mount_left']/child").get("comp") == "left_arm_base"


def test_one_sub_assembly_included_twice_gives_two_distinct_sets(cli, tmp_path, two_arms):
    out, _ = flat(cli, two_arms, tmp_path)
    for kind, names in ARM_NAMES.items():
        found = [e.get("name") for e in out.findall(kind)]
        assert len(found) == len(set(found)), kind
        left = {n.removeprefix("left_arm_") for n in found if n.startswith("left_arm_")}
        right = {n.removeprefix("right_arm_") for n in found if n.startswith("right_arm_")}
        assert left == right == names, kind
    for side in ("left_arm", "right_arm"):  # each copy's joints stay inside that copy
        for j in out.findall(f"joint[@name='{side}_shoulder']"):
            assert j.find("parent").get("comp").startswith(side)
            assert j.find("child").get("comp").startswith(side)
    left_net, right_net = out.findall("network")
    assert {h.get("device") for h in left_net.iter("hop")}.isdisjoint({h.get("device") for h in right_net.iter("hop")})


def test_nested_includes_compose_prefixes(cli, tmp_path):
    root = tmp_path / "r"
    write(
        root / "hand" / "hand.hcdf",
        hcdf(
            '<comp name="palm"/><comp name="finger"/>'
            '<joint name="knuckle" type="fixed"><parent comp="palm"/>'
            '<child comp="finger"/></joint>'
        ),
    )
    write(
        root / "arm.hcdf",
        hcdf(
            '<comp name="wrist"/>'
            '<joint name="wrist_to_hand" type="fixed"><parent comp="wrist"/><child comp="hand_palm"/></joint>'
            '<group name="g"><joint ref="hand_knuckle"/></group>'
            '<include uri="hand/hand.hcdf" name="hand"/>'
        ),
    )
    doc = write(root / "robot.hcdf", hcdf('<include uri="arm.hcdf" name="left"/>'))
    out, _ = flat(cli, doc, tmp_path)
    assert {c.get("name") for c in out.findall("comp")} == {"left_wrist", "left_hand_palm", "left_hand_finger"}
    j = out.find("joint[@name='left_wrist_to_hand']")
    assert j.find("child").get("comp") == "left_hand_palm"
    assert out.find("group/joint").get("ref") == "left_hand_knuckle"
    assert check_references(out)[0] == []


# --- pose composition ------------------------------------------------------------------


def qmul(a, b):
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return (
        w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
        w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
        w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
    )


def quat(roll, pitch, yaw):
    def axis(angle, i):
        q = [math.cos(angle / 2), 0.0, 0.0, 0.0]
        q[i] = math.sin(angle / 2)
        return tuple(q)

    return qmul(axis(yaw, 3), qmul(axis(pitch, 2), axis(roll, 1)))


def rotate(q, v):
    w, x, y, z = qmul(qmul(q, (0.0, *v)), (q[0], -q[1], -q[2], -q[3]))
    return (x, y, z)


def qpose(text: str):
    x, y, z, roll, pitch, yaw = (float(v) for v in text.split())
    return quat(roll, pitch, yaw), (x, y, z)


def qcompose(outer, inner):
    (qa, ta), (qb, tb) = outer, inner
    return qmul(qa, qb), tuple(r + t for r, t in zip(rotate(qa, tb), ta, strict=True))


def assert_same_pose(actual_text: str, expected, tol: float = 1e-9) -> None:
    q, t = qpose(actual_text)
    qe, te = expected
    assert max(abs(a - b) for a, b in zip(t, te, strict=True)) < tol, (actual_text, te)
    for basis in ((1, 0, 0), (0, 1, 0), (0, 0, 1)):
        got, want = rotate(q, basis), rotate(qe, basis)
        assert max(abs(a - b) for a, b in zip(got, want, strict=True)) < tol, (actual_text, basis)


def test_include_pose_composes_onto_the_comps_own_pose(cli, tmp_path):
    root = tmp_path / "r"
    write(
        root / "sub.hcdf",
        hcdf(
            '<comp name="a"><pose>1 0 0 0 0 0</pose><description>x</description></comp>'
            '<comp name="b"/>'
            '<joint name="j" type="fixed"><parent comp="a"/><child comp="b"/></joint>'
        ),
    )
    doc = write(root / "robot.hcdf", hcdf('<include uri="sub.hcdf" name="s" pose="1 2 3 0 0 1.5707963"/>'))
    out, _ = flat(cli, doc, tmp_path)
    a = out.find("comp[@name='s_a']")
    assert a[0].tag == "pose" and len(a.findall("pose")) == 1
    x, y, z = (float(v) for v in a[0].text.split()[:3])
    theta = 1.5707963
    assert abs(x - (1 + math.cos(theta))) < 1e-9
    assert abs(y - (2 + math.sin(theta))) < 1e-9
    assert abs(z - 3) < 1e-9
    assert_same_pose(a[0].text, qcompose(qpose("1 2 3 0 0 1.5707963"), qpose("1 0 0 0 0 0")))
    # A comp that hangs off a joint moves with its parent: no pose of its own.
    assert out.find("comp[@name='s_b']/pose") is None


def test_nested_include_poses_compose_outer_then_inner(cli, tmp_path):
    p_outer, p_inner, p_comp = "0.5 -1 2 0.3 -0.7 2.1", "-0.25 0.4 0.1 -1.2 0.9 -0.4", "0.1 0.2 0.3 0.5 0.6 0.7"
    root = tmp_path / "r"
    write(root / "leaf.hcdf", hcdf(f'<comp name="tip"><pose>{p_comp}</pose></comp><comp name="bare"/>'))
    write(root / "mid.hcdf", hcdf(f'<comp name="body"/><include uri="leaf.hcdf" name="leaf" pose="{p_inner}"/>'))
    doc = write(root / "robot.hcdf", hcdf(f'<include uri="mid.hcdf" name="mid" pose="{p_outer}"/>'))
    out, _ = flat(cli, doc, tmp_path)
    poses = {c.get("name"): c.findtext("pose") for c in out.findall("comp")}
    outer, inner, own = qpose(p_outer), qpose(p_inner), qpose(p_comp)
    assert_same_pose(poses["mid_leaf_tip"], qcompose(outer, qcompose(inner, own)))
    assert_same_pose(poses["mid_leaf_bare"], qcompose(outer, inner))
    assert_same_pose(poses["mid_body"], outer)
    with pytest.raises(AssertionError):  # the check can tell the wrong order apart
        assert_same_pose(poses["mid_leaf_tip"], qcompose(inner, qcompose(outer, own)))


angles = st.floats(min_value=-math.pi, max_value=math.pi, allow_nan=False)
lengths = st.floats(min_value=-10, max_value=10, allow_nan=False)
pitches = st.one_of(
    angles, st.sampled_from([math.pi / 2, -math.pi / 2]), st.floats(min_value=math.pi / 2 - 1e-6, max_value=math.pi / 2)
)
poses = st.tuples(lengths, lengths, lengths, angles, pitches, angles)


@settings(max_examples=300, deadline=None)
@given(poses, poses)
def test_pose_composition_matches_quaternions(a, b):
    text_a, text_b = (" ".join(repr(v) for v in p) for p in (a, b))
    composed = format_pose(parse_pose(text_a).compose(parse_pose(text_b)))
    assert_same_pose(composed, qcompose(qpose(text_a), qpose(text_b)), tol=1e-9)


@settings(max_examples=200, deadline=None)
@given(angles, st.floats(min_value=1e-13, max_value=1e-7), st.sampled_from([1, -1]), angles, angles, angles)
def test_pose_composition_is_exact_near_gimbal_lock(roll, off, sign, yaw, extra_roll, extra_yaw):
    """Composites whose pitch is a hair from ±90°, where roll and yaw are ill-conditioned."""
    pitch = sign * (math.pi / 2 - off)
    text_a = f"0 0 0 {roll!r} {pitch!r} {yaw!r}"
    text_b = f"1 2 3 {extra_roll!r} 0 0"
    text_c = f"0 0 0 0 0 {extra_yaw!r}"
    composed = parse_pose(text_c).compose(parse_pose(text_a).compose(parse_pose(text_b)))
    expected = qcompose(qpose(text_c), qcompose(qpose(text_a), qpose(text_b)))
    assert_same_pose(format_pose(composed), expected, tol=1e-9)


def test_pose_errors_name_the_include(cli, tmp_path):
    root = tmp_path / "r"
    write(root / "sub.hcdf", hcdf('<comp name="a"/>'))
    doc = write(root / "robot.hcdf", hcdf('<comp name="c"/>\n<include uri="sub.hcdf" name="s" pose="1 2 3"/>'))
    err, out = fails(cli, doc, tmp_path)
    assert f"robot.hcdf:{line_of(doc, '<include')}" in err and "1 2 3" in err
    assert not out.exists()
    with pytest.raises(FlattenError):
        parse_pose("1 2 3 nan 0 0")
    assert Pose.identity().compose(parse_pose("1 2 3 0 0 0")).t == (1, 2, 3)


# --- body-frame / world-frame ------------------------------------------------------------


def test_frame_mismatch_names_both_files_and_values_and_writes_nothing(cli, tmp_path):
    root = tmp_path / "r"
    write(root / "parts" / "drone_arm.hcdf", hcdf('<comp name="a"/>', attrs=' body-frame="FRD"'))
    doc = write(root / "robot.hcdf", hcdf('<include uri="parts/drone_arm.hcdf" name="d"/>', attrs=' body-frame="FLU"'))
    err, out = fails(cli, doc, tmp_path)
    assert "body-frame" in err
    assert "robot.hcdf" in err and "parts/drone_arm.hcdf" in err
    assert '"FLU"' in err and '"FRD"' in err
    assert not out.exists()
    assert not (root / "robot.hcdf.lock").exists()


def test_frames_mismatch_across_a_silent_middle_file(cli, tmp_path):
    root = tmp_path / "r"
    write(root / "leaf.hcdf", hcdf('<comp name="a"/>', attrs=' world-frame="NED"'))
    write(root / "mid.hcdf", hcdf('<comp name="m"/><include uri="leaf.hcdf" name="l"/>'))
    doc = write(root / "robot.hcdf", hcdf('<include uri="mid.hcdf" name="m"/>', attrs=' world-frame="ENU"'))
    err, _ = fails(cli, doc, tmp_path)
    assert "world-frame" in err and "robot.hcdf" in err and "leaf.hcdf" in err and "mid.hcdf:" not in err
    assert '"ENU"' in err and '"NED"' in err


def test_sibling_includes_must_agree_even_when_the_root_is_silent(cli, tmp_path):
    root = tmp_path / "r"
    write(root / "a.hcdf", hcdf('<comp name="x"/>', attrs=' body-frame="FLU"'))
    write(root / "b.hcdf", hcdf('<comp name="x"/>', attrs=' body-frame="FRD"'))
    doc = write(root / "robot.hcdf", hcdf('<include uri="a.hcdf" name="a"/><include uri="b.hcdf" name="b"/>'))
    err, _ = fails(cli, doc, tmp_path)
    assert "a.hcdf" in err and "b.hcdf" in err and '"FLU"' in err and '"FRD"' in err


def test_a_file_that_omits_the_frames_inherits_them(cli, tmp_path):
    root = tmp_path / "r"
    write(root / "a.hcdf", hcdf('<comp name="x"/>', attrs=' body-frame="FLU" world-frame="ENU"'))
    write(root / "b.hcdf", hcdf('<comp name="y"/>'))
    doc = write(
        root / "robot.hcdf",
        hcdf('<include uri="a.hcdf" name="a"/><include uri="b.hcdf" name="b"/>', attrs=' body-frame="FLU"'),
    )
    out, _ = flat(cli, doc, tmp_path)
    assert out.get("body-frame") == "FLU" and out.get("world-frame") == "ENU"


# --- name collisions -----------------------------------------------------------------------


def test_name_collision_after_prefixing_names_both_places(cli, tmp_path):
    root = tmp_path / "r"
    sub = write(root / "arm.hcdf", hcdf('<comp name="base"/>'))
    doc = write(root / "robot.hcdf", hcdf('<comp name="arm_base"/>\n<include uri="arm.hcdf" name="arm"/>'))
    out = root / "flat.hcdf"
    out.write_bytes(b"previous flattened output\n")
    before = out.stat()
    err, _ = fails(cli, doc, tmp_path)
    assert "collision" in err and '"arm_base"' in err
    assert f"robot.hcdf:{line_of(doc, 'arm_base')}" in err
    assert f"arm.hcdf:{line_of(sub, 'base')}" in err
    assert out.read_bytes() == b"previous flattened output\n"  # untouched
    assert out.stat().st_mtime_ns == before.st_mtime_ns


def test_including_one_file_twice_without_a_name_collides(cli, tmp_path):
    root = tmp_path / "r"
    write(
        root / "arm.hcdf",
        hcdf('<comp name="base"/>\n<joint name="j" type="fixed"><parent comp="base"/><child comp="base"/></joint>'),
    )
    doc = write(root / "robot.hcdf", hcdf('<include uri="arm.hcdf"/>\n<include uri="arm.hcdf"/>'))
    err, out = fails(cli, doc, tmp_path)
    assert '<comp name="base">' in err and "arm.hcdf:" in err
    assert not out.exists()


def test_an_include_name_that_would_be_ambiguous_is_refused(cli, tmp_path):
    root = tmp_path / "r"
    write(root / "arm.hcdf", hcdf('<comp name="base"/>'))
    doc = write(root / "robot.hcdf", hcdf('<include uri="arm.hcdf" name="left/arm"/>'))
    err, out = fails(cli, doc, tmp_path)
    assert "left/arm" in err and f"robot.hcdf:{line_of(doc, '<include')}" in err
    assert not out.exists()


# --- output form ---------------------------------------------------------------------------


def test_output_is_deterministic_utf8_with_declaration(tmp_path, two_arms):
    (two_arms.parent / "parts" / "arm.hcdf").write_text(
        ARM.replace('<comp name="cam">', '<comp name="cam"><description>Kamera, 90° Sicht</description>').replace(
            "Arm Works", "Armwerk Zürich"
        ),
        encoding="utf-8",
    )
    runs = [flatten(resolve(two_arms, ResolveOptions(cache_dir=str(tmp_path / f"c{i}")))) for i in range(2)]
    assert runs[0] == runs[1]
    assert runs[0].startswith(b'<?xml version="1.0" encoding="UTF-8"?>\n')
    text = runs[0].decode("utf-8")
    assert text.count("<description>Kamera, 90° Sicht</description>") == 2
    assert 'author "Armwerk Zürich"' in text  # the included file's metadata, as provenance
    assert hashlib.sha256(runs[0]).hexdigest() == hashlib.sha256(runs[1]).hexdigest()


def test_comments_travel_with_their_elements(cli, tmp_path, two_arms):
    _, data = flat(cli, two_arms, tmp_path)
    text = data.decode()
    assert text.count("<!-- the arm's base -->") == 2
    for side in ("left_arm", "right_arm"):
        assert f'<!-- the arm\'s base -->\n  <comp name="{side}_base">' in text
    assert 'module "2link-arm"' in text and 'author "Arm Works"' in text  # provenance


def test_file_references_are_rebased_so_the_output_resolves_to_the_same_files(cli, tmp_path):
    root = tmp_path / "r"
    glb = b"glTF-stand-in"
    write(root / "parts" / "meshes" / "shell.glb", "")
    (root / "parts" / "meshes" / "shell.glb").write_bytes(glb)
    pin = hashlib.sha256(glb).hexdigest()
    write(
        root / "parts" / "arm.hcdf",
        hcdf(f'<comp name="base"><visual name="v"><model uri="meshes/shell.glb" sha="{pin}"/></visual></comp>'),
    )
    doc = write(root / "robot.hcdf", hcdf('<include uri="parts/arm.hcdf" name="a"/>'))
    out, data = flat(cli, doc, tmp_path)
    assert out.find(".//model").get("uri") == "parts/meshes/shell.glb"
    again = cli("resolve", root / "flat.hcdf", "--cache-dir", tmp_path / "cache", "--no-lock", "--json")
    assert again.exit_code == 0, again.stderr
    arts = {(a["kind"], a["sha256"]) for a in again.json["artifacts"]}
    assert arts == {("model", pin)}


def test_flattened_valid_inputs_are_valid_hcdf(cli, tmp_path):
    """Schema order is restored and self-collision-disable merged into one element."""
    schema = etree.XMLSchema(etree.parse(str(HCDFORMAT / "hcdf.xsd")))
    root = tmp_path / "r"
    sub = write(
        root / "leg.hcdf",
        hcdf(
            '<comp name="hip"/><comp name="knee"/>'
            '<joint name="j" type="fixed"><parent comp="hip"/><child comp="knee"/></joint>'
            '<self-collision-disable><pair comp1="hip" comp2="knee"/></self-collision-disable>'
            '<material name="steel"/>',
            attrs=' body-frame="FLU"',
        ),
    )
    doc = write(
        root / "robot.hcdf",
        hcdf(
            '<description>robot</description><comp name="torso"/>'
            '<joint name="hip_l" type="fixed"><parent comp="torso"/><child comp="l_hip"/></joint>'
            '<self-collision-disable><pair comp1="torso" comp2="l_hip"/></self-collision-disable>'
            '<material name="steel"/>'
            '<include uri="leg.hcdf" name="l"/><include uri="leg.hcdf" name="r"/>'
        ),
    )
    assert schema.validate(etree.parse(str(sub))) and schema.validate(etree.parse(str(doc)))
    out, data = flat(cli, doc, tmp_path)
    assert schema.validate(etree.fromstring(data).getroottree()), schema.error_log
    assert [e.tag for e in out if isinstance(e.tag, str)] == (
        ["description"] + ["comp"] * 5 + ["joint"] * 3 + ["self-collision-disable"] + ["material"] * 3
    )
    assert len(out.findall("self-collision-disable/pair")) == 3


def test_an_include_outside_the_document_level_is_refused(cli, tmp_path):
    root = tmp_path / "r"
    write(root / "arm.hcdf", hcdf('<comp name="base"/>'))
    doc = write(root / "robot.hcdf", hcdf('<comp name="c">\n<include uri="arm.hcdf" name="a"/></comp>'))
    err, out = fails(cli, doc, tmp_path)
    assert "child of <hcdf>" in err and f"robot.hcdf:{line_of(doc, '<include')}" in err
    assert not out.exists()


def test_a_document_without_includes_flattens_to_the_same_content(cli, tmp_path):
    """The upstream humanoid (5 networks, MACsec, 19 devices) loses nothing but layout."""
    examples = tmp_path / "examples"
    shutil.copytree(HCDFORMAT / "examples", examples)
    source = examples / "humanoid-mobile-base.hcdf"
    out = examples / "flat.hcdf"  # beside the source, so relative references stay as written
    r = cli("resolve", source, "--cache-dir", tmp_path / "c", "--no-lock", "--out", out)
    assert r.exit_code == 0, r.stderr
    parser = etree.XMLParser(remove_blank_text=True)
    original, flattened = etree.parse(str(source), parser), etree.parse(str(out), parser)
    for tree in (original, flattened):
        for el in tree.getroot().iter():
            if el.text is not None and not el.text.strip():
                el.text = None
    assert etree.tostring(flattened, method="c14n") == etree.tostring(original, method="c14n")
