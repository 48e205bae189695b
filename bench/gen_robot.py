"""Generate benchmark trees: a large robot (>= 200 includes, >= 2,000 GLB stand-ins, >= 1 GB)
and the small flat trees ``run.py`` needs. Everything is deterministic from a seed.

Model files are GLB stand-ins: a 12-byte glTF header, the file's index, then
pseudo-random bytes taken from a seeded pool (SHAKE-128 of the seed), so every
file has distinct content and a distinct SHA-256 without paying for a slow
per-byte PRNG. Every reference (include or model) carries the full SHA-256.

    python bench/gen_robot.py [--seed N] [--out bench/work/robot] [--force]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import random
import shutil
import struct
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

HERE = Path(__file__).resolve().parent
WORK = HERE / "work"
POOL_BYTES = 64 << 20

ASSEMBLIES = 20
PARTS_PER_ASSEMBLY = 10  # 20 + 200 = 220 distinct include files
MODELS_PER_PART = 10  # 200 x 10 = 2,000 model files
TOTAL_BYTES = 1 << 30  # 1 GiB = 1.07 GB


@dataclass(frozen=True)
class Model:
    rel: str  # path relative to the tree root
    sha256: str
    size: int


_POOLS: dict[int, bytes] = {}


def pool(seed: int) -> bytes:
    if seed not in _POOLS:
        _POOLS[seed] = hashlib.shake_128(f"hcdf-trust bench pool {seed}".encode()).digest(POOL_BYTES)
    return _POOLS[seed]


def glb_bytes(seed: int, index: int, size: int) -> bytes:
    """``size`` deterministic bytes that look like the start of a GLB file."""
    header = b"glTF" + struct.pack("<II", 2, size & 0xFFFFFFFF) + struct.pack("<Q", index)
    header = header[:size]
    need = size - len(header)
    src = pool(seed)
    offset = random.Random(seed * 1_000_003 + index).randrange(len(src))
    parts = [header]
    while need > 0:
        take = src[offset : offset + need]
        parts.append(take)
        need -= len(take)
        offset = 0
    return b"".join(parts)


def write_model(root: Path, rel: str, seed: int, index: int, size: int) -> Model:
    path = root / rel
    path.parent.mkdir(parents=True, exist_ok=True)
    data = glb_bytes(seed, index, size)
    path.write_bytes(data)
    return Model(rel, hashlib.sha256(data).hexdigest(), size)


def write_big_model(root: Path, rel: str, seed: int, index: int, size: int) -> Model:
    """Like :func:`write_model`, in 64 MiB pieces, for files too large to build in memory."""
    path = root / rel
    path.parent.mkdir(parents=True, exist_ok=True)
    h = hashlib.sha256()
    src = pool(seed)
    with open(path, "wb") as f:
        head = glb_bytes(seed, index, min(size, 1 << 20))
        f.write(head)
        h.update(head)
        left = size - len(head)
        while left > 0:
            piece = src[: min(left, len(src))]
            f.write(piece)
            h.update(piece)
            left -= len(piece)
    return Model(rel, h.hexdigest(), size)


def model_xml(name: str, models: Sequence[tuple[str, str]], includes: Sequence[tuple[str, str, str]] = ()) -> bytes:
    """An HCDF document: one ``<comp>`` per model (uri/href alternate), then the includes.

    ``models`` is (uri, sha); ``includes`` is (uri, sha, name).
    """
    lines = ['<?xml version="1.0" encoding="UTF-8"?>', '<hcdf version="1.0">']
    for i, (uri, sha) in enumerate(models):
        attr = "uri" if i % 2 == 0 else "href"
        lines += [
            f'  <comp name="{name}-c{i:03d}" role="structure">',
            f'    <visual name="{name}-v{i:03d}">',
            f"      <pose>0 0 {i * 0.01:.2f} 0 0 0</pose>",
            f'      <model {attr}="{uri}" sha="{sha}"/>',
            "    </visual>",
            "  </comp>",
        ]
    for i, (uri, sha, inc_name) in enumerate(includes):
        lines.append(f'  <include uri="{uri}" sha="{sha}" name="{inc_name}" pose="{i * 0.1:.1f} 0 0 0 0 0"/>')
    lines.append("</hcdf>")
    return ("\n".join(lines) + "\n").encode()


def write_doc(path: Path, data: bytes) -> str:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)
    return hashlib.sha256(data).hexdigest()


def model_sizes(seed: int, count: int, total: int, minimum: int = 4096) -> list[int]:
    """``count`` sizes summing to exactly ``total``: log-normal spread (a few large meshes)."""
    rng = random.Random(seed)
    weights = [rng.lognormvariate(0.0, 1.0) for _ in range(count)]
    scale = (total - minimum * count) / sum(weights)
    sizes = [minimum + int(w * scale) for w in weights]
    sizes[-1] += total - sum(sizes)
    return sizes


def generate_robot(out: Path, *, seed: int, force: bool = False) -> dict:
    """Write the large robot under ``out``; skip if a matching stamp is already there.

    Layout: ``robot.hcdf`` includes 20 assemblies (one of them twice, under another
    name), each assembly includes 10 parts, each part has 10 models.
    """
    params = {
        "seed": seed,
        "assemblies": ASSEMBLIES,
        "parts_per_assembly": PARTS_PER_ASSEMBLY,
        "models_per_part": MODELS_PER_PART,
        "total_bytes": TOTAL_BYTES,
        "version": 1,
    }
    stamp = out / "STAMP.json"
    if not force and stamp.exists():
        old = json.loads(stamp.read_text())
        if old.get("params") == params and _intact(out, old):
            return old
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)

    nparts = ASSEMBLIES * PARTS_PER_ASSEMBLY
    sizes = model_sizes(seed, nparts * MODELS_PER_PART, TOTAL_BYTES)
    models: list[Model] = []
    part_shas: list[str] = []
    for p in range(nparts):
        refs = []
        for m in range(MODELS_PER_PART):
            idx = p * MODELS_PER_PART + m
            model = write_model(out, f"models/m{idx:04d}.glb", seed, idx, sizes[idx])
            models.append(model)
            refs.append((f"../models/m{idx:04d}.glb", model.sha256))
        part_shas.append(write_doc(out / f"parts/part_{p:03d}.hcdf", model_xml(f"part{p:03d}", refs)))
    asm_shas = []
    for a in range(ASSEMBLIES):
        incs = [
            (f"../parts/part_{p:03d}.hcdf", part_shas[p], f"p{p:03d}")
            for p in range(a * PARTS_PER_ASSEMBLY, (a + 1) * PARTS_PER_ASSEMBLY)
        ]
        asm_shas.append(write_doc(out / f"assemblies/asm_{a:02d}.hcdf", model_xml(f"asm{a:02d}", [], incs)))
    incs = [(f"assemblies/asm_{a:02d}.hcdf", asm_shas[a], f"a{a:02d}") for a in range(ASSEMBLIES)]
    incs.append(("assemblies/asm_00.hcdf", asm_shas[0], "a00-spare"))  # same file, second name
    root_sha = write_doc(out / "robot.hcdf", model_xml("robot", [], incs))

    info = {
        "params": params,
        "root": "robot.hcdf",
        "root_sha256": root_sha,
        "include_references": len(incs) + nparts,
        "include_files": ASSEMBLIES + nparts,
        "model_files": len(models),
        "model_bytes": sum(m.size for m in models),
        "largest_model": max(m.size for m in models),
        "models": {m.rel: m.sha256 for m in models},
    }
    stamp.write_text(json.dumps(info, indent=1, sort_keys=True))
    return info


def _intact(out: Path, info: dict) -> bool:
    models = info.get("models", {})
    try:
        total = sum((out / rel).stat().st_size for rel in models)
    except OSError:
        return False
    return total == info.get("model_bytes") and (out / "robot.hcdf").is_file()


def generate_flat(
    out: Path, *, seed: int, sizes: Sequence[int], uri_prefix: str = "models/", name: str = "robot.hcdf"
) -> tuple[Path, list[Model]]:
    """A one-document tree: ``name`` with one pinned model per size, files under ``out/models``.

    ``uri_prefix`` is what the document writes before each file name (e.g. an
    http URL for the loopback tests); the files are always written locally.
    """
    out.mkdir(parents=True, exist_ok=True)
    models = []
    refs = []
    for i, size in enumerate(sizes):
        rel = f"models/f{i:05d}.glb"
        writer = write_big_model if size > (64 << 20) else write_model
        model = writer(out, rel, seed, 1_000_000 + i, size)
        models.append(model)
        refs.append((f"{uri_prefix}f{i:05d}.glb", model.sha256))
    doc = out / name
    write_doc(doc, model_xml(out.name, refs))
    return doc, models


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=int(os.environ.get("BENCH_SEED", "1")))
    ap.add_argument("--out", type=Path, default=WORK / "robot")
    ap.add_argument("--force", action="store_true", help="regenerate even if the stamp matches")
    args = ap.parse_args(argv)
    info = generate_robot(args.out, seed=args.seed, force=args.force)
    print(
        f"{args.out}/{info['root']}: {info['include_references']} include references "
        f"({info['include_files']} files), {info['model_files']} models, "
        f"{info['model_bytes'] / 1e9:.3f} GB (largest {info['largest_model'] / 1e6:.1f} MB)",
        file=sys.stderr,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
