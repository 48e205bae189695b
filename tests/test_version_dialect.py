"""``version="2.0"`` documents (hcdf_models, dendrite) keep working, with one warning that
upstream's own reader (hcdformat-rs ``version.rs``: any 1.x, never a foreign major) refuses them."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.conftest import MODELS

BOARD = MODELS / "mr_mcxn_t1" / "optical-flow" / "d9507e38-optical-flow.hcdf"
CODE = "foreign-major-version"


def tree(root: Path, *, version: str) -> Path:
    """A robot including two boards, every document at ``version``."""
    root.mkdir()
    for name in ("a", "b"):
        (root / f"{name}.hcdf").write_text(f'<hcdf version="{version}"><comp name="{name}"/></hcdf>\n')
    doc = root / "robot.hcdf"
    doc.write_text(
        f'<hcdf version="{version}" name="bot">\n'
        '  <include uri="a.hcdf" name="a"/>\n  <include uri="b.hcdf" name="b"/>\n'
        "</hcdf>\n"
    )
    return doc


def codes(warnings: list[dict]) -> list[str]:
    return [w["code"] for w in warnings]


def test_a_2_0_tree_resolves_with_one_notice(cli, tmp_path):
    doc = tree(tmp_path / "bot", version="2.0")
    r = cli("resolve", doc, "--json", "--lock", tmp_path / "x.lock")
    assert r.exit_code == 0, r.stdout + r.stderr
    found = [w for w in r.json["warnings"] if w["code"] == CODE]
    assert len(found) == 1  # once per run, not once per document
    assert found[0]["file"].endswith("robot.hcdf") and found[0]["line"] == 1
    assert 'version="2.0"' in found[0]["message"] and "2 more documents" in found[0]["message"]
    assert "refuses" in found[0]["message"]
    r = cli("verify", doc, "--lock", tmp_path / "x.lock")
    assert r.exit_code == 0 and r.stderr.count("upstream's own reader") == 1, r.stderr


@pytest.mark.parametrize("version", ["1.0", "1.2", "1"])
def test_1_x_says_nothing(cli, tmp_path, version):
    doc = tree(tmp_path / "bot", version=version)
    r = cli("resolve", doc, "--json", "--lock", tmp_path / "x.lock")
    assert r.exit_code == 0 and CODE not in codes(r.json["warnings"])


def test_corpus_board_in_every_verb(cli, tmp_path):
    base = ["--base", MODELS, "--lock", tmp_path / "x.lock"]
    assert cli("resolve", BOARD, *base).exit_code == 0
    r = cli("validate", BOARD, "--base", MODELS, "--json")
    assert r.exit_code == 0, r.stdout
    assert [f["severity"] for f in r.json["findings"] if f["code"] == CODE] == ["warning"]
    r = cli("audit", BOARD, *base, "--json")
    assert r.exit_code == 0, r.stdout + r.stderr
    assert [f["severity"] for f in r.json["findings"] if f["check"] == CODE] == ["warning"]
    r = cli("macsec", "plan", BOARD, *base, "--json")
    assert r.exit_code == 0, r.stdout + r.stderr
    assert codes(r.json["warnings"]).count(CODE) == 1
    r = cli("sbom", BOARD, *base, "--format", "cyclonedx", "--json")
    assert r.exit_code == 0, r.stdout + r.stderr
    assert codes(r.json["warnings"]).count(CODE) == 1
