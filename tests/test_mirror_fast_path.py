"""Under a ``--mirror`` of ``file:`` URLs (a tree served from a cache or another server),
plain relative references take a fast path (Locator._plain_mirrored) that must give exactly
what the general path (urljoin, normalise, route through the mirrors) gives: the same
Location, or the same error."""

from __future__ import annotations

import itertools

import pytest

from hcdf_trust.errors import HcdfTrustError
from hcdf_trust.include.locate import Locator, file_url

URIS = [
    "../models/m0001.glb",
    "models/a.glb",
    "./models/a.glb",
    "  ../models/spaced.glb  ",
    "a/../../models/b.glb",
    "../models//double.glb",
    "../local/x.glb",
    "../local/../models/y.glb",
    "../other/z.glb",
    "same.glb",
    "../../../../../../../outside.glb",
    "../../sibling/escape.glb",
    "..",
    ".",
    "../models/",
    "/abs/path.glb",
    "https://example.com/m.glb",
    "../models/q.glb?x=1",
    "../models/%41.glb",
    "../models/with space.glb",
    "file:///etc/passwd",
]


def _outcome(locator, uri, referrer):
    try:
        return locator.locate(uri, referrer, file="doc.hcdf", line=3)
    except HcdfTrustError as exc:
        return type(exc).__name__, str(exc)


def _trees(tmp_path):
    root = tmp_path / "robot"
    (root / "parts").mkdir(parents=True)
    (root / "plain folder").mkdir()
    mirror_dir = tmp_path / "mirror"
    mirror_dir.mkdir()
    mirrors = [
        (f"{file_url(root / 'models')}/", "http://127.0.0.1:9/models/"),
        (f"{file_url(root / 'local')}/", str(mirror_dir)),
        (f"{file_url(root / 'models' / 'sub')}/", "https://cdn.example/sub/"),  # longer prefix wins
    ]
    referrers = [root / "parts" / "p001.hcdf", root / "robot.hcdf", root / "plain folder" / "d.hcdf"]
    return root, mirrors, referrers


@pytest.mark.parametrize("mirror_count", [1, 2, 3])
def test_the_fast_path_under_a_mirror_gives_what_the_general_path_gives(tmp_path, monkeypatch, mirror_count):
    root, mirrors, referrers = _trees(tmp_path)
    chosen = mirrors[:mirror_count]
    for base, ref_path in itertools.product([None, str(root / "parts")], referrers):
        fast = Locator.create(root=root, base=base, mirrors=chosen)
        ref = fast.for_document(ref_path)
        got = {uri: _outcome(fast, uri, ref) for uri in URIS + ["../models/sub/deep.glb"]}
        with monkeypatch.context() as m:
            m.setattr(Locator, "_plain_mirrored", lambda self, *a, **k: None)
            general = Locator.create(root=root, base=base, mirrors=chosen)
            want = {uri: _outcome(general, uri, ref) for uri in got}
        assert got == want


def test_mirrored_references_take_the_fast_path(tmp_path, monkeypatch):
    """The fast path is taken (not only agrees): no URL is joined for a plain mirrored reference."""
    root, mirrors, referrers = _trees(tmp_path)
    locator = Locator.create(root=root, mirrors=mirrors[:1])
    ref = locator.for_document(referrers[0])
    import hcdf_trust.include.locate as locate_module

    def no_join(*args, **kwargs):
        raise AssertionError("urljoin called")

    monkeypatch.setattr(locate_module, "urljoin", no_join)
    loc = locator.locate("../models/m0001.glb", ref, file="doc.hcdf", line=1)
    assert loc.url == f"{file_url(root / 'models')}/m0001.glb"
    assert loc.remote == "http://127.0.0.1:9/models/m0001.glb" and loc.path is None
