"""Hostile XML, as the root document and as an included one, for every command that reads it.

Each case must end in exit 3 with a message that names the specific refusal (so the
test fails if that protection is removed), in bounded time, with no network access
(Python sockets are patched out; libxml2's own C sockets are caught by a loopback
listener we own) and with nothing written (no lock, no --out, no cache blob, no pin edit).
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest

from hcdf_trust.errors import XmlError
from hcdf_trust.xml import MAX_DEPTH, parse_bytes

from ._hostile import (  # noqa: F401  (fixtures are used by name)
    HOSTILE_COMMANDS,
    LoopbackListener,
    command_args,
    fifo_watchdog,
    listener,
    no_network,
    sha256,
    snapshot,
    write_lock,
)

pytestmark = pytest.mark.usefixtures("no_network")

SECRET = "TOP-SECRET-7f3a91"
ROOT_INCLUDING_SUB = (
    b'<?xml version="1.0"?>\n<hcdf version="1.0" name="r">\n<include uri="sub.hcdf" name="s"/>\n</hcdf>\n'
)


@dataclass
class Ctx:
    work: Path
    listener: LoopbackListener

    @property
    def secret(self) -> Path:
        return self.work / "outside" / "secret.txt"

    @property
    def evil_dtd(self) -> Path:
        return self.work / "outside" / "evil.dtd"

    @property
    def fifo(self) -> Path:
        return self.work / "outside" / "pipe.dtd"


def _lol(levels: int) -> bytes:
    ents = '<!ENTITY lol0 "lol">'
    for i in range(1, levels + 1):
        ents += f'<!ENTITY lol{i} "{f"&lol{i - 1};" * 10}">'
    return (f'<?xml version="1.0"?>\n<!DOCTYPE hcdf [{ents}]>\n<hcdf version="1.0" name="&lol{levels};"/>\n').encode()


def _nest(depth: int) -> bytes:
    return b'<hcdf version="1.0">' + b"<comp>" * depth + b"</comp>" * depth + b"</hcdf>"


DOCTYPE_REFUSED = r"a DOCTYPE is not allowed in HCDF"


def _load_refused(target: str) -> str:
    return r"a DOCTYPE that loads '" + re.escape(target) + r"' is refused"


# id -> (document factory, regex the error message must match)
CASES: dict[str, tuple[Callable[[Ctx], bytes], Callable[[Ctx], str]]] = {
    "external-entity-file": (
        lambda c: (
            f'<?xml version="1.0"?>\n<!DOCTYPE hcdf [<!ENTITY x SYSTEM "file://{c.secret}">]>\n'
            f'<hcdf version="1.0"><description>&x;</description></hcdf>\n'
        ).encode(),
        lambda c: DOCTYPE_REFUSED,
    ),
    "external-entity-file-in-attribute": (
        lambda c: (
            f'<?xml version="1.0"?>\n<!DOCTYPE hcdf [<!ENTITY x SYSTEM "file://{c.secret}">]>\n'
            f'<hcdf version="1.0" name="&x;"/>\n'
        ).encode(),
        lambda c: r"malformed XML: Attribute references external entity 'x'",
    ),
    "external-entity-http": (
        lambda c: (
            f'<?xml version="1.0"?>\n<!DOCTYPE hcdf [<!ENTITY x SYSTEM "{c.listener.url("x")}">]>\n'
            f'<hcdf version="1.0"><description>&x;</description></hcdf>\n'
        ).encode(),
        lambda c: DOCTYPE_REFUSED,
    ),
    "parameter-entity-file": (
        lambda c: (
            f'<?xml version="1.0"?>\n<!DOCTYPE hcdf [<!ENTITY % p SYSTEM "file://{c.evil_dtd}"> %p;]>\n'
            f'<hcdf version="1.0"/>\n'
        ).encode(),
        lambda c: _load_refused(f"file://{c.evil_dtd}"),
    ),
    "parameter-entity-http": (
        lambda c: (
            f'<?xml version="1.0"?>\n<!DOCTYPE hcdf [<!ENTITY % p SYSTEM "{c.listener.url("p.dtd")}"> %p;]>\n'
            f'<hcdf version="1.0"/>\n'
        ).encode(),
        lambda c: _load_refused(c.listener.url("p.dtd")),
    ),
    "external-dtd-file": (
        lambda c: (
            f'<?xml version="1.0"?>\n<!DOCTYPE hcdf SYSTEM "file://{c.evil_dtd}">\n<hcdf version="1.0"/>\n'
        ).encode(),
        lambda c: _load_refused(f"file://{c.evil_dtd}"),
    ),
    "external-dtd-relative": (
        lambda c: b'<?xml version="1.0"?>\n<!DOCTYPE hcdf SYSTEM "evil.dtd">\n<hcdf version="1.0"/>\n',
        lambda c: _load_refused("evil.dtd"),
    ),
    "external-dtd-http": (
        lambda c: (
            f'<?xml version="1.0"?>\n<!DOCTYPE hcdf PUBLIC "-//X//Y//EN" "{c.listener.url("h.dtd")}">\n'
            f'<hcdf version="1.0"/>\n'
        ).encode(),
        lambda c: _load_refused(c.listener.url("h.dtd")),
    ),
    # Without the refusing resolver in xml.py, libxml2 opens this FIFO and blocks for ever.
    "external-dtd-fifo": (
        lambda c: (
            f'<?xml version="1.0"?>\n<!DOCTYPE hcdf SYSTEM "file://{c.fifo}">\n<hcdf version="1.0"/>\n'
        ).encode(),
        lambda c: _load_refused(f"file://{c.fifo}"),
    ),
    # 10^3 expansions: under libxml2's own amplification guard, so only our DOCTYPE refusal stops it.
    "billion-laughs-small": (lambda c: _lol(3), lambda c: DOCTYPE_REFUSED),
    "billion-laughs": (
        lambda c: _lol(9),
        lambda c: DOCTYPE_REFUSED + "|entity amplification factor exceeded",
    ),
    "nest-10000-deep": (lambda c: _nest(10_000), lambda c: r"[Ee]xcessive depth|nested deeper"),
    # Under libxml2's 256 but over our MAX_DEPTH: only xml._check_depth refuses it.
    "nest-250-deep": (
        lambda c: _nest(MAX_DEPTH + 50),
        lambda c: f"elements nested deeper than {MAX_DEPTH} levels",
    ),
    # 20 MB: under our byte limit, over libxml2's 10 MB text limit (kept by huge_tree=False).
    "attribute-20mb": (
        lambda c: b'<hcdf version="1.0" name="' + b"x" * (20 << 20) + b'"/>',
        lambda c: r"malformed XML: Resource limit exceeded",
    ),
    "invalid-utf8": (
        lambda c: b'<?xml version="1.0" encoding="UTF-8"?>\n<hcdf version="1.0" name="\xff\xfe\xc3"/>\n',
        lambda c: r"malformed XML: .*(bytes|encoding|UTF-8|Char)",
    ),
    "utf8-encoded-surrogate": (
        lambda c: b'<hcdf version="1.0" name="\xed\xa0\x80"/>\n',
        lambda c: r"malformed XML",
    ),
    "unknown-encoding": (
        lambda c: b'<?xml version="1.0" encoding="x-no-such-codec"?>\n<hcdf version="1.0"/>\n',
        lambda c: r"malformed XML",
    ),
    "nul-byte": (lambda c: b'<hcdf version="1.0">\x00</hcdf>', lambda c: r"malformed XML"),
    "truncated": (lambda c: b'<hcdf version="1.0"><comp name="a"><visual>', lambda c: r"malformed XML"),
    "not-hcdf-html": (
        lambda c: b"<html><body><p>hello</p></body></html>\n",
        lambda c: r"not an HCDF document.*: root element is <html>",
    ),
    "not-xml": (lambda c: b"just some text, no markup\n", lambda c: r"malformed XML"),
    "empty-file": (lambda c: b"", lambda c: r"empty document"),
    "whitespace-only": (lambda c: b"  \n\t\n", lambda c: r"empty document"),
}


@pytest.fixture
def ctx(tmp_path, listener) -> Ctx:  # noqa: F811
    work = tmp_path / "work"
    (work / "outside").mkdir(parents=True)
    c = Ctx(work=work, listener=listener)
    c.secret.write_text(SECRET + "\n")
    c.evil_dtd.write_text(f'<!ENTITY leak "{SECRET}">\n<!ENTITY % x "garbage-to-force-an-error">\n%x;\n')
    os.mkfifo(c.fifo)
    # A relative DTD name resolves against the current folder: put one there too.
    (work / "evil.dtd").write_text(c.evil_dtd.read_text())
    return c


def _check(result, ctx: Ctx, pattern: str, before, *, names: str, warning_only: bool = False) -> None:
    output = result.stdout + result.stderr
    if warning_only:
        # validate reads includes only for the cross-file frame rule; a hostile one is
        # an include-refused error naming the refusal, and the root is still validated.
        assert result.exit_code == 1, output
        assert "error[include-refused]" in result.stderr, output
    else:
        assert result.exit_code == 3, output
        assert "error:" in result.stderr, output
    assert re.search(pattern, result.stderr), f"expected /{pattern}/ in:\n{result.stderr}"
    assert names in result.stderr, output
    assert SECRET not in output
    assert "Traceback" not in output
    assert ctx.listener.connections() == 0, "the XML parser opened a connection"
    assert not (ctx.work / "flat.hcdf").exists()
    assert not (ctx.work / "cache").exists() or not any((ctx.work / "cache").rglob("*"))
    assert snapshot(ctx.work) == before, "a hostile run wrote or changed files"


def _run(cli, args, ctx: Ctx):
    with fifo_watchdog(ctx.fifo, seconds=5.0) as watch:
        result = cli(*args)
    assert not watch["hung"], "the command blocked on a FIFO"
    assert watch["elapsed"] < 5.0
    return result


@pytest.mark.parametrize("command", HOSTILE_COMMANDS)
@pytest.mark.parametrize("case", list(CASES))
def test_hostile_root_document(cli, ctx, monkeypatch, case, command):
    make, pattern = CASES[case]
    doc = ctx.work / "doc.hcdf"
    doc.write_bytes(make(ctx))
    if command == "verify":
        write_lock(ctx.work / "doc.hcdf.lock", "doc.hcdf", [])
    monkeypatch.chdir(ctx.work)
    before = snapshot(ctx.work)
    result = _run(cli, command_args(command, doc, ctx.work), ctx)
    _check(result, ctx, pattern(ctx), before, names="doc.hcdf")


@pytest.mark.parametrize("command", HOSTILE_COMMANDS)
@pytest.mark.parametrize("case", list(CASES))
def test_hostile_included_document(cli, ctx, monkeypatch, case, command):
    make, pattern = CASES[case]
    hostile = make(ctx)
    root = ctx.work / "root.hcdf"
    root.write_bytes(ROOT_INCLUDING_SUB)
    (ctx.work / "sub.hcdf").write_bytes(hostile)
    if command == "verify":
        # The lock pins exactly these bytes, so verify gets as far as parsing them.
        write_lock(
            ctx.work / "root.hcdf.lock",
            "root.hcdf",
            [{"uri": "sub.hcdf", "sha256": sha256(hostile), "size": len(hostile), "referenced_from": ["root.hcdf:3"]}],
        )
    monkeypatch.chdir(ctx.work)
    before = snapshot(ctx.work)
    result = _run(cli, command_args(command, root, ctx.work), ctx)
    _check(result, ctx, pattern(ctx), before, names="sub.hcdf", warning_only=command == "validate")


@pytest.mark.parametrize("case", ["external-entity-file", "external-dtd-http", "billion-laughs", "empty-file"])
def test_hostile_included_document_json(cli, ctx, monkeypatch, case):
    """--json names the error code, the file and the line of the include that led there."""
    make, _ = CASES[case]
    (ctx.work / "root.hcdf").write_bytes(ROOT_INCLUDING_SUB)
    (ctx.work / "sub.hcdf").write_bytes(make(ctx))
    monkeypatch.chdir(ctx.work)
    result = _run(cli, command_args("resolve", ctx.work / "root.hcdf", ctx.work, "--json"), ctx)
    assert result.exit_code == 3
    payload = result.json
    assert payload["ok"] is False
    codes = {e["code"] for e in payload["errors"]}
    assert codes == {"xml"}, payload["errors"]
    assert all(e["file"].endswith("sub.hcdf") for e in payload["errors"])
    assert not (ctx.work / "root.hcdf.lock").exists()


# --- a 100 MB attribute: refused by size, before it is read into memory ---------------

_MEASURE = """
import sys, time
started = time.monotonic()
from hcdf_trust.cli import main
code = 0
try:
    main.main(sys.argv[1:], prog_name="hcdf-trust")
except SystemExit as exc:
    code = exc.code
# VmHWM, not ru_maxrss: Linux carries the parent's peak across fork+exec into ru_maxrss.
hwm = next(line.split()[1] for line in open("/proc/self/status") if line.startswith("VmHWM:"))
sys.stderr.write(f"\\nMEASURED rss_kb={hwm} "
                 f"seconds={time.monotonic() - started:.3f} code={code}\\n")
"""


def _measure(args: list[str], cwd: Path) -> tuple[int, int, float, str]:
    proc = subprocess.run(
        [sys.executable, "-c", _MEASURE, *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=60,
        env={**os.environ, "XDG_CACHE_HOME": str(cwd / "xdg")},
    )
    m = re.search(r"MEASURED rss_kb=(\d+) seconds=([\d.]+) code=(\d+)", proc.stderr)
    assert m, proc.stderr
    return int(m.group(3)), int(m.group(1)), float(m.group(2)), proc.stderr


def _write_big_attribute(path: Path, megabytes: int) -> None:
    with open(path, "wb") as f:
        f.write(b'<?xml version="1.0"?>\n<hcdf version="1.0" name="')
        block = b"A" * (1 << 20)
        for _ in range(megabytes):
            f.write(block)
        f.write(b'"/>\n')


@pytest.fixture(scope="module")
def big_attribute(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("big")
    path = folder / "big.hcdf"
    _write_big_attribute(path, 100)
    return path


@pytest.mark.parametrize("command", HOSTILE_COMMANDS)
@pytest.mark.parametrize("where", ["root", "included"])
def test_100mb_attribute_bounded_time_and_memory(tmp_path, big_attribute, command, where):
    work = tmp_path / "w"
    work.mkdir()
    small = work / "small.hcdf"
    small.write_bytes(b'<?xml version="1.0"?>\n<hcdf version="1.0" name="small"/>\n')
    if where == "root":
        doc = work / "doc.hcdf"
        os.link(big_attribute, doc)  # no copy: the same 100 MB inode
    else:
        doc = work / "root.hcdf"
        doc.write_bytes(ROOT_INCLUDING_SUB)
        os.link(big_attribute, work / "sub.hcdf")
        if command == "verify":
            write_lock(
                work / "root.hcdf.lock",
                "root.hcdf",
                [
                    {
                        "uri": "sub.hcdf",
                        "sha256": "0" * 64,
                        "size": big_attribute.stat().st_size,
                        "referenced_from": ["root.hcdf:3"],
                    }
                ],
            )
    if command == "verify" and where == "root":
        write_lock(work / "doc.hcdf.lock", "doc.hcdf", [])
    # The same command on a tiny document is the baseline (imports, interpreter).
    _, base_rss, _, _ = _measure(command_args(command, small, work), work)
    before = snapshot(work)
    started = time.monotonic()
    code, rss, seconds, stderr = _measure(command_args(command, doc, work), work)
    wall = time.monotonic() - started
    if command == "validate" and where == "included":
        assert code == 1 and "error[include-refused]" in stderr, stderr  # see _check
    else:
        assert code in (1, 3), stderr
        assert "error:" in stderr
    if command not in ("verify", "validate") or where == "root":
        # verify of an include checks the lock's digest first: a mismatch (exit 1) is fine.
        assert code == 3, stderr
        assert re.search(r"over the \d+-byte limit|too large|limit", stderr), stderr
    assert "Traceback" not in stderr
    assert seconds < 5.0 and wall < 15.0, f"took {seconds:.1f} s"
    # Refused from its size, not after reading 100 MB (or parsing it at lxml's ~13x).
    assert rss - base_rss < 48 * 1024, f"peak RSS grew by {(rss - base_rss) // 1024} MB"
    assert snapshot(work) == before


# --- the parser factory itself ------------------------------------------------------


def test_parser_refuses_external_loads_before_opening_them(tmp_path):
    """The resolver in xml.py refuses the load: the file is never opened (a FIFO proves it)."""
    fifo = tmp_path / "never-opened.dtd"
    os.mkfifo(fifo)
    data = f'<!DOCTYPE hcdf SYSTEM "file://{fifo}"><hcdf/>'.encode()
    with fifo_watchdog(fifo, seconds=3.0) as watch, pytest.raises(XmlError) as info:
        parse_bytes(data, source="t.hcdf")
    assert not watch["hung"]
    assert "is refused" in info.value.message


def test_parser_keeps_entities_unexpanded_and_refuses_doctype():
    with pytest.raises(XmlError, match="DOCTYPE is not allowed"):
        parse_bytes(_lol(2), source="t.hcdf")


def test_parser_accepts_depth_just_under_the_limit():
    """The depth check is a limit, not a refusal of nesting: control case."""
    parse_bytes(_nest(MAX_DEPTH - 2), source="t.hcdf")


# --- validate --schema: the XSD is a file the tool reads, hostile in its own ways ------

XS_OPEN = '<xs:schema xmlns:xs="http://www.w3.org/2001/XMLSchema">'
SCHEMA_CASES: dict[str, tuple[Callable[[Ctx], bytes | None], Callable[[Ctx], str]]] = {
    "doctype-external-dtd": (
        lambda c: f'<?xml version="1.0"?><!DOCTYPE xs:schema SYSTEM "file://{c.fifo}">{XS_OPEN}</xs:schema>'.encode(),
        lambda c: _load_refused(f"file://{c.fifo}"),
    ),
    "doctype-entity": (
        lambda c: (
            f'<?xml version="1.0"?><!DOCTYPE xs:schema [<!ENTITY x SYSTEM "file://{c.secret}">]>'
            f"{XS_OPEN}<xs:annotation><xs:documentation>&x;</xs:documentation></xs:annotation></xs:schema>"
        ).encode(),
        lambda c: DOCTYPE_REFUSED,
    ),
    "include-dotdot": (
        lambda c: f'{XS_OPEN}<xs:include schemaLocation="../outside/x.xsd"/></xs:schema>'.encode(),
        lambda c: r"outside the root|refused",
    ),
    "include-absolute": (
        lambda c: f'{XS_OPEN}<xs:include schemaLocation="{c.work / "outside" / "x.xsd"}"/></xs:schema>'.encode(),
        lambda c: r"schema import .* refused",
    ),
    "import-http": (
        lambda c: (
            f'{XS_OPEN}<xs:import namespace="urn:x" schemaLocation="{c.listener.url("x.xsd")}"/></xs:schema>'
        ).encode(),
        lambda c: r"schema import 'http://127\.0\.0\.1:\d+/x\.xsd' refused",
    ),
    "include-fifo": (
        lambda c: f'{XS_OPEN}<xs:include schemaLocation="pipe.xsd"/></xs:schema>'.encode(),
        lambda c: r"is not a regular file",
    ),
    "not-xsd": (lambda c: b"<html/>", lambda c: r"not an XSD"),
    "empty": (lambda c: b"", lambda c: r"empty document"),
    "schema-is-a-fifo": (lambda c: None, lambda c: r"is not a regular file"),
}


@pytest.mark.parametrize("case", list(SCHEMA_CASES))
def test_hostile_schema(cli, ctx, monkeypatch, case):
    make, pattern = SCHEMA_CASES[case]
    schemas = ctx.work / "schemas"
    schemas.mkdir()
    (ctx.work / "outside" / "x.xsd").write_text(f"{XS_OPEN}</xs:schema>")
    os.mkfifo(schemas / "pipe.xsd")
    schema = schemas / "s.xsd"
    data = make(ctx)
    if data is None:
        os.mkfifo(schema)
    else:
        schema.write_bytes(data)
    doc = ctx.work / "doc.hcdf"
    doc.write_bytes(b'<hcdf version="1.0" name="ok"/>\n')
    monkeypatch.chdir(ctx.work)
    before = snapshot(ctx.work)
    with fifo_watchdog(schema if data is None else schemas / "pipe.xsd") as w1, fifo_watchdog(ctx.fifo) as w2:
        result = cli("validate", doc, "--schema", schema)
    assert not w1["hung"] and not w2["hung"], "validate blocked on a FIFO"
    _check(result, ctx, pattern(ctx), before, names="s.xsd")
