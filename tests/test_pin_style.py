"""Pins written ``sha256:<hex>`` (upstream hcdformat 05d27b58) and bare hex, at every pin site.

Oracles: hashlib over the files on disk, and the attribute text read back with lxml.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest
from lxml import etree

from hcdf_trust.digest import prefixed_style


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def make_tree(root: Path, *, style: str) -> Path:
    """robot.hcdf includes arm.hcdf and references a model, a mesh and a stream profile.

    ``style`` is how robot.hcdf's existing pins are written: ``prefixed`` (every pin
    ``sha256:``), ``bare``, ``mixed`` or ``none``; the model and the stream profile
    are left unpinned for ``pin --write`` to fill in.
    """
    (root / "models").mkdir(parents=True)
    (root / "profiles").mkdir()
    (root / "models" / "base.glb").write_bytes(b"glTF base")
    (root / "models" / "col.glb").write_bytes(b"glTF collision")
    (root / "profiles" / "op.streams.xml").write_bytes(b"<stream-profile name='op' version='1'/>\n")
    arm = root / "arm.hcdf"
    arm.write_bytes(b'<hcdf version="1.0"><comp name="arm"/></hcdf>\n')
    mesh = sha(root / "models" / "col.glb")
    include = sha(arm)
    pins = {
        "prefixed": (f"sha256:{include}", f"sha256:{mesh}"),
        "bare": (include, mesh),
        "mixed": (f"sha256:{include}", mesh),
        "none": (None, None),
    }[style]
    inc_attr = f' sha="{pins[0]}"' if pins[0] else ""
    mesh_attr = f' sha="{pins[1]}"' if pins[1] else ""
    doc = root / "robot.hcdf"
    doc.write_text(
        '<hcdf version="1.0" name="bot">\n'
        '  <comp name="base">\n'
        '    <visual><model uri="models/base.glb"/></visual>\n'
        f'    <collision><geometry><mesh uri="models/col.glb"{mesh_attr}/></geometry></collision>\n'
        "  </comp>\n"
        f'  <include uri="arm.hcdf" name="arm"{inc_attr}/>\n'
        '  <stream-profile uri="profiles/op.streams.xml" selection-role="default"/>\n'
        "</hcdf>\n"
    )
    return doc


def args(tmp_path: Path) -> list[str | Path]:
    return ["--cache-dir", tmp_path / "cache", "--lock", tmp_path / "x.lock"]


@pytest.mark.parametrize(("style", "prefix"), [("prefixed", "sha256:"), ("bare", ""), ("mixed", ""), ("none", "")])
def test_pin_write_uses_the_documents_pin_style(cli, tmp_path, style, prefix):
    doc = make_tree(tmp_path / "bot", style=style)
    r = cli("pin", doc, "--write", *args(tmp_path))
    assert r.exit_code == 0, r.stdout + r.stderr
    root = etree.parse(str(doc)).getroot()
    for tag, file in (("model", "models/base.glb"), ("stream-profile", "profiles/op.streams.xml")):
        written = root.find(f".//{tag}").get("sha")
        assert written == prefix + sha(doc.parent / file), (tag, written)
    # and a plain resolve accepts what pin wrote
    assert cli("resolve", doc, "--locked", *args(tmp_path)).exit_code == 0


def test_the_style_rule():
    assert prefixed_style(["sha256:ab" * 8, " SHA256:" + "cd" * 32]) is True
    assert prefixed_style(["sha256:" + "ab" * 32, "ab" * 32]) is False  # mixed: bare
    assert prefixed_style([None, "", "  "]) is False  # no pin at all: bare
    assert prefixed_style([None, "sha256:" + "ab" * 32]) is True


@pytest.mark.parametrize("written", ["sha256:{}", "SHA256:{}", "{}", "sha256:{short}", "{short}"])
def test_every_pin_site_accepts_both_spellings(cli, tmp_path, written):
    """<include>, <model>, <mesh> and <stream-profile>: ``sha256:<hex>`` and bare hex, full or weak."""
    root = tmp_path / "bot"
    doc = make_tree(root, style="none")
    files = {
        "include": root / "arm.hcdf",
        "model": root / "models" / "base.glb",
        "mesh": root / "models" / "col.glb",
        "stream-profile": root / "profiles" / "op.streams.xml",
    }
    text = doc.read_text()
    for tag, file in files.items():
        digest = sha(file)
        pin = written.format(digest, short=digest[:16])
        uri = file.relative_to(root).as_posix()
        text = text.replace(f'<{tag} uri="{uri}"', f'<{tag} uri="{uri}" sha="{pin}"')
        assert f'sha="{pin}"' in text, tag
    doc.write_text(text)
    r = cli("resolve", doc, "--json", *args(tmp_path))
    assert r.exit_code == 0, r.stdout + r.stderr
    # a wrong digest in either spelling is still a mismatch, at each site
    for tag, file in files.items():
        bad = text.replace(sha(file)[:16], "0" * 16, 1)
        doc.write_text(bad)
        r = cli("resolve", doc, *args(tmp_path))
        assert r.exit_code == 1, (tag, r.stderr)
        assert "digest mismatch" in r.stderr, tag


@pytest.mark.parametrize("verb", ["resolve", "verify", "pin"])
def test_include_mismatch_names_upstreams_canonical_pin(cli, tmp_path, verb):
    """A pin that is not the SHA-256 of the included bytes (say, upstream's canonical-form
    pin) stays an integrity error, and says what it may be and how to re-pin the bytes."""
    root = tmp_path / "bot"
    doc = make_tree(root, style="prefixed")
    canonical = hashlib.sha256(b'<hcdf version="1.0">\n  <comp name="arm"/>\n</hcdf>\n').hexdigest()
    text = doc.read_text().replace(sha(root / "arm.hcdf"), canonical)
    doc.write_text(text)
    before = doc.read_bytes()
    extra = ["--write"] if verb == "pin" else []
    r = cli(verb, doc, *extra, *args(tmp_path))
    assert r.exit_code == 1, r.stdout + r.stderr
    assert "arm.hcdf" in r.stderr and "digest mismatch" in r.stderr
    assert "canonical-form pin" in r.stderr
    assert "pin --write --update arm.hcdf" in r.stderr
    assert doc.read_bytes() == before
    # a model's mismatch is not an include: no word about upstream's canonical form
    good = before.decode().replace(canonical, sha(root / "arm.hcdf"))
    doc.write_text(good.replace('<model uri="models/base.glb"/>', f'<model uri="models/base.glb" sha="{canonical}"/>'))
    r = cli(verb, doc, *extra, *args(tmp_path))
    assert r.exit_code == 1 and "base.glb" in r.stderr
    assert "canonical-form" not in r.stderr
