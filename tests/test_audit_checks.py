"""Each audit check on a small tree made to trip it: the finding is there with its file and line,
and disappears when the policy disables that check (so removing the check fails its test)."""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest

from ._macsec import comp, hcdf, link, port
from ._macsec import lock as lock_tree

GLB = b"glTF stand-in"
SHA = hashlib.sha256(GLB).hexdigest()
ALL = ("gcm-aes-128", "gcm-aes-256")


def _write(root: Path, body: str, *, lock: bool = False) -> Path:
    (root / "a.glb").write_bytes(GLB)
    doc = root / "robot.hcdf"
    doc.write_text(hcdf(body))
    return lock_tree(doc) if lock else doc


def _line(doc: Path, needle: str) -> int:
    (line,) = [i for i, text in enumerate(doc.read_text().splitlines(), 1) if needle in text]
    return line


def _audit(cli, doc: Path, tmp_path: Path, *extra, disable: str | None = None):
    args = [*extra]
    if disable is not None:
        policy = tmp_path / "off.toml"
        policy.write_text(f"[checks.{disable}]\nenabled = false\n")
        args += ["--policy", policy]
    r = cli("audit", doc, "--json", *args)
    assert r.exit_code in (0, 1), r.stdout + r.stderr
    return r


def _codes(r, code: str) -> list[tuple[str, int | None]]:
    return [(Path(f["file"]).name, f["line"]) for f in r.json["findings"] if f["code"] == code]


def _wired(pcp: str, policy: str, *, key_store: str = "tpm", cipher: str = "gcm-aes-128", ports=ALL) -> str:
    devices = comp("a", port("p0", *ports)) + comp("b", port("p0", *ports))
    macsec = f'<macsec policy="{policy}" cipher="{cipher}" key-ref="k"/>'
    body = link("l", "a/p0", "b/p0", macsec).replace("</wired>", f'<vlan id="10" pcp="{pcp}"/></wired>')
    return (
        f'{devices}\n<network name="n">\n{body}\n'
        f'<macsec policy="must-secure"><key-store type="{key_store}" ref="x"/></macsec>\n</network>'
    )


# (check, document body, the text on the line the finding must name, lock the tree first)
CASES = [
    ("unpinned", '<comp name="c"><visual name="v"><model uri="a.glb"/></visual></comp>', "a.glb", False),
    ("weak-pin", f'<comp name="c"><visual name="v"><model uri="a.glb" sha="{SHA[:8]}"/></visual></comp>', "a.glb",
     False),
    ("plain-http", f'<comp name="c"><visual name="v"><model uri="http://127.0.0.1:9/a.glb" sha="{SHA}"/></visual>'
     "</comp>", "http://", False),
    ("firmware-no-hash", '<comp name="c"><software name="fw"><version>1.0.0</version></software></comp>',
     "<software", False),
    ("firmware-hash", '<comp name="c"><software name="fw"><version>1.0.0</version>\n<hash>abcdef12</hash>'
     "</software></comp>", "<hash>", False),
    ("firmware-version", f'<comp name="c"><software name="fw">\n<version>1.2</version><hash>{SHA}</hash>'
     "</software></comp>", "<version>", False),
    ("macsec-control-traffic", _wired("6", "should-secure"), '<link name="l">', True),
    ("macsec-file-key-store", _wired("3", "must-secure", key_store="file"), "key-store", True),
    ("macsec-capability", _wired("3", "must-secure", ports=("gcm-aes-256",)), '<comp name="a">', True),
]  # fmt: skip


@pytest.mark.parametrize(("check", "body", "needle", "locked"), CASES, ids=[c[0] for c in CASES])
def test_each_check_reports_and_can_be_switched_off(cli, tmp_path, check, body, needle, locked):
    doc = _write(tmp_path, body, lock=locked)
    r = _audit(cli, doc, tmp_path)
    found = _codes(r, check)
    assert found and all(f == ("robot.hcdf", _line(doc, needle)) for f in found), r.json["findings"]
    finding = next(f for f in r.json["findings"] if f["code"] == check)
    assert finding["check"] == check and finding["severity"] in ("info", "warning", "error")
    off = _audit(cli, doc, tmp_path, disable=check)
    assert _codes(off, check) == []


def test_control_traffic_needs_a_high_priority_vlan_or_a_chain(cli, tmp_path):
    doc = _write(tmp_path, _wired("4", "should-secure"), lock=True)
    assert _codes(_audit(cli, doc, tmp_path), "macsec-control-traffic") == []
    devices = comp("a", port("p0", *ALL)) + comp("b", port("p0", *ALL))
    chain = (
        f'{devices}<network name="n"><chain name="ch"><macsec policy="integrity-only" key-ref="k"/>'
        '<hop device="a" port="p0"/><hop device="b" port="p0"/></chain>\n'
        '<link name="plain"><wired><port>a/p0</port><port>b/p0</port></wired></link></network>'
    )
    doc = _write(tmp_path, chain, lock=True)
    found = _codes(_audit(cli, doc, tmp_path), "macsec-control-traffic")
    # the chain is not must-secure, and the link of the same network has no MACsec at all
    assert sorted(found) == [("robot.hcdf", _line(doc, '<chain name="ch">')), ("robot.hcdf", _line(doc, "plain"))]


def test_weak_cipher_against_the_policy_minimum(cli, tmp_path):
    doc = _write(tmp_path, _wired("3", "must-secure"), lock=True)
    assert _codes(_audit(cli, doc, tmp_path), "macsec-weak-cipher") == []  # default minimum: gcm-aes-128
    policy = tmp_path / "strong.toml"
    policy.write_text('[macsec]\nminimum-cipher = "gcm-aes-xpn-128"\n')
    r = cli("audit", doc, "--json", "--policy", policy)
    assert _codes(r, "macsec-weak-cipher") == [("robot.hcdf", _line(doc, "key-ref"))]
    doc = _write(tmp_path, _wired("3", "must-secure", cipher="gcm-aes-256"), lock=True)
    assert _codes(cli("audit", doc, "--json", "--policy", policy), "macsec-weak-cipher") == []


def test_lock_missing_entry_and_drift(cli, tmp_path):
    body = '<comp name="c"><visual name="v"><model uri="a.glb"/></visual></comp>'
    doc = _write(tmp_path, body)
    r = _audit(cli, doc, tmp_path)
    assert _codes(r, "not-locked") == [("robot.hcdf", None)]  # no lock file at all
    lock_tree(doc)
    r = _audit(cli, doc, tmp_path)
    assert r.json["findings"] == [] and r.exit_code == 0  # the lock pins the unpinned model
    (tmp_path / "b.glb").write_bytes(b"another")
    doc.write_text(hcdf(body.replace("</comp>", '<visual name="w"><model uri="b.glb"/></visual></comp>')))
    r = _audit(cli, doc, tmp_path)
    assert _codes(r, "not-locked") == [("robot.hcdf", _line(doc, "b.glb"))]
    assert _codes(r, "unpinned") == [("robot.hcdf", _line(doc, "b.glb"))]
    (tmp_path / "a.glb").write_bytes(b"changed")
    r = _audit(cli, doc, tmp_path)
    drift = [f for f in r.json["findings"] if f["code"] == "lock-drift"]
    assert [(Path(f["file"]).name, f["line"]) for f in drift] == [("robot.hcdf", _line(doc, "a.glb"))]
    assert hashlib.sha256(b"changed").hexdigest() in drift[0]["message"]
    assert _codes(_audit(cli, doc, tmp_path, disable="lock-drift"), "lock-drift") == []
    assert _codes(_audit(cli, doc, tmp_path, disable="not-locked"), "not-locked") == []


def test_an_unreadable_reference_is_an_integrity_error(cli, tmp_path):
    doc = _write(tmp_path, f'<comp name="c"><visual name="v"><model uri="a.glb" sha="{"0" * 64}"/></visual></comp>')
    r = _audit(cli, doc, tmp_path)
    assert r.exit_code == 1
    (f,) = [f for f in r.json["findings"] if f["check"] == "integrity"]
    assert f["code"] == "digest-mismatch" and f["severity"] == "error" and f["line"] == _line(doc, "a.glb")
    remote = _write(tmp_path, f'<comp name="c"><visual name="v"><model uri="https://127.0.0.1:9/a.glb" sha="{SHA}"/>'
                    "</visual></comp>")  # fmt: skip
    r = _audit(cli, remote, tmp_path)  # offline by default: never fetched, and said so
    assert [f["code"] for f in r.json["findings"] if f["check"] == "integrity"] == ["offline"]


def test_control_traffic_in_an_included_network(cli, tmp_path):
    """The plan prefixes an included network's name (``left_n``); the check still finds its VLANs."""
    sub = tmp_path / "arm.hcdf"
    sub.write_text(hcdf(_wired("7", "integrity-only")))
    doc = tmp_path / "robot.hcdf"
    sha = hashlib.sha256(sub.read_bytes()).hexdigest()
    doc.write_text(hcdf(f'<include uri="arm.hcdf" sha="{sha}" name="left"/>'))
    lock_tree(doc)
    r = _audit(cli, doc, tmp_path)
    (f,) = [f for f in r.json["findings"] if f["code"] == "macsec-control-traffic"]
    assert (Path(f["file"]).name, f["line"]) == ("arm.hcdf", _line(sub, '<link name="l">'))
    assert "left_n" in f["message"] and "pcp 7" in f["message"]
