"""Benchmark for ``hcdf-trust bundle push`` / ``bundle pull`` against plain curl, same run.

A bundle of FILES × SIZE random models (``bench/run.py``'s flat tree, ``hcdf-trust bundle``) is
pushed to and pulled from the Debian ``docker-registry`` on 127.0.0.1, and the same blob is
moved with curl, which verifies nothing (one ``POST`` + one ``PUT`` up, one ``GET`` down). Ours
verifies the bundle before the push and, on pull, hashes the blob as it streams, verifies it as
``verify X.hcdfz`` does in a staging folder and moves it into place. ``--before CLI`` pulls
the same bundle in the same rounds (order alternating), as in bench/oci.py. Each pull starts
from an empty content store; wall clock, CPU seconds (user + system) and peak RSS by GNU time.
Usage: ``.venv/bin/python bench/oci_bundle.py [--before CLI]``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from oci import OCI, Timed, curl_pull, curl_push, start_registry, timed  # noqa: E402
from run import CLI, WORK, ensure_flat, fresh_lock  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--files", type=int, default=100)
    ap.add_argument("--size", type=int, default=1 << 20)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--before", help="another hcdf-trust to pull with in the same rounds (an older checkout)")
    args = ap.parse_args()
    doc, _ = ensure_flat("bundle-oci", seed=7, sizes=[args.size] * args.files)
    fresh_lock(doc)
    bundle = WORK / "bundle-oci.hcdfz"
    bundle.unlink(missing_ok=True)
    subprocess.run([CLI, "bundle", doc, bundle], check=True, capture_output=True)
    pullers = {"pull": str(CLI), **({"before": args.before} if args.before else {})}
    proc, host = start_registry()
    try:
        res: dict[str, list[Timed]] = {k: [] for k in ("push", "curl_push", "curl_pull", *pullers)}
        for i in range(args.repeat):
            ref = f"oci://{host}/bench/b{i}:t"
            res["push"].append(timed([str(CLI), "bundle", "push", str(bundle), ref, "--json"]))
            res["curl_push"].append(Timed(curl_push(host, f"bench/c{i}", [bundle]), 0.0, 0))
            manifest = json.loads(
                subprocess.run(
                    ["curl", "-sS", "-H", "Accept: application/vnd.oci.image.manifest.v1+json",
                     f"http://{host}/v2/bench/b{i}/manifests/t"],
                    check=True, capture_output=True,
                ).stdout
            )  # fmt: skip
            order = ["curl", *pullers]
            for who in order[i % len(order) :] + order[: i % len(order)]:
                if who == "curl":
                    digest = manifest["layers"][0]["digest"]
                    res["curl_pull"].append(curl_pull(host, f"bench/b{i}", [digest], OCI / "curl"))
                    continue
                cache, out = OCI / f"cache-{who}{i}", OCI / f"pulled-{who}{i}.hcdfz"
                shutil.rmtree(cache, ignore_errors=True)
                res[who].append(
                    timed(
                        [
                            pullers[who],
                            "bundle",
                            "pull",
                            ref,
                            "--trust-tag",
                            "--out",
                            str(out),
                            "--cache-dir",
                            str(cache),
                            "--json",
                        ]
                    )  # fmt: skip
                )
                assert out.read_bytes() == bundle.read_bytes()
    finally:
        proc.terminate()
        proc.wait()

    def med(key: str, attr: str = "wall") -> float:
        return statistics.median(getattr(t, attr) for t in res[key])

    mib = bundle.stat().st_size / (1 << 20)
    print(f"bundle: {args.files} files x {args.size} B = {mib:.1f} MiB, median of {args.repeat}")
    print(f"push {med('push'):.2f} s vs curl {med('curl_push'):.2f} s: {med('push') / med('curl_push'):.2f}x")
    print(f"curl pull {med('curl_pull'):.2f} s wall, {med('curl_pull', 'cpu'):.2f} s CPU")
    for who in pullers:
        print(
            f"{who}: {med(who):.2f} s wall ({med(who) / med('curl_pull'):.2f}x curl), {med(who, 'cpu'):.2f} s CPU, "
            f"peak RSS {max(t.kib for t in res[who]) / 1024:.0f} MiB"
        )
    print(f"peak RSS: push {max(t.kib for t in res['push']) / 1024:.0f} MiB")


if __name__ == "__main__":
    main()
