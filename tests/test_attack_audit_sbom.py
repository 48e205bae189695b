"""Attack: make audit, sbom, ota and macsec read a description differently from resolve.

An element the schema allows once (hcdf.xsd ``maxOccurs="1"``), written twice, used to pass
resolve and verify while ``ota build`` and ``sbom`` took the last ``<hash>`` and ``audit`` the
first: the auditor checked one image, the release shipped another. Every verb now reads such
elements through one accessor (``hcdf_trust.document.single``) and refuses a second one: exit 3,
code ``ambiguous``, both lines named. Published ``hcdf_models`` boards (site-root hrefs) are
audited and given an SBOM with resolve's ``--base``.
"""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import pytest

from tests.conftest import MODELS, PROJECT

GOOD = "1" * 64
EVIL = "2" * 64

# One <software> whose duplicated child is chosen per test; line numbers are the oracle.
ROBOT = """<?xml version="1.0"?>
<hcdf version="1.0" name="dup">
  <comp name="mcu">
    <board>fmu</board>{board2}
    <software name="app">
      <version>1.0.0</version>{version2}
      <hash>{good}</hash>{hash2}
      <firmware-manifest-uri>app.latest.json</firmware-manifest-uri>{manifest2}
    </software>{software2}
  </comp>
</hcdf>
"""
SECOND = {
    "board2": "\n    <board>evil</board>",
    "version2": "\n      <version>9.9.9</version>",
    "hash2": f"\n      <hash>{EVIL}</hash>",
    "manifest2": "\n      <firmware-manifest-uri>evil.latest.json</firmware-manifest-uri>",
    "software2": f'\n    <software name="app"><version>1.0.0</version><hash>{EVIL}</hash></software>',
}
FIRST_LINE = {"board2": 4, "version2": 6, "hash2": 7, "manifest2": 8, "software2": 5}
TAG = {"board2": "board", "version2": "version", "hash2": "hash", "manifest2": "firmware-manifest-uri"}
TAG["software2"] = "software"


def _robot(folder: Path, twice: str | None = None) -> Path:
    """The robot, locked while clean; then (``twice``) with one element written a second time."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "app.latest.json").write_text("{}\n")
    (folder / "evil.latest.json").write_text("{}\n")
    doc = folder / "robot.hcdf"
    doc.write_text(ROBOT.format(good=GOOD, **dict.fromkeys(SECOND, "")))
    return doc if twice is None else _with(doc, twice)


def _with(doc: Path, twice: str) -> Path:
    fields = dict.fromkeys(SECOND, "")
    fields[twice] = SECOND[twice]
    doc.write_text(ROBOT.format(good=GOOD, **fields))
    return doc


def _second_line(doc: Path, twice: str) -> int:
    text = doc.read_text().splitlines()
    marker = SECOND[twice].strip().split(">")[0]  # e.g. '<hash' or '<software name="app"'
    hits = [i + 1 for i, line in enumerate(text) if line.strip().startswith(marker)]
    return hits[1] if twice != "software2" else hits[-1]


VERBS = {
    "resolve": lambda doc, extra: ("resolve", doc, "--json"),
    "verify": lambda doc, extra: ("verify", doc, "--json"),
    "pin": lambda doc, extra: ("pin", doc, "--json"),
    "validate": lambda doc, extra: ("validate", doc, "--json"),
    "audit": lambda doc, extra: ("audit", doc, "--json"),
    "sbom": lambda doc, extra: ("sbom", doc, "--format", "cyclonedx", "--json"),
    "macsec plan": lambda doc, extra: ("macsec", "plan", doc, "--json"),
    "ota build": lambda doc, extra: ("ota", "build", doc, "--json", *extra),
}


@pytest.fixture(scope="module")
def ota_key(tmp_path_factory):
    from hcdf_trust.ota.keys import generate, private_pem

    folder = tmp_path_factory.mktemp("key")
    key = folder / "k.pem"
    key.write_bytes(private_pem(generate("ecdsa-p256"), None))
    return key


@pytest.mark.parametrize("twice", sorted(SECOND))
@pytest.mark.parametrize("verb", sorted(VERBS))
def test_an_element_written_twice_is_refused_by_every_verb_naming_both_lines(cli, tmp_path, ota_key, verb, twice):
    doc = _robot(tmp_path / "robot")
    assert cli("resolve", doc).exit_code == 0  # the lock, made while the document was clean
    _with(doc, twice)
    extra = ("--firmware-dir", tmp_path, "--key", ota_key, "--out", tmp_path / "release")
    r = cli(*VERBS[verb](doc, extra))
    assert r.exit_code == 3, (r.stdout, r.stderr)
    errors = r.json["errors"]
    codes = {e["code"] for e in errors}
    assert "ambiguous" in codes, errors
    (error,) = [e for e in errors if e["code"] == "ambiguous"]
    first, second = FIRST_LINE[twice], _second_line(doc, twice)
    assert f"2 <{TAG[twice]}> elements, at lines {first} and {second}" in error["message"]
    assert error["line"] == second and error["file"].endswith("robot.hcdf")
    assert not (tmp_path / "release").exists()


@pytest.mark.parametrize("twice", ["hash2", "version2", "board2"])
def test_an_included_assembly_with_an_element_twice_is_refused(cli, tmp_path, twice):
    # The duplicate hides one level down, in a sub-assembly pinned by its sha: the include is
    # read (its digest is right) and refused, by resolve as by audit and pin (sbom, ota and macsec
    # need the lock resolve refuses to write).
    sub = _robot(tmp_path / "robot" / "arm", twice)
    sha = hashlib.sha256(sub.read_bytes()).hexdigest()
    doc = tmp_path / "robot" / "robot.hcdf"
    doc.write_text(f'<hcdf version="1.0" name="r"><include uri="arm/robot.hcdf" sha="{sha}" name="arm"/></hcdf>\n')
    for args in (("resolve", doc), ("audit", doc), ("pin", doc)):
        r = cli(*args)
        assert r.exit_code == 3, (args, r.stderr)
        assert f"2 <{TAG[twice]}> elements" in r.stderr and "arm/robot.hcdf" in r.stderr


@pytest.mark.parametrize("element", ["version", "board"])
def test_text_that_reads_two_ways_is_refused(cli, tmp_path, element):
    # "1.0<!-- -->.1": .text says 1.0, the string value 1.0.1. One reading or none.
    doc = _robot(tmp_path / "robot")
    assert cli("resolve", doc).exit_code == 0
    text = doc.read_text()
    old = "<version>1.0.0</version>" if element == "version" else "<board>fmu</board>"
    new = "<version>1.0<!-- -->.1</version>" if element == "version" else "<board>f<!-- x -->mu</board>"
    doc.write_text(text.replace(old, new))
    for args in (("verify", doc), ("audit", doc), ("sbom", doc, "--format", "cyclonedx")):
        r = cli(*args)
        assert r.exit_code == 3, (args, r.stderr)
        assert f"<{element}> contains a comment" in r.stderr


NETWORK = """<?xml version="1.0"?>
<hcdf version="1.0" name="net">
  <comp name="a"><port name="p0" type="ethernet"><capabilities>
    <speed unit="Mbps">100</speed>{speed2}
    <macsec><cipher>gcm-aes-128</cipher></macsec>
  </capabilities></port></comp>
  <comp name="b"><port name="p0" type="ethernet"><capabilities>
    <speed unit="Mbps">100</speed>
    <macsec><cipher>gcm-aes-128</cipher></macsec>
  </capabilities></port></comp>
  <network name="n">
    <link name="l"><wired>
      <port>a/p0</port><port>b/p0</port>
      <macsec policy="must-secure" key-ref="k"/>{override2}
    </wired></link>
    <macsec policy="must-secure" cipher="gcm-aes-128">
      <key-store type="file" ref="keys/a"/>{store2}
    </macsec>{network2}
  </network>
</hcdf>
"""
NET_SECOND = {
    "speed2": ('\n    <speed unit="Gbps">10</speed>', "speed", 4),
    "override2": ('\n      <macsec policy="disabled" key-ref="k2"/>', "macsec", 14),
    "store2": ('\n      <key-store type="file" ref="keys/b"/>', "key-store", 17),
    "network2": ('\n    <macsec policy="should-secure"/>', "macsec", 16),
}


@pytest.mark.parametrize("twice", sorted(NET_SECOND))
@pytest.mark.parametrize("verb", ["macsec plan", "audit"])
def test_macsec_elements_written_twice_are_refused(cli, tmp_path, verb, twice):
    # Which <macsec> secures the link, which key store, which speed (10 Gb/s decides whether a
    # static non-XPN key may be used): the planner and the audit read them through document.only.
    doc = tmp_path / "net.hcdf"
    fields = dict.fromkeys(NET_SECOND, "")
    fields[twice] = NET_SECOND[twice][0]
    doc.write_text(NETWORK.format(**fields))
    assert cli("resolve", doc).exit_code == 0
    args = ("macsec", "plan", doc, "--json") if verb == "macsec plan" else ("audit", doc, "--json")
    r = cli(*args)
    assert r.exit_code == 3, (r.stdout, r.stderr)
    (error,) = [e for e in r.json["errors"] if e["code"] == "ambiguous"]
    inserted, tag, first = NET_SECOND[twice]
    second = doc.read_text().splitlines().index(inserted.lstrip("\n")) + 1
    assert f"2 <{tag}> elements, at lines {first} and {second}" in error["message"]


def test_the_clean_robot_passes_every_verb(cli, tmp_path):
    # The control: without the second element, the same commands succeed.
    doc = _robot(tmp_path / "robot")
    assert cli("resolve", doc).exit_code == 0
    for args in (("verify", doc), ("sbom", doc, "--format", "cyclonedx"), ("macsec", "plan", doc)):
        r = cli(*args)
        assert r.exit_code == 0, (args, r.stderr)
    assert cli("audit", doc).exit_code in (0, 1)  # findings (no release) are the audit's business
    net = tmp_path / "net.hcdf"
    net.write_text(NETWORK.format(**dict.fromkeys(NET_SECOND, "")))
    assert cli("resolve", net).exit_code == 0
    r = cli("macsec", "plan", net, "--json")
    assert r.exit_code == 0, r.stderr
    assert [a["id"] for a in r.json["associations"]] == ["key-ref:k"]


# --- published boards and flattened documents: resolve's tree flags on audit, sbom, macsec ---

BOARDS = sorted(
    p
    for p in MODELS.glob("*/*/*.hcdf")
    if not p.is_symlink() and len(p.name.split("-", 1)[0]) == 8  # {short-sha}-{device}.hcdf
)


def _glb_digests(board: Path) -> dict[str, str]:
    """The oracle: every GLB the fragment names, hashed here from the site root."""
    import re

    hrefs = re.findall(r'href="(models/[^"]+\.glb)"', board.read_text())
    return {h: hashlib.sha256((MODELS / h).read_bytes()).hexdigest() for h in hrefs}


def test_the_published_boards_are_there():
    assert len(BOARDS) >= 5 and all(_glb_digests(b) for b in BOARDS[:1])


@pytest.mark.parametrize("board", BOARDS, ids=lambda p: p.parent.name)
def test_a_published_board_is_audited_and_given_an_sbom_with_base(cli, tmp_path, board):
    tree = ("--base", MODELS, "--lock", tmp_path / "board.lock", "--cache-dir", tmp_path / "cache")
    assert cli("resolve", board, *tree).exit_code == 0
    audit = cli("audit", board, *tree, "--json")
    assert audit.exit_code == 0, audit.stdout
    assert not [f for f in audit.json["findings"] if f["severity"] == "error"]
    r = cli("sbom", board, "--format", "cyclonedx", *tree, "--json")
    assert r.exit_code == 0, r.stderr
    assert r.json["ok"] is True and r.json["errors"] == []
    listed = {}
    for c in r.json["sbom"]["components"]:
        for h in c.get("hashes", []):
            if h["alg"] == "SHA-256" and c["name"].endswith(".glb"):
                listed[c["name"]] = h["content"]
    expected = _glb_digests(board)
    assert {name.rsplit("/", 1)[-1]: d for name, d in listed.items()} == {
        h.rsplit("/", 1)[-1]: d for h, d in expected.items()
    }


def test_without_base_the_message_names_a_flag_the_verb_takes(cli, tmp_path):
    board = BOARDS[0]
    tree = ("--lock", tmp_path / "board.lock", "--cache-dir", tmp_path / "cache")
    assert cli("resolve", board, "--base", MODELS, *tree).exit_code == 0
    r = cli("sbom", board, "--format", "spdx", *tree)
    assert r.exit_code == 1  # not found where the document is, and so not what the lock says
    assert f"give --base {MODELS} (every verb that reads a tree takes it)" in r.stderr
    # ... and following the advice works on this very verb:
    assert cli("sbom", board, "--format", "spdx", "--base", MODELS, *tree).exit_code == 0


def test_base_does_not_widen_what_the_tree_may_read(cli, tmp_path):
    # An attacker's fragment reaches out of the site root through --base: refused by sbom and
    # audit exactly as by resolve (path-escape, exit 3), never read.
    site = tmp_path / "site"
    (site / "models").mkdir(parents=True)
    (tmp_path / "secret.glb").write_bytes(b"not yours")
    board = site / "b" / "x.hcdf"
    board.parent.mkdir()
    board.write_text(
        '<hcdf version="1.0" name="x"><comp name="c"><visual name="v">'
        '<model href="models/../../secret.glb"/></visual></comp></hcdf>\n'
    )
    tree = ("--base", site, "--lock", tmp_path / "x.lock", "--cache-dir", tmp_path / "cache")
    for args in (("resolve", board, *tree), ("sbom", board, "--format", "spdx", *tree)):
        r = cli(*args, "--json")
        assert r.exit_code == 3, (args, r.stdout)
        assert "path-escape" in [e["code"] for e in r.json["errors"]]
    r = cli("audit", board, "--base", site, "--json")  # no lock: audit reports what it finds
    assert r.exit_code == 1 and any(f["code"] == "path-escape" for f in r.json["findings"])


def test_the_demos_flattened_document_is_planned_and_given_an_sbom_with_root(cli, tmp_path, monkeypatch):
    shutil.copytree(PROJECT / "examples", tmp_path / "examples", ignore=shutil.ignore_patterns("out"))
    monkeypatch.chdir(tmp_path)
    flat = "examples/out/scout2.flat.hcdf"
    cache = ("--cache-dir", "cache")
    r = cli("resolve", "examples/robot/robot.hcdf", "--locked", "--root", "examples", "--out", flat, *cache)
    assert r.exit_code == 0, r.stderr
    assert cli("resolve", flat, "--root", "examples", *cache).exit_code == 0
    # Without --root, the flattened document's references leave its folder: refused.
    assert cli("macsec", "plan", flat, *cache).exit_code != 0
    plan = cli("macsec", "plan", flat, "--root", "examples", *cache, "--json")
    assert plan.exit_code == 0, plan.stderr
    original = cli("macsec", "plan", "examples/robot/robot.hcdf", *cache, "--json")
    assert original.exit_code == 0, original.stderr
    assert sorted(a["id"] for a in plan.json["associations"]) == sorted(a["id"] for a in original.json["associations"])
    sbom = cli("sbom", flat, "--format", "cyclonedx", "--root", "examples", *cache, "--json")
    assert sbom.exit_code == 0, sbom.stderr
    assert sbom.json["ok"] is True and sbom.json["sbom"]["bomFormat"] == "CycloneDX"


@pytest.mark.parametrize("twice", ["override2", "network2"])
def test_validate_reads_a_links_macsec_as_the_planner_does(cli, tmp_path, twice):
    # validate's cipher rule judged the first <macsec>, the planner refuses two: one reading.
    doc = tmp_path / "net.hcdf"
    fields = dict.fromkeys(NET_SECOND, "")
    fields[twice] = NET_SECOND[twice][0]
    doc.write_text(NETWORK.format(**fields))
    r = cli("validate", doc, "--json")
    assert r.exit_code == 3, r.stdout
    assert [e["code"] for e in r.json["errors"]] == ["ambiguous"]


def test_validate_finds_site_root_includes_with_base_and_stays_inside_root(cli, tmp_path):
    # A site-root include hides a frame-convention mismatch from validate without --base (the
    # include is "not read", a warning); with resolve's --base it is read and judged.
    site = tmp_path / "site"
    (site / "b").mkdir(parents=True)
    (site / "parts").mkdir()
    doc = site / "b" / "x.hcdf"
    doc.write_text('<hcdf version="1.0" name="x" body-frame="FLU"><include uri="parts/p.hcdf" name="p"/></hcdf>\n')
    (site / "parts" / "p.hcdf").write_text('<hcdf version="1.0" name="p" body-frame="FRD"><comp name="c"/></hcdf>\n')
    blind = cli("validate", doc, "--json")
    assert blind.exit_code == 0 and [f["code"] for f in blind.json["findings"]] == ["include-unchecked"]
    seen = cli("validate", doc, "--base", site, "--json")
    assert seen.exit_code == 1
    assert [e["code"] for e in seen.json["errors"]] == ["frame-convention-mismatch"]
    # --root narrower than --base: the include lies outside it, refused as resolve refuses it.
    narrow = cli("validate", doc, "--base", site, "--root", site / "b", "--json")
    assert narrow.exit_code == 1
    assert [e["code"] for e in narrow.json["errors"]] == ["include-refused"]


def test_macsec_keys_for_the_flattened_document_with_root_and_no_index_for_it(cli, tmp_path, monkeypatch):
    # generate/export take --root like resolve. The export index (a fast path that assumes the
    # tree is where resolve finds it by default) is not written for such a run, so an export
    # without --root cannot reuse a plan made with it: it plans in full, and fails as resolve does.
    from hcdf_trust.macsec import index

    shutil.copytree(PROJECT / "examples", tmp_path / "examples", ignore=shutil.ignore_patterns("out"))
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("HCDF_TRUST_PASSPHRASE", "not a secret, a test")
    flat = "examples/out/scout2.flat.hcdf"
    r = cli("resolve", "examples/robot/robot.hcdf", "--root", "examples", "--out", flat, "--cache-dir", "c")
    assert r.exit_code == 0, r.stderr
    assert cli("resolve", flat, "--root", "examples", "--cache-dir", "c").exit_code == 0
    store = ("--store", "store")
    r = cli("macsec", "generate", flat, *store, "--root", "examples", "--cache-dir", "c", "--json")
    assert r.exit_code == 0, r.stderr
    assert r.json["created"]
    assert not (tmp_path / index.path_in("store")).exists()
    out = ["--device", "compute", "--format", "json", "-o", "keys"]
    r = cli("macsec", "export", flat, *store, *out, "--root", "examples", "--cache-dir", "c", "--json")
    assert r.exit_code == 0, r.stderr
    assert r.json["planned_from"] == "description" and r.json["files"]
    assert cli("macsec", "export", flat, *store, *out, "--cache-dir", "c").exit_code != 0
