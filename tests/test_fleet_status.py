"""``fleet status`` against in-process SMP devices (tests/_smp_responder.py): every verdict,
the exit codes, the HCDF group, and hostile devices. The real QEMU devices: test_fleet_qemu.py."""

from __future__ import annotations

import hashlib
import json
import os

import pytest

from ._fleet import COMPS, run, set_running, status, verdicts
from ._smp_responder import HOSTILE_MODES, SlotState


def test_all_current(fleet):
    r = status(fleet, "--json")
    assert r.exit_code == 0, r.stdout
    assert verdicts(r) == {"left": "current", "right": "current", "imu": "current"}
    doc = r.json
    assert doc["ok"] is True and doc["errors"] == []
    left = next(d for d in doc["devices"] if d["comp"] == "left")
    assert left["slots"][0]["hash"] == fleet["new"]["left"][1]
    assert left["expected"] == {"version": "1.2.0", "mcuboot_hash": fleet["new"]["left"][1]}
    assert left["description"]["sha256"] == fleet["doc_sha"] == left["description_expected"]
    # the devices were asked the image state and the HCDF group, nothing else
    assert set(fleet["devices"]["left"].requests) == {(0, 1, 0), (0, 100, 0)}


def test_table_says_what_each_device_runs(fleet):
    set_running(fleet, "right", "old")
    r = status(fleet, "--previous", fleet["old_dir"])
    assert r.exit_code == 1
    lines = r.stderr.splitlines()
    right = next(line for line in lines if line.startswith("right "))
    assert "outdated" in right and "1.0.0" in right and fleet["old"]["right"][1][:12] in right
    assert "unauthenticated" in lines[-1]


def test_outdated_needs_the_earlier_signed_release(fleet):
    set_running(fleet, "left", "old")
    r = status(fleet, "--json", "--previous", fleet["old_dir"])
    assert r.exit_code == 1
    assert verdicts(r)["left"] == "outdated" and verdicts(r)["right"] == "current"
    # without it, the old image is in no release this key signed that we know of
    r = status(fleet, "--json")
    assert r.exit_code == 1 and verdicts(r)["left"] == "unknown-image"
    err = next(e for e in r.json["errors"] if e["code"] == "unknown-image")
    assert err["expected"] == fleet["new"]["left"][1] and err["actual"] == fleet["old"]["left"][1]


def test_pending_and_unconfirmed(fleet):
    set_running(fleet, "left", "old", pending="new")
    set_running(fleet, "right", "new", confirmed=False)
    r = status(fleet, "--json", "--previous", fleet["old_dir"])
    assert r.exit_code == 1
    assert verdicts(r) == {"left": "pending", "right": "unconfirmed", "imu": "current"}
    right = next(d for d in r.json["devices"] if d["comp"] == "right")
    assert "revert" in right["reason"]


def test_unknown_image_is_an_integrity_failure(fleet):
    set_running(fleet, "imu", os.urandom(32).hex())
    r = status(fleet, "--json")
    assert r.exit_code == 1 and verdicts(r)["imu"] == "unknown-image"


def test_an_unknown_image_marked_to_run_next_is_named(fleet):
    d = fleet["devices"]["imu"]
    d.slots.append(SlotState(1, "6.6.6", os.urandom(32), pending=True))
    r = status(fleet, "--json")
    assert r.exit_code == 1 and verdicts(r)["imu"] == "unknown-image"
    assert "next reset" in next(x for x in r.json["devices"] if x["comp"] == "imu")["reason"]


def test_release_hash_with_another_version_is_not_current(fleet):
    fleet["devices"]["imu"].slots[0].version = "1.2.1"
    r = status(fleet, "--json")
    assert r.exit_code == 1 and verdicts(r)["imu"] == "unknown-image"


def test_no_hcdf_group_and_skip_description(fleet):
    set_running(fleet, "left", description=False)
    r = status(fleet, "--json")
    assert r.exit_code == 1 and verdicts(r)["left"] == "no-hcdf-group"
    r = status(fleet, "--json", "--skip-description")
    assert r.exit_code == 0 and verdicts(r)["left"] == "current"
    assert (0, 100, 0) not in fleet["devices"]["right"].requests[-1:]


def test_wrong_description(fleet):
    fleet["devices"]["right"].description = ("https://example.invalid/other.hcdf", "ab" * 32)
    r = status(fleet, "--json")
    assert r.exit_code == 1 and verdicts(r)["right"] == "wrong-description"
    err = next(e for e in r.json["errors"] if e["code"] == "wrong-description")
    assert err["expected"] == fleet["doc_sha"] and err["actual"] == "ab" * 32


@pytest.mark.parametrize("sha", ["ab" * 4, "zz" * 32, "ab" * 33])
def test_description_sha_of_the_wrong_form_is_malformed(fleet, sha):
    fleet["devices"]["right"].description = ("https://example.invalid/robot.hcdf", sha)
    r = status(fleet, "--json")
    assert r.exit_code == 3 and verdicts(r)["right"] == "malformed-answer"


def test_unreachable_exits_3(fleet):
    fleet["devices"]["imu"].mode = "silent"
    r = status(fleet, "--json", timeout="0.5")
    assert r.exit_code == 3
    assert verdicts(r) == {"left": "current", "right": "current", "imu": "unreachable"}
    assert next(e for e in r.json["errors"])["code"] == "unreachable"


def test_unknown_image_outranks_unreachable(fleet):
    fleet["devices"]["imu"].mode = "silent"
    set_running(fleet, "left", os.urandom(32).hex())
    r = status(fleet, "--json", timeout="0.5")
    assert r.exit_code == 1


def test_comp_without_address_is_unreachable(fleet):
    r = status(fleet, "--json", devices={k: v for k, v in fleet["uris"].items() if k != "imu"})
    assert r.exit_code == 3 and verdicts(r)["imu"] == "unreachable"
    assert "no address" in next(d for d in r.json["devices"] if d["comp"] == "imu")["reason"]


@pytest.mark.parametrize("mode", HOSTILE_MODES)
def test_hostile_devices(fleet, mode):
    fleet["devices"]["right"].mode = mode
    r = status(fleet, "--json", timeout="1")
    assert r.exit_code == 3, r.stdout
    v = verdicts(r)
    assert v["left"] == "current" and v["imu"] == "current"
    expected = "unreachable" if mode in ("silent", "oversized") else "malformed-answer"
    assert v["right"] == expected, r.json["devices"]


def test_release_that_does_not_verify_asks_no_device(fleet, tmp_path):
    import shutil

    bad = tmp_path / "rel"
    shutil.copytree(fleet["new_dir"], bad)
    image = next(bad.glob("board_l/motor/*.bin"))
    data = bytearray(image.read_bytes())
    data[-1] ^= 1
    image.write_bytes(bytes(data))
    before = len(fleet["devices"]["left"].requests)
    r = run(
        "fleet",
        "status",
        fleet["robot"].doc,
        "--release",
        bad,
        "--key",
        fleet["robot"].pub,
        "--device",
        f"left={fleet['uris']['left']}",
        "--json",
    )
    assert r.exit_code == 1
    assert len(fleet["devices"]["left"].requests) == before


@pytest.mark.parametrize(
    "device, code",
    [("left=ftp://127.0.0.1", 3), ("left=udp://127.0.0.1:99999", 3), ("nosuch=udp://127.0.0.1", 3), ("left", 2)],
)
def test_bad_device_arguments(fleet, device, code):
    r = run(
        "fleet",
        "status",
        fleet["robot"].doc,
        "--release",
        fleet["new_dir"],
        "--key",
        fleet["robot"].pub,
        "--device",
        device,
    )
    assert r.exit_code == code, r.stderr


def test_address_from_discovered(world, tmp_path):
    """<discovered><ip>/<port> is the UDP address when --device does not say."""
    for name, _, _ in COMPS:
        set_running(world, name)
    port = world["uris"]["imu"].rsplit(":", 1)[1]
    doc = world["robot"].doc
    text = doc.read_text()
    patched = text.replace(
        '<software name="imu-fw"><version>1.2.0</version></software>',
        '<software name="imu-fw"><version>1.2.0</version></software>'
        f"<discovered><ip>127.0.0.1</ip><port>{port}</port></discovered>",
    )
    assert patched != text
    doc.write_text(patched)
    try:
        world["devices"]["imu"].description = ("x", hashlib.sha256(patched.encode()).hexdigest())
        r = status(world, "--json", devices={k: v for k, v in world["uris"].items() if k != "imu"})
        assert verdicts(r)["imu"] == "current", json.dumps(r.json["devices"])
    finally:
        doc.write_text(text)


def test_description_of_a_comp_in_an_included_fragment(tmp_path):
    """A comp described in an included fragment was built for that fragment: its pinned sha."""
    from ._fleet import make_fleet_robot
    from ._smp_responder import FakeDevice, Responder

    robot = make_fleet_robot(tmp_path, [("arm", "board_a", "arm-fw")])
    robot.write(run, "2.0.0")
    fragment = robot.root / "arm.hcdf"
    fragment.write_text(robot.doc.read_text())
    frag_sha = hashlib.sha256(fragment.read_bytes()).hexdigest()
    robot.doc.write_text(
        f'<?xml version="1.0"?>\n<hcdf version="1.0" name="r">\n  <include uri="arm.hcdf" sha="{frag_sha}"/>\n</hcdf>\n'
    )
    assert run("resolve", robot.doc).exit_code == 0
    signed = robot.build(run, tmp_path / "rel")
    responder = Responder()
    try:
        device = FakeDevice(
            slots=[SlotState(0, "2.0.0", bytes.fromhex(signed["arm"][1]), active=True, confirmed=True)],
            description=("https://example.invalid/arm.hcdf", frag_sha),
        )
        uri = responder.add(device)
        args = [
            "fleet",
            "status",
            robot.doc,
            "--release",
            tmp_path / "rel",
            "--key",
            robot.pub,
            "--json",
            "--device",
            f"arm={uri}",
        ]
        r = run(*args)
        assert r.exit_code == 0 and verdicts(r) == {"arm": "current"}, r.stdout
        root_sha = hashlib.sha256(robot.doc.read_bytes()).hexdigest()
        device.description = ("https://example.invalid/robot.hcdf", root_sha)
        r = run(*args)
        assert r.exit_code == 1 and verdicts(r) == {"arm": "wrong-description"}
    finally:
        responder.close()


def test_serial_line_that_never_stops_sending(fleet):
    """A device on socket:// (a serial console over TCP) that streams console bytes forever:
    fleet reads at most 256 KiB for one answer, then calls it malformed (it stops by itself too)."""
    import socket
    import threading
    import time

    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(1)
    port = server.getsockname()[1]
    sent = []

    def flood() -> None:
        conn, _ = server.accept()
        total, deadline = 0, time.monotonic() + 60
        junk = b"boot log line that never ends " * 140
        try:
            while total < (64 << 20) and time.monotonic() < deadline:
                conn.sendall(junk)
                total += len(junk)
        except OSError:
            pass
        finally:
            sent.append(total)
            conn.close()
            server.close()

    thread = threading.Thread(target=flood, daemon=True)
    thread.start()
    devices = dict(fleet["uris"], imu=f"socket://127.0.0.1:{port}")
    r = status(fleet, "--json", devices=devices, timeout="60")
    thread.join(70)
    assert r.exit_code == 3, r.stdout
    imu = next(d for d in r.json["devices"] if d["comp"] == "imu")
    assert imu["verdict"] == "malformed-answer" and "262144 bytes" in imu["reason"], (imu["reason"], sent)
    assert sent and sent[0] < (64 << 20)  # the reader gave up, not the flood


def test_opening_a_serial_line_discards_a_bounded_amount():
    """Opening a socket:// line discards what is waiting, as pyserial does, but at most 256 KiB:
    pyserial's own loop reads until nothing is waiting, so a peer that keeps ahead of it kept
    ``fleet status`` inside open() until the peer stopped (a CI run saw it, on a loaded machine).
    The peer here has pushed over 512 KiB into the kernel's buffers before the line is reset."""
    import socket
    import threading
    import time

    import serial

    from hcdf_trust.fleet.smp import MAX_SERIAL_BYTES, _socket_line_class

    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(1)
    pushed, total, opened = [0], 2 << 20, threading.Event()

    def push() -> None:
        conn, _ = server.accept()
        try:
            opened.wait(10)  # open() resets the line too: nothing is sent before it returns
            while pushed[0] < total:
                conn.sendall(b"x" * (64 << 10))
                pushed[0] += 64 << 10
        finally:
            conn.close()  # the reader sees the end after the last byte
            server.close()

    thread = threading.Thread(target=push, daemon=True)
    thread.start()
    line = _socket_line_class()(None, timeout=0, write_timeout=0)
    line.port = f"socket://127.0.0.1:{server.getsockname()[1]}"
    line.open()
    opened.set()
    try:
        deadline = time.monotonic() + 20
        while pushed[0] < (512 << 10) and time.monotonic() < deadline:
            time.sleep(0.01)
        assert pushed[0] >= (512 << 10), "the kernel would not buffer 512 KiB on loopback"
        line.reset_input_buffer()
        assert line.in_waiting, "the reset read everything there was"
        rest, deadline = 0, time.monotonic() + 20
        with pytest.raises(serial.SerialException, match="disconnected"):
            while time.monotonic() < deadline:
                rest += len(line.read(1 << 16))
        assert total - rest == MAX_SERIAL_BYTES
    finally:
        line.close()
        thread.join(10)
