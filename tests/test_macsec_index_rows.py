"""The export index's association rows: every field of a planned association survives the
round trip through JSON exactly, so an export made through the index is made from the very
association the planner made (the CLI-level attacks are in test_macsec_index.py)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from hcdf_trust.macsec import index
from hcdf_trust.macsec.plan import Association, Plan, plan
from hcdf_trust.macsec.store import line_encoder

from ._macsec import comp, hcdf, humanoid, link, port, tree
from .test_macsec_plan import ROBOT, _two_arms


def _round_trip(p: Plan) -> None:
    assert p.associations
    for ca in p.associations.values():
        row = json.loads(line_encoder(sort_keys=False)(index._row(ca)))
        again = index._association(row)
        again.warned = ca.warned  # the planner's own bookkeeping (warnings given once), not exported
        assert again == ca, ca.id
        assert [type(e.line) for e in again.elements] == [type(e.line) for e in ca.elements]
        assert {k: type(v) for k, v in again.port_speeds_mbps.items()} == {
            k: type(v) for k, v in ca.port_speeds_mbps.items()
        }


def test_rows_hold_every_association_field_but_the_planner_bookkeeping():
    names = tuple(f.name for f in dataclasses.fields(Association))
    assert names == (*index.ROW_FIELDS, "warned")


def test_humanoid_associations_round_trip(tmp_path):
    _round_trip(plan(humanoid(tmp_path)))


def test_included_twice_and_shared_key_ref_round_trip(tmp_path):
    _round_trip(plan(_two_arms(tmp_path)))
    shared = plan(ROBOT)  # the example robot: one key-ref on two links (a CA of two elements)
    assert any(ca.shared for ca in shared.associations.values())
    _round_trip(shared)


def test_mesh_eap_tls_xpn_and_odd_names_round_trip(tmp_path: Path):
    doc = tree(
        tmp_path,
        {
            "robot.hcdf": hcdf(
                comp("a", port("p0", "gcm-aes-xpn-256", mbps=10000), port("p1", "gcm-aes-128")),
                comp("b\u00e9", port("p0", "gcm-aes-xpn-256", mbps=2500), port("p1", "gcm-aes-128")),
                '<network name="n">',
                link(
                    "x",
                    "a/p0",
                    "b\u00e9/p0",
                    '<macsec policy="must-secure" cipher="gcm-aes-xpn-256" key-ref="k\\&quot;1"'
                    ' confidentiality-offset="30"/>',
                ),
                '<mesh name="skin" standard="802.15.4" network-key-ref="thread-key">'
                '<node device="a" antenna="ant0"/><node device="b\u00e9" antenna="ant0"/></mesh>',
                '<macsec policy="should-secure" cipher="gcm-aes-128" rekey-interval-sec="600"/>',
                "</network>",
                '<network name="m">',
                link("e", "a/p1", "b\u00e9/p1"),
                '<macsec policy="must-secure" key-agreement="eap-tls"/>',
                "</network>",
                comp("c", port("p0", "gcm-aes-128")),
                '<network name="off">',
                link("o", "c/p0", "a/p2", '<macsec policy="disabled"/>'),
                "</network>",
            )
        },
    )
    p = plan(doc)
    assert not p.associations["link:off/o"].keyed
    kinds = {ca.kind for ca in p.associations.values()}
    assert kinds == {"macsec", "mesh-key"}
    assert {ca.policy.key_agreement for ca in p.associations.values() if ca.policy} == {"psk", "eap-tls"}
    _round_trip(p)


def test_a_device_line_lists_exactly_its_keyed_associations(tmp_path):
    """The least-privilege question the index answers must be the planner's own answer
    (a device only on a disabled link is in no keyed association: the index does not list it)."""
    test_mesh_eap_tls_xpn_and_odd_names_round_trip(tmp_path)
    p = plan(tmp_path / "robot.hcdf")
    assert not p.for_device("c")

    class _Store:  # seal() is all render needs of a store here: its MAC is tested at the CLI
        store_id = "s"

        def seal(self, body: bytes, *, label: bytes) -> bytes:
            return b'{"mac":"0",' + body[1:]

    raw = index.render(str(tmp_path / "robot.hcdf"), p, _Store())  # type: ignore[arg-type]
    assert raw is not None
    devices = {d for ca in p.associations.values() for d in ca.members}
    for device in devices:
        got = index._device_associations(raw, device)
        mine = [ca.id for ca in p.for_device(device)]
        assert (list(got) if got is not None else []) == mine and (got is None) == (not mine)
    assert index._device_associations(raw, "no-such-device") is None


@pytest.mark.parametrize("sort_keys", [False, True])
def test_the_line_encoder_writes_what_json_writes(sort_keys):
    values = [
        ["C", 'link:n/l\u00e9"\n\\', [None, 1, 2.5, 1000.0, 1e300, -0.0, True, [], {}]],
        {"z": 1, "a": {"y": [1, "\u2028"], "b": None}, "m": "\ud83d\ude00"},
        ["D", "d0", ["a", "b"]],
        "plain",
    ]
    encode = line_encoder(sort_keys=sort_keys)
    for value in values:
        assert encode(value) == json.dumps(value, sort_keys=sort_keys, separators=(",", ":"))


def test_the_code_digest_changes_with_any_source_file_and_only_with_them(tmp_path):
    """An index is bound to the code that wrote it: a copy of the package elsewhere has the
    same digest, a copy with one planner line changed (or a module added) another one."""
    import shutil

    import hcdf_trust

    package = Path(hcdf_trust.__file__).parent
    assert index.code_digest() == index.tree_digest(str(package))

    def copy(name: str) -> Path:
        dest = tmp_path / name / "hcdf_trust"
        shutil.copytree(package, dest, ignore=shutil.ignore_patterns("__pycache__"))
        return dest

    assert index.tree_digest(str(copy("same"))) == index.code_digest()
    edited = copy("edited")
    plan_py = edited / "macsec" / "plan.py"
    plan_py.write_text(plan_py.read_text().replace("return PN_SPACE", "return 2 * PN_SPACE", 1))
    assert index.tree_digest(str(edited)) != index.code_digest()
    added = copy("added")
    (added / "macsec" / "extra.py").write_text("")
    assert index.tree_digest(str(added)) != index.code_digest()
    before = index.tree_digest(str(added))
    (added / "macsec" / "extra.py").rename(added / "macsec" / "extrb.py")  # same bytes and place, another name
    assert index.tree_digest(str(added)) not in (before, index.code_digest())
    compiled = copy("compiled")
    (compiled / "macsec" / "__pycache__").mkdir()
    (compiled / "macsec" / "__pycache__" / "plan.cpython-311.pyc").write_bytes(b"not source")
    assert index.tree_digest(str(compiled)) == index.code_digest()
