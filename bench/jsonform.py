"""Benchmark for HCDF's JSON form (issue 19 §1): conversion time against lxml parsing the same XML.

    .venv/bin/python bench/jsonform.py [--repeat 20] [--corpus DIR]

In one process, median of ``--repeat`` runs, for each upstream example (drone-quadrotor,
humanoid-mobile-base, test-minimal) and the example robot:

* baseline: ``hcdf_trust.xml.parse_bytes`` of the XML (lxml, the reader every XML run uses);
* JSON -> XML: ``jsonform.read`` of its JSON form (strict JSON reader + schema-driven build);
* XML -> JSON: ``jsonform.to_json`` + ``jsonform.dumps`` of the parsed tree;
* once per run: importing xmlschema and building ``hcdf.xsd`` (what the first JSON document pays).

And, as fresh ``.venv/bin/hcdf-trust`` processes (median of 5): ``validate --schema`` of the
example robot as XML and as JSON. Ratio = JSON time / XML time (lower is better). Prints a
Markdown table and writes bench/work/jsonform.json.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

HERE = Path(__file__).resolve().parent
PROJECT = HERE.parent
CLI = Path(os.environ.get("HCDF_TRUST_CLI", PROJECT / ".venv" / "bin" / "hcdf-trust"))
WORK = HERE / "work"


def _median(fn: Callable[[], object], repeat: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeat", type=int, default=20)
    parser.add_argument(
        "--corpus", type=Path, default=Path(os.environ.get("HCDF_CORPUS", PROJECT.parent / "shared" / "corpus"))
    )
    args = parser.parse_args()
    sys.path.insert(0, str(PROJECT))
    xsd = args.corpus / "hcdformat" / "hcdf.xsd"

    start = time.perf_counter()
    from hcdf_trust import jsonform
    from hcdf_trust.xml import parse_bytes

    jsonform.use_schemas([str(xsd)])
    form = jsonform.form_for("1.0", source="bench")
    build = time.perf_counter() - start

    examples = args.corpus / "hcdformat" / "examples"
    inputs = [examples / f"{n}.hcdf" for n in ("drone-quadrotor", "humanoid-mobile-base", "test-minimal")]
    inputs.append(PROJECT / "examples" / "robot" / "robot.hcdf")
    rows = []
    for path in inputs:
        xml = path.read_bytes()
        tree = parse_bytes(xml, source=path.name)
        as_json = jsonform.dumps(jsonform.to_json(tree.getroot(), source=path.name, form=form).value).encode()
        lxml_s = _median(lambda: parse_bytes(xml, source=path.name), args.repeat)  # noqa: B023
        read_s = _median(lambda: jsonform.read(as_json, source=path.name), args.repeat)  # noqa: B023
        write_s = _median(
            lambda: jsonform.dumps(jsonform.to_json(tree.getroot(), source=path.name, form=form).value),  # noqa: B023
            args.repeat,
        )
        rows.append(
            {
                "document": path.name,
                "xml_bytes": len(xml),
                "json_bytes": len(as_json),
                "lxml_parse_s": lxml_s,
                "json_to_xml_s": read_s,
                "xml_to_json_s": write_s,
            }  # fmt: skip
        )

    # whole runs: the import and schema build included
    WORK.mkdir(parents=True, exist_ok=True)
    robot_json = WORK / "jsonform-robot.json"
    robot_json.write_bytes(jsonform.convert((PROJECT / "examples/robot/robot.hcdf").read_bytes(), source="r").data)
    runs = {}
    for name, doc in (("xml", PROJECT / "examples/robot/robot.hcdf"), ("json", robot_json)):
        cmd = [str(CLI), "validate", str(doc), "--schema", str(xsd), "-q"]

        def once(cmd: list[str] = cmd) -> None:
            subprocess.run(cmd, check=False, capture_output=True)

        runs[name] = _median(once, 5)

    print(f"xmlschema import + build of {xsd.name}: {build * 1000:.0f} ms (once per run, JSON documents only)\n")
    print("| document | XML bytes | lxml parse | JSON -> XML | ratio | XML -> JSON | ratio |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(
            f"| {r['document']} | {r['xml_bytes']} | {r['lxml_parse_s'] * 1000:.2f} ms | "
            f"{r['json_to_xml_s'] * 1000:.2f} ms | {r['json_to_xml_s'] / r['lxml_parse_s']:.0f}x | "
            f"{r['xml_to_json_s'] * 1000:.2f} ms | {r['xml_to_json_s'] / r['lxml_parse_s']:.0f}x |"
        )
    print(
        f"\n`validate --schema` of the example robot, whole process: XML {runs['xml'] * 1000:.0f} ms, "
        f"JSON {runs['json'] * 1000:.0f} ms ({runs['json'] / runs['xml']:.1f}x)"
    )
    (WORK / "jsonform.json").write_text(json.dumps({"build_s": build, "rows": rows, "validate_s": runs}, indent=2))


if __name__ == "__main__":
    main()
