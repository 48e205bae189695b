"""Benchmark for ``hcdf-trust bundle push`` / ``bundle pull`` against plain curl, same run.

A bundle of FILES × SIZE random models (``bench/run.py``'s flat tree, ``hcdf-trust bundle``) is
pushed to and pulled from the Debian ``docker-registry`` on 127.0.0.1, and the same blob is
moved with curl, which verifies nothing (one ``POST`` + one ``PUT`` up, one ``GET`` down). Ours
verifies the bundle before the push and, on pull, hashes the blob as it streams, verifies it as
``verify X.hcdfz`` does in a staging folder and copies it into place hashing it again.
Each pull starts from an empty content store. Usage: ``.venv/bin/python bench/oci_bundle.py``.
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
from oci import OCI, curl_pull, curl_push, peak_rss, start_registry  # noqa: E402
from run import CLI, WORK, ensure_flat, fresh_lock  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--files", type=int, default=100)
    ap.add_argument("--size", type=int, default=1 << 20)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    doc, _ = ensure_flat("bundle-oci", seed=7, sizes=[args.size] * args.files)
    fresh_lock(doc)
    bundle = WORK / "bundle-oci.hcdfz"
    bundle.unlink(missing_ok=True)
    subprocess.run([CLI, "bundle", doc, bundle], check=True, capture_output=True)
    proc, host = start_registry()
    try:
        res: dict[str, list[float]] = {"push": [], "curl_push": [], "pull": [], "curl_pull": []}
        rss: dict[str, int] = {"push": 0, "pull": 0}
        for i in range(args.repeat):
            ref = f"oci://{host}/bench/b{i}:t"
            wall, kib = peak_rss([str(CLI), "bundle", "push", str(bundle), ref, "--json"])
            res["push"].append(wall)
            rss["push"] = max(rss["push"], kib)
            res["curl_push"].append(curl_push(host, f"bench/c{i}", [bundle]))
            cache, out = OCI / f"cache{i}", OCI / f"pulled{i}.hcdfz"
            shutil.rmtree(cache, ignore_errors=True)
            wall, kib = peak_rss(
                [str(CLI), "bundle", "pull", ref, "--trust-tag", "--out", str(out), "--cache-dir", str(cache), "--json"]
            )
            res["pull"].append(wall)
            rss["pull"] = max(rss["pull"], kib)
            assert out.read_bytes() == bundle.read_bytes()
            manifest = json.loads(
                subprocess.run(
                    ["curl", "-sS", "-H", "Accept: application/vnd.oci.image.manifest.v1+json",
                     f"http://{host}/v2/bench/b{i}/manifests/t"],
                    check=True, capture_output=True,
                ).stdout
            )  # fmt: skip
            res["curl_pull"].append(curl_pull(host, f"bench/b{i}", [manifest["layers"][0]["digest"]], OCI / "curl"))
    finally:
        proc.terminate()
        proc.wait()
    med = {k: statistics.median(v) for k, v in res.items()}
    mib = bundle.stat().st_size / (1 << 20)
    print(f"bundle: {args.files} files x {args.size} B = {mib:.1f} MiB, median of {args.repeat}")
    print(f"push {med['push']:.2f} s vs curl {med['curl_push']:.2f} s: {med['push'] / med['curl_push']:.2f}x")
    print(f"pull {med['pull']:.2f} s vs curl {med['curl_pull']:.2f} s: {med['pull'] / med['curl_pull']:.2f}x")
    print(f"peak RSS: push {rss['push'] / 1024:.0f} MiB, pull {rss['pull'] / 1024:.0f} MiB")


if __name__ == "__main__":
    main()
