"""Hostile paths: every way a reference can try to leave its root or wedge the tool.

Each case is tried as an include, a model and a mesh reference, through resolve,
verify and pin: exit 3 with the specific error code (``path-escape``, ``input``,
``not-found``) naming the referencing file and line, within seconds (a FIFO never
blocks), without network and without writing anything.

The last tests change a file while the tool works on it: the digest it reports
and locks must be the digest of the bytes whose references it followed.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest

from hcdf_trust.include import resolver as resolver_module
from hcdf_trust.store import ContentStore

from ._hostile import (  # noqa: F401  (fixtures are used by name)
    command_args,
    fifo_watchdog,
    no_network,
    sha256,
    snapshot,
    write_lock,
)

pytestmark = pytest.mark.usefixtures("no_network")

SECRET = "TOP-SECRET-c0ffee"

TEMPLATES = {
    "include": '<hcdf version="1.0" name="r">\n<include uri="{uri}" name="s"/>\n</hcdf>\n',
    "model": (
        '<hcdf version="1.0" name="r">\n<comp name="c"><visual name="v"><model uri="{uri}"/></visual></comp>\n</hcdf>\n'
    ),
    "mesh": (
        '<hcdf version="1.0" name="r">\n<comp name="c"><collision name="k"><geometry>'
        '<mesh uri="{uri}"/></geometry></collision></comp>\n</hcdf>\n'
    ),
}


@dataclass
class Tree:
    work: Path  # everything the test may see change
    root: Path  # the confinement root: the document's folder
    outside: Path

    @property
    def fifo(self) -> Path:
        return self.root / "pipe.hcdf"


@pytest.fixture
def tree(tmp_path) -> Tree:
    work = tmp_path / "work"
    root = work / "root"
    outside = work / "outside"
    for d in (root / "adir", root / "inner", root / "mirror", outside / "d"):
        d.mkdir(parents=True)
    secret_doc = f'<hcdf version="1.0" name="{SECRET}"><include uri="loot.hcdf"/></hcdf>\n'
    (outside / "secret.hcdf").write_text(secret_doc)
    (outside / "d" / "secret.hcdf").write_text(secret_doc)
    (root / "inner" / "ok.hcdf").write_text('<hcdf version="1.0" name="ok"/>\n')
    os.mkfifo(root / "pipe.hcdf")
    return Tree(work=work, root=root, outside=outside)


def _q(path: Path) -> str:
    return str(path)


# id -> (set-up returning the uri to write, expected error code, regex on the message)
PathCase = tuple[Callable[[Tree], str], str, str]

CASES: dict[str, PathCase] = {
    "dotdot": (lambda t: "../outside/secret.hcdf", "path-escape", r"outside the root"),
    "dotdot-after-a-folder": (lambda t: "inner/../../outside/secret.hcdf", "path-escape", r"outside the root"),
    "dotdot-percent-encoded": (lambda t: "%2e%2e/outside/secret.hcdf", "path-escape", r"outside the root"),
    "dotdot-encoded-slashes": (lambda t: "..%2Foutside%2Fsecret.hcdf", "path-escape", r"outside the root"),
    "absolute-path": (lambda t: _q(t.outside / "secret.hcdf"), "path-escape", r"absolute local path"),
    "absolute-etc-passwd": (lambda t: "/etc/passwd", "path-escape", r"absolute local path"),
    "file-uri": (lambda t: "file://" + _q(t.outside / "secret.hcdf"), "path-escape", r"absolute local path"),
    "file-uri-localhost": (lambda t: "file://localhost/etc/passwd", "path-escape", r"absolute local path"),
    "file-uri-upper-case-scheme": (lambda t: "FILE:///etc/passwd", "path-escape", r"absolute local path"),
    "file-uri-into-root": (
        # Even a file: URI that points inside the root is refused: references are relative.
        lambda t: "file://" + _q(t.root / "inner" / "ok.hcdf"),
        "path-escape",
        r"absolute local path",
    ),
    "windows-drive": (lambda t: "C:/Windows/win.ini", "path-escape", r"absolute local path"),
    "windows-unc": (lambda t: r"\\server\share\x.hcdf", "path-escape", r"absolute local path"),
    "symlink-file-out": (
        lambda t: _link(t.root / "link.hcdf", t.outside / "secret.hcdf"),
        "path-escape",
        r"symlink escape",
    ),
    "symlink-relative-out": (
        lambda t: _link(t.root / "rel.hcdf", Path("../outside/secret.hcdf")),
        "path-escape",
        r"symlink escape",
    ),
    "symlink-dir-out": (
        lambda t: _link(t.root / "ldir", t.outside / "d", then="ldir/secret.hcdf"),
        "path-escape",
        r"symlink escape",
    ),
    "symlink-to-dev-zero": (lambda t: _link(t.root / "zero.glb", Path("/dev/zero")), "path-escape", r"symlink escape"),
    "symlink-loop": (
        lambda t: _loop(t.root / "loop-a.hcdf", t.root / "loop-b.hcdf"),
        "input",
        r"cannot open: Too many levels of symbolic links",
    ),
    "symlink-self-loop": (
        lambda t: _link(t.root / "self.hcdf", Path("self.hcdf")),
        "input",
        r"cannot open: Too many levels of symbolic links",
    ),
    "directory": (lambda t: "adir", "input", r"is a directory"),
    "directory-trailing-slash": (lambda t: "adir/", "input", r"is a directory"),
    "directory-dot": (lambda t: ".", "input", r"is a directory"),
    "fifo": (lambda t: "pipe.hcdf", "input", r"is not a regular file"),
    "symlink-to-fifo": (
        lambda t: _link(t.root / "pipelink.hcdf", Path("pipe.hcdf")),
        "input",
        r"is not a regular file",
    ),
    "missing": (lambda t: "nope.hcdf", "not-found", r"no such file"),
    "name-too-long": (lambda t: "a" * 300 + ".hcdf", "input", r"cannot open: File name too long"),
    "empty-uri": (lambda t: "", "input", r"has no uri|empty uri"),
    "unsupported-scheme": (lambda t: "ftp://example.invalid/x.hcdf", "input", r"unsupported URL scheme"),
    "data-uri": (lambda t: "data:,hello", "input", r"unsupported URL scheme"),
}


def _link(link: Path, target: Path, *, then: str | None = None) -> str:
    link.symlink_to(target)
    return then or link.name


def _loop(a: Path, b: Path) -> str:
    a.symlink_to(b.name)
    b.symlink_to(a.name)
    return a.name


def _write_doc(tree: Tree, kind: str, uri: str) -> Path:
    doc = tree.root / "doc.hcdf"
    doc.write_text(TEMPLATES[kind].format(uri=uri.replace("&", "&amp;").replace('"', "&quot;")))
    return doc


COMMANDS = ("resolve", "verify", "pin")


@pytest.mark.parametrize("command", COMMANDS)
@pytest.mark.parametrize("kind", list(TEMPLATES))
@pytest.mark.parametrize("case", list(CASES))
def test_hostile_reference_path(cli, tree, monkeypatch, case, kind, command):
    setup, code, pattern = CASES[case]
    uri = setup(tree)
    doc = _write_doc(tree, kind, uri)
    if command == "verify":
        write_lock(tree.root / "doc.hcdf.lock", "doc.hcdf", [])
    monkeypatch.chdir(tree.work)
    before = snapshot(tree.work)
    with fifo_watchdog(tree.fifo) as watch:
        result = cli(*command_args(command, doc, tree.work, "--json"))
    assert not watch["hung"], "blocked on a FIFO"
    assert watch["elapsed"] < 5.0
    assert result.exit_code == 3, result.stdout + result.stderr
    payload = json.loads(result.stdout)
    assert payload["ok"] is False
    errors = payload["errors"]
    assert {e["code"] for e in errors} == {code}, errors
    assert any(re.search(pattern, e["message"]) for e in errors), errors
    assert all(e["file"].endswith("doc.hcdf") and e["line"] == 2 for e in errors), errors
    assert SECRET not in result.stdout + result.stderr
    assert "loot.hcdf" not in result.stdout, "references of a file outside the root were followed"
    assert snapshot(tree.work) == before
    assert not (tree.work / "flat.hcdf").exists()


@pytest.mark.parametrize("command", COMMANDS)
def test_hostile_path_human_message(cli, tree, monkeypatch, command):
    """Without --json: one "error:" line on stderr naming file, line and the escape."""
    doc = _write_doc(tree, "include", "../outside/secret.hcdf")
    if command == "verify":
        write_lock(tree.root / "doc.hcdf.lock", "doc.hcdf", [])
    monkeypatch.chdir(tree.work)
    result = cli(*command_args(command, doc, tree.work))
    assert result.exit_code == 3
    assert re.search(r"^error: .*doc\.hcdf:2: .*outside the root", result.stderr, re.M), result.stderr
    assert "Traceback" not in result.stderr


def test_dotdot_that_stays_inside_is_allowed(cli, tree, monkeypatch):
    """Control case: the confinement is about where a path ends, not about '..' as text."""
    doc = _write_doc(tree, "include", "inner/../inner/ok.hcdf")
    monkeypatch.chdir(tree.work)
    result = cli("resolve", doc, "--offline", "--no-lock", "--cache-dir", tree.work / "cache")
    assert result.exit_code == 0, result.stderr


# --- --base and --mirror move the root: the same rules hold there ---------------------


def test_base_folder_confines_relative_references(cli, tree, monkeypatch):
    base = tree.root / "inner"
    doc = _write_doc(tree, "model", "../../outside/secret.hcdf")
    monkeypatch.chdir(tree.work)
    before = snapshot(tree.work)
    result = cli(*command_args("resolve", doc, tree.work, "--base", str(base), "--json"))
    assert result.exit_code == 3
    assert [e["code"] for e in result.json["errors"]] == ["path-escape"]
    assert snapshot(tree.work) == before


@pytest.mark.parametrize(
    ("uri", "code"),
    [
        ("https://mirror.example/%2e%2e/%2e%2e/outside/secret.hcdf", "path-escape"),
        ("https://mirror.example/%2E%2E%2F%2E%2E%2Foutside%2Fsecret.hcdf", "path-escape"),
        # Plain '..' in a URL is collapsed before the mirror applies: it cannot climb out.
        ("https://mirror.example/../../outside/secret.hcdf", "not-found"),
        ("https://mirror.example/escape/secret.hcdf", "path-escape"),  # symlink in the mirror
    ],
)
def test_mirror_folder_confines_urls(cli, tree, monkeypatch, uri, code):
    (tree.root / "mirror" / "escape").symlink_to(tree.outside / "d")
    doc = _write_doc(tree, "include", uri)
    monkeypatch.chdir(tree.work)
    before = snapshot(tree.work)
    result = cli(
        *command_args(
            "resolve", doc, tree.work, "--mirror", f"https://mirror.example/={tree.root / 'mirror'}", "--json"
        )
    )
    assert result.exit_code == 3, result.stdout
    assert [e["code"] for e in result.json["errors"]] == [code], result.json["errors"]
    assert SECRET not in result.stdout
    assert snapshot(tree.work) == before


# --- the root document itself -----------------------------------------------------


@pytest.mark.parametrize("command", ("resolve", "verify", "pin", "validate"))
def test_root_document_is_a_fifo(cli, tree, monkeypatch, command):
    monkeypatch.chdir(tree.work)
    before = snapshot(tree.work)
    with fifo_watchdog(tree.fifo) as watch:
        result = cli(*command_args(command, tree.fifo, tree.work))
    assert not watch["hung"], f"{command} blocked reading a FIFO"
    assert result.exit_code == 3, result.stderr
    assert re.search(r"^error: .*pipe\.hcdf.* is not a regular file", result.stderr, re.M), result.stderr
    assert snapshot(tree.work) == before


@pytest.mark.parametrize("command", ("resolve", "verify", "pin", "validate"))
def test_root_document_is_a_symlink_loop(cli, tree, monkeypatch, command):
    _loop(tree.root / "a.hcdf", tree.root / "b.hcdf")
    monkeypatch.chdir(tree.work)
    before = snapshot(tree.work)
    result = cli(*command_args(command, tree.root / "a.hcdf", tree.work))
    assert result.exit_code == 3, result.stderr
    assert re.search(r"^error: .*Too many levels of symbolic links", result.stderr, re.M), result.stderr
    assert snapshot(tree.work) == before


@pytest.mark.parametrize("command", ("resolve", "verify", "pin", "validate"))
def test_root_document_is_missing(cli, tree, monkeypatch, command):
    monkeypatch.chdir(tree.work)
    result = cli(*command_args(command, tree.root / "nope.hcdf", tree.work))
    assert result.exit_code == 3, result.stderr
    assert re.search(r"^error: .*nope\.hcdf.*(no such file|does not exist)", result.stderr, re.M | re.I)


@pytest.mark.parametrize("command", ("resolve", "verify", "pin", "validate"))
def test_root_document_is_a_directory(cli, tree, monkeypatch, command):
    """click refuses a directory for DOC before the tool runs: a usage error (exit 2)."""
    monkeypatch.chdir(tree.work)
    before = snapshot(tree.work)
    result = cli(*command_args(command, tree.root / "adir", tree.work))
    assert result.exit_code == 2, result.stderr
    assert "is a directory" in result.stderr
    assert snapshot(tree.work) == before


# --- a file that changes while the tool works on it ---------------------------------

MODEL_A = b"model A bytes"
MODEL_B = b"model B bytes, swapped in"
SUB_A = (
    b'<hcdf version="1.0" name="sub">\n<comp name="a"><visual name="v"><model uri="a.glb"/></visual></comp>\n</hcdf>\n'
)
SUB_B = (
    b'<hcdf version="1.0" name="sub">\n<comp name="b"><visual name="v"><model uri="b.glb"/></visual></comp>\n</hcdf>\n'
)


def _swap_tree(tree: Tree) -> Path:
    (tree.root / "a.glb").write_bytes(MODEL_A)
    (tree.root / "b.glb").write_bytes(MODEL_B)
    (tree.root / "sub.hcdf").write_bytes(SUB_A)
    doc = tree.root / "doc.hcdf"
    doc.write_text(TEMPLATES["include"].format(uri="sub.hcdf"))
    return doc


def _rewrite_in_place(path: Path, data: bytes) -> None:
    """Same inode, new content: what an editor or a racing attacker does to an open file."""
    with open(path, "r+b") as f:
        f.truncate(0)
        f.write(data)


def _lock_by_uri(lock: Path) -> dict[str, dict]:
    return {a["uri"]: a for a in json.loads(lock.read_text())["artifacts"]}


@pytest.mark.parametrize("moment", ["after-read", "after-open-before-read"])
def test_include_changed_while_read_is_locked_as_parsed(cli, tree, monkeypatch, moment):
    """The include is swapped from A to B on disk around the tool's read of it.

    Whichever version the tool read, the lock must carry that version's digest and
    the references of that same version: never A's digest with B's references.
    """
    doc = _swap_tree(tree)
    real_open_local = resolver_module.open_local
    swapped = []

    @contextlib.contextmanager
    def racing_open_local(path, root, **kw):
        with real_open_local(path, root, **kw) as fd:
            if Path(path).name == "sub.hcdf" and moment == "after-open-before-read":
                _rewrite_in_place(Path(path), SUB_B)
                swapped.append(moment)
            yield fd
            if Path(path).name == "sub.hcdf" and moment == "after-read":
                _rewrite_in_place(Path(path), SUB_B)
                swapped.append(moment)

    monkeypatch.setattr(resolver_module, "open_local", racing_open_local)
    monkeypatch.chdir(tree.work)
    result = cli("resolve", doc, "--offline", "--cache-dir", tree.work / "cache", "--jobs", "1")
    assert swapped, "the race was not staged: resolver no longer opens includes via open_local"
    assert result.exit_code == 0, result.stderr
    arts = _lock_by_uri(tree.root / "doc.hcdf.lock")
    parsed = SUB_A if moment == "after-read" else SUB_B
    followed, not_followed = ("a.glb", "b.glb") if parsed is SUB_A else ("b.glb", "a.glb")
    assert arts["sub.hcdf"]["sha256"] == sha256(parsed)
    assert arts["sub.hcdf"]["size"] == len(parsed)
    assert followed in arts and not_followed not in arts, sorted(arts)


def test_cached_include_swapped_after_verification_is_not_parsed(cli, tree, monkeypatch):
    """A cache blob that is verified, then replaced before it is read, must not be used:
    the bytes parsed would not be the bytes whose digest is reported."""
    cache = ContentStore(tree.work / "cache")
    cache.ingest([SUB_A])
    url = "https://example.invalid/sub.hcdf"
    doc = tree.root / "doc.hcdf"
    doc.write_text(f'<hcdf version="1.0" name="r">\n<include uri="{url}" sha="{sha256(SUB_A)}"/>\n</hcdf>\n')
    evil = SUB_B.replace(b"b.glb", b"https://evil.invalid/payload.glb")
    real = ContentStore.verified_path
    swapped = []

    def racing_verified_path(self, sha, **kwargs):
        path = real(self, sha, **kwargs)
        if path is not None and sha == sha256(SUB_A):
            os.chmod(path, 0o644)
            _rewrite_in_place(path, evil)
            swapped.append(path)
        return path

    monkeypatch.setattr(ContentStore, "verified_path", racing_verified_path)
    monkeypatch.chdir(tree.work)
    before = snapshot(tree.root)
    result = cli("resolve", doc, "--offline", "--cache-dir", tree.work / "cache", "--json")
    assert swapped, "the race was not staged: resolver no longer uses ContentStore.verified_path"
    assert "evil.invalid" not in result.stdout, "references of unverified bytes were followed"
    assert result.exit_code == 3, result.stdout
    assert snapshot(tree.root) == before  # no lock


def test_cached_include_is_parsed_from_the_verified_blob(cli, tree, monkeypatch):
    """Control for the race above: untouched, the cached include resolves offline."""
    cache = ContentStore(tree.work / "cache")
    cache.ingest([SUB_A.replace(b"a.glb", b"https://example.invalid/a.glb")])
    sub = SUB_A.replace(b"a.glb", b"https://example.invalid/a.glb")
    cache.ingest([MODEL_A])
    doc = tree.root / "doc.hcdf"
    doc.write_text(
        f'<hcdf version="1.0" name="r">\n<include uri="https://example.invalid/sub.hcdf" '
        f'sha="{sha256(sub)}"/>\n</hcdf>\n'
    )
    monkeypatch.chdir(tree.work)
    result = cli("resolve", doc, "--offline", "--cache-dir", tree.work / "cache", "--json")
    # a.glb is unpinned and remote: offline it cannot be found, but the include was used.
    assert result.exit_code == 3
    arts = {a["uri"]: a for a in result.json["artifacts"]}
    assert arts["https://example.invalid/sub.hcdf"]["source"] == "cache"
    assert "https://example.invalid/a.glb" in arts


def test_pin_refuses_an_include_changed_while_pinning(cli, tree, monkeypatch):
    """pin --write computes sub.hcdf's digest from the bytes it read; if the file changed
    since, writing that digest (or its edit of sub.hcdf) would pin or clobber bytes it never
    saw: it must stop and write nothing."""
    doc = _swap_tree(tree)
    doc_before = doc.read_bytes()
    real_open_local = resolver_module.open_local
    swapped = []

    @contextlib.contextmanager
    def racing_open_local(path, root, **kw):
        with real_open_local(path, root, **kw) as fd:
            yield fd
            if Path(path).name == "sub.hcdf" and not swapped:
                _rewrite_in_place(Path(path), SUB_B)
                swapped.append(path)

    monkeypatch.setattr(resolver_module, "open_local", racing_open_local)
    monkeypatch.chdir(tree.work)
    result = cli("pin", doc, "--write", "--offline", "--cache-dir", tree.work / "cache", "--jobs", "1")
    assert swapped, "the race was not staged: resolver no longer opens includes via open_local"
    assert result.exit_code == 3, result.stderr
    assert re.search(r"^error: .*sub\.hcdf.*changed", result.stderr, re.M), result.stderr
    assert doc.read_bytes() == doc_before
    assert (tree.root / "sub.hcdf").read_bytes() == SUB_B  # the newer content is not clobbered


@pytest.mark.parametrize("case", [c for c in CASES if c != "empty-uri"])
def test_validate_does_not_follow_a_hostile_include(cli, tree, monkeypatch, case):
    """validate reads local includes (for the cross-file frame rule) through the same
    locator and opener: a hostile one is not read and is an error that says why; a
    missing one is only a warning (the upstream test-minimal example has one)."""
    setup, code, pattern = CASES[case]
    doc = _write_doc(tree, "include", setup(tree))
    monkeypatch.chdir(tree.work)
    before = snapshot(tree.work)
    with fifo_watchdog(tree.fifo) as watch:
        result = cli("validate", doc)
    assert not watch["hung"], "validate blocked on a FIFO"
    if code == "not-found":
        assert result.exit_code == 0, result.stderr  # the root itself is fine
        finding = r"warning\[include-unchecked\]"
    else:
        assert result.exit_code == 1, result.stderr
        finding = r"error\[include-refused\]"
    assert re.search(r"doc\.hcdf:2: " + finding + ": .*" + pattern, result.stderr), result.stderr
    assert SECRET not in result.stderr
    assert snapshot(tree.work) == before
