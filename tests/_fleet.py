"""A test robot whose comps are MCUs reached over SMP, and signed releases for it."""

from __future__ import annotations

import random
from dataclasses import dataclass
from pathlib import Path

from hcdf_trust.ota.keys import generate, load_public, private_pem, public_pem
from hcdf_trust.ota.release import read_release

from .conftest import CORPUS

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
