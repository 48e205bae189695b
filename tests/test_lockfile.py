"""The lock file cannot hang, exhaust or fool the tool: bounded strict reading, one lock per root."""

from __future__ import annotations

import hashlib
import json
import os
import threading
import time
from pathlib import Path

import pytest

from hcdf_trust.include import lockfile
from hcdf_trust.include.lockfile import LockEntry

# Every verb that reads the lock file, with the flags that make it write what it can.
LOCK_READERS = {
    "resolve": ["resolve", "--offline"],
    "resolve --locked": ["resolve", "--offline", "--locked"],
    "resolve --update": ["resolve", "--offline", "--update"],
    "verify": ["verify"],
    "pin": ["pin", "--write", "--offline"],
}


def sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


@pytest.fixture
def tree(tmp_path):
    """robot.hcdf referencing one unpinned model, resolved once: robot.hcdf.lock exists."""
    root = tmp_path / "robot"
    root.mkdir()
    (root / "m.glb").write_bytes(b"model")
    doc = root / "robot.hcdf"
    doc.write_text(
        '<?xml version="1.0"?>\n<hcdf version="1.0" name="r">\n<comp name="c"><visual><model uri="m.glb"/>'
        "</visual></comp>\n</hcdf>\n"
    )
    return doc


def run(cli, verb: str, doc: Path, *extra):
    first, *flags = LOCK_READERS[verb]
    return cli(first, doc, *flags, "--cache-dir", doc.parent / "cache", "--json", *extra)


def good_entry(**over):
    entry = {
        "kind": "model",
        "uri": "m.glb",
        "url": "m.glb",
        "sha256": sha(b"model"),
        "size": 5,
        "referenced_from": ["robot.hcdf"],
    }
    entry.update(over)
    return entry


def good_lock(**over):
    lock = {"lock_version": 2, "root": "robot.hcdf", "artifacts": [good_entry()]}
    lock.update(over)
    return lock


MALFORMED = {
    "list": b"[]",
    "string": b'"lock"',
    "empty": b"",
    "not-json": b"{lock",
    "deep-list": b"[" * 100_000 + b"]" * 100_000,
    "deep-object": b'{"a":' * 100_000 + b"1" + b"}" * 100_000,
    "huge-float": json.dumps(good_lock(artifacts=[good_entry(size=1)])).replace('"size": 1', '"size": 1e999').encode(),
    "nan-size": json.dumps(good_lock(artifacts=[good_entry(size=1)])).replace('"size": 1', '"size": NaN').encode(),
    "float-size": json.dumps(good_lock(artifacts=[good_entry(size=5.0)])).encode(),
    "bool-size": json.dumps(good_lock(artifacts=[good_entry(size=True)])).encode(),
    "negative-size": json.dumps(good_lock(artifacts=[good_entry(size=-5)])).encode(),
    "string-size": json.dumps(good_lock(artifacts=[good_entry(size="5")])).encode(),
    "huge-int-size": json.dumps(good_lock(artifacts=[good_entry(size=1)]))
    .replace('"size": 1', '"size": ' + "9" * 5000)
    .encode(),
    "bool-version": json.dumps(good_lock(lock_version=True)).encode(),
    "string-version": json.dumps(good_lock(lock_version="2")).encode(),
    "missing-version": json.dumps({"root": "robot.hcdf", "artifacts": []}).encode(),
    "missing-artifacts": json.dumps({"lock_version": 2, "root": "robot.hcdf"}).encode(),
    "missing-root": json.dumps({"lock_version": 2, "artifacts": []}).encode(),
    "extra-top-key": json.dumps(good_lock(extra=1)).encode(),
    "root-not-string": json.dumps(good_lock(root=["robot.hcdf"])).encode(),
    "artifacts-object": json.dumps(good_lock(artifacts={"m.glb": good_entry()})).encode(),
    "artifact-string": json.dumps(good_lock(artifacts=["m.glb"])).encode(),
    "artifact-null": json.dumps(good_lock(artifacts=[None])).encode(),
    "missing-sha": json.dumps(good_lock(artifacts=[{k: v for k, v in good_entry().items() if k != "sha256"}])).encode(),
    "missing-referenced-from": json.dumps(
        good_lock(artifacts=[{k: v for k, v in good_entry().items() if k != "referenced_from"}])
    ).encode(),
    "sha-number": json.dumps(good_lock(artifacts=[good_entry(sha256=12345)])).encode(),
    "sha-short": json.dumps(good_lock(artifacts=[good_entry(sha256=sha(b"model")[:8])])).encode(),
    "url-number": json.dumps(good_lock(artifacts=[good_entry(url=7)])).encode(),
    "uri-null": json.dumps(good_lock(artifacts=[good_entry(uri=None)])).encode(),
    "kind-unknown": json.dumps(good_lock(artifacts=[good_entry(kind="firmware")])).encode(),
    "referenced-from-string": json.dumps(good_lock(artifacts=[good_entry(referenced_from="robot.hcdf")])).encode(),
    "referenced-from-numbers": json.dumps(good_lock(artifacts=[good_entry(referenced_from=[1])])).encode(),
    "duplicate-url": json.dumps(good_lock(artifacts=[good_entry(), good_entry()])).encode(),
    "duplicate-key": json.dumps(good_lock()).replace('"size": 5', '"size": 5, "size": 6').encode(),
    "utf16": json.dumps(good_lock()).encode("utf-16"),
    "invalid-utf8": json.dumps(good_lock()).replace("m.glb", "m\udcff.glb").encode("utf-8", "surrogateescape"),
}


@pytest.mark.parametrize("verb", list(LOCK_READERS))
@pytest.mark.parametrize("case", list(MALFORMED))
def test_malformed_lock_is_a_lock_file_error_under_every_verb(cli, tree, verb, case):
    lock = tree.parent / "robot.hcdf.lock"
    lock.write_bytes(MALFORMED[case])
    before = lock.read_bytes()
    r = run(cli, verb, tree)
    assert r.exit_code == 3, (r.stdout, r.stderr)
    [e] = r.json["errors"]
    assert e["code"] == "lock-file" and e["file"].endswith("robot.hcdf.lock"), e
    assert "Traceback" not in r.stdout + r.stderr
    assert lock.read_bytes() == before


def test_a_well_formed_lock_passes_every_verb(cli, tree):
    """The malformed cases above differ from this one lock in one field each."""
    (tree.parent / "robot.hcdf.lock").write_text(json.dumps(good_lock()))
    for verb in LOCK_READERS:
        r = run(cli, verb, tree)
        assert r.exit_code == 0, (verb, r.stdout)


def _feed_fifo_forever(path: Path, stop: threading.Event) -> None:
    """A writer that would block a reader that waits for end of file."""
    try:
        fd = os.open(path, os.O_WRONLY | os.O_NONBLOCK)
    except OSError:
        return
    try:
        while not stop.is_set():
            try:
                os.write(fd, b"[")
            except BlockingIOError:
                time.sleep(0.01)
            except OSError:
                return
    finally:
        os.close(fd)


@pytest.mark.parametrize("verb", list(LOCK_READERS))
@pytest.mark.parametrize("kind", ["fifo", "dev-zero", "directory", "too-large"])
def test_lock_that_is_not_a_small_regular_file_is_refused_at_once(cli, tree, verb, kind):
    lock = tree.parent / "robot.hcdf.lock"
    if kind == "fifo":
        os.mkfifo(lock)
    elif kind == "dev-zero":
        lock.symlink_to("/dev/zero")
    elif kind == "directory":
        lock.mkdir()
    else:
        with open(lock, "wb") as f:
            f.truncate(lockfile.MAX_LOCK_BYTES + 1)  # sparse: no disk used
    start = time.monotonic()
    r = run(cli, verb, tree)
    assert time.monotonic() - start < 5
    assert r.exit_code == 3, r.stdout
    [e] = r.json["errors"]
    assert e["code"] == "lock-file", e
    expected = {"fifo": "FIFO", "dev-zero": "device", "directory": "directory", "too-large": "limit"}[kind]
    assert expected in e["message"]


def test_lock_of_another_root_is_refused_naming_both(cli, tmp_path):
    (tmp_path / "m.glb").write_bytes(b"model")
    body = '<hcdf version="1.0" name="{}"><comp name="c"><visual><model uri="m.glb"/></visual></comp></hcdf>\n'
    (tmp_path / "a.hcdf").write_text(body.format("a"))
    (tmp_path / "b.hcdf").write_text(body.format("b"))
    assert cli("resolve", tmp_path / "a.hcdf").exit_code == 0
    for verb in (["resolve"], ["resolve", "--locked"], ["verify"]):
        r = cli(*verb, tmp_path / "b.hcdf", "--lock", tmp_path / "a.hcdf.lock", "--json")
        assert r.exit_code == 3
        [e] = r.json["errors"]
        assert e["code"] == "lock-file"
        assert "a.hcdf" in e["message"] and "b.hcdf" in e["message"]
        assert (e["expected"], e["actual"]) == ("b.hcdf", "a.hcdf")


def test_two_roots_in_one_folder_keep_their_own_locks(cli, tmp_path):
    (tmp_path / "x.glb").write_bytes(b"x")
    (tmp_path / "y.glb").write_bytes(b"y")
    tmpl = '<hcdf version="1.0" name="{0}"><comp name="c"><visual><model uri="{0}.glb"/></visual></comp></hcdf>\n'
    for name in ("x", "y"):
        (tmp_path / f"{name}.hcdf").write_text(tmpl.format(name))
        assert cli("resolve", tmp_path / f"{name}.hcdf").exit_code == 0
    for name in ("x", "y"):
        lock = json.loads((tmp_path / f"{name}.hcdf.lock").read_text())
        assert lock["root"] == f"{name}.hcdf"
        assert [a["url"] for a in lock["artifacts"]] == [f"{name}.glb"]
        assert cli("verify", tmp_path / f"{name}.hcdf").exit_code == 0
    assert not (tmp_path / "hcdf.lock").exists()


def test_version_1_lock_is_refused_with_how_to_regenerate(cli, tree):
    lock = tree.parent / "robot.hcdf.lock"
    lock.write_text(json.dumps(good_lock(lock_version=1)))
    for verb in LOCK_READERS:
        r = run(cli, verb, tree)
        assert r.exit_code == 3
        [e] = r.json["errors"]
        assert e["code"] == "lock-file" and "lock_version 1" in e["message"]
        assert "delete" in e["message"] and "hcdf-trust resolve" in e["message"]
        assert (e["expected"], e["actual"]) == ("2", "1")


# --- the writer and the loader agree --------------------------------------------------------


def _entries(n: int) -> list[LockEntry]:
    return [
        LockEntry(
            kind="model",
            uri=f'models/ü{i}"\\\n.glb',
            url=f'models/ü{i}"\\\n.glb' if i % 2 else f"https://h.example/{i}.glb",
            sha256=sha(str(i).encode()),
            size=i,
            referenced_from=("robot.hcdf", f"sub/ä{i}.hcdf"),
        )
        for i in range(n)
    ]


def test_render_is_valid_deterministic_json_one_artifact_per_line():
    entries = _entries(50)
    data = lockfile.render(entries, root="röbot.hcdf")
    assert data == lockfile.render(list(reversed(entries)), root="röbot.hcdf")
    doc = json.loads(data)  # the independent oracle: json itself
    assert doc == {
        "lock_version": 2,
        "root": "röbot.hcdf",
        "artifacts": [e.to_dict() for e in sorted(entries, key=lambda e: e.url)],
    }
    lines = data.decode().splitlines()
    artifact_lines = [line.rstrip(",") for line in lines if line.startswith('{"kind"')]
    assert artifact_lines == [
        json.dumps(e.to_dict(), sort_keys=True, ensure_ascii=False) for e in sorted(entries, key=lambda e: e.url)
    ]
    assert len(lines) == len(entries) + 4


def test_loader_accepts_exactly_what_the_writer_writes(tmp_path):
    for entries in ([], _entries(3)):
        path = tmp_path / "x.lock"
        path.write_bytes(lockfile.render(entries, root="robot.hcdf"))
        lock = lockfile.load(path)
        assert lock.root == "robot.hcdf"
        assert lock.entries == {e.url: e for e in entries}


def test_lock_write_computes_relative_paths_once_per_folder(tmp_path, monkeypatch):
    """10,000 files used to cost 20,000 os.path.relpath calls, more than resolving them."""
    from hcdf_trust.include import resolve

    (tmp_path / "models").mkdir()
    body = []
    for i in range(300):
        (tmp_path / "models" / f"m{i} %.glb").write_bytes(str(i).encode())
        body.append(f'<comp name="c{i}"><visual><model uri="models/m{i}%20%25.glb"/></visual></comp>')
    doc = tmp_path / "robot.hcdf"
    doc.write_text('<hcdf version="1.0" name="r">\n' + "\n".join(body) + "\n</hcdf>\n")
    res = resolve(doc)
    assert res.ok, res.errors
    calls = []
    real = os.path.relpath
    monkeypatch.setattr(os.path, "relpath", lambda *a: calls.append(a) or real(*a))
    data = res.render_lock()
    assert len(calls) <= 3, len(calls)
    lock = json.loads(data)
    assert {a["url"] for a in lock["artifacts"]} == {f"models/m{i} %.glb" for i in range(300)}
    assert {r for a in lock["artifacts"] for r in a["referenced_from"]} == {"robot.hcdf"}


@pytest.mark.parametrize(
    "path",
    ["robot/m.glb", "robot/models/a b%20c.glb", "robot/mödels/ü.glb", "other/x.glb", "m.glb", "robot/a/b/c/d.glb"],
)
def test_lock_urls_match_relpath(tmp_path, path):
    """The per-folder shortcut gives what os.path.relpath gives per file."""
    from hcdf_trust.include.locate import file_url
    from hcdf_trust.include.resolver import LockUrls

    base = tmp_path / "robot"
    target = tmp_path / path
    urls = LockUrls(base)
    url = file_url(target)
    rel = urls.to_lock(url)
    assert rel == Path(os.path.relpath(target, base)).as_posix()
    assert urls.to_lock(url) == rel  # remembered
    assert urls.to_lock("https://h.example/a%20b.glb") == "https://h.example/a%20b.glb"


GOOD_SHA = hashlib.sha256(b"x").hexdigest()


@pytest.mark.parametrize(
    "sha, ok",
    [
        (GOOD_SHA, True),
        (GOOD_SHA.upper(), True),  # read, and kept lower case
        (GOOD_SHA[:63], False),
        (GOOD_SHA + "0", False),
        (GOOD_SHA[:62] + " 0", False),  # 64 characters, 63 digits
        ("ab " * 21 + "a", False),  # digit pairs separated by spaces: fromhex would skip them
        (GOOD_SHA[:63] + "g", False),
        (GOOD_SHA[:63] + "\u0663", False),  # a non-ASCII digit
        (" " + GOOD_SHA[:63], False),
    ],
)
def test_lock_sha256_must_be_64_hex_digits(tmp_path, sha, ok):
    entry = {"kind": "model", "uri": "m.glb", "url": "m.glb", "sha256": sha, "size": 1, "referenced_from": ["r"]}
    path = tmp_path / "r.lock"
    path.write_text(json.dumps({"artifacts": [entry], "lock_version": 2, "root": "r"}))
    if ok:
        assert lockfile.load(path).entries["m.glb"].sha256 == GOOD_SHA
    else:
        with pytest.raises(lockfile.LockFileError, match="sha256 is not a full digest"):
            lockfile.load(path)


@pytest.mark.parametrize("refs", [[], ["a", "b"]])
def test_lock_referenced_from_lists_of_names_are_read(tmp_path, refs):
    entry = {"kind": "model", "uri": "m.glb", "url": "m.glb", "sha256": GOOD_SHA, "size": 1, "referenced_from": refs}
    path = tmp_path / "r.lock"
    path.write_text(json.dumps({"artifacts": [entry], "lock_version": 2, "root": "r"}))
    assert lockfile.load(path).entries["m.glb"].referenced_from == tuple(refs)


@pytest.mark.parametrize("refs", ["r", ["r", ""], ["r", 1], [["r"]], [None], {"r": 1}])
def test_lock_referenced_from_must_be_a_list_of_names(tmp_path, refs):
    entry = {"kind": "model", "uri": "m.glb", "url": "m.glb", "sha256": GOOD_SHA, "size": 1, "referenced_from": refs}
    path = tmp_path / "r.lock"
    path.write_text(json.dumps({"artifacts": [entry], "lock_version": 2, "root": "r"}))
    with pytest.raises(lockfile.LockFileError, match="referenced_from must be a list"):
        lockfile.load(path)


@pytest.mark.parametrize("drop, add", [("size", None), ("size", "extra"), (None, "extra")])
def test_lock_artifact_keys_are_exactly_the_six(tmp_path, drop, add):
    entry = {"kind": "model", "uri": "m.glb", "url": "m.glb", "sha256": GOOD_SHA, "size": 1, "referenced_from": []}
    if drop:
        del entry[drop]
    if add:
        entry[add] = 1
    path = tmp_path / "r.lock"
    path.write_text(json.dumps({"artifacts": [entry], "lock_version": 2, "root": "r"}))
    with pytest.raises(lockfile.LockFileError, match="expected an object with keys"):
        lockfile.load(path)
