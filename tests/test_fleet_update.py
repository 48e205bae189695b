"""``fleet update`` and ``fleet confirm`` against in-process SMP devices: upload, resume,
check, mark, confirm, and devices that lie or stall. The QEMU devices: test_fleet_qemu.py."""

from __future__ import annotations

import hashlib

import pytest

from ._fleet import COMPS, run, set_running, status, verdicts
from ._smp_responder import mcuboot_identity


def update(w, *extra, devices=None):
    args = [
        "fleet",
        "update",
        w["robot"].doc,
        "--release",
        w["new_dir"],
        "--key",
        w["robot"].pub,
        "--timeout",
        "5",
    ]
    for name, uri in (devices or w["uris"]).items():
        args += ["--device", f"{name}={uri}"]
    return run(*args, *extra)


def confirm(w, *extra):
    args = ["fleet", "confirm", w["robot"].doc, "--release", w["new_dir"], "--key", w["robot"].pub]
    for name, uri in w["uris"].items():
        args += ["--device", f"{name}={uri}"]
    return run(*args, *extra)


def release_image(w, name) -> bytes:
    board, app = next((b, a) for n, b, a in COMPS if n == name)
    return (w["new_dir"] / board / app / "1.2.0.bin").read_bytes()


def reset(w, name):
    """What MCUboot does for a test image on reset: swap, run it unconfirmed."""
    d = w["devices"][name]
    new = next(s for s in d.slots if s.slot == 1)
    old = next(s for s in d.slots if s.slot == 0)
    new.slot, old.slot = 0, 1
    new.active, old.active = True, False
    new.pending, new.confirmed, old.confirmed = False, new.permanent, True
    d.slots.sort(key=lambda s: s.slot)


@pytest.fixture
def outdated(fleet):
    for name, _, _ in COMPS:
        set_running(fleet, name, "old")
        fleet["devices"][name].upload = bytearray()
        fleet["devices"][name].upload_sha = b""
    return fleet


def test_update_then_reset_then_confirm(outdated):
    w = outdated
    r = update(w, "--json")
    assert r.exit_code == 0, r.stdout
    assert {d["comp"]: d["result"] for d in r.json["devices"]} == dict.fromkeys(("left", "right", "imu"), "updated")
    for name, _, _ in COMPS:
        d = w["devices"][name]
        image = release_image(w, name)
        assert bytes(d.upload) == image  # the verified release's bytes, whole
        slot1 = next(s for s in d.slots if s.slot == 1)
        assert (slot1.version, slot1.hash) == mcuboot_identity(image)
        assert slot1.hash.hex() == w["new"][name][1]
        assert slot1.pending and not slot1.permanent
    r = status(w, "--json", "--previous", w["old_dir"])
    assert set(verdicts(r).values()) == {"pending"}
    for name, _, _ in COMPS:
        reset(w, name)
    r = status(w, "--json", "--previous", w["old_dir"])
    assert r.exit_code == 1 and set(verdicts(r).values()) == {"unconfirmed"}
    r = confirm(w, "--json")
    assert r.exit_code == 0, r.stdout
    assert {d["result"] for d in r.json["devices"]} == {"confirmed"}
    r = status(w, "--json")
    assert r.exit_code == 0 and set(verdicts(r).values()) == {"current"}
    r = confirm(w, "--json")
    assert r.exit_code == 0 and {d["result"] for d in r.json["devices"]} == {"already-confirmed"}
    r = update(w, "--json")
    assert r.exit_code == 0 and {d["result"] for d in r.json["devices"]} == {"already-running"}


def test_confirm_leaves_devices_not_running_the_release_alone(outdated):
    r = confirm(outdated, "--json")
    assert r.exit_code == 1
    assert {d["result"] for d in r.json["devices"]} == {"not-running-release"}
    assert all((1, 0, 2) not in d.requests for d in outdated["devices"].values())  # no image-state write


def test_confirm_flag_marks_permanent(outdated):
    r = update(outdated, "--json", "--confirm", "--only", "imu")
    assert r.exit_code == 0
    slot1 = next(s for s in outdated["devices"]["imu"].slots if s.slot == 1)
    assert slot1.pending and slot1.permanent


def test_dry_run_and_only_send_nothing_else(outdated):
    before = {n: len(d.requests) for n, d in outdated["devices"].items()}
    r = update(outdated, "--json", "--dry-run", "--only", "left")
    assert r.exit_code == 0
    [left] = r.json["devices"]
    assert left["comp"] == "left" and left["result"] == "would-update" and "would upload" in left["detail"]
    assert outdated["devices"]["left"].requests[before["left"] :] == [(0, 1, 0)]  # one image-state read
    assert len(outdated["devices"]["right"].requests) == before["right"]
    assert not outdated["devices"]["left"].upload


def test_resume_sends_only_the_rest(outdated):
    d = outdated["devices"]["left"]
    image = release_image(outdated, "left")
    d.upload = bytearray(image[:4000])
    d.upload_len = len(image)
    d.upload_sha = hashlib.sha256(image).digest()
    r = update(outdated, "--json", "--only", "left")
    assert r.exit_code == 0, r.stdout
    sent = r.json["devices"][0]["bytes_sent"]
    assert bytes(d.upload) == image
    # the first chunk (at most one UDP datagram) again, then only from 4000 on
    assert sent < len(image) and sent <= len(image) - 4000 + 1472, sent


def test_device_reporting_another_hash_after_upload(outdated):
    outdated["devices"]["right"].mode = "lying-upload"
    r = update(outdated, "--json")
    assert r.exit_code == 1
    res = {d["comp"]: d["result"] for d in r.json["devices"]}
    assert res == {"left": "updated", "right": "failed", "imu": "updated"}
    assert not any(s.pending for s in outdated["devices"]["right"].slots)  # not marked


def test_stalled_upload_fails_as_malformed(outdated):
    outdated["devices"]["imu"].mode = "stuck-upload"
    r = update(outdated, "--json", "--only", "imu")
    assert r.exit_code == 3
    assert r.json["errors"][0]["code"] == "malformed-answer"
