"""Registry benchmark: publish and refresh 1,000 domains x 3 versions + 200 stream profiles.

    .venv/bin/python bench/registry.py [--domains 1000] [--versions 3] [--profiles 200] [--runs 5]

Measures, over a loopback server (bench/loopback.py): publish (load the source, check
every owner signature and content file, sign, write), a cold client refresh (empty
cache) and a warm one (nothing changed), with the server's request count, and the
metadata sizes. Targets on the 2-core machine: publish < 10 s, cold < 1 s, warm < 100 ms.
"""

from __future__ import annotations

import argparse
import hashlib
import statistics
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.loopback import LoopbackServer  # noqa: E402
from hcdf_trust.outputs import OutputPlan  # noqa: E402
from hcdf_trust.registry import edit  # noqa: E402
from hcdf_trust.registry import keys as keymod  # noqa: E402
from hcdf_trust.registry.client import RegistryClient  # noqa: E402
from hcdf_trust.registry.publish import publish  # noqa: E402
from hcdf_trust.registry.source import (  # noqa: E402
    Artifact,
    Domain,
    Release,
    artifact_path,
    domain_path,
    dump,
    load_source,
)

PASS = b"bench"


def build_source(base: Path, n_domains: int, n_versions: int, n_profiles: int) -> None:
    """A source whose owners' keys all live in base/keys (one folder, as one publisher run would see)."""
    from securesystemslib.signer import CryptoSigner

    src, keydir, content = base / "src", base / "keys", base / "content"
    plan = OutputPlan()
    edit.init(src, keydir, PASS, plan=plan)
    keydir.mkdir(mode=0o700)
    for i in range(n_domains):
        name = f"org.bench{i:04d}.ext"
        private = keymod.generate()
        key = keymod.plan_private(plan, keydir, private, PASS)
        signer = CryptoSigner(private)
        dom = Domain(name, "bench", "bench owner", 1, {key.keyid: key}, {}, "")
        versions = {}
        for v in range(n_versions):
            version = f"1.{v}"
            data = f"<xs:schema xmlns:xs='http://www.w3.org/2001/XMLSchema'><!-- {name} {version} -->".encode()
            data += b" " * 900 + b"</xs:schema>\n"
            file = f"ext/{name}/{version}.xsd"
            plan.add(content / file, data, flag="content")
            rel = Release(version, domain_path(name, version), file, hashlib.sha256(data).hexdigest(), len(data))
            versions[version] = replace(rel, signatures={key.keyid: signer.sign(dom.statement(rel)).signature})
        plan.add(src / "domains" / f"{name}.toml", dump(replace(dom, versions=versions)), flag="src")
    for i in range(n_profiles):
        name = f"profile{i:03d}"
        data = f'<stream-profile name="{name}" version="1.0"/>\n'.encode() + b" " * 2000
        file = f"profiles/{name}.streams.xml"
        plan.add(content / file, data, flag="content")
        rel = Release("1.0", artifact_path("profile", name, "1.0"), file, hashlib.sha256(data).hexdigest(), len(data))
        plan.add(src / "profiles" / f"{name}.toml", dump(Artifact("profile", name, "", {"1.0": rel})), flag="src")
    plan.commit()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--domains", type=int, default=1000)
    ap.add_argument("--versions", type=int, default=3)
    ap.add_argument("--profiles", type=int, default=200)
    ap.add_argument("--runs", type=int, default=5)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="hcdf-registry-bench-") as tmp:
        base = Path(tmp)
        t = time.perf_counter()
        build_source(base, args.domains, args.versions, args.profiles)
        print(f"source built in {time.perf_counter() - t:.2f} s (not part of publish)")
        t = time.perf_counter()
        source = load_source(base / "src")
        plan = OutputPlan()
        publish(source, keymod.KeyRing([base / "keys"], PASS), base / "content", base / "site", plan=plan)
        planned = time.perf_counter() - t
        plan.commit()
        total = time.perf_counter() - t
        print(
            f"publish: {total:.2f} s ({len(plan.paths)} files; {planned:.2f} s to check and sign, "
            f"{total - planned:.2f} s to write them, one fsync each)"
        )
        meta = base / "site" / "metadata"
        for f in sorted(meta.iterdir()):
            if f.name.split(".")[1] not in ("org", "extensions-001") or f.name.startswith("1.org.bench0000"):
                print(f"  {f.name}: {f.stat().st_size / 1024:.1f} KB")
        root = (meta / "1.root.json").read_bytes()
        cold, warm, warm_hits, lookup = [], [], [], []
        with LoopbackServer(base / "site") as srv:
            for run in range(args.runs):
                cache = base / f"cache{run}"
                t = time.perf_counter()
                RegistryClient(srv.url, trusted_root=root, cache_dir=cache).refresh()
                cold.append(time.perf_counter() - t)
                before = srv.hits
                t = time.perf_counter()
                RegistryClient(srv.url, trusted_root=root, cache_dir=cache).refresh()
                warm.append(time.perf_counter() - t)
                warm_hits.append(srv.hits - before)
                t = time.perf_counter()
                client = RegistryClient(srv.url, trusted_root=root, cache_dir=base / f"lookup{run}")
                client.download(client.versions(f"org.bench{run:04d}.ext")["1.0"])
                lookup.append(time.perf_counter() - t)
        print(
            f"cold refresh: median {statistics.median(cold) * 1000:.0f} ms (runs: "
            + ", ".join(f"{c * 1000:.0f}" for c in cold)
            + ")"
        )
        print(
            f"warm refresh: median {statistics.median(warm) * 1000:.0f} ms (runs: "
            + ", ".join(f"{w * 1000:.0f}" for w in warm)
            + f"); requests per warm refresh: {warm_hits}"
        )
        print(
            f"cold lookup (refresh + one shard + one domain role + one schema): median "
            f"{statistics.median(lookup) * 1000:.0f} ms"
        )


if __name__ == "__main__":
    main()
