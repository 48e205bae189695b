"""Real SMP devices: Zephyr's smp_server + MCUboot under qemu-system-arm, each with its
serial console on a TCP port of 127.0.0.1 (shared/fixtures/smp-server/README.md)."""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

from ._fleet import MICROBIT_HEX, MPS2_APP, MPS2_HEX


@dataclass
class QemuDevice:
    kind: str
    port: int
    proc: subprocess.Popen[bytes]

    @property
    def uri(self) -> str:
        return f"socket://127.0.0.1:{self.port}"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _command(kind: str, port: int) -> list[str]:
    chardev = ["-chardev", f"socket,id=con,host=127.0.0.1,port={port},server=on,wait=off", "-serial", "chardev:con"]
    if kind == "microbit":
        return [
            "qemu-system-arm",
            "-cpu",
            "cortex-m0",
            "-machine",
            "microbit",
            "-nographic",
            *chardev,
            "-monitor",
            "none",
            "-device",
            f"loader,file={MICROBIT_HEX}",
        ]
    return [
        "qemu-system-arm",
        "-cpu",
        "cortex-m3",
        "-machine",
        "mps2-an385",
        "-nographic",
        *chardev,
        "-serial",
        "null",
        "-monitor",
        "none",
        "-device",
        f"loader,file={MPS2_HEX}",
        "-device",
        f"loader,file={MPS2_APP},addr=0x20050000",
    ]


def require_qemu() -> None:
    """Skip (with the reason) only where this machine cannot run QEMU; in CI that is a failure."""
    why = None
    if shutil.which("qemu-system-arm") is None:
        why = "qemu-system-arm is not installed (.ci/apt-packages lists it)"
    elif not MICROBIT_HEX.is_file() or not MPS2_HEX.is_file():
        why = f"the SMP server images are missing from {MICROBIT_HEX.parent}"
    if why:
        if os.environ.get("CI"):
            pytest.fail(why)
        pytest.skip(why)


def start(kinds: list[str], log_dir: Path) -> list[QemuDevice]:
    """Start one emulated device per kind; each is up when its socket accepts a connection."""
    devices: list[QemuDevice] = []
    try:
        for i, kind in enumerate(kinds):
            port = _free_port()
            log = open(log_dir / f"qemu-{i}-{kind}.log", "wb")  # noqa: SIM115 - closed with the process
            proc = subprocess.Popen(_command(kind, port), stdin=subprocess.DEVNULL, stdout=log, stderr=log)
            log.close()
            devices.append(QemuDevice(kind, port, proc))
        for d in devices:
            deadline = time.monotonic() + 60
            while True:
                if d.proc.poll() is not None:
                    raise RuntimeError(f"qemu ({d.kind}) exited with {d.proc.returncode}; see {log_dir}")
                try:
                    socket.create_connection(("127.0.0.1", d.port), timeout=1).close()
                    break
                except OSError:
                    if time.monotonic() > deadline:
                        raise
                    time.sleep(0.1)
        return devices
    except BaseException:
        stop(devices)
        raise


def stop(devices: list[QemuDevice]) -> None:
    """Kill each QEMU by its own process id and reap it."""
    for d in devices:
        if d.proc.poll() is None:
            d.proc.kill()
    for d in devices:
        try:
            d.proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            pass
