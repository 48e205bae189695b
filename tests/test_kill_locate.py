"""locate.py: where a reference points, and the lexical root check (mutation-testing killers)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from hcdf_trust.errors import InputError, PathEscapeError
from hcdf_trust.include.locate import Location, Locator, display_path, file_url

from ._kill import hcdf, model, sha


def _doc(root: Path, name: str = "robot.hcdf") -> Location:
    return Locator.create(root=root).for_document(root / name)


# -- the root check: a sibling whose name starts with the root's is outside -----------


@pytest.mark.parametrize("sibling", ["robot-evil", "robotx", "robot.bak"])
def test_a_sibling_folder_sharing_the_roots_name_prefix_is_outside(tmp_path, sibling):
    root = tmp_path / "robot"
    loc = Locator.create(root=root)
    with pytest.raises(PathEscapeError) as info:
        loc.locate(f"../{sibling}/s.glb", _doc(root), file="robot.hcdf", line=4)
    err = info.value
    assert err.file == "robot.hcdf" and err.line == 4
    assert err.actual == str(tmp_path / sibling / "s.glb")
    assert str(root) in err.expected


def test_the_same_escape_through_the_general_url_path(tmp_path):
    """A percent escape keeps the reference off the fast path: urljoin, normalise, then the check."""
    root = tmp_path / "robot"
    with pytest.raises(PathEscapeError):
        Locator.create(root=root).locate("../robot-evil/s%2Eglb", _doc(root), file="d", line=1)


def test_the_same_escape_through_base(tmp_path):
    root = tmp_path / "robot"
    loc = Locator.create(root=root, base=str(root))
    with pytest.raises(PathEscapeError):
        loc.locate("../robot-evil/s.glb", _doc(root), file="d", line=1)


@pytest.mark.parametrize("uri", ["models/s.glb", "./models/s.glb"])  # the plain fast path, the general one
def test_a_plain_path_under_a_base_outside_the_root_is_outside(tmp_path, uri):
    """The lexical check holds on the fast path too (the descriptor check would still refuse
    the file, but as a "symlink escape": the wrong reason, and only once it is opened)."""
    root, elsewhere = tmp_path / "robot", tmp_path / "elsewhere"
    loc = Locator.create(root=root, base=str(elsewhere) + "/")
    with pytest.raises(PathEscapeError) as info:
        loc.locate(uri, _doc(root), file="robot.hcdf", line=3)
    assert info.value.actual == str(elsewhere / "models" / "s.glb")
    assert "is outside the root" in info.value.message


def test_a_mirror_folder_confines_its_own_files(tmp_path):
    mirror = tmp_path / "mirror"
    loc = Locator.create(root=tmp_path / "robot", mirrors=[("https://cdn.example/m/", str(mirror))])
    got = loc.locate("https://cdn.example/m/a/b.glb", _doc(tmp_path / "robot"), file="d", line=1)
    assert got.url == "https://cdn.example/m/a/b.glb" and got.remote is None
    assert got.path == str(mirror / "a" / "b.glb") and got.root == mirror
    with pytest.raises(PathEscapeError):
        loc.locate("https://cdn.example/m/..%2F..%2Fmirror-evil/x", _doc(tmp_path / "robot"), file="d", line=1)


def test_the_root_itself_and_files_inside_it_are_inside(tmp_path):
    root = tmp_path / "robot"
    loc = Locator.create(root=root)
    doc = _doc(root)
    assert loc.locate("models/a.glb", doc, file="d", line=1).path == str(root / "models" / "a.glb")
    assert loc.locate("models/../a.glb", doc, file="d", line=1).path == str(root / "a.glb")
    inside = loc.locate("../robot/x.glb", doc, file="d", line=1)
    assert inside.path == str(root / "x.glb") and inside.root == root
    assert inside.url == file_url(root / "x.glb")


def test_resolve_refuses_a_reference_into_a_sibling_with_the_roots_prefix(cli, tmp_path):
    root = tmp_path / "robot"
    evil = tmp_path / "robot-evil"
    root.mkdir()
    evil.mkdir()
    (evil / "s.glb").write_bytes(b"outside")
    doc = root / "robot.hcdf"
    doc.write_text(hcdf(model("../robot-evil/s.glb", sha(b"outside"))))
    r = cli("resolve", doc, "--json", "--no-lock", "--cache-dir", tmp_path / "c")
    assert r.exit_code == 3, r.stdout
    [e] = r.json["errors"]
    assert e["code"] == "path-escape" and e["line"] == 3


# -- locate: schemes, absolute paths, empty references ---------------------------------


@pytest.mark.parametrize("uri", ["/etc/passwd", "\\\\server\\share", "file:///etc/passwd", "C:\\x.glb", "c:/x.glb"])
def test_absolute_local_references_are_refused(tmp_path, uri):
    with pytest.raises(PathEscapeError) as info:
        Locator.create(root=tmp_path).locate(uri, _doc(tmp_path), file="d", line=2)
    assert info.value.actual == uri and info.value.line == 2


@pytest.mark.parametrize("uri", ["ftp://h/x", "data:,x", "javascript:alert(1)"])
def test_other_schemes_are_input_errors(tmp_path, uri):
    with pytest.raises(InputError) as info:
        Locator.create(root=tmp_path).locate(uri, _doc(tmp_path), file="d", line=2)
    assert not isinstance(info.value, PathEscapeError)
    assert "unsupported URL scheme" in str(info.value) and info.value.actual == uri


@pytest.mark.parametrize("uri", ["", "   "])
def test_an_empty_uri_is_an_input_error(tmp_path, uri):
    with pytest.raises(InputError, match="empty uri"):
        Locator.create(root=tmp_path).locate(uri, _doc(tmp_path), file="d", line=2)


def test_remote_references_keep_their_url_normalised(tmp_path):
    loc = Locator.create(root=tmp_path)
    got = loc.locate("HTTPS://h.example/a/./b/../c.glb?x=1", _doc(tmp_path), file="d", line=1)
    assert got.remote == got.url == "https://h.example/a/c.glb?x=1"
    assert not got.is_local and got.scheme == "https"
    slash = loc.locate("https://h.example/a/b/", _doc(tmp_path), file="d", line=1)
    assert slash.url == "https://h.example/a/b/"
    bare = loc.locate("https://h.example", _doc(tmp_path), file="d", line=1)
    assert bare.url == "https://h.example/"
    dbl = loc.locate("https://h.example//a//b", _doc(tmp_path), file="d", line=1)
    assert dbl.url == "https://h.example/a/b"


def test_relative_references_of_a_remote_document_stay_remote(tmp_path):
    loc = Locator.create(root=tmp_path)
    parent = Location(url="https://h.example/models/robot.hcdf", remote="https://h.example/models/robot.hcdf")
    got = loc.locate("../meshes/a.glb", parent, file="d", line=1)
    assert got.url == got.remote == "https://h.example/meshes/a.glb"
    assert got.path is None and got.is_local is False


def test_a_url_base_replaces_the_document_as_base(tmp_path):
    loc = Locator.create(root=tmp_path, base="https://h.example/pkg")
    got = loc.locate("m/a.glb", _doc(tmp_path), file="d", line=1)
    assert got.url == "https://h.example/pkg/m/a.glb"
    loc = Locator.create(root=tmp_path, base="https://h.example/pkg/")
    assert loc.locate("m/a.glb", _doc(tmp_path), file="d", line=1).url == "https://h.example/pkg/m/a.glb"


def test_a_folder_base_replaces_the_document_folder(tmp_path):
    base = tmp_path / "pub"
    loc = Locator.create(root=tmp_path, base=str(base))
    assert loc.base == file_url(base) + "/"
    doc = Locator.create(root=tmp_path).for_document(tmp_path / "deep" / "d.hcdf")
    assert loc.locate("a.glb", doc, file="d", line=1).path == str(base / "a.glb")
    assert loc.locate("a%20b.glb", doc, file="d", line=1).path == str(base / "a b.glb")


def test_plain_and_general_paths_agree_with_spaces_and_escapes(tmp_path):
    root = tmp_path / "my robot"
    loc = Locator.create(root=root)
    doc = loc.for_document(root / "r.hcdf")
    assert loc.locate("m/a.glb", doc, file="d", line=1).path == str(root / "m" / "a.glb")
    assert loc.locate("m/a%20b.glb", doc, file="d", line=1).path == str(root / "m" / "a b.glb")


def test_the_longest_mirror_prefix_wins(tmp_path):
    general, specific = tmp_path / "g", tmp_path / "s"
    loc = Locator.create(
        root=tmp_path,
        mirrors=[("https://h.example/", str(general)), ("https://h.example/models/", str(specific))],
    )
    got = loc.locate("https://h.example/models/a.glb", _doc(tmp_path), file="d", line=1)
    assert got.path == str(specific / "a.glb")
    got = loc.locate("https://h.example/other/a.glb", _doc(tmp_path), file="d", line=1)
    assert got.path == str(general / "other" / "a.glb")


def test_a_mirror_to_another_server(tmp_path):
    loc = Locator.create(root=tmp_path, mirrors=[("https://h.example/m/", "https://cache.example/x/")])
    got = loc.locate("https://h.example/m/a.glb", _doc(tmp_path), file="d", line=1)
    assert got.url == "https://h.example/m/a.glb" and got.remote == "https://cache.example/x/a.glb"
    assert got.scheme == "https"


def test_a_file_mirror_rewrites_local_references(tmp_path):
    root, mirror = tmp_path / "robot", tmp_path / "mirror"
    prefix = file_url(root / "models", directory=True)
    loc = Locator.create(root=root, mirrors=[(prefix, str(mirror))])
    got = loc.locate("models/a.glb", loc.for_document(root / "r.hcdf"), file="d", line=1)
    assert got.path == str(mirror / "a.glb") and got.url == file_url(root / "models" / "a.glb")


def test_file_url_and_display_path(tmp_path, monkeypatch):
    assert file_url(tmp_path / "a b") == "file://" + str(tmp_path).replace(" ", "%20") + "/a%20b"
    assert file_url(tmp_path, directory=True).endswith("/") and not file_url(tmp_path).endswith("/")
    assert file_url("/", directory=True) == "file:///"
    monkeypatch.chdir(tmp_path)
    assert display_path(tmp_path / "x" / "y") == os.path.join("x", "y")
    assert display_path("/elsewhere/z") == "/elsewhere/z"


def test_a_root_document_outside_the_root_is_named_as_given(tmp_path):
    loc = Locator.create(root=tmp_path / "robot")
    with pytest.raises(PathEscapeError) as info:
        loc.for_document(tmp_path / "other" / "d.hcdf")
    assert info.value.file == str(tmp_path / "other" / "d.hcdf") and info.value.line is None
    inside = loc.for_document(tmp_path / "robot" / "d.hcdf")
    assert inside.path == str(tmp_path / "robot" / "d.hcdf") and inside.url == file_url(inside.path)


@pytest.mark.parametrize("prefix", ["https://h.example/m", "https://h.example/m/"])
def test_mirror_prefixes_with_or_without_a_trailing_slash(tmp_path, prefix):
    doc = _doc(tmp_path)
    remote = Locator.create(root=tmp_path, mirrors=[(prefix, "https://cache.example/boX")])
    got = remote.locate("https://h.example/m/a/b.glb", doc, file="d", line=1)
    assert got.remote == "https://cache.example/boX/a/b.glb"
    local = Locator.create(root=tmp_path, mirrors=[(prefix, str(tmp_path / "mir"))])
    got = local.locate("https://h.example/m/a/b.glb", doc, file="d", line=1)
    assert got.path == str(tmp_path / "mir" / "a" / "b.glb")


def test_an_escape_from_a_mirror_folder_names_the_reference(tmp_path):
    loc = Locator.create(root=tmp_path, mirrors=[("https://h.example/m/", str(tmp_path / "mir"))])
    with pytest.raises(PathEscapeError) as info:
        loc.locate("https://h.example/m/%2E%2E/x", _doc(tmp_path), file="d.hcdf", line=6)
    assert (info.value.file, info.value.line) == ("d.hcdf", 6)


def test_segments_starting_with_x_survive_normalisation_and_mirrors(tmp_path):
    doc = _doc(tmp_path)
    loc = Locator.create(root=tmp_path)
    assert loc.locate("https://h.example//Xa/b", doc, file="d", line=1).url == "https://h.example/Xa/b"
    remote = Locator.create(root=tmp_path, mirrors=[("https://h.example/m/", "https://c.example/x/")])
    assert remote.locate("https://h.example/m/Xa.glb", doc, file="d", line=1).remote == "https://c.example/x/Xa.glb"
    local = Locator.create(root=tmp_path, mirrors=[("https://h.example/m/", str(tmp_path / "mir"))])
    assert local.locate("https://h.example/m/Xa.glb", doc, file="d", line=1).path == str(tmp_path / "mir" / "Xa.glb")


def test_a_missing_parent_relative_reference_gets_no_site_root_hint(cli, tmp_path):
    """`../x.glb` is relative to its document on purpose: no --base hint, even when a
    folder above holds a file of that name."""
    site = tmp_path / "site"
    (site / "robots").mkdir(parents=True)
    (site / "nothere").mkdir()
    (tmp_path / "nothere").mkdir()
    (tmp_path / "nothere" / "x.glb").write_bytes(b"x")  # a folder above holds ../nothere/x.glb
    doc = site / "robots" / "robot.hcdf"
    doc.write_text(hcdf(model("../nothere/x.glb")))
    r = cli("resolve", doc, "--json", "--cache-dir", tmp_path / "c", "--no-lock", "--root", site)
    assert r.exit_code == 3, r.stdout
    [err] = r.json["errors"]
    assert err["code"] == "not-found" and "--base" not in err["message"], err["message"]
