"""The semantic rules, one failing fixture and one passing fixture each.

``BASE`` is a small robot that is valid against hcdf.xsd and breaks no rule;
each failing case applies one textual mutation to it (checked to apply exactly
once) and expects its rule's code on the mutated line, and no other error.
"""

from __future__ import annotations

import pytest

from hcdf_trust.validate import semantic, validate_document
from hcdf_trust.xml import parse_bytes

from .conftest import HCDFORMAT

BASE = """<?xml version="1.0"?>
<hcdf version="1.0" name="fixture" body-frame="FLU" world-frame="ENU">
  <comp name="a">
    <switch>
      <port name="sw0" type="ethernet">
        <capabilities>
          <standard>802.3dm</standard>
          <phy role="master"/>
        </capabilities>
      </port>
      <macsec><cipher>gcm-aes-128</cipher><cipher>gcm-aes-256</cipher></macsec>
    </switch>
    <port name="eth0" type="ethernet">
      <capabilities>
        <standard>100base-t1</standard>
        <phy role="master"/>
        <macsec><cipher>gcm-aes-128</cipher></macsec>
      </capabilities>
    </port>
    <port name="eth2" type="ethernet">
      <capabilities>
        <standard>2.5GBASE-T1</standard>
        <phy role="master"/>
      </capabilities>
    </port>
    <port name="can0" type="CAN"/>
    <antenna name="ant" type="wifi"/>
    <motor name="m1" type="bldc"/>
  </comp>
  <comp name="b">
    <port name="eth0" type="ethernet">
      <capabilities>
        <standard>100base-t1</standard>
        <phy role="slave"/>
        <macsec><cipher>gcm-aes-128</cipher></macsec>
      </capabilities>
    </port>
    <port name="eth1" type="ethernet">
      <capabilities>
        <standard>802.3dm</standard>
        <phy role="slave"/>
      </capabilities>
    </port>
    <port name="eth2" type="ethernet">
      <capabilities>
        <standard>2.5GBASE-T1</standard>
        <phy role="slave"/>
      </capabilities>
    </port>
    <port name="can0" type="CAN"/>
    <antenna name="ant" type="wifi"/>
  </comp>
  <joint name="j1" type="revolute">
    <parent comp="a"/>
    <child comp="b"/>
    <axis xyz="0 0 1"/>
    <limit lower="-1.5" upper="1.5"/>
  </joint>
  <joint name="j2" type="fixed">
    <parent comp="a"/>
    <child comp="b"/>
  </joint>
  <joint name="j3" type="continuous">
    <parent comp="a"/>
    <child comp="b"/>
    <axis xyz="1 0 0"/>
    <mimic joint="j1" multiplier="-1"/>
  </joint>
  <joint name="j4" type="universal">
    <parent comp="a"/>
    <child comp="b"/>
    <axis xyz="1 0 0"/>
    <axis2 xyz="0 1 0"/>
  </joint>
  <joint name="j5" type="screw" thread_pitch="0.002">
    <parent comp="a"/>
    <child comp="b"/>
    <axis xyz="0 0 1"/>
  </joint>
  <group name="g1" type="kinematic-chain">
    <joint ref="j1"/>
  </group>
  <group name="g2" tip-comp="b">
    <group ref="g1"/>
  </group>
  <state name="home">
    <joint-position joint="j1" value="0"/>
  </state>
  <self-collision-disable>
    <pair comp1="a" comp2="b"/>
  </self-collision-disable>
  <network name="n">
    <link name="l1">
      <wired standard="100base-t1">
        <port>a/eth0</port>
        <port>b/eth0</port>
        <macsec policy="must-secure" cipher="gcm-aes-128" key-ref="k1"/>
      </wired>
    </link>
    <link name="l2">
      <wired standard="2.5gbase-t1">
        <port>a/eth2</port>
        <port>b/eth2</port>
      </wired>
    </link>
    <link name="w1">
      <wireless standard="802.11ax">
        <antenna>a/ant</antenna>
        <antenna>b/ant</antenna>
      </wireless>
    </link>
    <bus name="can" type="CAN">
      <participant device="a" port="can0"/>
      <participant device="b" port="can0"/>
    </bus>
    <chain name="c" type="802.3dm">
      <macsec policy="must-secure" key-ref="k2"/>
      <hop device="a" port="sw0" role="root"/>
      <hop device="b" ingress="eth1" role="tail"/>
    </chain>
    <mesh name="m" standard="802.15.4">
      <node device="a" antenna="ant"/>
      <node device="b" antenna="ant"/>
    </mesh>
    <gptp domain="0">
      <clock device="a" port="eth0" gm-capable="true"/>
    </gptp>
    <schedule name="s1" cycle-time-us="1000">
      <gate tc-mask="0x80" duration-us="400"/>
      <gate tc-mask="0x7F" duration-us="600"/>
    </schedule>
    <schedule-assignment>
      <assign schedule="s1" ports="a/eth0 b/eth0" chains="c"/>
    </schedule-assignment>
    <macsec policy="must-secure" cipher="gcm-aes-128"/>
  </network>
  <transmission name="t1" type="planetary">
    <motor ref="a.m1"/>
    <joint ref="j1"/>
  </transmission>
</hcdf>
"""


def mutate(text: str, old: str, new: str) -> str:
    assert text.count(old) == 1, f"{old!r} occurs {text.count(old)} times in the fixture"
    return text.replace(old, new)


def line_of(text: str, needle: str, nth: int | None = None) -> int:
    """The line of ``needle``: it must be unique, unless ``nth`` picks an occurrence."""
    lines = [i for i, line in enumerate(text.splitlines(), 1) if needle in line]
    if nth is None:
        assert len(lines) == 1, f"{needle!r} occurs on {len(lines)} lines"
        return lines[0]
    return lines[nth - 1]


def findings(text: str):
    root = parse_bytes(text.encode(), source="t.hcdf").getroot()
    return semantic.check(root, source="t.hcdf").findings


def test_base_fixture_is_schema_valid_and_breaks_no_rule(tmp_path):
    path = tmp_path / "base.hcdf"
    path.write_text(BASE)
    report = validate_document(path, schema=HCDFORMAT / "hcdf.xsd")
    assert report.checked == ["xsd", "semantic"]
    assert [str(f) for f in report.findings] == []
    assert any("8 written comp/port, 0 written comp.port" in n for n in report.notes), report.notes


# (rule code, severity, old text, new text, the line the first finding must point at:
#  a text that is unique in the mutated document, or (text, nth occurrence))
FAILING = [
    (
        "unresolved-comp",
        "error",
        '<joint name="j1" type="revolute">\n    <parent comp="a"/>',
        '<joint name="j1" type="revolute">\n    <parent comp="zz"/>',
        'comp="zz"',
    ),
    ("unresolved-comp", "error", '<pair comp1="a"', '<pair comp1="zz"', "<pair"),
    ("unresolved-comp", "error", 'tip-comp="b"', 'tip-comp="zz"', "tip-comp"),
    ("unresolved-device", "error", '<participant device="b"', '<participant device="zz"', 'device="zz"'),
    ("unresolved-device", "error", '<hop device="b"', '<hop device="zz"', 'device="zz"'),
    ("unresolved-device", "error", '<node device="b"', '<node device="zz"', 'device="zz"'),
    ("unresolved-port", "error", "<port>a/eth0</port>", "<port>a/eth9</port>", "a/eth9"),
    ("unresolved-port", "error", "<port>b/eth0</port>", "<port>zz/eth0</port>", "zz/eth0"),
    ("unresolved-port", "error", '<clock device="a" port="eth0"', '<clock device="a" port="nope"', "nope"),
    ("unresolved-port", "error", 'ingress="eth1"', 'ingress="eth7"', "eth7"),
    ("unresolved-port", "error", 'ports="a/eth0 b/eth0"', 'ports="a/eth0 b/eth5"', "b/eth5"),
    ("unresolved-port", "error", '<participant device="a" port="can0"', '<participant device="a" port="can9"', "can9"),
    ("unresolved-antenna", "error", "<antenna>b/ant</antenna>", "<antenna>b/nope</antenna>", "b/nope"),
    ("unresolved-antenna", "error", '<node device="a" antenna="ant"', '<node device="a" antenna="x"', 'antenna="x"'),
    ("unresolved-joint", "error", '<mimic joint="j1"', '<mimic joint="j9"', "<mimic"),
    ("unresolved-joint", "error", '<joint-position joint="j1"', '<joint-position joint="j9"', "joint-position"),
    ("unresolved-joint", "error", '<joint ref="j1"/>\n  </group>', '<joint ref="j9"/>\n  </group>', 'ref="j9"'),
    (
        "unresolved-joint",
        "error",
        '<joint ref="j1"/>\n  </transmission>',
        '<joint ref="j9"/>\n  </transmission>',
        'ref="j9"',
    ),
    ("unresolved-motor", "error", '<motor ref="a.m1"/>', '<motor ref="a.m9"/>', "a.m9"),
    ("unresolved-motor", "error", '<motor ref="a.m1"/>', '<motor ref="m9"/>', 'ref="m9"'),
    ("unresolved-group", "error", '<group ref="g1"/>', '<group ref="g9"/>', 'ref="g9"'),
    ("unresolved-schedule", "error", '<assign schedule="s1"', '<assign schedule="s9"', "<assign"),
    ("unresolved-chain", "error", 'chains="c"', 'chains="c d"', "<assign"),
    ("duplicate-name", "error", '<comp name="b">', '<comp name="a"/>\n  <comp name="b">', ('<comp name="a"', 2)),
    ("duplicate-name", "error", '<joint name="j2"', '<joint name="j1"', ('<joint name="j1"', 2)),
    ("schedule-cycle-mismatch", "error", 'duration-us="600"', 'duration-us="500"', "<schedule "),
    (
        "t1-phy-roles",
        "error",  # both ends master
        '<standard>100base-t1</standard>\n        <phy role="slave"/>',
        '<standard>100base-t1</standard>\n        <phy role="master"/>',
        '<wired standard="100base-t1">',
    ),
    (
        "t1-phy-roles",
        "warning",
        '<standard>100base-t1</standard>\n        <phy role="slave"/>',
        '<standard>100base-t1</standard>\n        <phy role="auto"/>',
        '<wired standard="100base-t1">',
    ),
    (
        "t1-phy-roles",
        "error",  # a T1 chain segment: hop a/sw0 -> hop b/eth1, both slave
        '<standard>802.3dm</standard>\n          <phy role="master"/>',
        '<standard>802.3dm</standard>\n          <phy role="slave"/>',
        '<hop device="b"',
    ),
    (
        "t1-phy-role-missing",
        "error",
        '<standard>100base-t1</standard>\n        <phy role="slave"/>',
        "<standard>100base-t1</standard>",
        '<wired standard="100base-t1">',
    ),
    (
        "t1-phy-role-missing",
        "warning",  # 2.5GBASE-T1: the schema does not require the role
        '<standard>2.5GBASE-T1</standard>\n        <phy role="slave"/>',
        "<standard>2.5GBASE-T1</standard>",
        '<wired standard="2.5gbase-t1">',
    ),
    ("joint-limit-order", "error", 'lower="-1.5" upper="1.5"', 'lower="1.5" upper="-1.5"', "<limit"),
    ("joint-requires", "error", '    <limit lower="-1.5" upper="1.5"/>\n', "", '<joint name="j1"'),
    (
        "joint-requires",
        "error",
        '<joint name="j2" type="fixed">',
        '<joint name="j2" type="prismatic">',
        '<joint name="j2"',
    ),
    (
        "joint-requires",
        "error",
        '<joint name="j2" type="fixed">',
        '<joint name="j2" type="cylindrical">',
        '<joint name="j2"',
    ),
    ("joint-requires", "error", '<axis xyz="1 0 0"/>\n    <mimic', "<mimic", '<joint name="j3"'),
    ("joint-requires", "error", '    <axis2 xyz="0 1 0"/>\n', "", '<joint name="j4"'),
    ("joint-requires", "error", ' thread_pitch="0.002"', "", '<joint name="j5"'),
    (
        "joint-forbids",
        "error",
        '<child comp="b"/>\n  </joint>\n  <joint name="j3"',
        '<child comp="b"/>\n    <axis xyz="0 1 1"/>\n  </joint>\n  <joint name="j3"',
        '<axis xyz="0 1 1"/>',
    ),
    (
        "joint-forbids",
        "error",
        '<joint name="j1" type="revolute">',
        '<joint name="j1" type="free">',
        ('<axis xyz="0 0 1"/>', 1),
    ),
    ("joint-ignored", "warning", '<joint name="j4" type="universal">', '<joint name="j4" type="ball">', "<axis2"),
    (
        "joint-ignored",
        "warning",
        '<joint name="j5" type="screw"',
        '<joint name="j5" type="continuous"',
        '<joint name="j5"',
    ),
    (
        "macsec-key-ref-conflict",
        "error",
        'policy="must-secure" key-ref="k2"',
        'policy="must-secure" cipher="gcm-aes-256" key-ref="k1"',
        'cipher="gcm-aes-256" key-ref="k1"',
    ),
    (
        "macsec-key-ref-conflict",
        "error",
        'policy="must-secure" key-ref="k2"',
        'policy="should-secure" cipher="gcm-aes-128" key-ref="k1"',
        'policy="should-secure"',
    ),
    (
        "macsec-cipher-unsupported",
        "warning",
        'cipher="gcm-aes-128" key-ref="k1"',
        'cipher="gcm-aes-256" key-ref="k1"',
        'cipher="gcm-aes-256" key-ref="k1"',
    ),
    ("port-ref-form-mixed", "warning", "<port>b/eth0</port>", "<port>b.eth0</port>", "b.eth0"),
]


def _case_id(case: tuple) -> str:
    at = case[4] if isinstance(case[4], str) else case[4][0]
    return f"{case[0]}:{at[:28]}"


@pytest.mark.parametrize("case", FAILING, ids=_case_id)
def test_rule_fails(case):
    code, severity, old, new, at = case
    text = mutate(BASE, old, new)
    found = findings(text)
    hits = [f for f in found if f.code == code]
    assert hits, [str(f) for f in found]
    assert {f.severity for f in hits} == {severity}, [str(f) for f in hits]
    needle, nth = (at, None) if isinstance(at, str) else at
    assert hits[0].line == line_of(text, needle, nth), str(hits[0])
    assert hits[0].file == "t.hcdf"
    others = [str(f) for f in found if f.code != code and f.is_error]
    assert not others, "collateral errors from other rules"


CHAIN_EXTRAS = '<macsec policy="must-secure" key-ref="k2"/>\n      {}\n      <hop device="a"'
LOOP = '<mimic joint="j1" multiplier="-1"/>'
BUS = '<bus name="can" type="CAN">'


@pytest.mark.parametrize(
    "where, insert, code",
    [
        (CHAIN_EXTRAS, '<dc reference-clock="a"/><tunnel chain="c" hop="b"/>', None),
        (CHAIN_EXTRAS, '<dc reference-clock="zz"/>', "unresolved-device"),
        (CHAIN_EXTRAS, '<tunnel chain="zz" hop="a"/>', "unresolved-chain"),
        (CHAIN_EXTRAS, '<tunnel chain="c" hop="zz"/>', "unresolved-device"),
        (LOOP, "<loop><predecessor>a</predecessor><successor>b</successor></loop>", None),
        (LOOP, "<loop><predecessor>a</predecessor><successor>zz</successor></loop>", "unresolved-comp"),
        (BUS, '<plca><coordinator device="a" port="can0"/></plca>', None),
        (BUS, '<plca><coordinator device="a" port="nope"/></plca>', "unresolved-port"),
    ],
    ids=lambda v: v if isinstance(v, str) and not v.startswith("<") else None,
)
def test_less_common_references(where, insert, code):
    old = where.format("").replace("\n      \n", "\n") if "{}" in where else where
    new = where.format(insert) if "{}" in where else f"{where}\n    {insert}"
    text = mutate(BASE, old, new)
    found = [(f.code, f.severity) for f in findings(text)]
    assert found == ([] if code is None else [(code, "error")]), found


def test_dot_form_port_reference_resolves_and_is_reported():
    text = mutate(BASE, 'ports="a/eth0 b/eth0"', 'ports="a.eth0 b.eth0"')
    root = parse_bytes(text.encode(), source="t.hcdf").getroot()
    result = semantic.check(root, source="t.hcdf")
    assert not [f for f in result.findings if f.code.startswith("unresolved")]
    assert [f.code for f in result.findings] == ["port-ref-form-mixed"]
    assert any("6 written comp/port, 2 written comp.port" in n for n in result.notes)
    wrong = findings(mutate(BASE, "<port>a/eth0</port>", "<port>a.eth9</port>"))
    assert any("(comp.port form)" in f.message for f in wrong if f.code == "unresolved-port")


def test_port_reference_without_comp_is_an_error():
    found = findings(mutate(BASE, "<port>a/eth0</port>", "<port>eth0</port>"))
    assert [(f.code, f.severity) for f in found] == [("unresolved-port", "error")]


def test_dotted_names_pick_the_split_that_resolves():
    text = mutate(BASE, '<comp name="b">', '<comp name="b.x">')
    for attr in ("comp", "comp2", "tip-comp", "device"):
        text = text.replace(f'{attr}="b"', f'{attr}="b.x"')
    text = text.replace("b/eth0", "b.x.eth0").replace("b/eth2", "b.x.eth2").replace("b/ant", "b.x/ant")
    found = [f for f in findings(text) if f.is_error]
    assert not found, [str(f) for f in found]


def test_non_t1_link_is_not_judged():
    text = mutate(BASE, '<wired standard="100base-t1">', '<wired standard="1000base-t">')
    text = mutate(
        text,
        '<standard>100base-t1</standard>\n        <phy role="slave"/>',
        '<standard>100base-t1</standard>\n        <phy role="master"/>',
    )
    assert not findings(text)


def test_continuous_joint_limits_are_not_ordered():
    limit = '<axis xyz="1 0 0"/>\n    <limit lower="1" upper="-1"/>\n    <mimic'
    text = mutate(BASE, '<axis xyz="1 0 0"/>\n    <mimic', limit)
    assert not findings(text)


def test_key_ref_default_cipher_equals_explicit_default():
    # k1 on the link says gcm-aes-128 explicitly; the chain says nothing (schema default gcm-aes-128)
    assert not findings(mutate(BASE, 'key-ref="k2"', 'key-ref="k1"'))


def test_macsec_cipher_from_network_default_and_switch():
    # the link inherits the network's cipher: gcm-aes-256 is not declared by a/eth0 or b/eth0
    text = mutate(BASE, '\n        <macsec policy="must-secure" cipher="gcm-aes-128" key-ref="k1"/>', "")
    text = mutate(
        text,
        '<macsec policy="must-secure" cipher="gcm-aes-128"/>\n  </network>',
        '<macsec policy="must-secure" cipher="gcm-aes-256"/>\n  </network>',
    )
    found = findings(text)
    warned = sorted(f.message.split("port ")[-1] for f in found if f.code == "macsec-cipher-unsupported")
    # a/sw0 inherits its switch's list (128 and 256), so only the link's two ports are warned about
    assert warned == ["a/eth0 declares only gcm-aes-128", "b/eth0 declares only gcm-aes-128"], warned
    assert all("network 'n' default" in f.message for f in found if f.code == "macsec-cipher-unsupported")
    # a disabled policy is not judged
    disabled = text.replace('policy="must-secure" cipher="gcm-aes-256"', 'policy="disabled" cipher="gcm-aes-256"')
    assert not findings(disabled)


def test_names_that_may_come_from_an_include_are_warnings():
    text = mutate(BASE, "  </transmission>\n", '  </transmission>\n  <include uri="arm.hcdf" name="arm"/>\n')
    text = mutate(text, '<pair comp1="a"', '<pair comp1="arm_base"')
    found = findings(text)
    assert [(f.code, f.severity) for f in found] == [("unresolved-comp", "warning")]
    assert "may come from the include of 'arm.hcdf'" in found[0].message
    # a name the include's prefix cannot produce is still an error
    found = findings(text.replace('comp1="arm_base"', 'comp1="leg_base"'))
    assert [(f.code, f.severity) for f in found] == [("unresolved-comp", "error")]


def test_every_error_is_collected():
    text = BASE
    for old, new in [
        ('<mimic joint="j1"', '<mimic joint="j9"'),
        ('duration-us="600"', 'duration-us="1"'),
        ('lower="-1.5" upper="1.5"', 'lower="2" upper="1"'),
        ("<port>a/eth0</port>", "<port>a/x</port>"),
    ]:
        text = mutate(text, old, new)
    codes = sorted(f.code for f in findings(text) if f.is_error)
    assert codes == ["joint-limit-order", "schedule-cycle-mismatch", "unresolved-joint", "unresolved-port"]


# --- frame conventions across the include chain (reads files) ----------------------

SUB = '<?xml version="1.0"?>\n<hcdf version="1.0" name="sub"{frames}>\n  <comp name="s"/>\n{includes}</hcdf>\n'


def _write(path, frames="", includes=""):
    path.write_text(SUB.format(frames=frames, includes=includes))
    return path


def _frame_findings(report):
    return [(f.code, f.severity, f.file.rsplit("/", 1)[-1], f.line) for f in report.findings]


def test_frames_agree_across_includes(tmp_path):
    _write(tmp_path / "arm.hcdf", ' body-frame="FLU" world-frame="ENU"')
    root = _write(tmp_path / "root.hcdf", ' body-frame="FLU" world-frame="ENU"', '  <include uri="arm.hcdf"/>\n')
    assert validate_document(root).findings == []


def test_frame_mismatch_in_an_include_is_an_error(tmp_path):
    _write(tmp_path / "arm.hcdf", ' body-frame="FRD" world-frame="ENU"')
    root = _write(tmp_path / "root.hcdf", ' body-frame="FLU" world-frame="ENU"', '  <include uri="arm.hcdf"/>\n')
    report = validate_document(root)
    assert _frame_findings(report) == [("frame-convention-mismatch", "error", "root.hcdf", 4)]
    assert "body-frame=FRD" in report.findings[0].message and "FLU" in report.findings[0].message


def test_frame_mismatch_two_levels_down_is_found_through_an_unset_file(tmp_path):
    (tmp_path / "parts").mkdir()
    _write(tmp_path / "parts" / "hand.hcdf", ' body-frame="FRD"')
    _write(tmp_path / "arm.hcdf", "", '  <include uri="parts/hand.hcdf"/>\n')
    root = _write(tmp_path / "root.hcdf", ' body-frame="FLU"', '  <include uri="arm.hcdf"/>\n')
    # arm.hcdf declares nothing and inherits FLU (as flattening does): hand.hcdf's FRD is the conflict
    assert _frame_findings(validate_document(root)) == [("frame-convention-mismatch", "error", "arm.hcdf", 4)]


def test_first_declaring_file_sets_the_chain_value(tmp_path):
    _write(tmp_path / "a.hcdf", ' world-frame="NED"')
    _write(tmp_path / "b.hcdf", ' world-frame="ENU"')
    root = _write(tmp_path / "root.hcdf", "", '  <include uri="a.hcdf"/>\n  <include uri="b.hcdf"/>\n')
    report = validate_document(root)
    assert _frame_findings(report) == [("frame-convention-mismatch", "error", "root.hcdf", 5)]
    assert "a.hcdf declares world-frame=NED" in report.findings[0].message


def test_includes_that_cannot_be_read_are_reported_and_hostile_ones_refused(tmp_path):
    includes = (
        '  <include uri="missing.hcdf"/>\n  <include uri="../outside.hcdf"/>\n'
        '  <include uri="https://example.invalid/x.hcdf"/>\n'
    )
    root = _write(tmp_path / "root.hcdf", ' body-frame="FLU"', includes)
    report = validate_document(root)
    assert [(c, s) for c, s, _, _ in _frame_findings(report)] == [
        ("include-unchecked", "warning"),
        ("include-refused", "error"),  # a path out of the root: resolve refuses it too
        ("include-unchecked", "warning"),
    ]
    assert [f.line for f in report.findings] == [4, 5, 6]
    assert not report.ok


def test_include_cycle_terminates(tmp_path):
    _write(tmp_path / "a.hcdf", ' body-frame="FLU"', '  <include uri="root.hcdf"/>\n')
    root = _write(tmp_path / "root.hcdf", ' body-frame="FLU"', '  <include uri="a.hcdf"/>\n')
    report = validate_document(root)
    assert _frame_findings(report) == [("include-unchecked", "warning", "a.hcdf", 4)]
    assert "include cycle" in report.findings[0].message


# --- names brought by includes, prefixed as flattening prefixes them -------------------

ARM = """<?xml version="1.0"?>
<hcdf version="1.0" name="arm">
  <comp name="shoulder">
    <port name="eth0" type="ethernet">
      <capabilities><standard>100base-t1</standard><phy role="{role}"/></capabilities>
    </port>
  </comp>
  <comp name="upper"/>
  <joint name="pitch" type="fixed"><parent comp="shoulder"/><child comp="upper"/></joint>
  <include uri="hand.hcdf" name="hand"/>
</hcdf>
"""
HAND = '<?xml version="1.0"?>\n<hcdf version="1.0" name="hand">\n  <comp name="palm"/>\n</hcdf>\n'
ROBOT = """<?xml version="1.0"?>
<hcdf version="1.0" name="robot">
  <comp name="torso"/>
  <joint name="mount_left" type="fixed"><parent comp="torso"/><child comp="left_arm_shoulder"/></joint>
  <joint name="mount_right" type="fixed"><parent comp="torso"/><child comp="right_arm_shoulder"/></joint>
  <joint name="grip" type="fixed"><parent comp="torso"/><child comp="left_arm_hand_palm"/></joint>
  <group name="arms"><joint ref="left_arm_pitch"/><joint ref="right_arm_pitch"/></group>
  <network name="n">
    <link name="l">
      <wired standard="100base-t1"><port>left_arm_shoulder/eth0</port><port>right_arm_shoulder/eth0</port></wired>
    </link>
  </network>
  <include uri="arm.hcdf" name="left_arm"/>
  <include uri="arm.hcdf" name="right_arm"/>
  <include uri="missing.hcdf" name="leg"/>
</hcdf>
"""


def _robot(tmp_path, text=ROBOT, role="master"):
    (tmp_path / "arm.hcdf").write_text(ARM.format(role=role))
    (tmp_path / "hand.hcdf").write_text(HAND)
    path = tmp_path / "robot.hcdf"
    path.write_text(text)
    return path


def test_names_from_readable_includes_resolve_with_the_flatten_prefix(tmp_path):
    report = validate_document(_robot(tmp_path))
    # every prefixed comp, nested prefix, port and joint resolves; the ports come from the
    # included file, so the T1 rule sees both ends are PHY master
    assert [(f.code, f.severity) for f in report.findings] == [
        ("t1-phy-roles", "error"),
        ("include-unchecked", "warning"),
    ]
    assert "left_arm_shoulder/eth0 is master, right_arm_shoulder/eth0 is master" in report.findings[0].message


def test_names_a_readable_include_does_not_define_are_errors(tmp_path):
    text = mutate(ROBOT, 'child comp="left_arm_hand_palm"', 'child comp="left_arm_hand_wrist"')
    text = mutate(text, '<joint ref="right_arm_pitch"/>', '<joint ref="leg_knee"/>')
    found = [(f.code, f.severity, f.line) for f in validate_document(_robot(tmp_path, text)).findings]
    assert ("unresolved-comp", "error", 6) in found  # arm.hcdf was read: no 'hand_wrist' in it
    assert ("unresolved-joint", "warning", 7) in found  # missing.hcdf (prefix leg_) was not read
