"""A small robot with firmware for the ota tests: documents, lock, binaries, keys."""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

from hcdf_trust.ota.keys import generate, private_pem, public_pem

ROBOT = """<?xml version="1.0"?>
<hcdf version="1.0" name="t">
  <comp name="main">
    <board>mr_mcxn_t1</board>
    <visual name="v"><model uri="body.glb" sha="{model_sha}"/></visual>
    <software name="flex-io"><version>{flex_version}</version>{flex_hash}</software>
  </comp>
  <comp name="gnss">
    <board>mr_mcxn_t1</board>
    <software name="rtk-gnss"><version>1.0.0+3</version></software>
  </comp>
  <comp name="compute">
    <software name="scout-os"><version>2026.11</version></software>
  </comp>
</hcdf>
"""

OTA_TOML = """[images.scout-os]
type = "raw"
"""


@dataclass
class Robot:
    root: Path
    doc: Path
    fw: Path
    key: Path
    pub: Path

    def rewrite(self, cli, *, flex_version: str = "v0.2.0", flex_hash: str | None = None) -> None:
        """Rewrite the document and lock it again."""
        hash_el = f"<hash>{flex_hash}</hash>" if flex_hash else ""
        model_sha = hashlib.sha256((self.root / "body.glb").read_bytes()).hexdigest()
        self.doc.write_text(ROBOT.format(flex_version=flex_version, flex_hash=hash_el, model_sha=model_sha))
        r = cli("resolve", self.doc)
        assert r.exit_code == 0, r.stderr

    def build(self, cli, out: Path, *extra: str | os.PathLike[str]):
        return cli(
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


def make_robot(tmp_path: Path, cli, *, kind: str = "ecdsa-p256", size: int = 10000) -> Robot:
    root = tmp_path / "robot"
    (root / "fw" / "mr_mcxn_t1").mkdir(parents=True)
    rng = __import__("random").Random(size)
    (root / "fw" / "mr_mcxn_t1" / "flex-io.bin").write_bytes(rng.randbytes(size))
    (root / "fw" / "rtk-gnss.bin").write_bytes(rng.randbytes(size // 2 + 1))
    (root / "fw" / "scout-os.bin").write_bytes(rng.randbytes(300))
    (root / "ota.toml").write_text(OTA_TOML)
    (root / "body.glb").write_bytes(b"glTF model stand-in")
    keydir = tmp_path / "keys"
    keydir.mkdir()
    key = generate(kind)
    (keydir / "fw.pem").write_bytes(private_pem(key, None))
    (keydir / "fw.pub.pem").write_bytes(public_pem(key))
    robot = Robot(root, root / "robot.hcdf", root / "fw", keydir / "fw.pem", keydir / "fw.pub.pem")
    robot.rewrite(cli)
    return robot


def tree(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` with its bytes (to prove a failed run changed nothing)."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}
