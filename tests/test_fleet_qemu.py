"""``fleet status`` and ``fleet update`` against real SMP servers: Zephyr 4.4.0 smp_server +
MCUboot under qemu-system-arm (started once for this module, killed by process id at the end).
Uploads under emulation take seconds and can stall under load: generous timeouts, nothing timed."""

from __future__ import annotations

import hashlib
import struct

import pytest
from click.testing import CliRunner

from hcdf_trust.cli import main

from . import _qemu
from ._fleet import MICROBIT_APP, MPS2_APP, make_fleet_robot
from .conftest import CliResult

COMPS = [("mb", "qemu_microbit", "smp-mb"), ("mps", "qemu_mps2", "smp-mps")]
TIMEOUT = "30"


def run(*args) -> CliResult:
    r = CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)
    return CliResult(r.exit_code, r.stdout, r.stderr)


def mcuboot_hash(path) -> str:
    """Independent oracle: MCUboot's image hash is SHA-256 over header + payload + protected TLVs,
    read here straight from the header (struct image_header in MCUboot's image.h)."""
    data = path.read_bytes()
    magic, _load, hdr_size, prot_tlv_size, img_size = struct.unpack_from("<IIHHI", data)
    assert magic == 0x96F3B83D
    return hashlib.sha256(data[: hdr_size + img_size + prot_tlv_size]).hexdigest()


@pytest.fixture(scope="module")
def qemu(tmp_path_factory):
    _qemu.require_qemu()
    tmp = tmp_path_factory.mktemp("qemu")
    devices = _qemu.start(["microbit", "mps2"], tmp)
    try:
        robot = make_fleet_robot(tmp, COMPS)
        robot.write(run, "1.2.3", size=20000)
        hashes = robot.build(run, tmp / "release")
        yield {
            "robot": robot,
            "release": tmp / "release",
            "hashes": hashes,
            "uris": {"mb": devices[0].uri, "mps": devices[1].uri},
            "devices": devices,
        }
    finally:
        _qemu.stop(devices)


def status(q, *extra):
    args = [
        "fleet",
        "status",
        q["robot"].doc,
        "--release",
        q["release"],
        "--key",
        q["robot"].pub,
        "--timeout",
        TIMEOUT,
        "--json",
    ]
    for name, uri in q["uris"].items():
        args += ["--device", f"{name}={uri}"]
    return run(*args, *extra)


def test_status_reads_the_real_devices(qemu):
    r = status(qemu)
    assert r.exit_code == 1, r.stdout
    by = {d["comp"]: d for d in r.json["devices"]}
    # they run the fixture's smp_server, which no release of this key lists
    assert by["mb"]["verdict"] == by["mps"]["verdict"] == "unknown-image"
    assert by["mb"]["slots"][0] | {"hash": None} == {
        "image": 0,
        "slot": 0,
        "version": "0.0.0",
        "hash": None,
        "active": True,
        "confirmed": True,
        "pending": False,
        "permanent": False,
        "bootable": True,
    }
    assert by["mb"]["slots"][0]["hash"] == mcuboot_hash(MICROBIT_APP)
    assert by["mps"]["slots"][0]["hash"] == mcuboot_hash(MPS2_APP)
    # neither implements the HCDF group: the answer is rc 8 (ENOTSUP), not a description
    assert by["mb"]["description"] is None


def test_update_uploads_to_slot_1_and_marks_it_pending(qemu):
    from ._smp_responder import mcuboot_identity

    image = (qemu["release"] / "qemu_microbit" / "smp-mb" / "1.2.3.bin").read_bytes()
    version, image_hash = mcuboot_identity(image)
    assert image_hash.hex() == qemu["hashes"]["mb"][1]
    base = [
        "fleet",
        "update",
        qemu["robot"].doc,
        "--release",
        qemu["release"],
        "--key",
        qemu["robot"].pub,
        "--device",
        f"mb={qemu['uris']['mb']}",
        "--device",
        f"mps={qemu['uris']['mps']}",
        "--only",
        "mb",
        "--timeout",
        "60",
        "--json",
    ]
    r = run(*base, "--dry-run")
    assert r.exit_code == 0 and r.json["devices"][0]["result"] == "would-update", r.stdout
    r = run(*base)
    assert r.exit_code == 0, r.stdout
    assert [d["result"] for d in r.json["devices"]] == ["updated"]
    assert r.json["devices"][0]["bytes_sent"] >= len(image)
    # what the real device now reports
    r = status(qemu)
    mb = next(d for d in r.json["devices"] if d["comp"] == "mb")
    slot1 = next(s for s in mb["slots"] if s["slot"] == 1)
    assert (slot1["version"], slot1["hash"]) == (version, image_hash.hex()) == ("1.2.3", qemu["hashes"]["mb"][1])
    assert slot1["pending"] and not slot1["permanent"] and not slot1["active"]
    assert mb["slots"][0]["hash"] == mcuboot_hash(MICROBIT_APP) and mb["verdict"] == "unknown-image"
    # a second run finds it there and sends nothing
    r = run(*base)
    assert r.exit_code == 0 and r.json["devices"][0]["bytes_sent"] == 0, r.stdout
