"""macsec over HCDF as upstream writes it since April 2026 (issue 18): top-level <link>, <bus>,
<chain>, <star>… with <configuration><macsec><policy>/<default-policy>/<override>.

The documents are in tests/macsec_upstream/, each saying which upstream file it is modeled on.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from ._macsec import lock

DOCS = Path(__file__).parent / "macsec_upstream"
PASS = b"upstream dialect passphrase"


def _doc(tmp: Path, name: str, edit: tuple[str, str] | None = None) -> Path:
    """A copy of test document ``name`` (with one text replacement), locked."""
    doc = tmp / name
    text = (DOCS / name).read_text()
    if edit is not None:
        assert edit[0] in text, edit
        text = text.replace(edit[0], edit[1])
    doc.write_text(text)
    return lock(doc)


def _line(doc: Path, text: str) -> int:
    return next(n for n, line in enumerate(doc.read_text().splitlines(), 1) if text in line)


@pytest.fixture
def keys(tmp_path):
    pp = tmp_path / "pass"
    pp.write_bytes(PASS)
    return ["--store", tmp_path / "keys", "--passphrase-file", pp]


# --- fail closed: MACsec policy is never "0 to key" ------------------------------------------------


def test_macsec_this_planner_cannot_read_is_an_error_not_nothing_to_key(tmp_path, cli, keys):
    # a <macsec> somewhere no reader consumes (here: under a <comp>, not a port's capabilities)
    doc = _doc(tmp_path, "chain-must-secure.hcdf", ('<comp name="tail-board">', '<comp name="tail-board"><macsec/>'))
    for verb in (
        ["plan"],
        ["generate", *keys],
        ["export", *keys, "--device", "tail-board", "--format", "json", "--out", tmp_path / "o"],
    ):
        r = cli("macsec", verb[0], doc, *verb[1:], "--json")
        assert r.exit_code == 3, (verb, r.stdout)
        assert any(
            "not read by this planner" in e["message"] and e["line"] == _line(doc, "<macsec/>")
            for e in r.json["errors"]
        ), r.json
    assert not (tmp_path / "o").exists() and not (tmp_path / "keys").exists()
