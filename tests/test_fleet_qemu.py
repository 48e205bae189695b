"""``fleet status``, ``update`` and ``confirm`` against real SMP servers: Zephyr 4.4.0
smp_server + MCUboot under qemu-system-arm (started once for this module, killed by process
id at the end). Uploads under emulation take seconds and can stall under load: generous
timeouts, nothing timed.

The micro:bit's release image is the fixture's own application (its payload, without
MCUboot's header and TLVs), signed by ``ota build`` with the test key at version 1.0.0: the
fixture's MCUboot checks the image hash only, so after ``update`` and a reset it swaps the
release's image in and runs it — unconfirmed until ``fleet confirm``.
"""

from __future__ import annotations

import hashlib
import struct
import time

import pytest

from . import _qemu
from ._fleet import MICROBIT_APP, MPS2_APP, make_fleet_robot, run

COMPS = [("mb", "qemu_microbit", "smp-mb"), ("mps", "qemu_mps2", "smp-mps")]
TIMEOUT = "120"


def mcuboot_hash(data: bytes) -> str:
    """Independent oracle: MCUboot's image hash is SHA-256 over header + payload + protected TLVs,
    read here straight from the header (struct image_header in MCUboot's image.h)."""
    magic, _load, hdr_size, prot_tlv_size, img_size = struct.unpack_from("<IIHHI", data)
    assert magic == 0x96F3B83D
    return hashlib.sha256(data[: hdr_size + img_size + prot_tlv_size]).hexdigest()


def payload(data: bytes) -> bytes:
    _magic, _load, hdr_size, _prot, img_size = struct.unpack_from("<IIHHI", data)
    return data[hdr_size : hdr_size + img_size]


@pytest.fixture(scope="module")
def qemu(tmp_path_factory):
    _qemu.require_qemu()
    tmp = tmp_path_factory.mktemp("qemu")
    devices = _qemu.start(["microbit", "mps2"], tmp)
    try:
        robot = make_fleet_robot(tmp, COMPS)
        robot.write(run, "1.0.0", size=20000)
        (robot.fw / "qemu_microbit" / "smp-mb.bin").write_bytes(payload(MICROBIT_APP.read_bytes()))
        hashes = robot.build(run, tmp / "release")
        yield {
            "robot": robot,
            "release": tmp / "release",
            "hashes": hashes,
            "uris": {"mb": devices[0].uri, "mps": devices[1].uri},
        }
    finally:
        _qemu.stop(devices)


def args(q, verb, *extra):
    out = [verb, q["robot"].doc, "--release", q["release"], "--key", q["robot"].pub, "--timeout", TIMEOUT, "--json"]
    for name, uri in q["uris"].items():
        out += ["--device", f"{name}={uri}"]
    return ["fleet", *out, *extra]


def by_comp(r) -> dict[str, dict]:
    return {d["comp"]: d for d in r.json["devices"]}


def reset_and_wait(uri: str) -> bytes:
    """What the user does after an update (here: SMP's os reset, on a raw connection to the
    console), then wait until the application has booted again — its log line after MCUboot's
    swap — so that no request lands while the bootloader runs. The console is returned."""
    import socket

    from smp import os_management as osm
    from smp import packet as smppacket

    port = int(uri.rsplit(":", 1)[1])
    console = b""
    with socket.create_connection(("127.0.0.1", port), timeout=1) as s:
        for chunk in smppacket.encode(osm.ResetWriteRequest().BYTES, line_length=128):
            s.sendall(chunk)
        deadline = time.monotonic() + 300  # a bound on the emulated swap, not an assertion
        while b"smp_sample" not in console.split(b"Jumping to the first image slot")[-1]:
            if time.monotonic() > deadline:
                break
            try:
                data = s.recv(4096)
            except TimeoutError:
                continue
            if not data:
                break
            console = (console + data)[-65536:]
    return console


def test_status_update_reset_confirm_on_real_devices(qemu):
    release_image = (qemu["release"] / "qemu_microbit" / "smp-mb" / "1.0.0.bin").read_bytes()
    want = qemu["hashes"]["mb"][1]
    assert mcuboot_hash(release_image) == want

    # 1. they run the fixture's smp_server, which no release of this key lists
    r = run(*args(qemu, "status"))
    assert r.exit_code == 1, r.stdout
    mb, mps = by_comp(r)["mb"], by_comp(r)["mps"]
    assert mb["verdict"] == mps["verdict"] == "unknown-image"
    assert mb["slots"][0] | {"hash": None} == {
        "image": 0, "slot": 0, "version": "0.0.0", "hash": None, "active": True, "confirmed": True,
        "pending": False, "permanent": False, "bootable": True,
    }  # fmt: skip
    assert mb["slots"][0]["hash"] == mcuboot_hash(MICROBIT_APP.read_bytes())
    assert mps["slots"][0]["hash"] == mcuboot_hash(MPS2_APP.read_bytes())
    assert mb["description"] is None  # no HCDF group: the device answers rc 8 (ENOTSUP)

    # 2. update: slot 1 of the real device reports the release image's hash and version, pending
    r = run(*args(qemu, "update", "--only", "mb", "--dry-run"))
    assert r.exit_code == 0 and by_comp(r)["mb"]["result"] == "would-update", r.stdout
    # An emulated UART can lose a chunk or its answer: the device then never answers, the run
    # ends unreachable (exit 3), and running update again resumes where the device says it
    # stopped — which may be past the bytes the lost answers would have acknowledged, so the
    # sum of bytes_sent is not the image size. The oracle is the device's own report below.
    sent = 0
    for _ in range(5):
        r = run(*args(qemu, "update", "--only", "mb"))
        sent += by_comp(r)["mb"]["bytes_sent"]
        if r.exit_code != 3:
            break
        assert r.json["errors"][0]["code"] == "unreachable", r.stdout
    assert r.exit_code == 0, r.stdout
    assert by_comp(r)["mb"]["result"] == "updated" and sent > 0
    mb = by_comp(run(*args(qemu, "status")))["mb"]
    slot1 = next(s for s in mb["slots"] if s["slot"] == 1)
    assert (slot1["version"], slot1["hash"]) == ("1.0.0", want)
    assert slot1["pending"] and not slot1["permanent"] and not slot1["active"]
    r = run(*args(qemu, "update", "--only", "mb"))  # found in slot 1: nothing sent again
    assert r.exit_code == 0 and by_comp(r)["mb"]["bytes_sent"] == 0, r.stdout

    # 3. reset: MCUboot swaps the release's image in; it runs unconfirmed (it would revert)
    console = reset_and_wait(qemu["uris"]["mb"])
    assert b"smp_sample" in console.split(b"Jumping to the first image slot")[-1], console[-2000:]
    r = run(*args(qemu, "status", "--skip-description"))
    mb = by_comp(r)["mb"]
    assert mb["verdict"] == "unconfirmed", (mb["reason"], mb["slots"], console[-2000:])
    assert mb["slots"][0]["hash"] == want and mb["slots"][0]["active"] and not mb["slots"][0]["confirmed"]

    # 4. confirm: only mb runs the release; mps is left alone (exit 1), mb is confirmed
    r = run(*args(qemu, "confirm"))
    assert r.exit_code == 1
    assert {c: d["result"] for c, d in by_comp(r).items()} == {"mb": "confirmed", "mps": "not-running-release"}
    r = run(*args(qemu, "status", "--skip-description"))
    assert by_comp(r)["mb"]["verdict"] == "current"
    assert by_comp(r)["mb"]["slots"][0]["confirmed"]
    # with the description check, a device without the HCDF group cannot be current
    assert by_comp(run(*args(qemu, "status")))["mb"]["verdict"] == "no-hcdf-group"
