"""Hostile digests: malformed ``sha`` text, case, and content addressing in the cache.

A ``sha`` that is not 8..64 hex digits is an input error (exit 3) naming file and
line, for every command; upper case is accepted and really verified; a cache blob
is used only for a full digest and only if its bytes still hash to its name.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from pathlib import Path

import pytest

from hcdf_trust.digest import MIN_WEAK_HEX, parse_pin
from hcdf_trust.errors import MalformedDigestError
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

MODEL = b"glTF stand-in: the model the document means"
OTHER = b"glTF stand-in: a different model, also in the cache"
SUB = b'<hcdf version="1.0" name="sub"/>\n'


def _lock_remote_model(work: Path) -> None:
    """A lock file that pins the remote model of :func:`_remote_doc` to MODEL."""
    entry = {"kind": "model", "uri": URL, "url": URL, "sha256": sha256(MODEL), "size": len(MODEL)}
    write_lock(work / "root" / "doc.hcdf.lock", "doc.hcdf", [{**entry, "referenced_from": ["doc.hcdf:2"]}])


def _doc(work: Path, *, model_sha: str | None = None, include_sha: str | None = None, model_uri: str = "m.glb") -> Path:
    root = work / "root"
    root.mkdir(parents=True, exist_ok=True)
    (root / "m.glb").write_bytes(MODEL)
    (root / "sub.hcdf").write_bytes(SUB)
    msha = "" if model_sha is None else f' sha="{model_sha}"'
    isha = "" if include_sha is None else f' sha="{include_sha}"'
    doc = root / "doc.hcdf"
    doc.write_text(
        '<hcdf version="1.0" name="r">\n'
        f'<include uri="sub.hcdf"{isha}/>\n'
        f'<comp name="c"><visual name="v"><model uri="{model_uri}"{msha}/></visual></comp>\n'
        "</hcdf>\n"
    )
    return doc


# --- malformed digest text -------------------------------------------------------

MALFORMED = {
    "too-short-7": ("abc1234", r"has 7 hex digits"),
    "too-short-1": ("a", r"has 1 hex digits"),
    "too-long-65": ("a" * 65, r"has 65 hex digits"),
    "too-long-128": (sha256(MODEL) * 2, r"has 128 hex digits"),
    "non-hex-corpus-style": ("abc123xyz", r"is not a hex SHA-256 digest"),
    "non-hex-64": ("g" * 64, r"is not a hex SHA-256 digest"),
    "0x-prefix": ("0x" + sha256(MODEL)[:62], r"is not a hex SHA-256 digest"),
    "inner-space": ("abcd1234 abcd1234", r"is not a hex SHA-256 digest"),
    "fullwidth-digits": ("\uff10\uff11\uff12\uff13\uff14\uff15\uff16\uff17", r"is not a hex"),
    "arabic-indic-digits": ("\u0661\u0662\u0663\u0664\u0665\u0666\u0667\u0668", r"is not a hex"),
    "other-algorithm-prefix": ("md5:" + "0" * 32, r"is not a hex SHA-256 digest"),
    "sha256-prefix-non-hex": ("sha256:zz" + "0" * 62, r"is not a hex SHA-256 digest"),
}


@pytest.mark.parametrize("command", ["resolve", "verify", "pin"])
@pytest.mark.parametrize("where", ["model", "include"])
@pytest.mark.parametrize("case", list(MALFORMED))
def test_malformed_sha_is_an_input_error(cli, tmp_path, monkeypatch, case, where, command):
    text, pattern = MALFORMED[case]
    work = tmp_path / "work"
    doc = _doc(work, **{f"{where}_sha": text})
    if command == "verify":
        # The lock pins the well-formed sibling, so the bad sha is the only finding.
        sibling = {"model": ("include", "sub.hcdf", SUB, 2), "include": ("model", "m.glb", MODEL, 3)}
        kind, uri, data, line = sibling[where]
        write_lock(
            work / "root" / "doc.hcdf.lock",
            "doc.hcdf",
            [
                {
                    "kind": kind,
                    "uri": uri,
                    "sha256": sha256(data),
                    "size": len(data),
                    "referenced_from": [f"doc.hcdf:{line}"],
                }
            ],
        )
    monkeypatch.chdir(work)
    before = snapshot(work)
    result = cli(*command_args(command, doc, work, "--json"))
    assert result.exit_code == 3, result.stdout + result.stderr
    errors = result.json["errors"]
    bad = [e for e in errors if e["code"] == "bad-digest"]
    assert bad, errors
    line = 2 if where == "include" else 3
    assert bad[0]["file"].endswith("doc.hcdf") and bad[0]["line"] == line, bad
    assert bad[0]["actual"] == text
    assert re.search(pattern, bad[0]["message"]), bad[0]["message"]
    assert snapshot(work) == before


@pytest.mark.parametrize("text", [v[0] for v in MALFORMED.values()])
def test_parse_pin_rejects(text):
    with pytest.raises(MalformedDigestError):
        parse_pin(text, file="f.hcdf", line=7)


def test_parse_pin_accepts_the_bounds():
    full = sha256(MODEL)
    assert parse_pin(full.upper()).hex == full
    assert parse_pin(" sha256:" + full.upper() + " ").hex == full
    assert parse_pin(full[:MIN_WEAK_HEX]).is_full is False
    assert parse_pin(None) is None and parse_pin("  ") is None


# --- upper case: accepted, and really checked ------------------------------------


def test_upper_case_full_pins_are_verified_and_locked_lower_case(cli, tmp_path, monkeypatch):
    work = tmp_path / "work"
    doc = _doc(work, model_sha=sha256(MODEL).upper(), include_sha=sha256(SUB).upper())
    monkeypatch.chdir(work)
    result = cli("resolve", doc, "--offline", "--cache-dir", work / "cache", "--strict", "--json")
    assert result.exit_code == 0, result.stdout
    assert {a["uri"]: a["pin"] for a in result.json["artifacts"]} == {"m.glb": "full", "sub.hcdf": "full"}
    lock = json.loads((work / "root" / "doc.hcdf.lock").read_text())
    assert {a["uri"]: a["sha256"] for a in lock["artifacts"]} == {"m.glb": sha256(MODEL), "sub.hcdf": sha256(SUB)}
    # And verify accepts the tree it locked.
    assert cli("verify", doc, "--cache-dir", work / "cache").exit_code == 0


@pytest.mark.parametrize("where", ["model", "include"])
def test_upper_case_wrong_pin_is_a_mismatch(cli, tmp_path, monkeypatch, where):
    work = tmp_path / "work"
    doc = _doc(work, **{f"{where}_sha": sha256(OTHER).upper()})
    monkeypatch.chdir(work)
    before = snapshot(work)
    result = cli("resolve", doc, "--offline", "--cache-dir", work / "cache", "--json")
    assert result.exit_code == 1, result.stdout
    (err,) = [e for e in result.json["errors"] if e["code"] == "digest-mismatch"]
    assert err["expected"] == sha256(OTHER)
    assert err["actual"] == sha256(MODEL if where == "model" else SUB)
    assert snapshot(work) == before


def test_upper_case_weak_pin_is_weak(cli, tmp_path, monkeypatch):
    work = tmp_path / "work"
    doc = _doc(work, model_sha=sha256(MODEL)[:8].upper())
    monkeypatch.chdir(work)
    result = cli("resolve", doc, "--offline", "--no-lock", "--cache-dir", work / "cache", "--json")
    assert result.exit_code == 0
    assert {a["uri"]: a["pin"] for a in result.json["artifacts"]}["m.glb"] == "weak"
    assert any("weak pin (32 bits)" in w["message"] for w in result.json["warnings"])
    strict = cli("resolve", doc, "--offline", "--no-lock", "--cache-dir", work / "cache", "--strict", "--json")
    assert strict.exit_code == 1
    assert [e["code"] for e in strict.json["errors"]] == ["weak-pin"]


def test_upper_case_lock_digests_verify(cli, tmp_path, monkeypatch):
    work = tmp_path / "work"
    doc = _doc(work)
    write_lock(
        work / "root" / "doc.hcdf.lock",
        "doc.hcdf",
        [
            {
                "kind": "include",
                "uri": "sub.hcdf",
                "sha256": sha256(SUB).upper(),
                "size": len(SUB),
                "referenced_from": ["doc.hcdf:2"],
            },
            {
                "kind": "model",
                "uri": "m.glb",
                "sha256": sha256(MODEL).upper(),
                "size": len(MODEL),
                "referenced_from": ["doc.hcdf:3"],
            },
        ],
    )
    monkeypatch.chdir(work)
    result = cli("verify", doc, "--cache-dir", work / "cache")
    assert result.exit_code == 0, result.stderr


@pytest.mark.parametrize(
    ("lock_sha", "pattern"),
    [("abc123", r"not a full digest"), ("z" * 64, r"not a full digest"), ("a" * 65, r"not a full digest")],
)
def test_malformed_lock_digest_is_an_input_error(cli, tmp_path, monkeypatch, lock_sha, pattern):
    work = tmp_path / "work"
    doc = _doc(work)
    lock = work / "root" / "doc.hcdf.lock"
    lock.write_text(
        json.dumps(
            {
                "lock_version": 2,
                "root": "doc.hcdf",
                "artifacts": [
                    {
                        "kind": "model",
                        "uri": "m.glb",
                        "url": "m.glb",
                        "sha256": lock_sha,
                        "size": 1,
                        "referenced_from": ["doc.hcdf"],
                    }
                ],
            }
        )
    )
    monkeypatch.chdir(work)
    result = cli("verify", doc, "--cache-dir", work / "cache", "--json")
    assert result.exit_code == 3
    (err,) = result.json["errors"]
    assert err["code"] == "lock-file" and re.search(pattern, err["message"])


# --- content addressing: the cache serves bytes by digest, never by name or prefix ---

URL = "https://models.example.invalid/robot/m.glb"


def _remote_doc(work: Path, sha: str | None) -> Path:
    root = work / "root"
    root.mkdir(parents=True, exist_ok=True)
    doc = root / "doc.hcdf"
    pin = "" if sha is None else f' sha="{sha}"'
    doc.write_text(
        '<hcdf version="1.0" name="r">\n'
        f'<comp name="c"><visual name="v"><model uri="{URL}"{pin}/></visual></comp>\n'
        "</hcdf>\n"
    )
    return doc


def _blobs(cache: Path) -> set[str]:
    return {p.name for p in (cache / "sha256").rglob("*") if p.is_file()} if cache.exists() else set()


def test_full_pin_is_satisfied_by_the_blob_with_that_digest(cli, tmp_path, monkeypatch):
    """The blob came from somewhere else; content addressing makes it the right bytes."""
    work = tmp_path / "work"
    cache = work / "cache"
    ContentStore(cache).ingest([OTHER])
    doc = _remote_doc(work, sha256(OTHER))
    monkeypatch.chdir(work)
    result = cli("resolve", doc, "--offline", "--cache-dir", cache, "--json")
    assert result.exit_code == 0, result.stdout
    (art,) = result.json["artifacts"]
    assert (art["source"], art["sha256"], art["size"]) == ("cache", sha256(OTHER), len(OTHER))


@pytest.mark.parametrize("command", ["resolve", "verify"])
@pytest.mark.parametrize("tamper", ["rewritten", "other-blob-copied-under-this-name", "truncated"])
def test_tampered_cache_blob_is_detected_and_not_used(cli, tmp_path, monkeypatch, command, tamper):
    work = tmp_path / "work"
    cache = work / "cache"
    store = ContentStore(cache)
    _, blob = store.ingest([MODEL])
    store.ingest([OTHER])
    os.chmod(blob, 0o644)
    blob.write_bytes(
        {"rewritten": b"evil bytes", "other-blob-copied-under-this-name": OTHER, "truncated": MODEL[:-1]}[tamper]
    )
    doc = _remote_doc(work, sha256(MODEL))
    if command == "verify":
        _lock_remote_model(work)
    monkeypatch.chdir(work)
    blobs_before = _blobs(cache)
    args = ["--cache-dir", cache, "--json"]
    result = cli(command, doc, *(["--offline"] if command == "resolve" else []), *args)
    assert result.exit_code == 3, result.stdout
    assert [e["code"] for e in result.json["errors"]] == ["offline"], result.json["errors"]
    assert all(a["sha256"] is None for a in result.json["artifacts"])
    if command == "resolve":  # verify only reads; resolve also drops the bad blob
        assert not blob.exists(), "a blob whose content no longer matches its name was kept"
    assert _blobs(cache) <= blobs_before, "a new cache blob was written"
    assert not (work / "root" / "doc.hcdf.lock").exists() or command == "verify"


def test_verified_path_refuses_a_blob_that_does_not_match_its_name(tmp_path):
    store = ContentStore(tmp_path / "cache")
    _, blob = store.ingest([MODEL])
    assert store.verified_path(sha256(MODEL)) == blob
    os.chmod(blob, 0o644)
    blob.write_bytes(OTHER)
    assert store.verified_path(sha256(MODEL)) is None
    assert not blob.exists()


@pytest.mark.parametrize("planted", ["fifo", "directory", "symlink-loop"])
def test_non_file_planted_in_the_cache_is_not_used_and_does_not_hang(cli, tmp_path, monkeypatch, planted):
    work = tmp_path / "work"
    cache = work / "cache"
    store = ContentStore(cache)
    path = store.path_for(sha256(MODEL))
    path.parent.mkdir(parents=True)
    if planted == "fifo":
        os.mkfifo(path)
    elif planted == "directory":
        path.mkdir()
    else:
        path.symlink_to(path.name)
    doc = _remote_doc(work, sha256(MODEL))
    monkeypatch.chdir(work)
    with fifo_watchdog(path) as watch:
        assert store.verified_path(sha256(MODEL)) is None
        result = cli("resolve", doc, "--offline", "--cache-dir", cache, "--json")
    assert not watch["hung"], "a FIFO in the cache blocked the tool"
    assert result.exit_code == 3, result.stdout + result.stderr
    assert [e["code"] for e in result.json["errors"]] == ["offline"]


def test_weak_pin_never_selects_a_cache_blob(cli, tmp_path, monkeypatch):
    """Only a full digest addresses the cache: a 32-bit prefix could be a chosen collision."""
    work = tmp_path / "work"
    cache = work / "cache"
    ContentStore(cache).ingest([MODEL])
    doc = _remote_doc(work, sha256(MODEL)[:8])
    monkeypatch.chdir(work)
    result = cli("resolve", doc, "--offline", "--cache-dir", cache, "--json")
    assert result.exit_code == 3
    assert [e["code"] for e in result.json["errors"]] == ["offline"]


def test_local_file_is_hashed_even_when_the_pin_is_in_the_cache(cli, tmp_path, monkeypatch):
    """A pin that names a cached blob does not make a different local file acceptable."""
    work = tmp_path / "work"
    cache = work / "cache"
    ContentStore(cache).ingest([OTHER])
    doc = _doc(work, model_sha=sha256(OTHER))
    monkeypatch.chdir(work)
    before = snapshot(work)
    result = cli("resolve", doc, "--offline", "--cache-dir", cache, "--json")
    assert result.exit_code == 1
    (err,) = result.json["errors"]
    assert (err["code"], err["expected"], err["actual"]) == ("digest-mismatch", sha256(OTHER), sha256(MODEL))
    assert snapshot(work) == before


def test_lock_digest_addresses_the_cache_for_an_unpinned_reference(cli, tmp_path, monkeypatch):
    work = tmp_path / "work"
    cache = work / "cache"
    _, blob = ContentStore(cache).ingest([MODEL])
    doc = _remote_doc(work, None)
    _lock_remote_model(work)
    monkeypatch.chdir(work)
    assert cli("verify", doc, "--cache-dir", cache).exit_code == 0
    os.chmod(blob, 0o644)
    blob.write_bytes(OTHER)
    result = cli("verify", doc, "--cache-dir", cache, "--json")
    assert result.exit_code == 3
    assert [e["code"] for e in result.json["errors"]] == ["offline"]


def test_pin_and_lock_disagree(cli, tmp_path, monkeypatch):
    """The document pins OTHER (in the cache), the lock says MODEL: lock drift, exit 1."""
    work = tmp_path / "work"
    cache = work / "cache"
    ContentStore(cache).ingest([OTHER])
    ContentStore(cache).ingest([MODEL])
    doc = _remote_doc(work, sha256(OTHER))
    _lock_remote_model(work)
    monkeypatch.chdir(work)
    result = cli("verify", doc, "--cache-dir", cache, "--json")
    assert result.exit_code == 1, result.stdout
    codes = {e["code"] for e in result.json["errors"]}
    assert codes == {"lock-drift"}, result.json["errors"]


@pytest.mark.parametrize("bad", ["ABCD" * 16, "abc", "../" * 10 + "etc/passwd", "a" * 63 + "/"])
def test_store_path_for_accepts_only_full_lower_case_digests(tmp_path, bad):
    with pytest.raises(ValueError):
        ContentStore(tmp_path).path_for(bad)


def test_store_ingest_rejected_content_leaves_nothing(tmp_path):
    store = ContentStore(tmp_path / "cache")
    hashed, path = store.ingest([MODEL], accept=lambda h: False)
    assert path is None and hashed.sha256 == sha256(MODEL)
    assert _blobs(tmp_path / "cache") == set()
    assert list((tmp_path / "cache" / "tmp").iterdir()) == []


def test_verify_leaves_a_tampered_cache_blob_in_place(tmp_path):
    """verify writes nothing, not even cache repairs; resolve drops the bad blob."""
    store = ContentStore(tmp_path / "c")
    hashed, path = store.ingest([b"genuine"])
    path.chmod(0o644)
    path.write_bytes(b"tampered")
    assert store.verified_path(hashed.sha256, repair=False) is None
    assert path.read_bytes() == b"tampered"
    assert store.verified_path(hashed.sha256) is None
    assert not path.exists()


def test_a_directory_where_a_blob_goes_is_an_input_error(tmp_path):
    from hcdf_trust.errors import InputError

    store = ContentStore(tmp_path / "c")
    dest = store.path_for(hashlib.sha256(b"x").hexdigest())
    (dest / "sub").mkdir(parents=True)
    with pytest.raises(InputError, match="cannot store cache blob"):
        store.ingest([b"x"])
    assert list((tmp_path / "c" / "tmp").iterdir()) == []


def test_a_cache_blob_removed_after_verification_is_an_input_error(tmp_path, monkeypatch):
    """Another process may delete a blob between the check and its use: a clear error, no traceback."""
    from hcdf_trust.errors import InputError
    from hcdf_trust.include import resolver as resolver_module

    work = tmp_path
    cache = work / "cache"
    ContentStore(cache).ingest([MODEL])
    doc = _remote_doc(work, sha256(MODEL))
    real = ContentStore.verified_path

    def vanishing(self, sha, **kwargs):
        path = real(self, sha, **kwargs)
        if path is not None:
            path.unlink()
        return path

    monkeypatch.setattr(ContentStore, "verified_path", vanishing)
    res = resolver_module.resolve(doc, resolver_module.ResolveOptions(cache_dir=str(cache), offline=True))
    [err] = res.errors
    assert isinstance(err, InputError) and "vanished after it was verified" in err.message
