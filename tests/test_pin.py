"""``hcdf-trust pin``: minimal text edits of sha attributes, bottom-up over the include tree.

The oracle is independent of the code under test: hashlib over the files on disk,
lxml for reading attributes back, and a regex that strips sha attributes to prove
nothing else in the text changed.
"""

from __future__ import annotations

import hashlib
import os
import random
import re
from pathlib import Path

import pytest
from lxml import etree

from hcdf_trust.digest import Pin
from hcdf_trust.document import Document
from hcdf_trust.include.pin import apply_pins, decide, scan_start_tags

PINNED_TAGS = ("include", "model", "stream-profile")
SHA_ATTR = re.compile(rb"""\s+sha\s*=\s*(?:"[^"]*"|'[^']*')""")
WRONG = hashlib.sha256(b"an older version of the file").hexdigest()


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def strip_sha(data: bytes) -> bytes:
    return SHA_ATTR.sub(b"", data)


def build_tree(root: Path) -> dict[str, Path]:
    """A root that includes arm.hcdf twice and sensor.hcdf, which includes parts/lens.hcdf.

    Starting state (what pin must repair):
      root.hcdf   base.glb model: no sha (in a comment, a decoy copy of that line);
                  arm include #1: no sha; arm include #2: outdated, single quotes, multi-line;
                  sensor include: a *correct* full pin, outdated once sensor.hcdf is edited
      arm.hcdf    href model with a weak 12-digit prefix; a multi-line model with an
                  outdated upper-case digest; a stream profile with no sha; a mesh (never pinned)
      sensor.hcdf the same uri three times: no sha, a correct pin on the same line, and
                  an outdated ``sha256:``-prefixed pin; a correct pin of lens.hcdf
      lens.hcdf   a model with no sha
    """
    rng = random.Random(2)
    models = root / "models"
    models.mkdir(parents=True)
    (root / "parts").mkdir()
    (root / "profiles").mkdir()
    for name in ("base", "arm", "gripper", "cam", "lens", "arm-collision"):
        (models / f"{name}.glb").write_bytes(b"glTF" + rng.randbytes(rng.randint(100, 5000)))
    (root / "profiles" / "imu.xml").write_bytes(b"<stream-profile name='imu'/>\n")

    lens = root / "parts" / "lens.hcdf"
    lens.write_bytes(
        b'<?xml version="1.0" encoding="UTF-8"?>\n'
        b'<hcdf version="1.1">\n'
        b'\t<comp name="lens"><visual><model uri="../models/lens.glb"/></visual></comp>\n'
        b"</hcdf>\n"
    )
    sensor = root / "sensor.hcdf"
    cam = sha(models / "cam.glb")
    sensor.write_bytes(
        (
            '<?xml version="1.0"?>\n'
            '<hcdf version="1.1">\n'
            '  <comp name="cam" description="x > y &amp; z">\n'
            '    <visual name="a"><model uri="models/cam.glb"/></visual>'
            f'<visual name="b"><model uri="models/cam.glb" sha="{cam}"/></visual>\n'
            "    <visual name='c'>\n"
            f"      <model uri = 'models/cam.glb'   sha = 'sha256:{WRONG}' />\n"
            "    </visual>\n"
            "  </comp>\n"
            f'  <include uri="parts/lens.hcdf" name="lens" sha="{sha(lens)}"/>\n'
            "  <software name='fw'><version>1.0</version><hash>deadbeef</hash></software>\n"
            "</hcdf>\n"
        ).encode()
    )
    arm = root / "arm.hcdf"
    weak = sha(models / "arm.glb")[:12]
    arm.write_bytes(
        (
            "<?xml version='1.0' encoding='UTF-8'?>\n"
            "<hcdf version='1.1'>\n"
            "  <!-- the arm sub-assembly, included twice -->\n"
            "  <comp name='arm'>\n"
            f"    <visual><model href='models/arm.glb' sha='{weak}'/></visual>\n"
            "    <visual>\n"
            "      <model\n"
            '         name="gripper"\n'
            '         uri="models/gripper.glb"\n'
            f'         sha="{WRONG.upper()}"\n'
            "      />\n"
            "    </visual>\n"
            "    <collision><geometry><mesh uri='models/arm-collision.glb'/></geometry>\n"
            "    </collision>\n"
            "  </comp>\n"
            "  <stream-profile uri='profiles/imu.xml'\tactive='true'/>\n"
            "</hcdf>\n"
        ).encode()
    )
    doc = root / "root.hcdf"
    doc.write_bytes(
        (
            '<?xml version="1.0" encoding="UTF-8"?>\n'
            "<!-- test robot: comments and formatting must survive pin -->\n"
            '<hcdf version="1.1" name="bot">\n'
            '  <!-- was: <model uri="models/base.glb" sha="0123456789abcdef"/> -->\n'
            '  <comp name="base"><visual><model uri="models/base.glb" /></visual></comp>\n'
            '  <include uri="arm.hcdf" name="left"\n'
            '           pose="0 0.2 0 0 0 0"/>\n'
            "  <include\n"
            "      name='right'\n"
            "      uri='arm.hcdf'\n"
            f"      sha='{WRONG}'\n"
            "      pose='0 -0.2 0 0 0 0' />\n"
            f'  <include uri="sensor.hcdf" sha="{sha(sensor)}" name="sensor"/>\n'
            "</hcdf>\n"
        ).encode()
    )
    return {"root": doc, "arm": arm, "sensor": sensor, "lens": lens}


def snapshot(folder: Path) -> dict[str, bytes]:
    files = sorted(p for p in folder.rglob("*") if p.is_file())
    return {str(p.relative_to(folder)): p.read_bytes() for p in files}


@pytest.fixture
def tree(tmp_path):
    folder = tmp_path / "robot"
    docs = build_tree(folder)
    return folder, docs


def run_args(tmp_path: Path) -> list[str | Path]:
    """A cache and a lock outside the robot's folder, so snapshots of it see only the documents."""
    return ["--cache-dir", tmp_path / "cache", "--lock", tmp_path / "x.lock"]


def test_original_tree_does_not_resolve(cli, tree, tmp_path):
    """Sanity: the tree really needs pin (resolve exits 1 on its outdated pins)."""
    _, docs = tree
    r = cli("resolve", docs["root"], *run_args(tmp_path))
    assert r.exit_code == 1, r.stderr


def test_outdated_pins_are_refused_unless_named(cli, tree, tmp_path):
    """The tree's wrong full pins are digest mismatches until --all (or --update) names them."""
    folder, docs = tree
    before = snapshot(folder)
    r = cli("pin", docs["root"], "--write", "--json", *run_args(tmp_path))
    assert r.exit_code == 1, r.stdout + r.stderr
    refused = sorted((Path(e["file"]).name, e["line"]) for e in r.json["errors"])
    assert [name for name, _ in refused] == ["arm.hcdf", "root.hcdf", "sensor.hcdf"], refused
    assert {e["code"] for e in r.json["errors"]} == {"digest-mismatch"}
    assert all("--update" in e["message"] and e["expected"] == WRONG for e in r.json["errors"])
    assert r.json["wrote"] == []
    assert snapshot(folder) == before and not (tmp_path / "x.lock").exists()


def test_dry_run_reports_every_repair_and_writes_nothing(cli, tree, tmp_path):
    folder, docs = tree
    before = snapshot(folder)
    r = cli("pin", docs["root"], "--all", "--json", *run_args(tmp_path))
    assert r.exit_code == 0, r.stdout + r.stderr
    out = r.json
    assert out["ok"] is True and out["wrote"] == []
    planned = sorted(Path(p).name for p in out["planned"])
    assert planned == ["arm.hcdf", "lens.hcdf", "root.hcdf", "sensor.hcdf", "x.lock"]
    got = sorted((Path(c["file"]).name, c["uri"], c["reason"]) for c in out["changes"])
    assert got == sorted(
        [
            ("root.hcdf", "models/base.glb", "missing"),
            ("root.hcdf", "arm.hcdf", "missing"),
            ("root.hcdf", "arm.hcdf", "outdated"),
            ("root.hcdf", "sensor.hcdf", "include-edited"),  # a correct pin, but sensor is edited
            ("arm.hcdf", "models/arm.glb", "weak"),
            ("arm.hcdf", "models/gripper.glb", "outdated"),
            ("arm.hcdf", "profiles/imu.xml", "missing"),
            ("sensor.hcdf", "models/cam.glb", "missing"),
            ("sensor.hcdf", "models/cam.glb", "outdated"),
            ("sensor.hcdf", "parts/lens.hcdf", "include-edited"),
            ("lens.hcdf", "../models/lens.glb", "missing"),
        ]
    )
    for c in out["changes"]:
        assert re.fullmatch(r"[0-9a-f]{64}", c["new"])
    assert all(c["lock"] == "no entry" and c["lock_sha256"] is None for c in out["changes"])
    assert snapshot(folder) == before and not (tmp_path / "x.lock").exists()
    assert not (tmp_path / "cache").exists() or not any((tmp_path / "cache").rglob("*.glb"))


def test_write_pins_every_reference_with_a_minimal_edit(cli, tree, tmp_path):
    folder, docs = tree
    (docs["arm"]).chmod(0o640)
    before = snapshot(folder)
    r = cli("pin", docs["root"], "--write", "--all", "--json", *run_args(tmp_path))
    assert r.exit_code == 0, r.stdout + r.stderr
    assert len(r.json["changes"]) == 11
    assert sorted(Path(p).name for p in r.json["wrote"]) == [
        "arm.hcdf",
        "lens.hcdf",
        "root.hcdf",
        "sensor.hcdf",
        "x.lock",
    ]
    after = snapshot(folder)
    assert after.keys() == before.keys()  # no stray temporary files

    # 1. every include / model / stream-profile pin is the full digest of the file on disk
    checked = 0
    for path in docs.values():
        tree_ = etree.parse(str(path))
        for el in tree_.iter(*PINNED_TAGS):
            uri = el.get("uri") or el.get("href")
            value = el.get("sha").lower().removeprefix("sha256:")
            assert value == sha(path.parent / uri), f"{path.name}:{el.sourceline} {uri}"
            checked += 1
        for mesh in tree_.iter("mesh"):
            assert mesh.get("sha") is None  # the schema has no sha on <mesh>
        for h in tree_.iter("hash"):
            assert h.text == "deadbeef"  # firmware digests are not pin's business
    assert checked == 12

    # 2. the only difference is sha attributes: same text once they are stripped
    for name, data in before.items():
        assert strip_sha(after[name]) == strip_sha(data), name
    # ... quote style and the sha256: prefix kept, new attributes follow the uri's quotes
    assert b"href='models/arm.glb' sha='" in after["arm.hcdf"]
    assert b"<stream-profile uri='profiles/imu.xml' sha='" in after["arm.hcdf"]
    assert b"uri='arm.hcdf'\n      sha='" in after["root.hcdf"]
    assert b'uri="arm.hcdf" sha="' in after["root.hcdf"]
    assert b"sha = 'sha256:" in after["sensor.hcdf"]
    decoy = b'<!-- was: <model uri="models/base.glb" sha="0123456789abcdef"/> -->'
    assert decoy in after["root.hcdf"]
    assert os.stat(docs["arm"]).st_mode & 0o777 == 0o640

    # 3. the lock is already what resolve writes, and a second pin has nothing left to do
    lock = (tmp_path / "x.lock").read_bytes()
    r = cli("resolve", docs["root"], "--locked", *run_args(tmp_path))
    assert r.exit_code == 0, r.stderr
    assert (tmp_path / "x.lock").read_bytes() == lock
    r = cli("pin", docs["root"], "--write", "--json", *run_args(tmp_path))
    assert r.exit_code == 0, r.stdout + r.stderr
    assert r.json["changes"] == [] and r.json["wrote"] == []
    assert snapshot(folder) == after


def test_missing_file_exits_3_and_writes_nothing(cli, tree, tmp_path):
    folder, docs = tree
    (folder / "models" / "gripper.glb").unlink()
    before = snapshot(folder)
    r = cli("pin", docs["root"], "--write", *run_args(tmp_path))
    assert r.exit_code == 3, r.stderr
    assert "gripper.glb" in r.stderr
    assert snapshot(folder) == before


def test_malformed_sub_document_exits_3_and_writes_nothing(cli, tree, tmp_path):
    folder, docs = tree
    docs["lens"].write_bytes(docs["lens"].read_bytes().replace(b"</comp>", b"</cmp>"))
    before = snapshot(folder)
    r = cli("pin", docs["root"], "--write", *run_args(tmp_path))
    assert r.exit_code == 3, r.stderr
    assert "lens.hcdf" in r.stderr
    assert snapshot(folder) == before


def test_mesh_sha_is_not_repaired(cli, tree, tmp_path):
    """A wrong off-schema sha on <mesh> is left to the user: exit 1, nothing written."""
    folder, docs = tree
    arm = docs["arm"]
    arm.write_bytes(
        arm.read_bytes().replace(
            b"<mesh uri='models/arm-collision.glb'/>",
            f"<mesh uri='models/arm-collision.glb' sha='{WRONG}'/>".encode(),
        )
    )
    before = snapshot(folder)
    r = cli("pin", docs["root"], "--write", *run_args(tmp_path))
    assert r.exit_code == 1, r.stderr
    assert "arm-collision.glb" in r.stderr and "mesh" in r.stderr
    assert snapshot(folder) == before


def test_symlinked_document_is_edited_through_the_link(cli, tree, tmp_path):
    folder, docs = tree
    real = folder / "parts" / "lens-real.hcdf"
    docs["lens"].rename(real)
    docs["lens"].symlink_to("lens-real.hcdf")
    r = cli("pin", docs["root"], "--write", "--all", *run_args(tmp_path))
    assert r.exit_code == 0, r.stderr
    assert docs["lens"].is_symlink()
    assert b'sha="' in real.read_bytes()
    r = cli("resolve", docs["root"], "--locked", *run_args(tmp_path))
    assert r.exit_code == 0, r.stderr


def test_file_changed_after_reading_is_not_overwritten(tree, monkeypatch):
    """A document edited by someone else between resolve and write: nothing is written."""
    from hcdf_trust.include import pin as pin_module

    folder, docs = tree
    real_resolve = pin_module.resolve

    def racing_resolve(*args, **kwargs):
        res = real_resolve(*args, **kwargs)
        with open(docs["sensor"], "ab") as f:
            f.write(b"<!-- edited meanwhile -->\n")
        return res

    monkeypatch.setattr(pin_module, "resolve", racing_resolve)
    before = snapshot(folder)
    report = pin_module.pin_tree(docs["root"], write=True, update_all=True)
    assert len(report.errors) == 1 and "sensor.hcdf" in str(report.errors[0])
    assert "changed on disk" in str(report.errors[0])
    assert report.written == []
    after = snapshot(folder)
    assert after.pop("sensor.hcdf").endswith(b"<!-- edited meanwhile -->\n")
    before.pop("sensor.hcdf")
    assert after == before


def test_remote_documents_are_not_edited(tmp_path):
    """A sub-assembly served from a URL (here through a --mirror folder) is never edited:
    its own missing pins are skipped with a warning; the local pin of it is written."""
    from hcdf_trust.include.pin import pin_tree
    from hcdf_trust.include.resolver import ResolveOptions

    site = tmp_path / "site"
    (site / "models").mkdir(parents=True)
    (site / "models" / "m.glb").write_bytes(b"glTF" + random.Random(3).randbytes(300))
    sub = site / "sub.hcdf"
    sub.write_bytes(b'<hcdf><comp name="c"><visual><model uri="models/m.glb"/></visual></comp></hcdf>\n')
    local = tmp_path / "robot"
    local.mkdir()
    root = local / "root.hcdf"
    root.write_bytes(b'<hcdf>\n  <include uri="https://robots.invalid/sub.hcdf" name="s"/>\n</hcdf>\n')
    options = ResolveOptions(
        mirrors=(("https://robots.invalid/", str(site)),),
        offline=True,
        cache_dir=str(tmp_path / "c"),
    )
    site_before = snapshot(site)
    report = pin_tree(root, options, write=True)
    assert report.ok, report.errors
    assert [(c.uri, c.reason) for c in report.changes] == [("https://robots.invalid/sub.hcdf", "missing")]
    assert len(report.warnings) == 1 and "models/m.glb" in str(report.warnings[0])
    assert "remote" in str(report.warnings[0]) and report.warnings[0].code == "pin-remote"
    assert snapshot(site) == site_before
    assert etree.parse(str(root)).find("include").get("sha") == sha(sub)


# -- the text layer, directly -------------------------------------------------------


def test_decide():
    full = hashlib.sha256(b"x").hexdigest()
    edited = hashlib.sha256(b"x, edited").hexdigest()

    def d(pin, *, settled=full, locked=None, vouched=False, named=False):
        return decide(pin, read=full, settled=settled, locked=locked, vouched=vouched, named=named)

    assert d(None) == ("missing", None)
    assert d(Pin(full[:10])) == ("weak", None)
    assert d(Pin(full)) == (None, None)
    assert d(Pin(full), settled=edited) == ("include-edited", None)
    # a pin that disagrees with the content: refused unless named
    for pin in (Pin(WRONG), Pin(WRONG[:10])):
        assert d(pin) == (None, "pin-differs")
        assert d(pin, locked=full) == (None, "pin-differs")
        assert d(pin, named=True) == ("outdated", None)
    # without a full pin the lock entry is the pin
    for pin in (None, Pin(full[:10])):
        assert d(pin, locked=full) == (("missing" if pin is None else "weak"), None)
        assert d(pin, locked=WRONG) == (None, "lock-differs")
        assert d(pin, locked=WRONG, named=True) == ("outdated", None)
        assert d(pin, locked=WRONG, vouched=True)[1] is None  # another reference pins the content in full


def test_scanner_skips_comments_cdata_and_processing_instructions():
    data = (
        b"<?xml version='1.0'?>\n<!-- <model uri='a'/> -->\n<?pi <model uri='b'/> ?>\n"
        b"<hcdf a='1>2'\n  b=\"x\"><![CDATA[<model uri='c'/>]]><model uri='d'/></hcdf>\n"
    )
    tags = scan_start_tags(data)
    assert [t.name for t in tags] == [b"hcdf", b"model"]
    assert (tags[0].first_line, tags[0].last_line) == (4, 5)
    assert [a.name for a in tags[0].attrs] == [b"a", b"b"]
    assert data[tags[1].start : tags[1].end] == b"<model uri='d'/>"


def test_same_uri_twice_on_one_line_edits_the_right_element():
    a = hashlib.sha256(b"a").hexdigest()
    data = (
        '<hcdf>\n  <visual><model uri="m.glb" sha="' + WRONG + '"/></visual>'
        '<visual><model uri="m.glb"/></visual>'
        '<visual><model uri="m.glb" sha="' + a + '"/></visual>\n</hcdf>\n'
    ).encode()
    doc = Document.from_bytes(data, source="t.hcdf")
    refs = doc.references()
    assert len(refs) == 3
    out = apply_pins(doc, [(refs[0], a), (refs[1], a)])
    assert out == data.replace(WRONG.encode(), a.encode()).replace(
        b'<model uri="m.glb"/>', b'<model uri="m.glb" sha="' + a.encode() + b'"/>'
    )
    assert [el.get("sha") for el in etree.fromstring(out).iter("model")] == [a, a, a]
