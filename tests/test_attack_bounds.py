"""Attack: inputs that are small but deep, and numbers that are huge or not numbers at all.

Every TOML input goes through ``localfile.read_toml`` (size and nesting caps checked before
tomllib, which recurses without limit, sees the text); every number and time from a flag or
the environment through one click type per kind (``hcdf_trust/cli/params.py``): a value out
of range is a usage error (exit 2) in every verb, never a traceback or a silent default.
The ``cli`` fixture does not catch exceptions: a RecursionError or OverflowError fails the test.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from ._macsec import comp, hcdf, link, port, tree
from ._ota import make_robot

PROJECT = Path(__file__).resolve().parents[1]
ROBOT = PROJECT / "examples" / "robot" / "robot.hcdf"
PASS = "correct horse battery staple"
T0 = "2026-01-01T00:00:00Z"

DEEP = {
    "arrays": "a = " + "[" * 5000 + "]" * 5000 + "\n",
    "inline-tables": "a = " + "{b = " * 5000 + "1" + "}" * 5000 + "\n",
    "dotted-keys": "a" + ".a" * 3000 + " = 1\n",
}


@pytest.fixture(params=sorted(DEEP))
def deep(request, tmp_path) -> Path:
    path = tmp_path / "deep.toml"
    path.write_text(DEEP[request.param])
    return path


def test_the_reader_measures_nesting_outside_strings_and_comments(tmp_path):
    from hcdf_trust.localfile import MAX_TOML_DEPTH, read_toml

    path = tmp_path / "ok.toml"
    nested = "[" * MAX_TOML_DEPTH + "]" * MAX_TOML_DEPTH
    path.write_text(
        f'a = "{"[" * 100}"\n'
        f"b = '{{{{{{{{'\n"
        f'c = """ \\""" [[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[ """\n'
        f"d = '''\n{'[' * 100}\n'''\n"
        f"# {'[' * 100}\n"
        f"e = {nested}\n"
        '[t."[[[["]\nf = 1\n'
    )
    doc = read_toml(path, limit=1 << 20, what="test")
    assert doc["a"] == "[" * 100 and doc["t"]["[[[["]["f"] == 1
    path.write_text(f"e = {'[' * (MAX_TOML_DEPTH + 1)}{']' * (MAX_TOML_DEPTH + 1)}\n")
    with pytest.raises(Exception, match="levels deep"):
        read_toml(path, limit=1 << 20, what="test")


def test_audit_policy(cli, deep):
    r = cli("audit", ROBOT, "--policy", deep)
    assert r.exit_code == 3 and "levels deep" in r.stderr, r.stderr


def test_ota_config_and_ota_toml(cli, tmp_path, deep):
    robot = make_robot(tmp_path, cli)
    out = tmp_path / "rel"
    r = robot.build(cli, out, "--config", deep)
    assert r.exit_code == 3 and "levels deep" in r.stderr, r.stderr
    (robot.root / "ota.toml").write_bytes(deep.read_bytes())  # the one found beside the document
    r = robot.build(cli, out)
    assert r.exit_code == 3 and "levels deep" in r.stderr, r.stderr
    assert not out.exists()


@pytest.fixture
def registry(tmp_path, cli, monkeypatch):
    monkeypatch.setenv("HCDF_TRUST_PASSPHRASE", PASS)
    src, keys = tmp_path / "src", tmp_path / "keys"
    assert cli("registry", "init", src, "--keys", keys).exit_code == 0
    (tmp_path / "content").mkdir()
    return src, keys, tmp_path


def test_registry_root_and_domain_files(cli, registry, deep):
    src, keys, tmp = registry
    publish = ("registry", "publish", src, "--keys", keys, "--content", tmp / "content", "--out", tmp / "site")
    (src / "domains").mkdir(exist_ok=True)
    (src / "domains" / "org.example.toml").write_bytes(deep.read_bytes())
    r = cli(*publish)
    assert r.exit_code == 3 and "levels deep" in r.stderr, r.stderr
    (src / "domains" / "org.example.toml").unlink()
    (src / "root.toml").write_bytes(deep.read_bytes())
    r = cli(*publish)
    assert r.exit_code == 3 and "levels deep" in r.stderr, r.stderr
    assert not (tmp / "site").exists()


def test_registry_owner_key(cli, registry, deep):
    src, _keys, tmp = registry
    schema = tmp / "content" / "x.xsd"
    schema.write_text('<xs:schema xmlns:xs="http://www.w3.org/2001/XMLSchema"/>')
    r = cli("registry", "add", src, "--domain", "org.example", "--version", "1.0", "--schema", schema,
            "--content", tmp / "content", "--owner", "them", "--owner-key", deep)  # fmt: skip
    assert r.exit_code == 3 and "levels deep" in r.stderr, r.stderr


# --- numbers and times -------------------------------------------------------------------------


@pytest.mark.parametrize("epoch", ["yesterday", "-1", "1e9", "99999999999999999999", "32503680000"])
def test_source_date_epoch_is_checked_the_same_by_ota_build_and_sbom(cli, tmp_path, monkeypatch, epoch):
    robot = make_robot(tmp_path, cli)
    monkeypatch.setenv("SOURCE_DATE_EPOCH", epoch)
    out = tmp_path / "rel"
    r = robot.build(cli, out)
    assert r.exit_code == 2 and "SOURCE_DATE_EPOCH" in r.stderr, r.stderr
    assert not out.exists()
    r = cli("sbom", robot.doc, "--format", "cyclonedx")
    assert r.exit_code == 2 and "SOURCE_DATE_EPOCH" in r.stderr and r.stdout == ""


def test_source_date_epoch_dates_the_release(cli, tmp_path, monkeypatch):
    robot = make_robot(tmp_path, cli)
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1764547200")
    assert robot.build(cli, tmp_path / "rel").exit_code == 0
    latest = next((tmp_path / "rel").glob("*/*/latest.json"))
    assert json.loads(latest.read_text())["latest"]["date"] == "2025-12-01T00:00:00Z"


@pytest.fixture
def macsec(tmp_path, cli, monkeypatch):
    monkeypatch.setenv("HCDF_TRUST_PASSPHRASE", PASS)
    body = [
        comp("a", port("p0", "gcm-aes-128")) + comp("b", port("p0", "gcm-aes-128")),
        '<network name="n">',
        link("l0", "a/p0", "b/p0", '<macsec policy="must-secure" cipher="gcm-aes-128" key-ref="k0"/>'),
        "</network>",
    ]
    doc = tree(tmp_path, {"robot.hcdf": hcdf(*body)})
    store = ("--store", tmp_path / "keys")
    assert cli("macsec", "generate", doc, *store, "--now", T0).exit_code == 0
    return doc, store


@pytest.mark.parametrize(
    "args",
    [
        ("rotate", "--now", "9999-12-31T23:59:59Z"),  # + the overlap: past the last date Python holds
        ("rotate", "--now", "0001-01-01T00:00:00+01:00"),
        ("rotate", "--now", "2026-01-01T00:00:00"),  # no zone
        ("rotate", "--overlap", "99999999999999999999"),
        ("rotate", "--overlap", "-5"),
        ("status", "--now", "yesterday"),
        ("retire", "--now", "9999-12-31T23:59:59Z"),
    ],
)
def test_macsec_times_and_durations_are_range_checked(cli, macsec, args):
    doc, store = macsec
    verb, *rest = args
    head = [] if verb == "retire" else [doc]
    r = cli("macsec", verb, *head, *store, *rest)
    assert r.exit_code == 2, r.stderr


def test_audit_now_is_range_checked(cli, macsec):
    doc, store = macsec
    r = cli("audit", doc, *store, "--now", "9999-12-31T23:59:59Z")
    assert r.exit_code == 2, r.stderr


@pytest.mark.parametrize(
    "args",
    [
        ("resolve", "{doc}", "--timeout", "inf"),
        ("resolve", "{doc}", "--timeout", "1e400"),
        ("resolve", "{doc}", "--max-size", "9" * 40),
        ("resolve", "{doc}", "--max-depth", "9" * 40),
        ("registry", "verify", "https://127.0.0.1:9/", "--trusted-root", "{doc}", "--timeout", "nan"),
        (
            "registry",
            "publish",
            "{tmp}",
            "--keys",
            "{tmp}",
            "--content",
            "{tmp}",
            "--out",
            "{tmp}/s",
            "--expires",
            "9" * 40 + "w",
        ),  # fmt: skip
    ],
)
def test_other_numbers_are_range_checked(cli, tmp_path, args):
    doc = tmp_path / "robot.hcdf"
    doc.write_text('<?xml version="1.0"?>\n<hcdf version="1.0" name="r"/>\n')
    r = cli(*(a.format(doc=doc, tmp=tmp_path) for a in args))
    assert r.exit_code == 2, r.stderr
