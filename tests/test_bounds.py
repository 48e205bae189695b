"""Bounded work: an exponential include tree is refused before it is expanded, and a
1,000-file include chain goes through every verb without hitting the recursion limit."""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import click
import pytest
from lxml import etree

from hcdf_trust.cli import main
from hcdf_trust.errors import XmlError
from hcdf_trust.include import ResolveOptions, resolve
from hcdf_trust.include.flatten import DEFAULT_MAX_ELEMENTS, expanded_elements
from hcdf_trust.xml import MAX_DOCUMENT_ELEMENTS, parse_bytes

# The refusal must come before any copying: well under this address space and time.
MEMORY_LIMIT = 1 << 30
TIME_LIMIT = 60.0


def hcdf(body: str, name: str = "t") -> str:
    return f'<?xml version="1.0"?>\n<hcdf version="1.0" name="{name}">\n{body}\n</hcdf>\n'


def exponential_tree(folder: Path, *, levels: int, fan_out: int) -> Path:
    """level0 includes level1 ``fan_out`` times under distinct names, and so on down."""
    folder.mkdir(parents=True)
    for level in range(levels):
        body = '  <comp name="c"><port name="p" type="CAN"/></comp>'
        if level + 1 < levels:
            body += "".join(
                f'\n  <include uri="level{level + 1}.hcdf" name="i{k}" pose="{k} 0 0 0 0 0"/>' for k in range(fan_out)
            )
        (folder / f"level{level}.hcdf").write_text(hcdf(body, f"level{level}"))
    return folder / "level0.hcdf"


def _elements(path: Path) -> int:
    """Independent count: every element lxml finds in the file."""
    return sum(1 for el in etree.parse(str(path)).iter() if isinstance(el.tag, str))


def run_bounded(*args: str | Path) -> tuple[subprocess.CompletedProcess[str], float]:
    """``hcdf-trust ARGS`` in a child process limited to MEMORY_LIMIT bytes of address space."""
    code = textwrap.dedent(
        f"""
        import resource, sys
        resource.setrlimit(resource.RLIMIT_AS, ({MEMORY_LIMIT}, {MEMORY_LIMIT}))
        from hcdf_trust.cli import main
        sys.argv = ["hcdf-trust", *sys.argv[1:]]
        main()
        """
    )
    start = time.monotonic()
    done = subprocess.run(
        [sys.executable, "-c", code, *map(str, args)], capture_output=True, text=True, timeout=TIME_LIMIT
    )
    return done, time.monotonic() - start


def test_36_kb_of_exponential_includes_is_refused_before_expanding(tmp_path):
    doc = exponential_tree(tmp_path / "bomb", levels=15, fan_out=40)
    size = sum(p.stat().st_size for p in (tmp_path / "bomb").iterdir())
    assert 30_000 < size < 40_000, size
    out = tmp_path / "bomb" / "flat.hcdf"
    done, elapsed = run_bounded("resolve", doc, "--no-lock", "--cache-dir", tmp_path / "c", "--out", out)
    assert done.returncode == 3, done.stderr[-2000:]
    assert "Traceback" not in done.stderr and "MemoryError" not in done.stderr
    # names the count (level l is expanded 40^l times), the cap and the flag
    total = sum(_elements(tmp_path / "bomb" / f"level{level}.hcdf") * 40**level for level in range(15))
    assert f"would have about 10^{len(str(total)) - 1} elements" in done.stderr
    assert f"over the limit of {DEFAULT_MAX_ELEMENTS:,}" in done.stderr and "--max-elements" in done.stderr
    assert "level14.hcdf" in done.stderr
    assert not out.exists()
    assert elapsed < TIME_LIMIT / 2


def test_deep_exponential_tree_with_a_large_max_depth_is_refused_too(tmp_path):
    doc = exponential_tree(tmp_path / "deep", levels=200, fan_out=2)
    done, _ = run_bounded(
        "resolve",
        doc,
        "--no-lock",
        "--cache-dir",
        tmp_path / "c",
        "--max-depth",
        "500",
        "--out",
        tmp_path / "f.hcdf",
        "--max-elements",
        "1000000",
    )
    assert done.returncode == 3, done.stderr[-2000:]
    total = sum(_elements(tmp_path / "deep" / f"level{level}.hcdf") * 2**level for level in range(200))
    assert f"about 10^{len(str(total)) - 1} elements" in done.stderr
    assert "over the limit of 1,000,000" in done.stderr


def test_the_count_is_instances_times_elements_over_the_include_graph(cli, tmp_path):
    root = tmp_path / "r"
    root.mkdir()
    (root / "b.hcdf").write_text(hcdf('<comp name="b"><port name="p" type="CAN"/></comp><material name="m"/>'))
    includes = "".join(f'<include uri="b.hcdf" name="b{i}"/>' for i in range(3))
    (root / "a.hcdf").write_text(hcdf(includes + '<comp name="a"/>'))
    doc = root / "robot.hcdf"
    doc.write_text(hcdf('<include uri="a.hcdf" name="l"/><include uri="a.hcdf" name="r"/><comp name="x"/>'))
    # root once, a twice, b 2 × 3 times
    expected = _elements(doc) + 2 * _elements(root / "a.hcdf") + 6 * _elements(root / "b.hcdf")
    res = resolve(doc, ResolveOptions(cache_dir=str(tmp_path / "c")))
    total, top, times = expanded_elements(res)
    assert (total, Path(top.removeprefix("file://")).name, times) == (expected, "b.hcdf", 6)

    args = ("resolve", doc, "--no-lock", "--out", root / "flat.hcdf", "--json")
    refused = cli(*args, "--max-elements", expected - 1)
    assert refused.exit_code == 3
    (err,) = refused.json["errors"]
    assert f"would have {expected:,} elements, over the limit of {expected - 1:,}" in err["message"]
    assert (err["expected"], err["actual"]) == (f"at most {expected - 1:,} elements", f"{expected:,}")
    assert not (root / "flat.hcdf").exists()
    assert cli(*args, "--max-elements", expected).exit_code == 0


def test_the_cli_default_is_the_documented_one():
    (param,) = [p for p in main.commands["resolve"].params if p.name == "max_elements"]
    assert param.default == DEFAULT_MAX_ELEMENTS


@pytest.mark.parametrize("verb", [("resolve",), ("bundle", "write")])
def test_max_elements_cannot_exceed_what_the_xml_reader_accepts(cli, tmp_path, verb):
    """A flattened or bundled document over the reader's cap could never be read again."""
    command = main
    for name in verb:
        command = command.get_command(click.Context(command), name)  # type: ignore[attr-defined]
    (param,) = [p for p in command.params if p.name == "max_elements"]
    assert param.type.max == MAX_DOCUMENT_ELEMENTS
    doc = tmp_path / "r.hcdf"
    doc.write_text(hcdf('<comp name="a"/>'))
    refused = cli(
        *verb,
        doc,
        *(["--out", tmp_path / "f.hcdf"] if verb == ("resolve",) else [tmp_path / "r.hcdfz"]),
        "--max-elements",
        MAX_DOCUMENT_ELEMENTS + 1,
    )
    assert refused.exit_code == 2 and "--max-elements" in refused.stderr


def test_an_xml_document_of_too_many_elements_is_refused_before_its_tree_is_built():
    """32 MiB of ``<a/>`` is 8 million elements (~1.2 GB in lxml); the count stops at the cap."""
    flood = b'<hcdf version="1.0">' + b"<a/>" * (MAX_DOCUMENT_ELEMENTS + 1) + b"</hcdf>"
    with pytest.raises(XmlError) as refused:
        parse_bytes(flood, source="flood.hcdf")
    assert refused.value.args[0].startswith(f"more than {MAX_DOCUMENT_ELEMENTS:,} elements")
    assert (refused.value.file, refused.value.expected) == ("flood.hcdf", f"at most {MAX_DOCUMENT_ELEMENTS:,} elements")
    at_cap = b'<hcdf version="1.0">' + b"<a/>" * (MAX_DOCUMENT_ELEMENTS - 1) + b"</hcdf>"
    assert len(parse_bytes(at_cap, source="ok.hcdf").getroot()) == MAX_DOCUMENT_ELEMENTS - 1
    # "<" in a comment is not an element: counted, then accepted
    many_lt = b'<hcdf version="1.0"><!--' + b"<" * (MAX_DOCUMENT_ELEMENTS + 1) + b"--></hcdf>"
    assert parse_bytes(many_lt, source="c.hcdf").getroot().tag == "hcdf"


# --- a 1,000-file chain ------------------------------------------------------------------------

CHAIN = 1000


@pytest.fixture(scope="module")
def chain(tmp_path_factory):
    """f0000 includes f0001 (as "n") includes f0002 ... f0999; each has one comp with a pinned model."""
    folder = tmp_path_factory.mktemp("chain")
    glb = b"model bytes"
    (folder / "m.glb").write_bytes(glb)
    pin = hashlib.sha256(glb).hexdigest()
    for i in range(CHAIN):
        include = f'\n  <include uri="f{i + 1:04d}.hcdf" name="n"/>' if i + 1 < CHAIN else ""
        model = f'<comp name="c"><visual name="v"><model uri="m.glb" sha="{pin}"/></visual></comp>'
        (folder / f"f{i:04d}.hcdf").write_text(hcdf(f"  {model}{include}", f"f{i}"))
    return folder


DEPTH = ("--max-depth", str(CHAIN + 10))


def test_a_1000_file_chain_resolves_flattens_and_verifies(cli, chain, tmp_path):
    assert sys.getrecursionlimit() < 2 * CHAIN  # otherwise this test proves nothing
    doc = chain / "f0000.hcdf"
    cache = ("--cache-dir", str(tmp_path / "c"))
    lock = ("--lock", str(tmp_path / "chain.lock"))
    out = chain / "flat.hcdf"
    r = cli("resolve", doc, *DEPTH, *cache, *lock, "--out", out)
    assert r.exit_code == 0, r.stderr[-2000:]
    comps = [el.get("name") for el in etree.parse(str(out)).getroot().iter("comp")]
    assert len(comps) == CHAIN
    assert comps[-1] == "n_" * (CHAIN - 1) + "c"  # every level's prefix, outermost first
    assert cli("verify", doc, *DEPTH, *cache, *lock).exit_code == 0
    again = cli("resolve", out, *cache, "--no-lock", "--json")
    assert again.exit_code == 0 and again.json["summary"]["references"] == CHAIN


def test_a_1000_file_chain_validates(cli, chain):
    r = cli("validate", chain / "f0000.hcdf", "--json")
    assert r.exit_code == 0, r.stdout[-2000:]


def test_a_1000_file_chain_is_pinned_bottom_up(cli, chain, tmp_path):
    r = cli("pin", chain / "f0000.hcdf", *DEPTH, "--cache-dir", tmp_path / "c", "--json")
    assert r.exit_code == 0, r.stdout[-2000:]
    changes = r.json["changes"]
    assert len(changes) == CHAIN - 1 and {c["reason"] for c in changes} == {"missing"}
    # the deepest include is pinned with the digest of the (unchanged) last file
    last = next(c for c in changes if c["uri"] == f"f{CHAIN - 1:04d}.hcdf")
    assert last["new"] == hashlib.sha256((chain / f"f{CHAIN - 1:04d}.hcdf").read_bytes()).hexdigest()


def test_a_1000_file_cycle_is_reported_not_recursed(cli, tmp_path):
    folder = tmp_path / "ring"
    folder.mkdir()
    for i in range(CHAIN):
        (folder / f"f{i:04d}.hcdf").write_text(hcdf(f'<include uri="f{(i + 1) % CHAIN:04d}.hcdf"/>'))
    r = cli("resolve", folder / "f0000.hcdf", *DEPTH, "--no-lock", "--json")
    assert r.exit_code == 3
    assert [e["code"] for e in r.json["errors"]] == ["include-cycle"]
    assert os.path.basename(r.json["errors"][0]["file"]) == f"f{CHAIN - 1:04d}.hcdf"
