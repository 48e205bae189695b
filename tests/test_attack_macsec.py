"""Issue 16 §6, from an attacker's (or a tired operator's) point of view: MACsec keys go only
where they belong. Each test fails without its protection (checked by reverting it)."""

from __future__ import annotations

import json
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest

from ._macsec import comp, hcdf, link, tree

PASS = b"attack test passphrase"


def _robot(root: Path, name: str, *, speed: str = '<speed unit="Mbps">1000</speed>', macsec: str = "") -> Path:
    """A two-device robot called ``name``: one must-secure link ``n/l0`` between a/p0 and b/p0."""
    port = f'<port name="p0" type="ethernet"><capabilities>{speed}</capabilities></port>'
    policy = macsec or '<macsec policy="must-secure" cipher="gcm-aes-128"/>'
    net = ('<network name="n">', link("l0", "a/p0", "b/p0"), policy, "</network>")
    text = hcdf(comp("a", port), comp("b", port), *net)
    return tree(root, {"robot.hcdf": text.replace('name="t"', f'name="{name}"', 1)})


@pytest.fixture
def keys(tmp_path):
    pp = tmp_path / "pass"
    pp.write_bytes(PASS)
    return ["--store", tmp_path / "keys", "--passphrase-file", pp]


# --- a store is bound to its robot -----------------------------------------------------------


def test_another_robots_store_gives_it_no_keys(tmp_path, cli, keys):
    robot_a = _robot(tmp_path / "a", "robot-a")
    robot_b = _robot(tmp_path / "b", "robot-b")  # the same association ids: link:n/l0
    assert cli("macsec", "generate", robot_a, *keys).exit_code == 0
    store = Path(keys[1]) / "macsec-keys.json"
    before = store.read_bytes()
    out = tmp_path / "out"
    attempts = {
        "generate": cli("macsec", "generate", robot_b, *keys),
        "status": cli("macsec", "status", robot_b, *keys),
        "rotate": cli("macsec", "rotate", robot_b, *keys),
        "export": cli("macsec", "export", robot_b, *keys, "--device", "a", "--format", "json", "--out", out),
    }
    for verb, r in attempts.items():
        assert r.exit_code == 1, (verb, r.stderr)
        assert "'robot-a'" in r.stderr and "'robot-b'" in r.stderr, (verb, r.stderr)
    assert store.read_bytes() == before and not out.exists()
    # robot A still uses its store
    assert cli("macsec", "export", robot_a, *keys, "--device", "a", "--format", "json", "--out", out).exit_code == 0


def test_the_recorded_robot_cannot_be_edited(tmp_path, cli, keys):
    robot_a = _robot(tmp_path / "a", "robot-a")
    robot_b = _robot(tmp_path / "b", "robot-b")
    assert cli("macsec", "generate", robot_a, *keys).exit_code == 0
    store = Path(keys[1]) / "macsec-keys.json"
    store.write_bytes(store.read_bytes().replace(b'"robot":"robot-a"', b'"robot":"robot-b"', 1))
    r = cli("macsec", "export", robot_b, *keys, "--device", "a", "--format", "json", "--out", tmp_path / "out")
    assert r.exit_code == 1 and "MAC" in r.stderr


def test_a_store_that_records_no_robot_is_refused(tmp_path, cli, keys):
    robot_a = _robot(tmp_path / "a", "robot-a")
    assert cli("macsec", "generate", robot_a, *keys).exit_code == 0
    store = Path(keys[1]) / "macsec-keys.json"
    store.write_bytes(store.read_bytes().replace(b'"robot":"robot-a",', b"", 1))
    r = cli("macsec", "status", robot_a, *keys)
    assert r.exit_code in (1, 3) and "robot-a" not in r.stdout


def test_the_export_index_does_not_carry_keys_to_another_robot(tmp_path, cli, keys):
    # robot B's document placed where robot A's was, same lock layout: the index no longer matches,
    # and planning B's description meets the store's robot
    root = tmp_path / "r"
    _robot(root, "robot-a")
    assert cli("macsec", "generate", root / "robot.hcdf", *keys).exit_code == 0
    _robot(root, "robot-b")
    out = ["--device", "b", "--format", "json", "--out", tmp_path / "o"]
    r = cli("macsec", "export", root / "robot.hcdf", *keys, *out)
    assert r.exit_code == 1 and "'robot-a'" in r.stderr


# --- one reading of a link speed ---------------------------------------------------------------


@pytest.mark.parametrize(
    "speed",
    [
        '<speed unit="Gb/s">10</speed>',
        "<speed>10G</speed>",
        '<speed unit="Gbps">10.0</speed>',
        '<speed unit="bit/s">10000000000</speed>',
        '<speed unit="GB/s">1.25</speed>',  # bytes: 10 Gb/s
        '<speed-tx unit="kb/s">10000000</speed-tx><speed-rx unit="Mb/s">100</speed-rx>',
        '<rate min="1000000000" max="10000000000" nominal="10000000000" unit="bit/s"/>',  # upstream's form
    ],
)
def test_a_10g_link_written_any_way_refuses_static_non_xpn_keys(tmp_path, cli, keys, speed):
    doc = _robot(tmp_path / "r", "r", speed=speed)
    assert cli("macsec", "generate", doc, *keys).exit_code == 0
    r = cli("macsec", "export", doc, *keys, "--device", "a", "--format", "iproute2", "--out", tmp_path / "o")
    assert r.exit_code == 3 and "XPN" in r.stderr and "10000 Mb/s" in r.stderr, r.stderr
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(
    "speed",
    ['<speed unit="furlongs">10</speed>', "<speed>fast</speed>", '<speed unit="MHz">15</speed>', "<speed>-10</speed>"],
)
def test_a_speed_that_cannot_be_read_on_a_secured_link_is_an_error(tmp_path, cli, keys, speed):
    doc = _robot(tmp_path / "r", "r", speed=speed)
    for verb in (["plan"], ["generate", *keys]):
        r = cli("macsec", *verb, doc, "--json")
        assert r.exit_code == 3, r.stdout
        errors = r.json["errors"]  # one per port: comps a and b are on lines 3 and 4
        assert all("cannot be read" in e["message"] for e in errors), errors
        assert sorted(e["line"] for e in errors) == [3, 4]
    # the same port on a link without MACsec is not the planner's business
    plain = _robot(tmp_path / "p", "p", speed=speed, macsec='<macsec policy="disabled"/>')
    assert cli("macsec", "plan", plain).exit_code == 0


# --- retire never removes the key in use; status says when there is none ---------------------


def test_retire_in_the_future_keeps_todays_key(tmp_path, cli, keys):
    doc = _robot(tmp_path / "r", "r")
    assert cli("macsec", "generate", doc, *keys).exit_code == 0  # at the real time
    assert cli("macsec", "rotate", doc, *keys, "--overlap", "3600").exit_code == 0  # g2 sends in an hour
    future = (datetime.now(UTC) + timedelta(days=3)).strftime("%Y-%m-%dT%H:%M:%SZ")
    r = cli("macsec", "retire", *keys, "--now", future, "--json")
    assert r.exit_code == 0 and r.json["retired"] == []
    r = cli("macsec", "status", doc, *keys, "--json")
    assert r.exit_code == 0 and r.json["ok"] is True
    (row,) = r.json["associations"]
    assert row["active_generation"] == 1 and [g["generation"] for g in row["generations"]] == [1, 2]


def test_status_fails_when_an_association_has_no_usable_key(tmp_path, cli, keys):
    doc = _robot(tmp_path / "r", "r")
    # keys made for a time to come: nothing is active now
    assert cli("macsec", "generate", doc, *keys, "--now", "2099-01-01T00:00:00Z").exit_code == 0
    r = cli("macsec", "status", doc, *keys, "--json")
    assert r.exit_code == 1 and r.json["ok"] is False
    (err,) = r.json["errors"]
    assert err["code"] == "macsec-no-key" and "link:n/l0" in err["message"]
    assert r.json["associations"][0]["active_generation"] is None
    human = cli("macsec", "status", doc, *keys)
    assert human.exit_code == 1 and "NO ACTIVE KEY" in human.stdout and "gNone" not in human.stdout
    # an association the store has no key for at all
    other = _robot(tmp_path / "o", "r")  # same robot name, a fresh store
    fresh = ["--store", tmp_path / "keys2", *keys[2:]]
    assert cli("macsec", "generate", other, *fresh).exit_code == 0
    (tmp_path / "o" / "robot.hcdf").write_text(
        (tmp_path / "o" / "robot.hcdf").read_text().replace('name="l0"', 'name="l1"')
    )
    from ._macsec import lock

    lock(tmp_path / "o" / "robot.hcdf")
    r = cli("macsec", "status", other, *fresh, "--json")
    assert r.exit_code == 1 and "link:n/l1" in json.dumps(r.json["errors"]) and r.json["missing"] == ["link:n/l1"]
