"""Helpers for the macsec tests: small locked HCDF trees written in a temporary folder."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

from hcdf_trust.include.resolver import ResolveOptions, resolve

from .conftest import HCDFORMAT

HUMANOID = HCDFORMAT / "examples" / "humanoid-mobile-base.hcdf"


def lock(doc: Path) -> Path:
    """Resolve ``doc`` offline and write its lock under the default name; return ``doc``."""
    res = resolve(doc, ResolveOptions(offline=True))
    assert res.ok, [str(e) for e in res.errors]
    res.write_lock()
    return doc


def tree(root: Path, files: dict[str, str], doc: str = "robot.hcdf") -> Path:
    """Write ``files`` under ``root`` and lock ``doc``."""
    for name, text in files.items():
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return lock(root / doc)


def humanoid(tmp: Path) -> Path:
    """The corpus humanoid example and its stream profile, copied and locked (the corpus is read-only)."""
    shutil.copy(HUMANOID, tmp / HUMANOID.name)
    shutil.copytree(HUMANOID.parent / "profiles", tmp / "profiles")
    return lock(tmp / HUMANOID.name)


def port(name: str, *ciphers: str, mbps: int = 1000, kind: str = "ethernet") -> str:
    caps = "".join(f"<cipher>{c}</cipher>" for c in ciphers)
    macsec = f"<macsec>{caps}</macsec>" if ciphers else ""
    return (
        f'<port name="{name}" type="{kind}"><capabilities><speed unit="Mbps">{mbps}</speed>'
        f"{macsec}</capabilities></port>"
    )


def comp(name: str, *ports: str) -> str:
    return f'<comp name="{name}">{"".join(ports)}</comp>'


def link(name: str, a: str, b: str, macsec: str = "") -> str:
    return f'<link name="{name}"><wired><port>{a}</port><port>{b}</port>{macsec}</wired></link>'


def hcdf(*body: str) -> str:
    return '<?xml version="1.0"?>\n<hcdf version="1.0" name="t">\n' + "\n".join(body) + "\n</hcdf>\n"


def store_lines(path: Path) -> tuple[dict[str, Any], dict[str, Any]]:
    """A key store file read without checking it: its header and CA id -> association (JSON Lines)."""
    head, *lines = path.read_text().splitlines()
    return json.loads(head), dict(json.loads(line) for line in lines)


def write_store_lines(path: Path, head: dict[str, Any], assocs: dict[str, Any]) -> None:
    """Write a header and associations back in the store's layout (the MAC is left as it was)."""
    dump = lambda v: json.dumps(v, sort_keys=True, separators=(",", ":"))  # noqa: E731
    body = [dump(head), *(dump([ca, a]) for ca, a in sorted(assocs.items()))]
    path.write_text("\n".join(body) + "\n")


def generate(cli: Any, tmp: Path, doc: Path, passphrase: bytes) -> list[Any]:
    """``macsec generate DOC`` into ``tmp/keys`` with a passphrase file; the store flags for the next verbs."""
    pp = tmp / "pass"
    pp.write_bytes(passphrase)
    base: list[Any] = ["--store", tmp / "keys", "--passphrase-file", pp]
    r = cli("macsec", "generate", doc, *base)
    assert r.exit_code == 0, r.stderr
    return base


# ``python -c KILLER WHEN NAME ARGS...``: the CLI with ARGS, killed (SIGKILL) just "before" or
# "after" it renames a file named NAME into place (an interrupted write).
KILLER = """
import os, signal, sys
when, name = sys.argv[1], sys.argv[2]
real = os.replace
def replace(src, dst, **kw):
    if when == "before" and str(dst).endswith(name):
        os.kill(os.getpid(), signal.SIGKILL)
    real(src, dst, **kw)
    if when == "after" and str(dst).endswith(name):
        os.kill(os.getpid(), signal.SIGKILL)
os.replace = replace
from hcdf_trust.cli import main
main(sys.argv[3:], prog_name="hcdf-trust")
"""
