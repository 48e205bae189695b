"""Run a random sample of the mutants `make mutation` has not checked yet, per module.

    .venv/bin/python tests/mutation_sample.py RESULTS.json hcdf_trust.digest=25 hcdf_trust.xml=20 ...

After `make mutation` has generated mutants/ and its stats (stop it once it runs mutants), this
runs each sampled mutant the way mutmut does: only the tests that reached the mutated function
(mutmut's own stats), fastest first, stopping at the first failure, with MUTANT_UNDER_TEST set
in mutants/. The sample is drawn per module with a generator seeded by the module's name, so a
rerun picks the same mutants (and skips those already in RESULTS.json); modules take turns, so
a run stopped early still covers every module. Each result is killed / survived / timeout / rc N
(rc 4: a test id in the stats no longer exists; rerun those by hand). Tests that reach the code
only through a subprocess are not in mutmut's stats: rerun a survivor against them by hand
(`cd mutants && MUTANT_UNDER_TEST=NAME ../.venv/bin/python -m pytest tests/test_x.py`).
Why not mutmut itself: it has no sampling, and its full run is ~3,500 mutants at 5-300 s each.
"""

from __future__ import annotations

import json
import os
import random
import re
import subprocess
import sys
import time
from collections import defaultdict
from pathlib import Path

PROJECT = Path(__file__).resolve().parent.parent
MUTANTS = PROJECT / "mutants"
PYTHON = PROJECT / ".venv" / "bin" / "python"
LEFT_OUT = ("test_macsec_pkcs11", "test_ota_hsm", "test_less_common_references", "test_parallel_fetch_beats")


def pending() -> dict[str, list[str]]:
    out = subprocess.run(
        [PROJECT / ".venv" / "bin" / "mutmut", "results", "--all", "true"],
        cwd=PROJECT, capture_output=True, text=True, check=True,
    ).stdout  # fmt: skip
    by_module: dict[str, list[str]] = defaultdict(list)
    for line in out.splitlines():
        m = re.match(r"^\s*(\S+): not checked$", line)
        if m:
            module = re.match(r"(.*?)\.x[_ǁ]", m[1])
            if module:
                by_module[module[1]].append(m[1])
    return by_module


def main() -> int:
    results_path = Path(sys.argv[1])
    wanted = dict(arg.split("=") for arg in sys.argv[2:])
    stats = json.loads((MUTANTS / "mutmut-stats.json").read_text())
    tests_by_fn, duration = stats["tests_by_mangled_function_name"], stats["duration_by_test"]
    done = json.loads(results_path.read_text()) if results_path.exists() else {}
    todo = pending()
    queues = []
    for module, count in wanted.items():
        mine = [n for n in done if n.startswith(module + ".x")]
        names = sorted(todo[module])
        rest = [n for n in random.Random(module).sample(names, len(names)) if n not in mine]
        queues.append(mine + rest[: max(0, int(count) - len(mine))])
    plan = [q[i] for i in range(max(map(len, queues), default=0)) for q in queues if i < len(q)]
    for name in plan:
        if name in done:
            continue
        fn = name.rsplit("__mutmut_", 1)[0]
        tests = sorted(tests_by_fn.get(fn, []), key=lambda t: duration.get(t, 1.0))
        tests = [t for t in tests if not any(x in t for x in LEFT_OUT)]
        started = time.monotonic()
        if not tests:
            done[name] = "no tests"
        else:
            env = dict(os.environ, MUTANT_UNDER_TEST=name, HCDF_FUZZ_EXAMPLES="10")
            env.setdefault("HCDF_CORPUS", str(PROJECT.parent / "shared" / "corpus"))
            try:
                proc = subprocess.run(
                    [PYTHON, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider", *tests],
                    cwd=MUTANTS, env=env, capture_output=True, text=True,
                    timeout=60 + 5 * sum(duration.get(t, 1.0) for t in tests),
                )  # fmt: skip
                done[name] = {0: "survived", 1: "killed"}.get(proc.returncode, f"rc {proc.returncode}")
            except subprocess.TimeoutExpired:
                done[name] = "timeout"
        print(f"{name}: {done[name]} ({time.monotonic() - started:.0f} s)", flush=True)
        results_path.write_text(json.dumps(done, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
