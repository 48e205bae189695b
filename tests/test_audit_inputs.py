"""audit's own inputs when hostile: the document, the lock, the network."""

from __future__ import annotations

import os

from ._hostile import fifo_watchdog
from .conftest import PROJECT

ROBOT = PROJECT / "examples" / "robot" / "robot.hcdf"


def test_fifo_document_and_lock_are_refused(cli, tmp_path):
    fifo = tmp_path / "robot.hcdf"
    os.mkfifo(fifo)
    with fifo_watchdog(fifo) as state:
        r = cli("audit", fifo)
    assert not state["hung"] and r.exit_code == 3 and "robot.hcdf" in r.stderr
    lock = tmp_path / "x.lock"
    os.mkfifo(lock)
    with fifo_watchdog(lock) as state:
        r = cli("audit", ROBOT, "--lock", lock, "--json")
    assert not state["hung"] and r.exit_code == 3
    assert r.json["errors"][0]["code"] == "lock-file"


def test_missing_malformed_and_foreign_locks(cli, tmp_path):
    r = cli("audit", ROBOT, "--lock", tmp_path / "none.lock")
    assert r.exit_code == 3 and "none.lock" in r.stderr
    bad = tmp_path / "bad.lock"
    bad.write_text("{not json")
    assert cli("audit", ROBOT, "--lock", bad).exit_code == 3
    r = cli("audit", ROBOT, "--lock", ROBOT)  # the document itself is not a lock
    assert r.exit_code == 3 and "Traceback" not in r.stderr
    other = PROJECT / "examples" / "robot" / "robot.hcdf.lock"
    doc = tmp_path / "other.hcdf"
    doc.write_text('<hcdf version="1.0" name="o"><comp name="c"/></hcdf>')
    r = cli("audit", doc, "--lock", other)  # belongs to another root
    assert r.exit_code == 3 and "belongs to" in r.stderr


def test_a_remote_registry_needs_online(cli, tmp_path):
    r = cli("audit", ROBOT, "--registry", "https://127.0.0.1:9/reg", "--trusted-root", ROBOT)
    assert r.exit_code == 2 and "--online" in r.stderr


def test_not_hcdf_is_an_input_error(cli, tmp_path):
    doc = tmp_path / "robot.hcdf"
    doc.write_text("<robot/>")
    r = cli("audit", doc, "--json")
    assert r.exit_code == 3 and r.json["errors"][0]["code"] == "not-hcdf"
