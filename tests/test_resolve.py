"""resolve / verify on small trees built per test: pins, includes, lock file, confinement."""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import pytest

from hcdf_trust.document import Document, Kind


def sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def hcdf(body: str, *, name: str = "t", attrs: str = "") -> str:
    return f'<?xml version="1.0"?>\n<hcdf version="1.0" name="{name}"{attrs}>\n{body}\n</hcdf>\n'


def model(uri: str, pin: str | None = None) -> str:
    sha_attr = f' sha="{pin}"' if pin is not None else ""
    return f'<comp name="c_{abs(hash(uri)) % 10**6}"><visual><model uri="{uri}"{sha_attr}/></visual></comp>'


@pytest.fixture
def tree(tmp_path):
    """A root that includes one sub-assembly twice and pins a GLB; returns its paths."""
    root = tmp_path / "robot"
    (root / "models").mkdir(parents=True)
    glb = os.urandom(3000)
    (root / "models" / "a.glb").write_bytes(glb)
    sub = hcdf(model("models/a.glb", sha(glb)), name="sub")
    (root / "sub.hcdf").write_text(sub)
    doc = root / "robot.hcdf"
    doc.write_text(
        hcdf(
            model("models/a.glb", sha(glb))
            + f'\n<include uri="sub.hcdf" sha="{sha(sub.encode())}" name="l" pose="0 1 0 0 0 0"/>'
            + f'\n<include uri="sub.hcdf" sha="{sha(sub.encode())}" name="r" pose="0 -1 0 0 0 0"/>'
        )
    )
    return {
        "root": root,
        "doc": doc,
        "glb": root / "models" / "a.glb",
        "sub": root / "sub.hcdf",
        "cache": tmp_path / "cache",
    }


def resolve(cli, t, *extra):
    return cli("resolve", t["doc"], "--cache-dir", t["cache"], "--json", *extra)


def test_each_distinct_file_is_listed_once_with_all_its_references(cli, tree):
    r = resolve(cli, tree)
    assert r.exit_code == 0, r.stdout
    arts = {a["url"]: a for a in r.json["artifacts"]}
    assert set(arts) == {"models/a.glb", "sub.hcdf"}
    assert len(arts["sub.hcdf"]["referenced_from"]) == 2
    assert arts["models/a.glb"]["sha256"] == sha(tree["glb"].read_bytes())
    assert r.json["summary"]["bytes_verified"] == 3000 + tree["sub"].stat().st_size


def test_lock_file_is_deterministic_and_records_everything(cli, tree):
    assert resolve(cli, tree).exit_code == 0
    lock_path = tree["root"] / "robot.hcdf.lock"
    first = lock_path.read_bytes()
    assert resolve(cli, tree).exit_code == 0
    assert lock_path.read_bytes() == first
    lock = json.loads(first)
    assert lock["lock_version"] == 2
    for art in lock["artifacts"]:
        assert set(art) == {"kind", "uri", "url", "sha256", "size", "referenced_from"}
        assert art["sha256"] == sha((tree["root"] / art["url"]).read_bytes())
        assert art["size"] == (tree["root"] / art["url"]).stat().st_size


def test_mismatch_names_file_line_expected_actual_and_writes_nothing(cli, tree):
    data = tree["glb"].read_bytes()
    tree["glb"].write_bytes(data[:-1] + bytes([data[-1] ^ 0xFF]))
    r = resolve(cli, tree, "--out", tree["root"] / "flat.hcdf")
    assert r.exit_code == 1
    errs = r.json["errors"]
    assert {e["code"] for e in errs} == {"digest-mismatch"}
    # the root and the sub-assembly both pin the GLB: both places are named
    assert {Path(e["file"]).name for e in errs} == {"robot.hcdf", "sub.hcdf"}
    for e in errs:
        assert e["expected"] == sha(data) and e["actual"] == sha(tree["glb"].read_bytes())
        assert e["line"] >= 2
    assert not (tree["root"] / "robot.hcdf.lock").exists()
    assert not (tree["root"] / "flat.hcdf").exists()


def test_human_message_names_everything_on_stderr(cli, tree):
    tree["glb"].write_bytes(b"not the model")
    r = cli("resolve", tree["doc"], "--cache-dir", tree["cache"])
    assert r.exit_code == 1
    assert "robot.hcdf:3" in r.stderr and "models/a.glb" in r.stderr
    assert sha(b"not the model") in r.stderr and r.stdout == ""


def test_weak_pin_is_reported_and_refused_by_strict(cli, tmp_path):
    glb = os.urandom(100)
    (tmp_path / "m.glb").write_bytes(glb)
    doc = tmp_path / "d.hcdf"
    doc.write_text(hcdf(model("m.glb", sha(glb)[:8].upper())))
    r = cli("resolve", doc, "--json")
    assert r.exit_code == 0
    assert r.json["artifacts"][0]["pin"] == "weak"
    assert any("32 bits" in w["message"] for w in r.json["warnings"])
    r = cli("resolve", doc, "--json", "--strict", "--no-lock")
    assert r.exit_code == 1 and r.json["errors"][0]["code"] == "weak-pin"
    doc.write_text(hcdf(model("m.glb", "00000000")))
    assert cli("resolve", doc, "--json").json["errors"][0]["code"] == "digest-mismatch"


@pytest.mark.parametrize("bad", ["abc123xyz", "abc", "g" * 64, "a" * 65])
def test_malformed_digest_is_an_input_error(cli, tmp_path, bad):
    (tmp_path / "m.glb").write_bytes(b"x")
    doc = tmp_path / "d.hcdf"
    doc.write_text(hcdf(model("m.glb", bad)))
    r = cli("resolve", doc, "--json")
    assert r.exit_code == 3
    [e] = r.json["errors"]
    assert e["code"] == "bad-digest" and e["line"] == 3 and bad in e["message"]


def test_unpinned_is_an_error_under_locked_unless_the_lock_pins_it(cli, tree):
    tree["doc"].write_text(tree["doc"].read_text().replace("</hcdf>", model("models/a.glb") + "\n</hcdf>"))
    tree["doc"].write_text(tree["doc"].read_text().replace('<comp name="c_', '<comp name="x_', 1))
    (tree["root"] / "models" / "b.stl").write_bytes(b"solid")
    tree["doc"].write_text(
        tree["doc"]
        .read_text()
        .replace(
            "</hcdf>",
            '<comp name="m"><collision><geometry><mesh uri="models/b.stl"/></geometry></collision></comp>\n</hcdf>',
        )
    )
    r = resolve(cli, tree, "--locked")
    assert r.exit_code == 3 and r.json["errors"][0]["code"] == "lock-file"  # no lock yet
    assert resolve(cli, tree).exit_code == 0  # writes the lock
    assert resolve(cli, tree, "--locked").exit_code == 0  # the lock pins the mesh
    (tree["root"] / "models" / "b.stl").write_bytes(b"solid changed")
    r = resolve(cli, tree, "--locked")
    assert r.exit_code == 1
    [e] = r.json["errors"]
    assert e["code"] == "lock-drift" and e["expected"] == sha(b"solid") and e["actual"] == sha(b"solid changed")


def test_locked_reports_new_and_removed_artifacts(cli, tree):
    assert resolve(cli, tree).exit_code == 0
    (tree["root"] / "models" / "n.glb").write_bytes(b"new")
    text = tree["doc"].read_text()
    tree["doc"].write_text(
        text.replace("models/a.glb", "models/n.glb").replace(sha(tree["glb"].read_bytes()), sha(b"new"), 1)
    )
    r = resolve(cli, tree, "--locked")
    assert r.exit_code == 1
    messages = [e["message"] for e in r.json["errors"]]
    assert any("not in the lock file" in m for m in messages)
    assert not any("no longer referenced" in m for m in messages)  # a.glb is still used by sub.hcdf


def test_verify_is_offline_and_writes_nothing(cli, tree):
    assert resolve(cli, tree).exit_code == 0
    lock = tree["root"] / "robot.hcdf.lock"
    before = {p: p.stat().st_mtime_ns for p in tree["root"].rglob("*")}
    r = cli("verify", tree["doc"], "--cache-dir", tree["cache"], "--json")
    assert r.exit_code == 0 and r.json["ok"]
    assert {p: p.stat().st_mtime_ns for p in tree["root"].rglob("*")} == before
    tree["glb"].write_bytes(b"tampered")
    r = cli("verify", tree["doc"], "--cache-dir", tree["cache"], "--json")
    assert r.exit_code == 1
    assert {e["code"] for e in r.json["errors"]} >= {"digest-mismatch", "lock-drift"}
    assert lock.stat().st_mtime_ns == before[lock]


def test_verify_without_lock_is_an_input_error(cli, tree):
    r = cli("verify", tree["doc"], "--json")
    assert r.exit_code == 3 and r.json["errors"][0]["code"] == "lock-file"


def _chain_docs(root: Path, names: list[str], *, back_to: str | None = None) -> Path:
    for i, name in enumerate(names):
        nxt = names[i + 1] if i + 1 < len(names) else back_to
        body = f'<comp name="{name}"/>' + (f'\n<include uri="{nxt}.hcdf" name="{name}"/>' if nxt else "")
        (root / f"{name}.hcdf").write_text(hcdf(body, name=name))
    return root / f"{names[0]}.hcdf"


def test_include_cycle_is_an_error_naming_the_chain(cli, tmp_path):
    doc = _chain_docs(tmp_path, ["a", "b", "c"], back_to="b")
    r = cli("resolve", doc, "--json")
    assert r.exit_code == 3
    [e] = r.json["errors"]
    assert e["code"] == "include-cycle"
    assert "b.hcdf → c.hcdf → b.hcdf" in e["message"].replace(f"{tmp_path}/", "")
    assert e["file"].endswith("c.hcdf")
    assert not (tmp_path / "a.hcdf.lock").exists()


def test_cycle_between_documents_first_reached_by_different_paths(cli, tmp_path):
    # a includes b and c; b includes c and c includes b: a breadth-first walk sees each once
    (tmp_path / "b.hcdf").write_text(hcdf('<include uri="c.hcdf"/>', name="b"))
    (tmp_path / "c.hcdf").write_text(hcdf('<include uri="b.hcdf"/>', name="c"))
    doc = tmp_path / "a.hcdf"
    doc.write_text(hcdf('<include uri="b.hcdf"/>\n<include uri="c.hcdf"/>', name="a"))
    r = cli("resolve", doc, "--json")
    assert r.exit_code == 3
    assert [e["code"] for e in r.json["errors"]] == ["include-cycle"]


def test_include_depth_limit_names_the_chain(cli, tmp_path):
    names = [f"d{i}" for i in range(6)]
    doc = _chain_docs(tmp_path, names)
    assert cli("resolve", doc, "--json", "--max-depth", "5").exit_code == 0
    r = cli("resolve", doc, "--json", "--max-depth", "4", "--no-lock")
    assert r.exit_code == 3
    [e] = r.json["errors"]
    assert e["code"] == "include-depth"
    chain = "d0.hcdf → d1.hcdf → d2.hcdf → d3.hcdf → d4.hcdf → d5.hcdf"
    assert chain in e["message"].replace(f"{tmp_path}/", "")


def test_dotdot_escape_and_absolute_paths_are_refused(cli, tmp_path):
    (tmp_path / "secret.glb").write_bytes(b"s")
    root = tmp_path / "robot"
    root.mkdir()
    doc = root / "r.hcdf"
    for uri in ["../secret.glb", "models/../../secret.glb", str(tmp_path / "secret.glb"), "file:///etc/passwd"]:
        doc.write_text(hcdf(model(uri)))
        r = cli("resolve", doc, "--json")
        assert r.exit_code == 3, uri
        [e] = r.json["errors"]
        assert e["code"] == "path-escape" and e["line"] == 3, uri


def test_symlink_out_of_the_root_is_refused_and_inside_is_allowed(cli, tmp_path):
    (tmp_path / "outside.glb").write_bytes(b"o")
    root = tmp_path / "robot"
    (root / "models").mkdir(parents=True)
    (root / "models" / "real.glb").write_bytes(b"r")
    (root / "models" / "inside.glb").symlink_to("real.glb")
    (root / "models" / "escape.glb").symlink_to(tmp_path / "outside.glb")
    doc = root / "r.hcdf"
    doc.write_text(hcdf(model("models/inside.glb", sha(b"r"))))
    assert cli("resolve", doc, "--json").exit_code == 0
    doc.write_text(hcdf(model("models/escape.glb")))
    r = cli("resolve", doc, "--json", "--no-lock")
    assert r.exit_code == 3
    assert r.json["errors"][0]["code"] == "path-escape"
    assert "symlink" in r.json["errors"][0]["message"]


def test_base_and_root_options(cli, tmp_path):
    site = tmp_path / "site"
    (site / "models").mkdir(parents=True)
    (site / "models" / "m.glb").write_bytes(b"m")
    (site / "boards" / "x").mkdir(parents=True)
    doc = site / "boards" / "x" / "x.hcdf"
    doc.write_text(hcdf(model("models/m.glb", sha(b"m"))))
    assert cli("resolve", doc, "--json", "--no-lock").exit_code == 3  # relative to the document: missing
    assert cli("resolve", doc, "--json", "--no-lock", "--base", site).exit_code == 0


def test_mirror_to_a_local_folder_keeps_the_logical_url(cli, tmp_path):
    mirror = tmp_path / "mirror"
    (mirror / "models").mkdir(parents=True)
    (mirror / "models" / "m.glb").write_bytes(b"mirrored")
    doc = tmp_path / "r.hcdf"
    doc.write_text(hcdf(model("https://models.example.invalid/models/m.glb", sha(b"mirrored"))))
    r = cli("resolve", doc, "--json", "--offline", "--mirror", f"https://models.example.invalid/={mirror}")
    assert r.exit_code == 0, r.stdout
    [a] = r.json["artifacts"]
    assert a["url"] == "https://models.example.invalid/models/m.glb" and a["source"] == "mirror"
    lock = json.loads((tmp_path / "r.hcdf.lock").read_text())
    assert lock["artifacts"][0]["url"] == "https://models.example.invalid/models/m.glb"


def test_offline_without_cache_or_mirror_names_the_url(cli, tmp_path):
    doc = tmp_path / "r.hcdf"
    doc.write_text(hcdf(model("https://models.example.invalid/m.glb", "a" * 64)))
    r = cli("resolve", doc, "--json", "--offline")
    assert r.exit_code == 3
    [e] = r.json["errors"]
    assert e["code"] == "offline" and "https://models.example.invalid/m.glb" in e["message"]


def test_walker_finds_every_kind_with_its_line():
    text = hcdf(
        """<comp name="c">
  <visual><model href="m.glb" sha="ab12ab12"/></visual>
  <collision><geometry><mesh uri="m.stl"/></geometry></collision>
  <software name="fw"><version>1.2</version><hash>ff</hash>
    <firmware-manifest-uri>fw/latest.json</firmware-manifest-uri></software>
  <extension domain="org.ros2" version="1.0"><model uri="ignored.glb"/></extension>
  <future-element><unknown attr="1"/></future-element>
</comp>
<network name="n"><mesh name="wireless"/><stream-profile uri="p.xml" active="false"/></network>
<include uri="sub.hcdf" name="s" pose="1 2 3 0 0 0"/>""",
        attrs=' body-frame="FLU"',
    ).replace('<hcdf version="1.0"', '<hcdf version="2.0"', 1)
    refs = Document.from_bytes(text.encode(), source="t.hcdf").references()
    got = [(r.kind, r.line, r.uri) for r in refs]
    assert got == [
        (Kind.MODEL, 4, "m.glb"),
        (Kind.MESH, 5, "m.stl"),
        (Kind.FIRMWARE, 6, None),
        (Kind.FIRMWARE_MANIFEST, 7, "fw/latest.json"),
        (Kind.EXTENSION, 8, None),
        (Kind.STREAM_PROFILE, 11, "p.xml"),
        (Kind.INCLUDE, 12, "sub.hcdf"),
    ]
    assert refs[0].uri_attr == "href" and refs[2].sha == "ff" and refs[2].version == "1.2"
    assert refs[4].domain == "org.ros2" and refs[5].selected is False and refs[6].pose == "1 2 3 0 0 0"


def test_not_hcdf_is_an_input_error(cli, tmp_path):
    doc = tmp_path / "x.hcdf"
    doc.write_text("<html><body/></html>")
    r = cli("resolve", doc, "--json")
    assert r.exit_code == 3 and "not an HCDF document" in r.json["errors"][0]["message"]


def test_flattened_output_elsewhere_still_points_at_the_same_files(cli, tree, tmp_path):
    out = tmp_path / "dist" / "flat" / "robot.flat.hcdf"
    assert resolve(cli, tree, "--out", out, "--root", tmp_path).exit_code == 0
    r = cli("resolve", out, "--root", tmp_path, "--no-lock", "--json")
    assert r.exit_code == 0, r.stdout
    shas = {a["sha256"] for a in r.json["artifacts"]}
    assert shas == {sha(tree["glb"].read_bytes())}
    assert "<include" not in out.read_text()
