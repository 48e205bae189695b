"""lockfile.load reads the lines render writes without json's per-object hook: same result, same errors.

The oracle is json itself (with the hooks that refuse duplicate keys, floats and
constants) followed by lockfile._check, the path every other form of lock takes.
"""

from __future__ import annotations

import os

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hcdf_trust.errors import LockFileError
from hcdf_trust.include import lockfile
from hcdf_trust.include.lockfile import LockEntry
from hcdf_trust.localfile import JsonError, parse_json

SETTINGS = settings(
    max_examples=int(os.environ.get("HCDF_FUZZ_EXAMPLES", "100")),
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.too_slow],
)
SHA = "0123456789abcdef" * 4


def _general(text: str, name: str) -> lockfile.Lock | str:
    """What json + _check make of ``text``: the lock, or the error's message."""
    try:
        doc = parse_json(text.encode(), source=name, limit=lockfile.MAX_LOCK_BYTES, floats=False)
        return lockfile._check(doc, name)
    except LockFileError as exc:
        return exc.message
    except JsonError as exc:
        return f"not JSON: {exc.message}"


def _loaded(path, text: str) -> lockfile.Lock | str:
    path.write_text(text, encoding="utf-8")
    try:
        return lockfile.load(path)
    except LockFileError as exc:
        return exc.message


def _same(tmp_path, text: str) -> None:
    path = tmp_path / "robot.hcdf.lock"
    expected, got = _general(text, lockfile.display_path(path)), _loaded(path, text)
    if isinstance(expected, str):  # an error: load names the same problem
        assert isinstance(got, str) and (expected in got or expected.startswith("not JSON")), (expected, got)
    else:
        assert got == expected


names = st.text(min_size=0, max_size=12)  # quotes, backslashes, control characters, non-ASCII
entries = st.builds(
    LockEntry,
    kind=st.sampled_from(sorted(lockfile.KINDS) + ["", "firmware"]),
    uri=names,
    url=names,
    sha256=st.sampled_from([SHA, SHA.upper(), SHA[:-1], SHA[:-1] + "g"]),
    size=st.sampled_from([0, 1, 4096, -1, 10**20]),
    referenced_from=st.lists(names, max_size=3).map(tuple),
)


@SETTINGS
@given(st.lists(entries, max_size=6), names)
def test_any_rendered_lock_loads_as_json_reads_it(tmp_path_factory, items, root):
    tmp_path = tmp_path_factory.mktemp("lock")
    _same(tmp_path, lockfile.render(items, root=root).decode())


def _edited_render(items: list[LockEntry], data: st.DataObject, *, replace: bool) -> str:
    """A rendered lock with one character replaced (or deleted, as the empty one) or inserted."""
    text = lockfile.render(items, root="robot.hcdf").decode()
    at = data.draw(st.integers(0, len(text) - 1))
    char = data.draw(st.sampled_from(list(' ",:[]{}\\\n\t0aA-é') + [""]))
    return text[:at] + char + text[at + replace :]


@SETTINGS
@given(st.lists(entries, min_size=1, max_size=4), st.data())
def test_any_edit_of_a_rendered_lock_loads_as_json_reads_it(tmp_path_factory, items, data):
    """One character replaced, inserted or deleted anywhere in a canonical lock."""
    how = data.draw(st.sampled_from(["replace", "insert"]))
    _same(tmp_path_factory.mktemp("lock"), _edited_render(items, data, replace=how == "replace"))


@pytest.mark.parametrize(
    "edit",
    [
        lambda t: t.replace('"size": 4096', '"size": 04096'),
        lambda t: t.replace('"size": 4096', '"size": 4096.0'),
        lambda t: t.replace('"kind": "model", ', '"kind": "model", "kind": "mesh", ', 1),
        lambda t: t.replace('"robot.hcdf"]', '"robot.hcdf", ""]', 1),
        lambda t: t.replace('"uri": "m.glb"', '"uri": ""'),
        lambda t: t.replace('"url": "m.glb"', '"url": "n.glb"'),
        lambda t: t.replace('"lock_version": 2', '"lock_version": 3'),
        lambda t: t.replace('"root": "robot.hcdf"', '"root": ""'),
        lambda t: t.replace("},\n{", "}\n{"),
        lambda t: t.replace("},\n{", "},\n{},\n{"),
    ],
)
def test_malformed_canonical_looking_locks_are_refused_as_before(tmp_path, edit):
    items = [LockEntry("model", "m.glb", "m.glb", SHA, 4096, ("robot.hcdf",)), LockEntry("mesh", "n", "n.glb", SHA, 1)]
    text = edit(lockfile.render(items, root="robot.hcdf").decode())
    assert isinstance(_general(text, "robot.hcdf.lock"), str)
    _same(tmp_path, text)


def test_a_canonical_lock_is_read_without_json(tmp_path, monkeypatch):
    """The fast path is taken for what render writes (json is not called at all)."""
    items = [LockEntry("model", f"m{i}.glb", f"m{i}.glb", SHA, i, ("robot.hcdf",)) for i in range(50)]
    path = tmp_path / "robot.hcdf.lock"
    path.write_bytes(lockfile.render(items, root="robot.hcdf"))
    monkeypatch.setattr(lockfile.json, "loads", lambda *a, **k: pytest.fail("json.loads was called"))
    lock = lockfile.load(path)
    assert lock.root == "robot.hcdf" and lock.entries == {e.url: e for e in items}


def _rendered_is_render(tmp_path, text: str) -> None:
    """A lock loaded with ``rendered`` set: those are the file's bytes, and render's for its entries."""
    got = _loaded(tmp_path / "robot.hcdf.lock", text)
    if isinstance(got, lockfile.Lock) and got.rendered is not None:
        assert got.rendered == text.encode()
        assert lockfile.render(list(got.entries.values()), root=got.root) == got.rendered
        assert lockfile.render_unchanged(list(got.entries.values()), root=got.root, before=got) is got.rendered


@SETTINGS
@given(st.lists(entries, max_size=6), names, st.randoms(use_true_random=False))
def test_a_lock_that_keeps_its_bytes_is_exactly_what_render_writes(tmp_path_factory, items, root, rnd):
    """Rendered, or in render's line format with its lines in any order."""
    tmp_path = tmp_path_factory.mktemp("lock")
    text = lockfile.render(items, root=root).decode()
    _rendered_is_render(tmp_path, text)
    head, _, rest = text.partition("[\n")
    body, sep, tail = rest.rpartition("\n]")
    lines = body.split(",\n")
    rnd.shuffle(lines)
    _rendered_is_render(tmp_path, head + "[\n" + ",\n".join(lines) + sep + tail)


@SETTINGS
@given(st.lists(entries, min_size=1, max_size=4), st.data())
def test_an_edited_lock_keeps_its_bytes_only_when_they_are_what_render_writes(tmp_path_factory, items, data):
    _rendered_is_render(tmp_path_factory.mktemp("lock"), _edited_render(items, data, replace=True))


def test_an_unchanged_lock_is_reused_and_any_change_is_rendered(tmp_path):
    items = [LockEntry("model", f"m{i}.glb", f"m{i}.glb", SHA, i, ("robot.hcdf",)) for i in range(3)]
    path = tmp_path / "robot.hcdf.lock"
    path.write_bytes(lockfile.render(items, root="robot.hcdf"))
    lock = lockfile.load(path)
    assert lock.rendered == path.read_bytes()
    assert lockfile.render_unchanged(items[::-1], root="robot.hcdf", before=lock) is lock.rendered
    changes = [
        (items[:2], "robot.hcdf"),
        ([*items, LockEntry("mesh", "n", "n.glb", SHA, 1)], "robot.hcdf"),
        ([items[0]._replace(size=7), *items[1:]], "robot.hcdf"),
        ([items[0]._replace(uri="other"), *items[1:]], "robot.hcdf"),
        ([items[0]._replace(referenced_from=("a.hcdf", "robot.hcdf")), *items[1:]], "robot.hcdf"),
        ([items[0], items[1], items[1]], "robot.hcdf"),  # as many entries, one url twice
        (items, "other.hcdf"),
    ]
    for entries, root in changes:
        out = lockfile.render_unchanged(entries, root=root, before=lock)
        assert out == lockfile.render(entries, root=root) != lock.rendered
    swapped = path.read_text().replace("m0.glb", "m9.glb")  # out of render's order
    path.write_text(swapped)
    assert lockfile.load(path).rendered is None
