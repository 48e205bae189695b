"""Benchmark for ``hcdf-trust ota build`` (issue 7), against ``imgtool sign`` measured in the same run.

    .venv/bin/python bench/ota.py [--images 50] [--size 1048576] [--repeat 3] [--no-hsm]

A release of ``--images`` images of ``--size`` random bytes each (one ``<comp>`` per
image), built by one ``hcdf-trust ota build`` process (resolve under the lock, sign
every image, latest.json, the signed SUIT manifest), is compared with invoking the
``imgtool sign`` CLI once per image in sequence, which is what release scripts do
today. With SoftHSM2 installed, the same build is timed with the key in a PKCS#11
token. Wall clock and CPU time (user + system of the child processes), medians of
``--repeat`` runs after one untimed warm-up, with the 1-minute load average; inputs are
read once first so both sides hash from the page cache. Files go to bench/work/ota/.
Targets: imgtool / ota build ≥ 10×; HSM build ≤ 2× the file-key build.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import resource
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
PROJECT = HERE.parent
WORK = HERE / "work" / "ota"
BIN = PROJECT / ".venv" / "bin"
CLI = Path(os.environ.get("HCDF_TRUST_CLI", BIN / "hcdf-trust"))
IMGTOOL = BIN / "imgtool"
ENV = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
ENV["PYTHONPYCACHEPREFIX"] = str(HERE / "work" / "pycache")
SOFTHSM_MODULES = ("/usr/lib/softhsm/libsofthsm2.so", "/usr/lib/x86_64-linux-gnu/softhsm/libsofthsm2.so")
PIN = "1234"


CPU: list[float] = []  # CPU seconds (user + system) of the processes of the current measurement


def run(argv: list[str | os.PathLike[str]], env: dict[str, str] | None = None) -> float:
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    proc = subprocess.run([str(a) for a in argv], capture_output=True, text=True, env=env or ENV)
    wall = time.perf_counter() - t
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    CPU.append(after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime)
    if proc.returncode != 0:
        sys.exit(f"failed ({proc.returncode}): {' '.join(map(str, argv))}\n{proc.stderr}")
    return wall


def timed(fn, repeat: int) -> tuple[float, float]:
    """Median wall clock and median CPU time of ``repeat`` runs of ``fn`` after a warm-up."""
    fn()  # warm-up
    walls, cpus = [], []
    for _ in range(repeat):
        CPU.clear()
        walls.append(fn())
        cpus.append(sum(CPU))
    return statistics.median(walls), statistics.median(cpus)


def generate(images: int, size: int) -> Path:
    shutil.rmtree(WORK, ignore_errors=True)
    (WORK / "fw").mkdir(parents=True)
    rng = random.Random(7)
    comps = []
    for i in range(images):
        app = f"app-{i:03d}"
        (WORK / "fw" / f"{app}.bin").write_bytes(rng.randbytes(size))
        comps.append(
            f'  <comp name="c{i:03d}"><board>bench</board>'
            f'<software name="{app}"><version>1.0.0</version></software></comp>'
        )
    doc = WORK / "robot.hcdf"
    doc.write_text('<?xml version="1.0"?>\n<hcdf version="1.0" name="bench">\n' + "\n".join(comps) + "\n</hcdf>\n")
    (WORK / "ota.toml").write_text("[boards.default]\nheader_size = 0x200\nslot_size = 0x200000\n")
    run([CLI, "resolve", doc])
    run([CLI, "ota", "keygen", "--type", "ecdsa-p256", "-o", WORK / "key.pem", "--force"])
    for f in (WORK / "fw").iterdir():
        f.read_bytes()
    return doc


def softhsm(env: dict[str, str]) -> str | None:
    module = next((m for m in SOFTHSM_MODULES if os.path.exists(m)), None)
    util = shutil.which("softhsm2-util")
    if module is None or util is None:
        return None
    tokens = WORK / "softhsm" / "tokens"
    tokens.mkdir(parents=True)
    conf = WORK / "softhsm" / "softhsm2.conf"
    conf.write_text(f"directories.tokendir = {tokens}\nobjectstore.backend = file\nlog.level = ERROR\n")
    env["SOFTHSM2_CONF"] = str(conf)
    subprocess.run(
        [util, "--init-token", "--free", "--label", "bench", "--pin", PIN, "--so-pin", "87654321"],
        check=True,
        capture_output=True,
        env=env,
    )
    script = (
        "import pkcs11,sys\n"
        "from pkcs11 import Attribute, KeyType\n"
        "from pkcs11.util.ec import encode_named_curve_parameters\n"
        f"lib = pkcs11.lib({module!r})\n"
        f"with lib.get_token(token_label='bench').open(user_pin={PIN!r}, rw=True) as s:\n"
        "    p = s.create_domain_parameters(KeyType.EC, {Attribute.EC_PARAMS: "
        "encode_named_curve_parameters('secp256r1')}, local=True)\n"
        "    p.generate_keypair(store=True, label='fw')\n"
    )
    subprocess.run([BIN / "python", "-c", script], check=True, env=env)
    env["HCDF_TRUST_PKCS11_PIN"] = PIN
    return f"pkcs11:token=bench;object=fw?module-path={module}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--images", type=int, default=50)
    ap.add_argument("--size", type=int, default=1 << 20)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--no-hsm", action="store_true")
    args = ap.parse_args()
    doc = generate(args.images, args.size)
    out = WORK / "release"
    signed = WORK / "imgtool"
    signed.mkdir()

    def build(key: str | os.PathLike[str] = WORK / "key.pem", env: dict[str, str] | None = None) -> float:
        shutil.rmtree(out, ignore_errors=True)
        return run([CLI, "ota", "build", doc, "--firmware-dir", WORK / "fw", "--key", key, "--out", out], env=env)

    def imgtool_each() -> float:
        total = 0.0
        for f in sorted((WORK / "fw").iterdir()):
            total += run(
                [
                    IMGTOOL,
                    "sign",
                    "-k",
                    WORK / "key.pem",
                    "--version",
                    "1.0.0",
                    "-H",
                    "0x200",
                    "--pad-header",
                    "-S",
                    "0x200000",
                    f,
                    signed / f.name,
                ]
            )
        return total

    results: dict[str, float] = {"load_before": os.getloadavg()[0]}
    results["ota_build_s"], results["ota_build_cpu_s"] = timed(build, args.repeat)
    results["imgtool_cli_s"], results["imgtool_cli_cpu_s"] = timed(imgtool_each, args.repeat)
    results["ratio_imgtool_over_ota"] = results["imgtool_cli_s"] / results["ota_build_s"]
    if not args.no_hsm:
        env = dict(ENV)
        uri = softhsm(env)
        if uri is not None:
            results["ota_build_hsm_s"], results["ota_build_hsm_cpu_s"] = timed(lambda: build(uri, env), args.repeat)
            results["ratio_hsm_over_file"] = results["ota_build_hsm_s"] / results["ota_build_s"]
    results["load_after"] = os.getloadavg()[0]
    n = args.images
    rows = [
        ("`imgtool sign` CLI, once per image", "imgtool_cli_s"),
        ("`hcdf-trust ota build` (whole release)", "ota_build_s"),
    ]
    if "ota_build_hsm_s" in results:
        rows.append(("`hcdf-trust ota build`, key in SoftHSM2", "ota_build_hsm_s"))
    print(f"| {n} × {args.size >> 20} MiB images | seconds | per image | CPU seconds |")
    print("|---|---|---|---|")
    for label, key in rows:
        cpu = results[key.removesuffix("_s") + "_cpu_s"]
        print(f"| {label} | {results[key]:.2f} | {results[key] / n * 1000:.0f} ms | {cpu:.2f} |")
    print(f"\nimgtool CLI / ota build: {results['ratio_imgtool_over_ota']:.1f}× (target ≥ 10×)")
    if "ratio_hsm_over_file" in results:
        print(f"HSM / file key: {results['ratio_hsm_over_file']:.2f}× (target ≤ 2×)")
    print(f"1-minute load average: {results['load_before']:.1f} before, {results['load_after']:.1f} after")
    (WORK / "results.json").write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()
