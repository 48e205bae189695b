"""resolve against the real corpus: published fragments, GLB pins, upstream examples."""

from __future__ import annotations

import hashlib
import os
import re
import shutil
from pathlib import Path

import pytest

from .conftest import HCDFORMAT, MODELS

# The published fragments are named {first 8 hex of their sha256}-{device}.hcdf; beside each is
# a {device}.hcdf pointer, a real symlink or a git symlink stub depending on the checkout.
PUBLISHED = re.compile(r"^[0-9a-f]{8}-.+\.hcdf$")
FRAGMENTS = sorted(p for p in MODELS.glob("*/*/*.hcdf") if PUBLISHED.match(p.name))


def sha256_file(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_corpus_is_present():
    assert len(FRAGMENTS) >= 5, f"corpus fragments not found under {MODELS}"


@pytest.mark.parametrize("fragment", FRAGMENTS, ids=lambda p: str(p.relative_to(MODELS)))
def test_every_fragment_resolves_and_every_glb_verifies(cli, tmp_path, fragment):
    lock = tmp_path / "hcdf.lock"
    r = cli("resolve", fragment, "--base", MODELS, "--lock", lock, "--cache-dir", tmp_path / "c", "--json")
    assert r.exit_code == 0, r.stdout + r.stderr
    out = r.json
    models = [a for a in out["artifacts"] if a["kind"] == "model"]
    assert models, "every published fragment references GLB models"
    for art in models:
        glb = MODELS / art["uri"]
        # independent oracle: hashlib over the file on disk, and the name's 8-hex prefix
        assert art["sha256"] == sha256_file(glb)
        assert glb.name.startswith(art["sha256"][:8])
        assert art["pin"] == "full"
    assert lock.is_file()


def test_flipped_byte_in_one_glb_exits_1_naming_it(cli, tmp_path):
    models = tmp_path / "hcdf_models"
    shutil.copytree(MODELS, models, symlinks=True)
    for p in models.rglob("*"):
        p.chmod(0o755 if p.is_dir() else 0o644)
    victim = models / "models" / "72eef172-optical_flow.glb"
    data = bytearray(victim.read_bytes())
    data[len(data) // 2] ^= 0x01
    victim.write_bytes(bytes(data))
    doc = models / "mr_mcxn_t1" / "optical-flow" / "d9507e38-optical-flow.hcdf"
    lock = tmp_path / "hcdf.lock"
    r = cli("resolve", doc, "--base", models, "--lock", lock, "--cache-dir", tmp_path / "c", "--json")
    assert r.exit_code == 1
    errors = r.json["errors"]
    assert [e["code"] for e in errors] == ["digest-mismatch"]
    err = errors[0]
    assert "72eef172-optical_flow.glb" in err["message"]
    assert err["file"].endswith("d9507e38-optical-flow.hcdf")
    assert doc.read_text().splitlines()[err["line"] - 1].strip().startswith('<model href="models/72eef172')
    assert err["expected"] == "72eef1724ebbf6d7df57edba6465ef9e35ac25a4db10365ef29b9a2b39d0636a"
    assert err["actual"] == hashlib.sha256(bytes(data)).hexdigest()
    assert not lock.exists(), "no lock file is written on failure"


def _pointer_target(pointer: Path) -> str:
    """The name a corpus ``{device}.hcdf`` pointer names, whichever layout this checkout has."""
    return os.readlink(pointer) if pointer.is_symlink() else pointer.read_text().strip()


def _model_repository(tmp_path: Path, layout: str) -> Path:
    """A copy of hcdf_models whose {device}.hcdf pointers are all real symlinks or all stubs."""
    models = tmp_path / f"hcdf_models-{layout}"
    shutil.copytree(MODELS, models, symlinks=True)
    for p in models.rglob("*"):
        if not p.is_symlink():
            p.chmod(0o755 if p.is_dir() else 0o644)
    pointers = [p for p in models.glob("*/*/*.hcdf") if not PUBLISHED.match(p.name)]
    assert pointers, "every published device has a {device}.hcdf pointer"
    for pointer in pointers:
        target = _pointer_target(pointer)
        assert PUBLISHED.match(target) and (pointer.parent / target).is_file()
        pointer.unlink()
        if layout == "symlink":
            pointer.symlink_to(target)
        else:
            pointer.write_text(target)  # what git writes with core.symlinks=false: the target, no newline
    return models


@pytest.mark.parametrize("layout", ["symlink", "stub"])
def test_device_pointer_is_followed_to_its_sibling_in_either_layout(cli, tmp_path, layout):
    models = _model_repository(tmp_path, layout)
    pointer = models / "mr_mcxn_t1" / "optical-flow" / "optical-flow.hcdf"
    assert pointer.is_symlink() == (layout == "symlink")
    target = pointer.parent / _pointer_target(pointer)
    args = ("--base", models, "--cache-dir", tmp_path / "c", "--json")
    via_pointer = cli("resolve", pointer, "--lock", tmp_path / "pointer.lock", *args)
    assert via_pointer.exit_code == 0, via_pointer.stdout + via_pointer.stderr
    direct = cli("resolve", target, "--lock", tmp_path / "direct.lock", *args)
    assert direct.exit_code == 0, direct.stdout
    # the pointer is read as the fragment it names: same root, same artifacts, same lock bytes
    assert via_pointer.json["root"] == direct.json["root"]
    assert via_pointer.json["root"].endswith(target.name)
    assert via_pointer.json["artifacts"] == direct.json["artifacts"]
    oracle = {(m, hashlib.sha256((models / m).read_bytes()).hexdigest()) for m in _hrefs(target)}
    assert {(a["uri"], a["sha256"]) for a in via_pointer.json["artifacts"]} == oracle
    assert (tmp_path / "pointer.lock").read_bytes() == (tmp_path / "direct.lock").read_bytes()
    r = cli("verify", pointer, "--base", models, "--lock", tmp_path / "direct.lock")
    assert r.exit_code == 0, r.stderr
    r = cli("validate", pointer, "--json")
    assert r.exit_code == 0 and r.json["ok"], r.stdout


def test_a_lock_written_on_one_layout_verifies_on_the_other(cli, tmp_path):
    """A lock committed from a checkout with symlinks holds on one without (and back)."""
    locks = {}
    for layout in ("symlink", "stub"):
        models = _model_repository(tmp_path, layout)
        pointer = models / "navq95" / "default" / "default.hcdf"
        lock = models / "hcdf.lock"
        r = cli("resolve", pointer, "--base", models, "--lock", lock, "--cache-dir", tmp_path / "c")
        assert r.exit_code == 0, r.stderr
        locks[layout] = (models, pointer, lock.read_bytes())
    assert locks["symlink"][2] == locks["stub"][2]
    for mine, theirs in (("symlink", "stub"), ("stub", "symlink")):
        models, pointer, _ = locks[mine]
        (models / "other.lock").write_bytes(locks[theirs][2])
        r = cli("verify", pointer, "--base", models, "--lock", models / "other.lock")
        assert r.exit_code == 0, r.stderr


def _hrefs(doc: Path) -> set[str]:
    from lxml import etree

    return {str(v) for v in etree.parse(str(doc)).xpath("//model/@href | //model/@uri")}


def test_humanoid_resolves_with_its_stream_profile_unpinned(cli, tmp_path):
    doc = HCDFORMAT / "examples" / "humanoid-mobile-base.hcdf"
    r = cli("resolve", doc, "--lock", tmp_path / "hcdf.lock", "--cache-dir", tmp_path / "c", "--json")
    assert r.exit_code == 0, r.stdout
    [profile] = [a for a in r.json["artifacts"] if a["kind"] == "stream-profile"]
    assert profile["pin"] == "unpinned"
    assert profile["sha256"] == sha256_file(HCDFORMAT / "examples" / "profiles" / "operational.streams.xml")
    assert len(profile["referenced_from"]) == 2  # two networks name the same file: fetched once
    assert r.json["summary"]["unpinned"] == 1
    assert any("unpinned" in w["message"] for w in r.json["warnings"])


def test_test_minimal_missing_include_with_non_digest_sha_exits_3(cli, tmp_path):
    doc = HCDFORMAT / "examples" / "test-minimal.hcdf"
    lock = tmp_path / "hcdf.lock"
    r = cli("resolve", doc, "--lock", lock, "--cache-dir", tmp_path / "c", "--json")
    assert r.exit_code == 3
    lines = doc.read_text().splitlines()
    include_line = next(i for i, text in enumerate(lines, 1) if "<include" in text)
    [err] = [e for e in r.json["errors"] if e["line"] == include_line]
    assert err["file"].endswith("test-minimal.hcdf")
    assert err["code"] == "bad-digest"
    assert "abc123" in err["message"]
    assert not lock.exists()


def test_later_dialects_walk_and_report_the_missing_model(cli, tmp_path):
    # dendrite's optical-flow.hcdf is version="2.0" and pins a GLB the model repository
    # no longer publishes: the others verify, the missing one is named.
    doc = MODELS.parent / "dendrite" / "optical-flow.hcdf"
    r = cli("resolve", doc, "--base", MODELS, "--lock", tmp_path / "l", "--cache-dir", tmp_path / "c", "--json")
    assert r.exit_code == 3
    [err] = r.json["errors"]
    assert err["code"] == "not-found" and "fc0bc0ac-mcxnt1hub.glb" in err["message"]
    verified = {a["uri"] for a in r.json["artifacts"] if a["sha256"]}
    assert len(verified) == 3
