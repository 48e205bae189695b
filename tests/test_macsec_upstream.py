"""macsec over HCDF as upstream writes it since April 2026 (issue 18): top-level <link>, <bus>,
<chain>, <star>… with <configuration><macsec><policy>/<default-policy>/<override>.

The documents are in tests/macsec_upstream/, each saying which upstream file it is modeled on.
"""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest

from hcdf_trust.macsec.connectivity import store_kind
from hcdf_trust.macsec.plan import plan

from ._macsec import lock

DOCS = Path(__file__).parent / "macsec_upstream"
PASS = b"upstream dialect passphrase"


def _doc(tmp: Path, name: str, *edits: tuple[str, str]) -> Path:
    """A copy of test document ``name`` (with text replacements), locked."""
    doc = tmp / name
    text = (DOCS / name).read_text()
    for old, new in edits:
        assert old in text, old
        text = text.replace(old, new)
    doc.write_text(text)
    return lock(doc)


def _line(doc: Path, text: str) -> int:
    return next(n for n, line in enumerate(doc.read_text().splitlines(), 1) if text in line)


@pytest.fixture
def keys(tmp_path):
    pp = tmp_path / "pass"
    pp.write_bytes(PASS)
    return ["--store", tmp_path / "keys", "--passphrase-file", pp]


# --- fail closed: MACsec policy is never "0 to key" ------------------------------------------------


def test_macsec_this_planner_cannot_read_is_an_error_not_nothing_to_key(tmp_path, cli, keys):
    # a <macsec> somewhere no reader consumes (here: under a <comp>, not a port's capabilities)
    doc = _doc(tmp_path, "chain-must-secure.hcdf", ('<comp name="tail-board">', '<comp name="tail-board"><macsec/>'))
    for verb in (
        ["plan"],
        ["generate", *keys],
        ["export", *keys, "--device", "tail-board", "--format", "json", "--out", tmp_path / "o"],
    ):
        r = cli("macsec", verb[0], doc, *verb[1:], "--json")
        assert r.exit_code == 3, (verb, r.stdout)
        assert any(
            "not read by this planner" in e["message"] and e["line"] == _line(doc, "<macsec/>")
            for e in r.json["errors"]
        ), r.json
    assert not (tmp_path / "o").exists() and not (tmp_path / "keys").exists()


# --- the associations a MACsec engineer would draw ----------------------------------------------


def _cas(p) -> dict[str, tuple]:
    out = {}
    for ca in p.associations.values():
        pol = ca.policy
        members = tuple(sorted((m.device, tuple(m.ports)) for m in ca.members.values()))
        out[ca.id] = (members, pol.policy, pol.cipher, pol.key_agreement, pol.rekey_interval_sec,
                      pol.key_store_type, pol.key_store_ref)  # fmt: skip
    return out


def test_the_humanoid_backbone(tmp_path):
    p = plan(_doc(tmp_path, "humanoid-backbone.hcdf"))
    se = ("must-secure", "gcm-aes-128", "psk", 3600, "secure-element", "se051")
    assert _cas(p) == {
        "link:s32n79_to_thor_p0": (
            (("agx-thor", ("mgbe0",)), ("s32n79", ("e810_p0",))),
            "must-secure", "gcm-aes-256", "psk", 3600, "tpm", "tpm0",
        ),
        "link:n79_to_j100_p0": ((("s32j100", ("eth_up0",)), ("s32n79", ("qxgmii_p0",))), *se),
        "leg:left-arm-chain/s32n79-to-mcn1-l": ((("mcn1-l", ("eth0",)), ("s32n79", ("xfi_left",))), *se),
        "leg:left-arm-chain/mcn1-l-to-mcn2-l": ((("mcn1-l", ("eth1",)), ("mcn2-l", ("eth0",))), *se),
    }  # fmt: skip
    assert [e.label for e in p.unprotected] == ["bus:base_can"]
    assert [(e.label, why) for e, why in p.skipped] == [("bus:power_bus", "not a communication network")]
    # the 25 Gb/s link's packet numbers: the selected rate, read by the one rate reader
    assert p.associations["link:s32n79_to_thor_p0"].max_speed_mbps == 25000
    assert [w.code for w in p.warnings] == ["macsec-pn-exhaustion"]


def test_a_chain_default_policy_and_a_leg_override(tmp_path):
    p = plan(_doc(tmp_path, "chain-must-secure.hcdf"))
    assert _cas(p) == {
        "leg:test-chain/parent-to-board": (
            (("parent-body", ("eth0",)), ("test-board", ("eth0",))),
            "must-secure", "gcm-aes-128", "psk", None, "secure-element", "se051",
        ),
        "leg:test-chain/board-to-tail": (
            (("tail-board", ("eth0",)), ("test-board", ("eth1",))),
            "should-secure", "gcm-aes-256", "psk", 3600, "tpm", "tpm0",
        ),
    }  # fmt: skip
    assert {e.label for e in p.unprotected} == {"link:test_link", "bus:test_can"}
    # the chain runs at its selected 100 Mb/s, whatever the ports could do
    assert p.associations["leg:test-chain/parent-to-board"].max_speed_mbps == 100


def test_a_bus_a_star_mka_and_a_network_override(tmp_path):
    p = plan(_doc(tmp_path, "bus-star.hcdf"))
    three = (("compute", ("t1s0",)), ("zone-a", ("t1s0",)), ("zone-b", ("t1s0",)))
    assert _cas(p) == {
        "bus:body-t1s": (three, "must-secure", "gcm-aes-128", "psk", None, "file", "keys/main"),
        "star:zone-switch": (
            (("compute", ("sw0",)), ("zone-a", ("eth0",)), ("zone-b", ("eth0",))),
            "must-secure", "gcm-aes-xpn-128", "psk", None, None, "keystore:control-bus",
        ),
        # the <override> of the whole network wins over its default ("off")
        "link:teleop-link": (
            (("compute", ("mgmt",)), ("teleop", ("eth0",))),
            "integrity-only", "gcm-aes-128", "psk", None, "runtime", "runtime:teleop-agent",
        ),
    }  # fmt: skip
    assert p.associations["link:teleop-link"].policy.confidentiality_offset == 30
    assert p.associations["bus:body-t1s"].max_speed_mbps == 10


@pytest.mark.parametrize(
    ("ref", "kind"),
    [("tpm0", "tpm"), ("tpm:owner", "tpm"), ("se051", "secure-element"), ("secure-element:a71ch", "secure-element"),
     ("pkcs11:token=hcdf", "hsm"), ("hsm1", "hsm"), ("keys/main", "file"), ("file:/etc/keys", "file"),
     ("runtime:agent", "runtime"), ("keystore:control-bus", None)],
)  # fmt: skip
def test_credential_store_kinds(ref, kind):
    assert store_kind(ref) == kind


def test_one_robot_in_both_dialects_plans_the_same(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    old, new = plan(_doc(tmp_path / "a", "robot-1.0.hcdf")), plan(_doc(tmp_path / "b", "robot-upstream.hcdf"))

    def by_members(p):
        return {
            members: (rest, ca.keyed, ca.max_speed_mbps, ca.policy.confidentiality_offset)
            for ca in p.associations.values()
            for members, *rest in [_cas(p)[ca.id]]
        }

    assert by_members(old) == by_members(new)
    assert len(old.associations) == len(new.associations) == 3 and len(old.keyed()) == 2
    assert {ca.id for ca in new.associations.values()} == {"link:a-b", "link:a-c", "link:b-c"}
    assert old.robot == new.robot == "twin"


def test_generate_status_rotate_and_export_in_the_new_dialect(tmp_path, cli, keys):
    doc = _doc(tmp_path, "humanoid-backbone.hcdf")
    t0 = datetime(2026, 1, 1, tzinfo=UTC)
    at = lambda dt: dt.strftime("%Y-%m-%dT%H:%M:%SZ")  # noqa: E731
    r = cli("macsec", "generate", doc, *keys, "--now", at(t0), "--json")
    assert r.exit_code == 0 and len(r.json["created"]) == 4
    # rekey-interval-ns="3600000000000" is one hour: due after it
    r = cli("macsec", "status", doc, *keys, "--now", at(t0 + timedelta(seconds=3599)), "--json")
    assert r.exit_code == 0 and not any(row["due"] for row in r.json["associations"])
    r = cli("macsec", "status", doc, *keys, "--now", at(t0 + timedelta(seconds=3600)), "--json")
    assert all(row["due"] for row in r.json["associations"])
    r = cli(
        "macsec", "rotate", doc, *keys, "--now", at(t0 + timedelta(hours=2)), "--network", "left-arm-chain", "--json"
    )
    assert r.exit_code == 0 and {x["id"] for x in r.json["rotated"]} == {
        "leg:left-arm-chain/s32n79-to-mcn1-l",
        "leg:left-arm-chain/mcn1-l-to-mcn2-l",
    }
    # least privilege: the middle arm node holds its two legs, nothing else
    out = tmp_path / "mcn1"
    r = cli("macsec", "export", doc, *keys, "--device", "mcn1-l", "--format", "json", "--out", out, "--json")
    assert r.exit_code == 0, r.stderr
    assert r.json["associations"] == ["leg:left-arm-chain/mcn1-l-to-mcn2-l", "leg:left-arm-chain/s32n79-to-mcn1-l"]
    r = cli(
        "macsec", "export", doc, *keys, "--device", "agx-thor", "--format", "json", "--out", tmp_path / "t", "--json"
    )
    assert r.exit_code == 0 and r.json["associations"] == ["link:s32n79_to_thor_p0"]
    # static non-XPN keys on the 25 Gb/s backbone are refused, as in 1.0
    r = cli("macsec", "export", doc, *keys, "--device", "agx-thor", "--format", "iproute2", "--out", tmp_path / "i")
    assert r.exit_code == 3 and "XPN" in r.stderr and not (tmp_path / "i").exists()
    r = cli(
        "macsec", "export", doc, *keys, "--device", "s32j100", "--format", "wpa_supplicant", "--out", tmp_path / "w"
    )
    assert r.exit_code == 0 and "mka_cak=" in (tmp_path / "w" / "wpa_supplicant-wired-eth_up0.conf").read_text()


# --- fail closed, for plan and for export ------------------------------------------------------

_POLICY = '<default-policy><macsec-policy-ref network="test-chain" policy="secure"/></default-policy>'
_OVERRIDE = (
    '<override><target><leg-ref network="test-chain" leg="board-to-tail"/></target>'
    '<macsec-policy-ref network="test-chain" policy="tail"/></override>'
)
_CAN = '<participant name="parent-body" role="hcdf:controller">'
_CAN_MACSEC = (
    '<configuration><macsec><policy name="p" enforcement="must-secure"/><default-policy>'
    '<macsec-policy-ref network="test_can" policy="p"/></default-policy></macsec></configuration>'
)
_RATE = '<nominal value="100000000" unit="bit/s"/></rate></selected>\n    <configuration>'
_EEE = '<eee default-mode="disabled"/>'
_TAIL_PORT = 'port-ref component="tail-board" port="eth0"'
# case: (edits of chain-must-secure.hcdf, a text on the line the error must name)
FAIL_CLOSED = {
    "unknown cipher": ([('cipher="ieee:gcm-aes-128"', 'cipher="ieee:chacha20-poly1305"')], 'name="secure"'),
    "cipher of an unknown authority": ([("ieee8021ae:gcm-aes-256", "acme:gcm-aes-256")], 'name="tail"'),
    "unknown key agreement": ([('key-agreement="vendor:psk"', 'key-agreement="vendor:quantum"')], 'name="secure"'),
    "no enforcement": ([('enforcement="must-secure" ', "")], 'name="secure"'),
    "unknown policy attribute": ([('"se051"/>', '"se051" sak="0"/>')], 'name="secure"'),
    "rekey interval not in ns": ([('rekey-interval-ns="3600000000000"', 'rekey-interval-ns="1h"')], 'name="tail"'),
    "unknown <macsec> child": ([(_POLICY, "<group-key/>" + _POLICY)], "<group-key/>"),
    "default policy names nothing": ([('policy="secure"/></default', 'policy="sec"/></default')], "<default-policy>"),
    "override names no policy": ([('policy="tail"/></override>', 'policy="tale"/></override>')], "<override><target>"),
    "override targets no leg": ([('leg="board-to-tail"', 'leg="board-to-nowhere"')], "<override><target>"),
    "participant's port does not exist": ([(_TAIL_PORT, _TAIL_PORT.replace("eth0", "eth9"))], 'port="eth9"'),
    "participant's component does not exist": ([(_TAIL_PORT, _TAIL_PORT.replace("tail-", "ghost-"))], "ghost-board"),
    "a secured leg with one member": ([('participant="tail-board"/></to>', 'participant="nobody"/></to>')], "nobody"),
    "a policy that keys nothing": ([(_POLICY, ""), (_OVERRIDE, "")], "<macsec>"),
    "a chain without legs": ([("<leg name=", "<legg name="), ("</leg>", "</legg>")], '<chain name="test-chain">'),
    "MACsec on a CAN bus": ([(_CAN, _CAN_MACSEC + _CAN)], '<policy name="p"'),
    "two <macsec> in one configuration": ([(_EEE, "<macsec/>" + _EEE)], "<macsec/><eee"),
    "a selected rate that cannot be read": ([(_RATE, _RATE.replace("bit/s", "furlong/s"))], "furlong/s"),
}  # fmt: skip


@pytest.mark.parametrize("case", list(FAIL_CLOSED))
def test_what_the_planner_does_not_understand_is_refused(tmp_path, cli, keys, case):
    edits, marker = FAIL_CLOSED[case]
    (tmp_path / "good").mkdir()
    good = _doc(tmp_path / "good", "chain-must-secure.hcdf")
    assert cli("macsec", "generate", good, *keys).exit_code == 0
    doc = _doc(tmp_path, "chain-must-secure.hcdf", *edits)
    line = _line(doc, marker)
    r = cli("macsec", "plan", doc, "--json")
    assert r.exit_code == 3, (case, r.stdout)
    assert any(e["line"] == line and e["file"].endswith("chain-must-secure.hcdf") for e in r.json["errors"]), (
        line,
        r.json["errors"],
    )
    out = tmp_path / "out"
    r = cli("macsec", "export", doc, *keys, "--device", "test-board", "--format", "json", "--out", out, "--json")
    assert r.exit_code == 3 and any(e["line"] == line for e in r.json["errors"]), r.json
    assert not out.exists()


ARM = """<?xml version="1.0"?>
<!-- An arm in upstream's model (its chain written as humanoid-mobile-base's left-arm-chain), included twice. -->
<hcdf version="1.0" name="arm">
  <comp name="mcn1"><port name="eth0"/><port name="eth1"/></comp>
  <comp name="mcn2"><port name="eth0"/></comp>
  <chain name="arm-chain">
    <selected purpose="communication" carrier="electrical"><rate><nominal value="1000000000" unit="bit/s"/></rate>
    </selected>
    <configuration><macsec>
      <policy name="arm" enforcement="must-secure" cipher="ieee8021ae:gcm-aes-128" key-agreement="local:psk"/>
      <default-policy><macsec-policy-ref network="arm-chain" policy="arm"/></default-policy>
    </macsec></configuration>
    <participant name="mcn1-out"><endpoint><port-ref component="mcn1" port="eth1"/></endpoint></participant>
    <participant name="mcn2"><endpoint><port-ref component="mcn2" port="eth0"/></endpoint></participant>
    <hop name="mcn1"><owner><component-ref component="mcn1"/></owner></hop>
    <hop name="mcn2"><owner><component-ref component="mcn2"/></owner></hop>
    <leg name="mcn1-to-mcn2"><from><hop-ref network="arm-chain" hop="mcn1"/><participant-ref network="arm-chain"
      participant="mcn1-out"/></from><to><hop-ref network="arm-chain" hop="mcn2"/><participant-ref network="arm-chain"
      participant="mcn2"/></to></leg>
  </chain>
</hcdf>
"""


def test_an_arm_included_twice_gets_two_sets_of_keys(tmp_path, cli, keys):
    from ._macsec import tree

    root = (
        '<?xml version="1.0"?>\n<hcdf version="1.0" name="two-arms">\n'
        '<include uri="arm.hcdf" name="left_arm"/>\n<include uri="arm.hcdf" name="right_arm"/>\n</hcdf>\n'
    )
    doc = tree(tmp_path, {"robot.hcdf": root, "arm.hcdf": ARM})
    p = plan(doc)
    assert {ca.id: sorted(ca.members) for ca in p.keyed()} == {
        "leg:left_arm_arm-chain/mcn1-to-mcn2": ["left_arm_mcn1", "left_arm_mcn2"],
        "leg:right_arm_arm-chain/mcn1-to-mcn2": ["right_arm_mcn1", "right_arm_mcn2"],
    }
    assert cli("macsec", "generate", doc, *keys).exit_code == 0
    r = cli("macsec", "export", doc, *keys, "--device", "left_arm_mcn2", "--format", "json", "--out", tmp_path / "o",
            "--json")  # fmt: skip
    assert r.exit_code == 0 and r.json["associations"] == ["leg:left_arm_arm-chain/mcn1-to-mcn2"]


def test_the_readme_shows_one_robot_in_both_dialects(tmp_path):
    import re
    import textwrap

    from .conftest import PROJECT

    readme = (PROJECT / "docs" / "macsec.md").read_text()
    after = readme[readme.index("<!-- macsec-dialects:") :]
    blocks = [textwrap.dedent(b) for b in re.findall(r"```xml\n(.*?)\s*```", after, re.S)[:2]]
    plans = []
    for name, text in zip(("old", "new"), blocks, strict=True):
        (tmp_path / name).mkdir()
        (tmp_path / name / "robot.hcdf").write_text(text)
        plans.append(plan(lock(tmp_path / name / "robot.hcdf")))
    old, new = plans
    assert sorted(ca.id for ca in old.keyed()) == ["link:body/a-b", "link:body/a-c"]
    assert sorted(ca.id for ca in new.keyed()) == ["leg:body/a-b", "leg:body/a-c"]

    def by_members(p):
        return {m: (rest, ca.max_speed_mbps) for ca in p.associations.values() for m, *rest in [_cas(p)[ca.id]]}

    assert by_members(old) == by_members(new)


@pytest.mark.parametrize("ns", ["", ' xmlns:x="urn:x"'])
def test_policy_macsec_outside_any_network_is_refused_in_any_namespace(tmp_path, cli, ns):
    # plain name tests for a document that declares no namespace, local-name() tests otherwise: both find it
    # (an element in a namespace is refused by the resolver before any planning)
    tag = "macsec"
    text = (
        f'<?xml version="1.0"?>\n<hcdf version="1.0" name="t"{ns}>\n<comp name="c">\n'
        '<port name="p"><capabilities><macsec><cipher>gcm-aes-128</cipher></macsec></capabilities></port>\n'
        f'<{tag} policy="must-secure"/>\n</comp>\n</hcdf>\n'
    )
    doc = tmp_path / "robot.hcdf"
    doc.write_text(text)
    r = cli("macsec", "plan", lock(doc), "--json")
    assert r.exit_code == 3 and [e["line"] for e in r.json["errors"]] == [5], r.json


# --- audit reads the new model too -----------------------------------------------------------------


def test_audit_finds_control_traffic_and_file_stores_in_the_new_model(tmp_path, cli):
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    chain = _doc(tmp_path / "a", "chain-must-secure.hcdf")
    r = cli("audit", chain, "--json")
    # the chain's traffic classes include pcp 7 (ptp): its should-secure leg is an error, as a 1.0 VLAN pcp >= 5 is
    assert r.exit_code == 1
    assert [(f["code"], f["line"]) for f in r.json["findings"]] == [
        ("macsec-control-traffic", _line(chain, 'leg name="board-to-tail"'))
    ]
    stars = _doc(tmp_path / "b", "bus-star.hcdf")
    r = cli("audit", stars, "--json")
    assert [(f["code"], f["line"]) for f in r.json["findings"]] == [
        ("macsec-file-key-store", _line(stars, 'credential-store-ref="keys/main"'))
    ]


@pytest.mark.parametrize(
    ("case", "code"),
    [
        ("participant's port does not exist", "unresolved-port"),
        ("participant's component does not exist", "unresolved-comp"),
        ("a secured leg with one member", "unresolved-participant"),
        ("override names no policy", "unresolved-participant"),
    ],
)
def test_validate_checks_the_new_models_references(tmp_path, cli, case, code):
    edits, marker = FAIL_CLOSED[case]
    assert cli("validate", _doc(tmp_path, "chain-must-secure.hcdf"), "--json").exit_code == 0
    doc = _doc(tmp_path, "chain-must-secure.hcdf", *edits)
    r = cli("validate", doc, "--json")
    assert r.exit_code == 1
    found = [(f["code"], f["line"]) for f in r.json["findings"] if f["severity"] == "error"]
    assert (code, _line(doc, marker)) in found, found
