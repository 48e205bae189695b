"""Benchmark for ``hcdf-trust ota push`` / ``ota pull`` (issue 22) against plain curl, same run.

    .venv/bin/python bench/oci.py [--images 50] [--size 1048576] [--repeat 3]

A release of ``--images`` MCUboot images of ``--size`` random bytes (bench/ota.py's
generator, one ``ota build``) is pushed to and pulled from the Debian ``docker-registry``
(CNCF distribution) started on 127.0.0.1 with its own configuration. Baselines move the
same bytes with curl and verify nothing: uploads are one ``POST`` + one ``PUT`` curl
process per blob (what a shell script does), downloads one curl process fetching every
blob over one connection. ``ota pull`` starts from an empty cache and an empty folder and
does everything it always does (digests while streaming, content store, ``ota verify`` of
every image in a staging folder, the referrers, the output plan). Medians of ``--repeat``
runs after a warm-up, wall clock, and the peak RSS of the hcdf-trust process (GNU time).
Targets: pull ≤ 1.5× curl; memory independent of image size.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from ota import CLI, ENV, WORK, generate, run  # noqa: E402

OCI = WORK.parent / "oci"
TIME = "/usr/bin/time"


def start_registry() -> tuple[subprocess.Popen[bytes], str]:
    shutil.rmtree(OCI, ignore_errors=True)
    OCI.mkdir(parents=True)
    config = {
        "version": 0.1,
        "log": {"level": "info"},
        "storage": {"filesystem": {"rootdirectory": str(OCI / "storage")}, "delete": {"enabled": True}},
        "http": {"addr": "127.0.0.1:0", "secret": "bench"},
    }
    (OCI / "config.yml").write_text(json.dumps(config))
    log = open(OCI / "registry.log", "wb")  # noqa: SIM115
    proc = subprocess.Popen(["docker-registry", "serve", str(OCI / "config.yml")], stdout=log, stderr=log)
    for _ in range(500):
        m = re.search(rb"listening on (127\.0\.0\.1:\d+)", (OCI / "registry.log").read_bytes())
        if m:
            return proc, m.group(1).decode()
        time.sleep(0.02)
    proc.kill()
    sys.exit("docker-registry did not start")


def peak_rss(argv: list[str]) -> tuple[float, int]:
    """Wall clock and peak RSS (KiB) of one hcdf-trust process."""
    t = time.perf_counter()
    p = subprocess.run([TIME, "-f", "%M", *argv], capture_output=True, text=True, env=ENV)
    wall = time.perf_counter() - t
    if p.returncode != 0:
        sys.exit(f"failed: {' '.join(argv)}\n{p.stderr}")
    return wall, int(p.stderr.strip().splitlines()[-1])


def curl_push(host: str, repo: str, files: list[Path]) -> float:
    t = time.perf_counter()
    for f in files:
        digest = "sha256:" + hashlib.sha256(f.read_bytes()).hexdigest()
        head = subprocess.run(
            ["curl", "-sS", "-f", "-D", "-", "-o", "/dev/null", "-X", "POST", f"http://{host}/v2/{repo}/blobs/uploads/"],
            capture_output=True, text=True, check=True,
        )  # fmt: skip
        loc = next(
            line.split(":", 1)[1].strip() for line in head.stdout.splitlines() if line.lower().startswith("location:")
        )
        sep = "&" if "?" in loc else "?"
        subprocess.run(
            ["curl", "-sS", "-f", "-o", "/dev/null", "-X", "PUT", "-H", "Content-Type: application/octet-stream",
             "--data-binary", f"@{f}", f"{loc}{sep}digest={digest}"],
            check=True,
        )  # fmt: skip
    return time.perf_counter() - t


def curl_pull(host: str, repo: str, digests: list[str], dest: Path) -> float:
    shutil.rmtree(dest, ignore_errors=True)
    dest.mkdir(parents=True)
    argv = ["curl", "-sS", "-f", "-L"]
    for i, d in enumerate(digests):
        argv += [f"http://{host}/v2/{repo}/blobs/{d}", "-o", str(dest / f"{i}")]
    t = time.perf_counter()
    subprocess.run(argv, check=True)
    return time.perf_counter() - t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--images", type=int, default=50)
    ap.add_argument("--size", type=int, default=1 << 20)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    doc = generate(args.images, args.size)
    release = WORK / "release"
    run([CLI, "ota", "build", doc, "--firmware-dir", WORK / "fw", "--key", WORK / "key.pem", "--out", release])
    pub = WORK / "key.pub.pem"
    files = sorted(p for p in release.rglob("*") if p.is_file())
    proc, host = start_registry()
    try:
        n = iter(range(10_000))
        res: dict[str, list[float]] = {"push": [], "curl_push": [], "pull": [], "curl_pull": [], "verify": []}
        rss: dict[str, list[int]] = {"push": [], "pull": []}
        for i in range(args.repeat + 1):  # the first round is the warm-up
            repo = f"bench/r{next(n)}"
            w, m = peak_rss([str(CLI), "ota", "push", str(release), f"oci://{host}/{repo}:1"])
            c = curl_push(host, f"bench/c{i}", files)
            cache, out = OCI / f"cache{i}", OCI / f"out{i}"
            pw, pm = peak_rss(
                [str(CLI), "ota", "pull", f"oci://{host}/{repo}:1", "--key", str(pub), "--out", str(out),
                 "--cache-dir", str(cache), "--json"]
            )  # fmt: skip
            manifest = json.loads(
                subprocess.run(
                    ["curl", "-sS", "-H", "Accept: application/vnd.oci.image.manifest.v1+json",
                     f"http://{host}/v2/{repo}/manifests/1"], capture_output=True, check=True,
                ).stdout
            )  # fmt: skip
            cp = curl_pull(host, repo, [x["digest"] for x in manifest["layers"]], OCI / f"curl{i}")
            vw, _ = peak_rss([str(CLI), "ota", "verify", str(out), "--key", str(pub)])
            if i:
                res["push"].append(w)
                res["curl_push"].append(c)
                res["pull"].append(pw)
                res["curl_pull"].append(cp)
                res["verify"].append(vw)
                rss["push"].append(m)
                rss["pull"].append(pm)
    finally:
        proc.terminate()
        proc.wait()
    med = {k: statistics.median(v) for k, v in res.items()}
    total = sum(f.stat().st_size for f in files)
    print(f"{len(files)} files, {total / (1 << 20):.1f} MiB; load {os.getloadavg()[0]:.1f}; medians of {args.repeat}")
    print(f"push {med['push']:.2f} s vs curl {med['curl_push']:.2f} s: {med['push'] / med['curl_push']:.2f}×")
    print(f"pull {med['pull']:.2f} s vs curl {med['curl_pull']:.2f} s: {med['pull'] / med['curl_pull']:.2f}×")
    print(
        f"ota verify alone (same folder) {med['verify']:.2f} s; pull minus verify {med['pull'] - med['verify']:.2f} s"
    )
    print(f"peak RSS: push {max(rss['push']) / 1024:.0f} MiB, pull {max(rss['pull']) / 1024:.0f} MiB")


if __name__ == "__main__":
    main()
