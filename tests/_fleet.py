"""A test robot whose comps are MCUs reached over SMP, and signed releases for it; the
``world`` and ``fleet`` fixtures (a plugin of conftest.py): in-process SMP devices for it."""

from __future__ import annotations

import hashlib
import random
from dataclasses import dataclass
from pathlib import Path

import pytest
from click.testing import CliRunner

from hcdf_trust.cli import main
from hcdf_trust.ota.keys import generate, load_public, private_pem, public_pem
from hcdf_trust.ota.release import read_release

from .conftest import CORPUS, CliResult

FIXTURES = CORPUS.parent / "fixtures" / "smp-server"
MICROBIT_HEX = FIXTURES / "zephyr_4.4.0_smp_server_0eae053d_qemu_cortex_m0_serial.merged.hex"
MICROBIT_APP = FIXTURES / "zephyr_4.4.0_smp_server_0eae053d_qemu_cortex_m0_serial.signed.bin"
MPS2_HEX = FIXTURES / "zephyr_4.4.0_smp_server_0eae053d_mps2_an385_serial_recovery_buf2048.hex"
MPS2_APP = FIXTURES / "zephyr_4.4.0_smp_server_0eae053d_mps2_an385_serial_recovery_buf2048.signed.bin"

COMP = """  <comp name="{name}">
    <board>{board}</board>
    <software name="{app}"><version>{version}</version></software>{discovered}
  </comp>
"""


@dataclass
class FleetRobot:
    root: Path
    doc: Path
    fw: Path
    key: Path
    pub: Path
    comps: list[tuple[str, str, str]]  # (comp, board, app)

    def write(self, cli, version: str, *, discovered: dict[str, str] | None = None, size: int = 6000) -> None:
        """Firmware of ``version`` for every comp, the document, and its lock."""
        rng = random.Random(f"{version}-{size}")
        body = ""
        for name, board, app in self.comps:
            (self.fw / board).mkdir(parents=True, exist_ok=True)
            (self.fw / board / f"{app}.bin").write_bytes(rng.randbytes(size))
            disc = (discovered or {}).get(name)
            body += COMP.format(name=name, board=board, app=app, version=version, discovered=disc or "")
        self.doc.write_text(f'<?xml version="1.0"?>\n<hcdf version="1.0" name="fleet">\n{body}</hcdf>\n')
        r = cli("resolve", self.doc)
        assert r.exit_code == 0, r.stderr

    def build(self, cli, out: Path, *extra: str | Path) -> dict[str, tuple[str, str]]:
        """Build a release into ``out``; returns comp -> (version, mcuboot_hash) as signed."""
        r = cli(
            "ota",
            "build",
            self.doc,
            "--firmware-dir",
            self.fw,
            "--key",
            self.key,
            "--out",
            out,
            "--base-url",
            "https://fw.example.com/r",
            *extra,
        )
        assert r.exit_code == 0, r.stderr
        release, _ = read_release(str(out), load_public(str(self.pub)))
        return {name: (c.version, c.mcuboot_hash) for c in release.components for name in c.comps}


def make_fleet_robot(tmp_path: Path, comps: list[tuple[str, str, str]]) -> FleetRobot:
    root = tmp_path / "robot"
    (root / "fw").mkdir(parents=True)
    keydir = tmp_path / "keys"
    keydir.mkdir()
    key = generate("ecdsa-p256")
    (keydir / "fw.pem").write_bytes(private_pem(key, None))
    (keydir / "fw.pub.pem").write_bytes(public_pem(key))
    return FleetRobot(root, root / "robot.hcdf", root / "fw", keydir / "fw.pem", keydir / "fw.pub.pem", comps)


COMPS = [("left", "board_l", "motor"), ("right", "board_r", "motor-r"), ("imu", "board_i", "imu-fw")]


def run(*args) -> CliResult:
    r = CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)
    return CliResult(r.exit_code, r.stdout, r.stderr)


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """One robot, an old and a new signed release, three fake devices (one per comp)."""
    tmp = tmp_path_factory.mktemp("fleet")
    robot = make_fleet_robot(tmp, COMPS)
    robot.write(run, "1.0.0")
    old = robot.build(run, tmp / "old")
    robot.write(run, "1.2.0")
    new = robot.build(run, tmp / "new", "--previous", tmp / "old")
    from ._smp_responder import FakeDevice, Responder, SlotState  # noqa: F401 - smp only where used

    responder = Responder()
    devices = {name: FakeDevice(slots=[]) for name, _, _ in COMPS}
    uris = {name: responder.add(d) for name, d in devices.items()}
    yield {
        "robot": robot,
        "old": old,
        "new": new,
        "old_dir": tmp / "old",
        "new_dir": tmp / "new",
        "devices": devices,
        "uris": uris,
        "doc_sha": hashlib.sha256(robot.doc.read_bytes()).hexdigest(),
    }
    responder.close()


def set_running(world, name, which="new", *, confirmed=True, description=True, pending=None):
    """Device ``name`` runs release ``which``'s image (or raw bytes); ``pending``: slot 1's."""
    d = world["devices"][name]
    h = world[which][name][1] if which in ("old", "new") else which
    version = world[which][name][0] if which in ("old", "new") else "9.9.9"
    from ._smp_responder import SlotState

    d.slots = [SlotState(0, version, bytes.fromhex(h), active=True, confirmed=confirmed, bootable=True)]
    if pending is not None:
        d.slots.append(SlotState(1, world[pending][name][0], bytes.fromhex(world[pending][name][1]), pending=True))
    d.description = ("https://example.invalid/robot.hcdf", world["doc_sha"]) if description else None
    d.mode = None
    d.latency = 0.0


def status(world, *extra, devices=None, timeout="5"):
    args = [
        "fleet",
        "status",
        world["robot"].doc,
        "--release",
        world["new_dir"],
        "--key",
        world["robot"].pub,
        "--timeout",
        timeout,
    ]
    for name, uri in (devices or world["uris"]).items():
        args += ["--device", f"{name}={uri}"]
    return run(*args, *extra)


def verdicts(r) -> dict[str, str]:
    return {d["comp"]: d["verdict"] for d in r.json["devices"]}


@pytest.fixture
def fleet(world):
    for name, _, _ in COMPS:
        set_running(world, name)
    return world
