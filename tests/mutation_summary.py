"""Per-module kill rate of the last `make mutation` run (reads `mutmut results --all true`)."""

from __future__ import annotations

import collections
import re
import subprocess
import sys
from pathlib import Path

LINE = re.compile(r"^\s*(?P<module>[\w.]+)\.x[_ǁ].*__mutmut_\d+: (?P<status>.+)$")


def main() -> int:
    mutmut = Path(sys.executable).with_name("mutmut")
    out = subprocess.run([mutmut, "results", "--all", "true"], capture_output=True, text=True, check=True).stdout
    counts: dict[str, collections.Counter[str]] = collections.defaultdict(collections.Counter)
    for line in out.splitlines():
        m = LINE.match(line)
        if m:
            counts[m["module"]][m["status"].strip()] += 1
    print(f"{'module':32} {'mutants':>7} {'killed':>6} {'survived':>8} {'other':>5} {'kill %':>6}")
    for module, c in sorted(counts.items()):
        total = sum(c.values())
        killed = c["killed"] + c["timeout"] + c["segfault"] + c["caught by type check"]
        survived = c["survived"]
        done = killed + survived
        rate = f"{100 * killed / done:.0f}" if done else "-"
        print(f"{module:32} {total:7} {killed:6} {survived:8} {total - done:5} {rate:>6}")
    print("other: not checked yet, no tests, suspicious or skipped. Survivors: `.venv/bin/mutmut results`;")
    print("a mutant's diff: `.venv/bin/mutmut show NAME`. Equivalent survivors are listed in tests/MUTATION.md.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
