"""Benchmark for ``hcdf-trust fleet status`` (issue 23): 100 simulated devices, each
answering after ``--latency`` (20 ms), asked with the default parallelism vs one after another.

    .venv/bin/python bench/fleet.py [--devices 100] [--latency 0.02] [--repeat 3]

The devices are the tests' in-process SMP responder (tests/_smp_responder.py: asyncio UDP
on 127.0.0.1, built from the smp package's models), every one running the release's image
and reporting the description's SHA-256, so every request of a real run is made (image
state + HCDF group per device). Two measurements, medians of ``--repeat`` after a warm-up:
the whole command (``hcdf-trust fleet status`` in its own process: start-up, resolve,
release verification, the devices) with the default ``--jobs`` and with ``--jobs 1``, and
the device phase alone (in-process :func:`hcdf_trust.fleet.status.ask_all`), with the cost
per device. Target: ≥ 10× with the default parallelism. Files go to bench/work/fleet/.
"""

from __future__ import annotations

import argparse
import asyncio
import hashlib
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
PROJECT = HERE.parent
sys.path.insert(0, str(PROJECT))
WORK = HERE / "work" / "fleet"
CLI = Path(os.environ.get("HCDF_TRUST_CLI", PROJECT / ".venv" / "bin" / "hcdf-trust"))


def setup(n: int) -> tuple[Path, Path, Path, str]:
    from hcdf_trust.ota.keys import generate, private_pem, public_pem

    shutil.rmtree(WORK, ignore_errors=True)
    (WORK / "fw" / "sim").mkdir(parents=True)
    (WORK / "fw" / "sim" / "fw.bin").write_bytes(os.urandom(4096))
    comps = "".join(
        f'  <comp name="mcu{i}"><board>sim</board><software name="fw"><version>1.0.0</version></software></comp>\n'
        for i in range(n)
    )
    doc = WORK / "robot.hcdf"
    doc.write_text(f'<?xml version="1.0"?>\n<hcdf version="1.0" name="bench">\n{comps}</hcdf>\n')
    key = generate("ecdsa-p256")
    (WORK / "fw.pem").write_bytes(private_pem(key, None))
    (WORK / "fw.pub.pem").write_bytes(public_pem(key))
    for argv in (
        [CLI, "resolve", doc],
        [
            CLI,
            "ota",
            "build",
            doc,
            "--firmware-dir",
            WORK / "fw",
            "--key",
            WORK / "fw.pem",
            "--out",
            WORK / "rel",
            "--base-url",
            "https://fw.example.invalid/",
        ],
    ):
        subprocess.run([str(a) for a in argv], check=True, capture_output=True)
    return doc, WORK / "rel", WORK / "fw.pub.pem", hashlib.sha256(doc.read_bytes()).hexdigest()


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--devices", type=int, default=100)
    ap.add_argument("--latency", type=float, default=0.02)
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args()

    from hcdf_trust.fleet import status as st
    from hcdf_trust.ota.keys import load_public
    from hcdf_trust.ota.release import read_release
    from tests._smp_responder import FakeDevice, Responder, SlotState

    doc, rel, pub, doc_sha = setup(a.devices)
    release, _ = read_release(str(rel), load_public(str(pub)))
    [component] = release.components
    responder = Responder()
    uris = {}
    for i in range(a.devices):
        device = FakeDevice(
            slots=[SlotState(0, "1.0.0", bytes.fromhex(component.mcuboot_hash), active=True, confirmed=True)],
            description=("bench", doc_sha),
            latency=a.latency,
        )
        uris[f"mcu{i}"] = responder.add(device)
    base = [str(CLI), "fleet", "status", str(doc), "--release", str(rel), "--key", str(pub), "--json"]
    for name, uri in uris.items():
        base += ["--device", f"{name}={uri}"]

    def cli(jobs: list[str]) -> float:
        t = time.perf_counter()
        p = subprocess.run(base + jobs, capture_output=True, text=True)
        wall = time.perf_counter() - t
        assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-2000:]
        return wall

    from hcdf_trust.include.resolver import TreeOptions

    res = st.resolve_tree(str(doc), TreeOptions())
    targets, _ = st.targets(res, release, uris, check_description=True)

    def phase(jobs: int) -> float:
        t = time.perf_counter()
        results = asyncio.run(st.ask_all(targets, {}, jobs=jobs, timeout=5))
        wall = time.perf_counter() - t
        assert {r.verdict for r in results} == {"current"}, {r.verdict for r in results}
        return wall

    try:
        cli([]), phase(st.DEFAULT_JOBS)  # warm-up
        rows = {}
        for label, fn in (
            (f"command, --jobs {st.DEFAULT_JOBS} (default)", lambda: cli([])),
            ("command, --jobs 1", lambda: cli(["--jobs", "1"])),
            (f"devices only, {st.DEFAULT_JOBS} at once", lambda: phase(st.DEFAULT_JOBS)),
            ("devices only, one after another", lambda: phase(1)),
        ):
            rows[label] = statistics.median(fn() for _ in range(a.repeat))
    finally:
        responder.close()
    load = os.getloadavg()[0]
    print(f"fleet status, {a.devices} devices, {a.latency * 1000:g} ms latency each, median of {a.repeat}, ", end="")
    print(f"load {load:.1f}")
    for label, wall in rows.items():
        print(f"  {label:40s} {wall:7.3f} s  ({wall / a.devices * 1000:6.1f} ms per device)")
    labels = list(rows)
    print(f"  ratio, whole command: {rows[labels[1]] / rows[labels[0]]:.1f}x")
    print(f"  ratio, device phase:  {rows[labels[3]] / rows[labels[2]]:.1f}x")


if __name__ == "__main__":
    main()
