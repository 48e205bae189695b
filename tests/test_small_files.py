"""The per-file fast paths of a resolve over many small files, each against the plain path it replaces."""

from __future__ import annotations

import dataclasses
import hashlib
import inspect
import os
from pathlib import Path

import pytest

from hcdf_trust.document import Kind, Reference
from hcdf_trust.include import resolver
from hcdf_trust.include.locate import Location
from hcdf_trust.include.resolver import PARALLEL_MIN_BYTES, ResolveOptions, resolve
from hcdf_trust.localfile import SMALL_FILE, ConfinedFolders


def sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


@pytest.fixture
def hostile_tree(tmp_path: Path) -> Path:
    """A document over plain small files and every kind of file the fast path must leave alone."""
    root, outside = tmp_path / "robot", tmp_path / "secret"
    (root / "m").mkdir(parents=True)
    (root / "sub" / "deep").mkdir(parents=True)
    outside.mkdir()
    (outside / "key").write_bytes(b"secret")
    files = {f"m/f{i}.glb": os.urandom(100 + i) for i in range(20)}
    files["sub/deep/b.glb"] = b"b" * 3000
    files["m/big.glb"] = os.urandom(SMALL_FILE + 1)  # over the one-read size, under the pool's
    files["m/bigger.glb"] = os.urandom(PARALLEL_MIN_BYTES + 1)  # hashed by the pool
    files["m/empty.glb"] = b""
    for rel, data in files.items():
        (root / rel).write_bytes(data)
    (root / "m" / "in-link.glb").symlink_to("../sub/deep/b.glb")
    (root / "m" / "out-link.glb").symlink_to(outside / "key")
    (root / "in-dir").symlink_to("sub/deep")
    (root / "out-dir").symlink_to(outside)
    (root / "m" / "dir").mkdir()
    os.mkfifo(root / "m" / "fifo")
    (root / "m" / "zero").symlink_to("/dev/zero")
    refs = [f'<model uri="{rel}" sha="{sha(data)}"/>' for rel, data in files.items()]
    refs += [f'<model uri="{rel}"/>' for rel in ("m/in-link.glb", "in-dir/b.glb")]
    refs += [f'<model uri="{rel}" sha="{"0" * 64}"/>' for rel in ("m/f1.glb", "m/empty.glb")]  # mismatches
    bad = ("m/out-link.glb", "out-dir/key", "m/dir", "m/fifo", "m/zero", "m/missing.glb", "nope/x.glb")
    refs += [f'<model uri="{rel}"/>' for rel in bad]
    body = "\n".join(f'<comp name="c{i}"><visual>{r}</visual></comp>' for i, r in enumerate(refs))
    doc = root / "robot.hcdf"
    doc.write_text(f'<?xml version="1.0"?>\n<hcdf version="1.0">\n{body}\n</hcdf>\n')
    return doc


def _outcome(doc: Path, cache: Path, **kw: object) -> tuple:
    res = resolve(doc, ResolveOptions(cache_dir=str(cache), **kw))  # type: ignore[arg-type]
    arts = {url: (a.sha256, a.size, a.source, a.inode, str(a.error)) for url, a in res.artifacts.items()}
    errors = [(type(e).__name__, str(e), e.file, e.line, e.expected, e.actual) for e in res.errors]
    warnings = [n.to_dict() for n in res.warnings]
    return arts, errors, warnings, res.render_lock()


@pytest.mark.parametrize("jobs", [1, 16])
def test_the_small_file_path_resolves_exactly_as_the_plain_path(hostile_tree, tmp_path, monkeypatch, jobs):
    fast = _outcome(hostile_tree, tmp_path / "c1", jobs=jobs)
    calls: list[str] = []

    def plain(self: ConfinedFolders, path: str, root: object) -> None:
        calls.append(path)
        return None  # every file through ConfinedFolders.hash, as before the fast path

    monkeypatch.setattr(ConfinedFolders, "hash_entry", plain)
    assert _outcome(hostile_tree, tmp_path / "c2", jobs=jobs) == fast
    assert len(calls) > 20  # the fast path was offered every small local file
    arts, errors, _, _ = fast
    assert sum(a[2] == "file" for a in arts.values()) == 26
    assert {e[0] for e in errors} == {"DigestMismatchError", "PathEscapeError", "InputError", "NotFoundError"}


def test_the_small_file_path_hashes_most_files_without_the_plain_path(hostile_tree, tmp_path, monkeypatch):
    """The fast path is used: only the files it leaves alone reach ConfinedFolders.hash."""
    seen: list[str] = []
    real = ConfinedFolders.hash

    def spy(self: ConfinedFolders, path: str, *a: object, **kw: object) -> object:
        seen.append(os.path.relpath(path, hostile_tree.parent))
        return real(self, path, *a, **kw)  # type: ignore[arg-type]

    monkeypatch.setattr(ConfinedFolders, "hash", spy)
    resolve(hostile_tree, ResolveOptions(cache_dir=str(tmp_path / "c")))
    assert sorted(seen) == sorted(
        ["m/in-link.glb", "m/out-link.glb", "out-dir/key", "m/dir", "m/fifo", "m/zero", "m/missing.glb", "nope/x.glb"]
        + ["m/bigger.glb"]  # on the pool's threads
    )


@pytest.mark.parametrize("cls", [Reference, Location])
def test_a_hand_written_init_takes_every_field_in_order_with_the_dataclass_defaults(cls):
    """Reference and Location set all fields in one call: their __init__ must stay the dataclass's."""
    params = list(inspect.signature(cls.__init__).parameters.values())[1:]
    fields = dataclasses.fields(cls)
    assert [p.name for p in params] == [f.name for f in fields]
    for p, f in zip(params, fields, strict=True):
        assert p.default == (inspect.Parameter.empty if f.default is dataclasses.MISSING else f.default)
    values = {f.name: object() for f in fields}
    obj = cls(**values)
    assert all(getattr(obj, name) is value for name, value in values.items())
    assert obj == cls(*values.values()) and hash(obj) == hash(cls(**values))
    with pytest.raises(dataclasses.FrozenInstanceError):
        obj.uri = "x"


def test_reference_compares_and_replaces_as_a_dataclass():
    a = Reference(Kind.MODEL, 3, uri="m.glb", element=object())
    assert a == Reference(Kind.MODEL, 3, "m.glb") and hash(a) == hash(Reference(Kind.MODEL, 3, "m.glb"))
    assert dataclasses.replace(a, line=4) == Reference(Kind.MODEL, 4, uri="m.glb")


def test_an_unchanged_tree_reuses_the_lock_bytes_and_a_changed_one_renders_them(tmp_path):
    from hcdf_trust.include import lockfile

    root = tmp_path / "robot"
    (root / "m").mkdir(parents=True)
    for i in range(5):
        (root / "m" / f"{i}.glb").write_bytes(b"%d" % i)
    doc = root / "robot.hcdf"

    def write_doc(n: int) -> None:
        refs = "".join(f'<comp name="c{i}"><visual><model uri="m/{i}.glb"/></visual></comp>' for i in range(n))
        doc.write_text(f'<hcdf version="1.0">{refs}</hcdf>')

    def run() -> tuple[resolver.Resolution, bytes]:
        res = resolve(doc, ResolveOptions(cache_dir=str(tmp_path / "c")))
        assert res.ok, res.errors
        rendered = lockfile.render(res.lock_entries(), root=res.lock_url(res.root_location.url))
        assert res.render_lock() == rendered  # the oracle: rendering the entries
        res.write_lock()
        return res, rendered

    write_doc(4)
    first, _ = run()
    assert first.locked is None
    again, rendered = run()
    assert again.locked is not None and again.render_lock() is again.locked.rendered
    write_doc(5)  # a new reference: the lock changes
    grown, rendered = run()
    assert grown.render_lock() != grown.locked.rendered and doc.with_name("robot.hcdf.lock").read_bytes() == rendered
    (root / "m" / "0.glb").write_bytes(b"changed")  # drift: the run fails and writes nothing
    drift = resolve(doc, ResolveOptions(cache_dir=str(tmp_path / "c")))
    assert [type(e).__name__ for e in drift.errors] == ["LockDriftError"]


def _located(loc, uri: str, doc) -> object:
    try:
        return loc.locate(uri, doc, file="d.hcdf", line=3)
    except Exception as exc:  # noqa: BLE001 -- the outcome compared: type and message
        return type(exc).__name__, str(exc), getattr(exc, "expected", None), getattr(exc, "actual", None)


@pytest.mark.parametrize("root_rel", ["robot", "robot/sub", "robot/sub/deep", "rob", "robot-evil", "."])
def test_a_folder_checked_once_locates_as_every_path_checked(tmp_path, monkeypatch, root_rel):
    """Locator._below_root (the containment check once per folder) against _local's check per path."""
    from hcdf_trust.include.locate import Locator, file_url

    root = (tmp_path / root_rel).resolve()
    docs = [tmp_path / "robot" / "r.hcdf", tmp_path / "robot" / "sub" / "d.hcdf", tmp_path / "robot-evil" / "e.hcdf"]
    uris = ["m/a.glb", "a.glb", "sub/deep/x.glb", "deep/b.glb", "robot/x", "-evil/x", "m/../a.glb", "../x.glb"]

    def outcomes() -> list[object]:
        loc = Locator.create(root=root)
        referrers = [Location(file_url(doc), str(doc), doc.parent) for doc in docs]
        return [_located(loc, uri, doc) for doc in referrers for uri in uris]

    fast = outcomes()
    # plain_joiner (the resolver's per-document fast path) gives locate's result or None
    loc = Locator.create(root=root)
    for doc in docs:
        referrer = Location(file_url(doc), str(doc), doc.parent)
        join = loc.plain_joiner(referrer)
        for uri in [*uris, " a.glb", "a.glb\n", "a%20b.glb", "./a.glb", "a//b.glb", "https://h.example/a.glb", ""]:
            joined = join(uri)
            if joined is not None:
                assert joined == loc.locate(uri, referrer, file="d.hcdf", line=3)
        assert (join("m/a.glb") is not None) == f"{doc.parent}/".startswith(str(root).rstrip("/") + "/")
    monkeypatch.setattr(Locator, "_below_root", lambda self, folder: False)
    assert outcomes() == fast


MODELS = [
    '<model uri="m/a.glb" sha="ab"/>',
    '<model href="m/a.glb"/>',
    '<model uri="m/a.glb" href="m/a.glb"/>',
    '<model uri="m/a.glb" href="m/b.glb"/>',
    "<model/>",
    '<model uri=""/>',
    '<model uri=" m/a.glb"/>',
    '<model uri="m/a.glb "/>',
    '<model uri="m/a  b.glb"/>',
    '<model uri="m/a b.glb"/>',
    '<model uri="m/\u00e9.glb"/>',
    '<model uri="m/a\u200b.glb"/>',
    '<model uri="m/a&#9;.glb"/>',
    '<model uri="m/a.glb"> </model>',
    '<model uri="m/a.glb">text</model>',
    '<model uri="m/a.glb"><!-- c --></model>',
    '<model uri="m/a.glb"><uri>x</uri></model>',
    '<model uri="m/a.glb"><sha>x</sha></model>',
    '<model uri="m/a.glb" xmlns:x="urn:x" x:sha="1"/>',
]


@pytest.mark.parametrize("xml", MODELS)
def test_a_plain_model_reads_as_the_general_walker_reads_it(xml):
    """document._plain_model is _reference's result or None (then _reference decides)."""
    from lxml import etree

    from hcdf_trust import document
    from hcdf_trust.errors import HcdfTrustError

    el = etree.fromstring(f"<hcdf>\n\n{xml}</hcdf>")[0]
    fast = document._plain_model(el)
    try:
        general: object = document._reference(el, "model", "d.hcdf")
    except HcdfTrustError as exc:
        general = type(exc)
    if fast is not None:
        assert fast == general and fast.line == 3 and fast.element is el
    # uri="" is the resolver's error; a namespaced attribute, the namespace scan's (_walk)
    taken = (*MODELS[:2], '<model uri=""/>', '<model uri="m/a b.glb"/>', MODELS[-1])
    assert (fast is not None) == (xml in taken)
