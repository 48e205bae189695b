"""Benchmark for ``hcdf-trust macsec`` (issue 8): plan + generate for a large robot, one export, one rotate.

    .venv/bin/python bench/macsec.py [--networks 1000] [--links 10] [--repeat 3]

Generates under bench/work/macsec/ a robot with N networks of L point-to-point psk links
each (one switch comp with L ports and L end devices per network; every link its own
connectivity association), locks it, then times fresh ``.venv/bin/hcdf-trust`` processes,
wall clock, median of ``--repeat`` runs:

* ``macsec plan`` and ``macsec generate`` into an empty store (target: plan + generate < 2 s);
* ``macsec export --device <one end device> --format json`` from that store (target < 0.3 s),
  which plans from the export index generate wrote (the run fails if it did not), and the
  same export with the index moved aside (the full resolve and plan, for comparison);
* ``macsec rotate --key-ref`` of one key-ref, checking that exactly one entry's ciphertexts change.

Prints a Markdown table (times, store size) and writes bench/work/macsec/results.json.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import statistics
import subprocess
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
PROJECT = HERE.parent
CLI = Path(os.environ.get("HCDF_TRUST_CLI", PROJECT / ".venv" / "bin" / "hcdf-trust"))
WORK = HERE / "work" / "macsec"
PASSPHRASE = "bench passphrase, not a secret"


def robot(networks: int, links: int) -> str:
    out = ['<?xml version="1.0"?>', '<hcdf version="1.0" name="macsec-bench">']
    caps = '<capabilities><speed unit="Mbps">1000</speed><macsec><cipher>gcm-aes-128</cipher></macsec></capabilities>'
    for n in range(networks):
        ports = "".join(f'<port name="p{i}" iface="swp{i}" type="ethernet">{caps}</port>' for i in range(links))
        out.append(f'<comp name="sw{n}"><switch>{ports}</switch></comp>')
        for i in range(links):
            out.append(f'<comp name="d{n}_{i}"><port name="eth0" iface="eth0" type="ethernet">{caps}</port></comp>')
    for n in range(networks):
        out.append(f'<network name="net{n}">')
        for i in range(links):
            ref = f' key-ref="k{n}_{i}"' if i % 2 else ""
            out.append(
                f'<link name="l{i}"><wired standard="1000base-t1"><port>sw{n}/p{i}</port><port>d{n}_{i}/eth0</port>'
                f'<macsec policy="must-secure" cipher="gcm-aes-128" key-agreement="psk"{ref}/></wired></link>'
            )
        out.append('<macsec policy="must-secure" cipher="gcm-aes-128" key-agreement="psk"/></network>')
    out.append("</hcdf>")
    return "\n".join(out) + "\n"


CPU: dict[str, list[float]] = {}


def _children_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def timed(args: list[str], env: dict[str, str], *, label: str | None = None) -> float:
    """Wall seconds of one run; its CPU seconds (user + sys) go to CPU[label or verb]."""
    return timed_output(args, env, label=label)[0]


def timed_output(args: list[str], env: dict[str, str], *, label: str | None = None) -> tuple[float, str]:
    cpu = _children_cpu()
    start = time.perf_counter()
    proc = subprocess.run([str(CLI), *args], env=env, capture_output=True, text=True)
    elapsed = time.perf_counter() - start
    CPU.setdefault(label or " ".join(args[:2]), []).append(_children_cpu() - cpu)
    if proc.returncode != 0:
        raise SystemExit(f"hcdf-trust {' '.join(args)} failed ({proc.returncode}):\n{proc.stderr[-2000:]}")
    return elapsed, proc.stdout


def ciphertexts(store: Path) -> dict[str, list[str]]:
    """CA id -> its generations' ciphertexts (the store is JSON Lines: a header, then [CA_ID, entry] lines)."""
    lines = (store / "macsec-keys.json").read_text().splitlines()[1:]
    return {ca: [g["ciphertext"] for g in e["generations"]] for ca, e in map(json.loads, lines)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--networks", type=int, default=1000)
    ap.add_argument("--links", type=int, default=10)
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args()
    shutil.rmtree(WORK, ignore_errors=True)
    WORK.mkdir(parents=True)
    doc = WORK / "robot.hcdf"
    doc.write_text(robot(a.networks, a.links))
    env = dict(os.environ, HCDF_TRUST_PASSPHRASE=PASSPHRASE, XDG_CACHE_HOME=str(WORK / "cache"))
    timed(["resolve", str(doc), "--offline"], env)  # writes the lock under its default name

    plan_t, gen_t, export_t = [], [], []
    store = WORK / "store"
    for _ in range(a.repeat):
        shutil.rmtree(store, ignore_errors=True)
        plan_t.append(timed(["macsec", "plan", str(doc), "--json"], env))
        gen_t.append(timed(["macsec", "generate", str(doc), "--store", str(store)], env))
    device = f"d{a.networks // 2}_1"
    export = ["macsec", "export", str(doc), "--store", str(store), "--device", device, "--format", "json", "--json"]
    for i in range(a.repeat):
        elapsed, out = timed_output([*export, "--out", str(WORK / f"export{i}")], env)
        if json.loads(out)["planned_from"] != "index":
            raise SystemExit("export did not plan from the export index that generate wrote")
        export_t.append(elapsed)
    index = store / "macsec-export-index.json"
    index.rename(WORK / "index.aside")
    full_t = [
        timed([*export, "--out", str(WORK / f"full{i}")], env, label="export without index") for i in range(a.repeat)
    ]
    (WORK / "index.aside").rename(index)
    for i in range(a.repeat):
        for f in (WORK / f"full{i}").iterdir():
            if f.read_bytes() != (WORK / f"export{i}" / f.name).read_bytes():
                raise SystemExit(f"{f.name}: the export from the index differs from the full export")
    before = ciphertexts(store)
    rotate_t = timed(["macsec", "rotate", str(doc), "--store", str(store), "--key-ref", f"k{a.networks // 2}_1"], env)
    after = ciphertexts(store)
    changed = sorted(ca for ca in after if after[ca] != before.get(ca))
    untouched_g1 = all(after[ca][0] == before[ca][0] for ca in before)

    links = a.networks * a.links
    results = {
        "networks": a.networks,
        "links": links,
        "plan_s": statistics.median(plan_t),
        "generate_s": statistics.median(gen_t),
        "export_one_device_s": statistics.median(export_t),
        "export_without_index_s": statistics.median(full_t),
        "index_bytes": index.stat().st_size,
        "rotate_one_key_ref_s": rotate_t,
        "store_bytes": (store / "macsec-keys.json").stat().st_size,
        "entries_rewritten_by_rotate": changed,
        "existing_ciphertexts_unchanged": untouched_g1,
    }
    (WORK / "results.json").write_text(json.dumps(results, indent=2) + "\n")
    cpu = {verb: statistics.median(v) for verb, v in CPU.items()}
    results["cpu_s"] = cpu
    (WORK / "results.json").write_text(json.dumps(results, indent=2) + "\n")
    total = results["plan_s"] + results["generate_s"]
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    print(f"| {a.networks} networks × {a.links} links ({links} CAs) | wall s | CPU s | target |")
    print("|---|---|---|---|")
    print(f"| plan | {results['plan_s']:.2f} | {cpu['macsec plan']:.2f} | |")
    print(f"| generate (empty store; plans too) | {results['generate_s']:.2f} | {cpu['macsec generate']:.2f} | |")
    print(f"| plan + generate | {total:.2f} | | < 2 |")
    print(f"| export one device (json) | {results['export_one_device_s']:.3f} | {cpu['macsec export']:.2f} | < 0.3 |")
    print(
        f"| the same export, index moved aside | {results['export_without_index_s']:.3f} "
        f"| {cpu['export without index']:.2f} | |"
    )
    print(f"| rotate one key-ref | {rotate_t:.2f} | {cpu['macsec rotate']:.2f} | entries rewritten: {len(changed)} |")
    print(f"| store size | {results['store_bytes'] / 1e6:.1f} MB | | |")
    print(f"| export index size | {results['index_bytes'] / 1e6:.1f} MB | | |")


if __name__ == "__main__":
    main()
