"""Tests written against `make mutation`'s survivors in ``hcdf_trust/include/pin.py``.

They go through the CLI and ``pin_tree`` (the race window between reading and writing
is opened by wrapping the resolve that pin calls, as tests/test_pin.py does).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path

import pytest

from .conftest import PROJECT

ARM = "assemblies/arm.hcdf"


@pytest.fixture
def robot(tmp_path, monkeypatch):
    shutil.copytree(PROJECT / "examples" / "robot", tmp_path / "robot")
    monkeypatch.chdir(tmp_path / "robot")
    return tmp_path


def pin(cli, robot, *extra):
    return cli("pin", "robot.hcdf", "--write", "--json", "--cache-dir", robot / "cache", *extra)


def race(monkeypatch, action):
    """Run ``action`` once pin has read everything, as it edits the first document: the
    files change between reading and writing."""
    from hcdf_trust.include import pin as pin_module

    real = pin_module.apply_pins
    done = []

    def racing(*args, **kwargs):
        if not done:
            done.append(action())
        return real(*args, **kwargs)

    monkeypatch.setattr(pin_module, "apply_pins", racing)


def test_every_document_changed_while_pinning_is_named(cli, robot, monkeypatch):
    """pin --write edits arm.hcdf (gripper's weak pin) and robot.hcdf (arm's sha): both are
    checked again, the second even when the first cannot be read any more."""

    def meanwhile():
        with open(ARM, "ab") as f:  # a regular file still, but over the size limit: unreadable
            f.truncate(33 << 20)
        with open("robot.hcdf", "ab") as f:
            f.write(b"<!-- edited meanwhile -->\n")

    race(monkeypatch, meanwhile)
    r = pin(cli, robot)
    assert r.exit_code == 3, r.stdout
    errors = [(e["file"], e["message"]) for e in r.json["errors"]]
    assert errors[1] == ("robot.hcdf", "changed on disk while pinning: run pin again"), errors
    assert errors[0] == (ARM, f"cannot re-read: document is over the {32 << 20}-byte limit"), errors
    assert len(errors) == 2 and r.json["wrote"] == []


def test_a_lock_changed_while_pinning_is_named_even_when_it_is_no_lock_any_more(cli, robot, monkeypatch):
    race(monkeypatch, lambda: Path("robot.hcdf.lock").write_text("not a lock at all\n"))
    r = pin(cli, robot)
    assert r.exit_code == 3, r.stdout
    assert [(e["file"], e["message"]) for e in r.json["errors"]] == [
        ("robot.hcdf.lock", "the lock file changed on disk while pinning: run pin again")
    ]


def test_a_lock_that_cannot_be_read_again_is_an_error_not_a_crash(cli, robot, monkeypatch):
    def meanwhile():  # still a regular file (the output plan takes it), but over the size limit
        with open("robot.hcdf.lock", "ab") as f:
            f.truncate(33 << 20)

    race(monkeypatch, meanwhile)
    r = pin(cli, robot)
    assert r.exit_code == 3, r.stdout
    (err,) = r.json["errors"]
    assert err["file"] == "robot.hcdf.lock" and "lock file" in err["message"] and "limit" in err["message"], err


def _tamper_chassis() -> tuple[str, str]:
    path = Path("models/chassis.glb")
    old = hashlib.sha256(path.read_bytes()).hexdigest()
    path.write_bytes(path.read_bytes() + b"!")
    return old, hashlib.sha256(path.read_bytes()).hexdigest()


def _set_lock_entry(url: str, sha256: str | None, size: int | None = None) -> None:
    """Rewrite (or with None, remove) one entry of the lock, as a person with an editor would."""
    lock = Path("robot.hcdf.lock")
    lines = lock.read_text().splitlines(keepends=True)
    out = []
    for line in lines:
        if line.startswith('{"kind"') and json.loads(line.rstrip().rstrip(","))["url"] == url:
            if sha256 is None:
                continue
            entry = json.loads(line.rstrip().rstrip(","))
            entry["sha256"], entry["size"] = sha256, size if size is not None else entry["size"]
            line = json.dumps(entry, sort_keys=True) + ("," if line.rstrip().endswith(",") else "") + "\n"
        out.append(line)
    text = "".join(out).replace(",\n]", "\n]")
    lock.write_text(text)


@pytest.mark.parametrize("lock", ["agrees", "new", "third", "none"])
def test_a_refused_sha_says_what_the_lock_held(cli, robot, lock):
    old, new = _tamper_chassis()
    size = Path("models/chassis.glb").stat().st_size
    third = "ab" * 32
    if lock == "new":
        _set_lock_entry("models/chassis.glb", new, size)
    elif lock == "third":
        _set_lock_entry("models/chassis.glb", third)
    elif lock == "none":
        _set_lock_entry("models/chassis.glb", None)
    r = pin(cli, robot)
    assert r.exit_code == 1, r.stdout
    (err,) = r.json["errors"]
    said = {
        "agrees": "the lock agrees with the sha: the file changed after it was pinned",
        "new": "the lock has the new content",
        "third": f"the lock has a third digest, {third}",
        "none": "the lock has no entry for it",
    }[lock]
    assert f"the content is not what the sha pins ({said}); " in err["message"], err["message"]
    assert (err["expected"], err["actual"]) == (old, new)


def test_one_file_reached_as_two_documents_that_need_different_edits_is_not_edited(cli, tmp_path, monkeypatch):
    """b/sub.hcdf is a link to a/sub.hcdf: its m.glb is a/m.glb from one and b/m.glb from the
    other, so the one file would need two different shas."""
    for folder, body in (("a", b"glTF-A"), ("b", b"glTF-B")):
        (tmp_path / folder).mkdir()
        (tmp_path / folder / "m.glb").write_bytes(body)
    sub = '<hcdf version="1.0" name="s"><comp name="c"><visual name="v"><model uri="m.glb"/></visual></comp></hcdf>\n'
    (tmp_path / "a" / "sub.hcdf").write_text(sub)
    (tmp_path / "b" / "sub.hcdf").symlink_to("../a/sub.hcdf")
    (tmp_path / "robot.hcdf").write_text(
        '<hcdf version="1.0" name="r">\n<include uri="a/sub.hcdf" name="x"/>\n<include uri="b/sub.hcdf" name="y"/>\n'
        "</hcdf>\n"
    )
    monkeypatch.chdir(tmp_path)
    r = cli("pin", "robot.hcdf", "--write", "--json", "--cache-dir", tmp_path / "c")
    assert r.exit_code == 3, r.stdout
    assert [(e["code"], e["file"], e["message"]) for e in r.json["errors"]] == [
        (
            "pin-edit",
            "b/sub.hcdf",
            f"{tmp_path / 'a' / 'sub.hcdf'} is reached as two documents that need different edits (a symlink?): "
            "refusing to edit it",
        )
    ]
    assert (tmp_path / "a" / "sub.hcdf").read_text() == sub and not (tmp_path / "robot.hcdf.lock").exists()


def test_a_document_in_an_encoding_pin_cannot_edit_is_refused_by_name(cli, tmp_path, monkeypatch):
    (tmp_path / "m.glb").write_bytes(b"glTF")
    text = '<?xml version="1.0" encoding="UTF-16"?>\n<hcdf version="1.0" name="r"><comp name="c">'
    text += '<visual name="v"><model uri="m.glb"/></visual></comp></hcdf>\n'
    (tmp_path / "robot.hcdf").write_bytes(text.encode("utf-16"))
    monkeypatch.chdir(tmp_path)
    r = cli("pin", "robot.hcdf", "--write", "--json", "--cache-dir", tmp_path / "c")
    assert r.exit_code == 3, r.stdout
    assert [(e["code"], e["file"], e["message"]) for e in r.json["errors"]] == [
        ("pin-edit", "robot.hcdf", "cannot edit a document encoded as UTF-16")
    ]


def test_a_remote_file_that_changed_since_it_was_locked_is_refused_not_pinned(cli, tmp_path, https_server, tls):
    """The lock's entry for a remote URL is its pin (no sha in the document): pin must find it
    under the URL, as written, and refuse the new content unless told to accept it."""
    from ._kill import hcdf, model

    old, new = os.urandom(300), os.urandom(300)
    url = https_server.add("/pkg/m.glb", old)
    doc = tmp_path / "robot.hcdf"
    doc.write_text(hcdf(model(url)))
    args = ("pin", doc, "--json", "--cache-dir", tmp_path / "c2", "--ca-bundle", tls.ca_pem)  # not the first cache
    assert cli("resolve", doc, "--cache-dir", tmp_path / "c", "--ca-bundle", tls.ca_pem).exit_code == 0
    assert url in (tmp_path / "robot.hcdf.lock").read_text()
    https_server.add("/pkg/m.glb", new)
    before = doc.read_bytes()
    r = cli(*args, "--write")
    assert r.exit_code == 1, r.stdout
    [err] = r.json["errors"]
    assert err["message"].startswith(f"{url} changed since it was locked in ")
    assert (err["expected"], err["actual"]) == (hashlib.sha256(old).hexdigest(), hashlib.sha256(new).hexdigest())
    assert doc.read_bytes() == before
    r = cli(*args, "--write", "--update", url)
    assert r.exit_code == 0, r.stdout
    assert hashlib.sha256(new).hexdigest() in doc.read_text()
