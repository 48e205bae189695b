"""Benchmark for ``hcdf-trust ota push`` / ``ota pull`` (issue 22) against plain curl, same run.

    .venv/bin/python bench/oci.py [--images 50] [--size 1048576] [--repeat 5] [--before [NAME=]CLI ...]

A release of ``--images`` MCUboot images of ``--size`` random bytes (bench/ota.py's
generator, one ``ota build``) is pushed to and pulled from the Debian ``docker-registry``
(CNCF distribution) started on 127.0.0.1 with its own configuration. Baselines move the
same bytes with curl and verify nothing: uploads are one ``POST`` + one ``PUT`` curl
process per blob (what a shell script does), downloads one curl process fetching every
blob over one connection. ``ota pull`` starts from an empty cache and an empty folder and
does everything it always does (digests while streaming, content store, ``ota verify`` of
every image in a staging folder, the referrers, the output plan). ``--before CLI`` (e.g. a
wrapper running an older checkout; repeatable, ``NAME=CLI`` to name each) pulls the same
release in the same rounds, the order of the pulls rotating from round to round. Each
process is timed by GNU time: wall clock, CPU seconds (user + system: what the process
itself cost, whatever the machine's load) and peak RSS. Medians of ``--repeat`` rounds after a warm-up round.
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


class Timed:
    """One process as GNU time saw it."""

    def __init__(self, wall: float, cpu: float, kib: int) -> None:
        self.wall, self.cpu, self.kib = wall, cpu, kib


def timed(argv: list[str], *, check: bool = True) -> Timed:
    """Run ``argv`` under GNU time: wall clock, user + system CPU seconds, peak RSS (KiB)."""
    t = time.perf_counter()
    p = subprocess.run([TIME, "-f", "%U %S %M", *argv], capture_output=True, text=True, env=ENV)
    wall = time.perf_counter() - t
    if check and p.returncode != 0:
        sys.exit(f"failed: {' '.join(argv)}\n{p.stderr}")
    user, system, kib = p.stderr.strip().splitlines()[-1].split()
    return Timed(wall, float(user) + float(system), int(kib))


def peak_rss(argv: list[str]) -> tuple[float, int]:
    """Wall clock and peak RSS (KiB) of one hcdf-trust process."""
    t = timed(argv)
    return t.wall, t.kib


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


def curl_pull(host: str, repo: str, digests: list[str], dest: Path) -> Timed:
    shutil.rmtree(dest, ignore_errors=True)
    dest.mkdir(parents=True)
    argv = ["curl", "-sS", "-f", "-L"]
    for i, d in enumerate(digests):
        argv += [f"http://{host}/v2/{repo}/blobs/{d}", "-o", str(dest / f"{i}")]
    return timed(argv)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--images", type=int, default=50)
    ap.add_argument("--size", type=int, default=1 << 20)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument(
        "--before",
        action="append",
        default=[],
        metavar="[NAME=]CLI",
        help="another hcdf-trust to pull with in the same rounds (an older checkout); repeatable",
    )
    args = ap.parse_args()
    doc = generate(args.images, args.size)
    release = WORK / "release"
    run([CLI, "ota", "build", doc, "--firmware-dir", WORK / "fw", "--key", WORK / "key.pem", "--out", release])
    pub = WORK / "key.pub.pem"
    files = sorted(p for p in release.rglob("*") if p.is_file())
    pullers = {"pull": str(CLI)}
    for n, given in enumerate(args.before):
        name, cli = given.split("=", 1) if "=" in given else (f"before{n + 1 if n else ''}", given)
        pullers[name] = cli
    proc, host = start_registry()
    loads = []
    try:
        res: dict[str, list[Timed]] = {k: [] for k in ("push", "curl_push", "curl_pull", "verify", *pullers)}
        for i in range(args.repeat + 1):  # the first round is the warm-up
            repo = f"bench/r{i}"
            push = timed([str(CLI), "ota", "push", str(release), f"oci://{host}/{repo}:1"])
            c = curl_push(host, f"bench/c{i}", files)
            manifest = json.loads(
                subprocess.run(
                    ["curl", "-sS", "-H", "Accept: application/vnd.oci.image.manifest.v1+json",
                     f"http://{host}/v2/{repo}/manifests/1"], capture_output=True, check=True,
                ).stdout
            )  # fmt: skip
            digests = [x["digest"] for x in manifest["layers"]]
            order = ["curl", *pullers]
            order = order[i % len(order) :] + order[: i % len(order)]  # who goes first rotates
            pulled: dict[str, Timed] = {}
            for who in order:
                if who == "curl":
                    pulled[who] = curl_pull(host, repo, digests, OCI / f"curl{i}")
                    continue
                cache, out = OCI / f"cache-{who}{i}", OCI / f"out-{who}{i}"
                pulled[who] = timed(
                    [pullers[who], "ota", "pull", f"oci://{host}/{repo}:1", "--key", str(pub), "--out", str(out),
                     "--cache-dir", str(cache), "--json"]
                )  # fmt: skip
            verify = timed([str(CLI), "ota", "verify", str(OCI / f"out-pull{i}"), "--key", str(pub)])
            loads.append(os.getloadavg()[0])
            if i:
                res["push"].append(push)
                res["curl_push"].append(Timed(c, 0.0, 0))
                res["curl_pull"].append(pulled["curl"])
                res["verify"].append(verify)
                for who in pullers:
                    res[who].append(pulled[who])
    finally:
        proc.terminate()
        proc.wait()

    def med(key: str, attr: str = "wall") -> float:
        return statistics.median(getattr(t, attr) for t in res[key])

    total = sum(f.stat().st_size for f in files)
    print(
        f"{len(files)} files, {total / (1 << 20):.1f} MiB; 1-min load {min(loads):.1f}–{max(loads):.1f}; "
        f"medians of {args.repeat} rounds"
    )
    print(f"push {med('push'):.2f} s vs curl {med('curl_push'):.2f} s: {med('push') / med('curl_push'):.2f}×")
    curl_wall, curl_cpu = med("curl_pull"), med("curl_pull", "cpu")
    print(f"curl pull: {curl_wall:.2f} s wall, {curl_cpu:.2f} s CPU")
    for who in pullers:
        ratios = [t.wall / c.wall for t, c in zip(res[who], res["curl_pull"], strict=True)]
        print(
            f"{who}: {med(who):.2f} s wall ({med(who) / curl_wall:.2f}× curl; per-round ratio median "
            f"{statistics.median(ratios):.2f}×, {min(ratios):.2f}–{max(ratios):.2f}), "
            f"{med(who, 'cpu'):.2f} s CPU, peak RSS {max(t.kib for t in res[who]) / 1024:.0f} MiB"
        )
    print(f"ota verify alone (same folder) {med('verify'):.2f} s wall, {med('verify', 'cpu'):.2f} s CPU")
    print(f"peak RSS: push {max(t.kib for t in res['push']) / 1024:.0f} MiB")


if __name__ == "__main__":
    main()
