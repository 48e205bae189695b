"""resolve's less travelled paths, where a removed check or a dropped error field would pass unseen
(mutation-testing killers for include/resolver.py, second batch).

Mostly through the CLI; the two races that no CLI run can hit on purpose (a cache blob swapped
between its check and its read, a worker thread that dies of an unexpected exception) are tested on
the resolver's own helpers.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from hcdf_trust.errors import HcdfTrustError
from hcdf_trust.include import resolver

from ._kill import hcdf, include, model, sha


def _resolve(cli, doc: Path, cache: Path, *extra: str | os.PathLike[str]):
    return cli("resolve", doc, "--json", "--cache-dir", cache, *extra)


def test_a_lock_flag_naming_the_document_is_refused_and_names_the_lock(cli, tmp_path):
    (tmp_path / "m.glb").write_bytes(b"mesh")
    doc = tmp_path / "robot.hcdf"
    doc.write_text(hcdf(model("m.glb")))
    before = doc.read_bytes()
    r = _resolve(cli, doc, tmp_path / "c", "--lock", doc)
    assert r.exit_code == 3, r.stdout
    [err] = r.json["errors"]
    assert err["code"] == "output" and err["file"] is not None and Path(err["file"]).name == "robot.hcdf"
    assert "is the root document: refusing to overwrite an input" in err["message"]
    assert doc.read_bytes() == before


# -- remote references found in the cache by their lock entry ---------------------------


@pytest.fixture
def remote_locked(cli, tmp_path, https_server, tls):
    """A root whose model is remote, fetched and locked once; then the server forgets it."""
    body = os.urandom(3000)
    url = https_server.add("/m.glb", body)
    cache = tmp_path / "c"
    docs = {}
    for name, pin in (("unpinned", None), ("weak", sha(body)[:16])):
        doc = tmp_path / f"{name}.hcdf"
        doc.write_text(hcdf(model(url, pin)))
        r = _resolve(cli, doc, cache, "--ca-bundle", tls.ca_pem)
        assert r.exit_code == 0, r.stdout
        docs[name] = doc
    return {"docs": docs, "cache": cache, "body": body, "url": url}


@pytest.mark.parametrize("kind", ["unpinned", "weak"])
def test_offline_resolve_finds_a_locked_remote_file_in_the_cache(cli, remote_locked, kind):
    r = _resolve(cli, remote_locked["docs"][kind], remote_locked["cache"], "--offline")
    assert r.exit_code == 0, r.stdout
    [art] = r.json["artifacts"]
    assert art["source"] == "cache" and art["sha256"] == sha(remote_locked["body"])


def test_update_offline_takes_the_locked_content_from_the_cache(cli, remote_locked):
    """--update looks for the content as it is now, but offline that can only be the cache."""
    r = _resolve(cli, remote_locked["docs"]["unpinned"], remote_locked["cache"], "--offline", "--update")
    assert r.exit_code == 0, r.stdout
    [art] = r.json["artifacts"]
    assert art["source"] == "cache" and art["sha256"] == sha(remote_locked["body"])


def test_a_weak_pin_that_disagrees_with_the_lock_does_not_take_the_locked_blob(cli, remote_locked):
    doc = remote_locked["docs"]["weak"]
    good = sha(remote_locked["body"])
    wrong = ("0" if good[0] != "0" else "1") + good[1:16]
    doc.write_text(doc.read_text().replace(good[:16], wrong))
    r = _resolve(cli, doc, remote_locked["cache"], "--offline")
    assert r.exit_code != 0, r.stdout
    assert not any(a.get("source") == "cache" for a in r.json.get("artifacts", []))


# -- a remote include read without writing the cache -------------------------------------


def test_pin_without_write_reads_a_remote_include_and_its_references(cli, tmp_path, https_server, tls):
    """`pin` (no --write) fetches into memory, not into the cache: the include's own
    references must still be found in the bytes it fetched."""
    mesh = os.urandom(500)
    mesh_url = https_server.add("/m.glb", mesh)
    sub_url = https_server.add("/sub.hcdf", hcdf(model(mesh_url), name="sub").encode())
    doc = tmp_path / "robot.hcdf"
    doc.write_text(hcdf(include(sub_url)))
    cache = tmp_path / "c"
    r = cli("pin", doc, "--json", "--cache-dir", cache, "--ca-bundle", tls.ca_pem)
    assert r.exit_code == 0, r.stdout
    locked = {c["url"]: c["new"] for c in r.json["lock_changes"]}
    assert locked[mesh_url] == sha(mesh)  # found inside the fetched include
    assert sub_url in locked
    assert not (cache / "sha256").exists() or not any(p.is_file() for p in (cache / "sha256").rglob("*"))


# -- the races, on the helpers themselves -------------------------------------------------


def test_a_cache_blob_changed_after_its_check_is_refused_naming_the_reference(tmp_path):
    blob = tmp_path / "blob"
    blob.write_bytes(b"<hcdf/>")
    with pytest.raises(HcdfTrustError) as info:
        resolver._read_blob(blob, sha(b"something else"), file="robot.hcdf", line=7, url="https://h/x.hcdf")
    err = info.value
    assert (err.file, err.line, err.url) == ("robot.hcdf", 7, "https://h/x.hcdf")
    assert "changed after it was verified" in str(err)


def test_a_cache_blob_gone_before_its_read_is_refused_naming_the_reference(tmp_path):
    with pytest.raises(HcdfTrustError) as info:
        resolver._read_blob(tmp_path / "gone", sha(b"x"), file="robot.hcdf", line=7, url="https://h/x.hcdf")
    assert (info.value.file, info.value.line) == ("robot.hcdf", 7)


def test_an_oversize_cache_blob_is_refused_naming_its_url(tmp_path):
    blob = tmp_path / "blob"
    with blob.open("wb") as f:
        f.truncate(resolver.MAX_DOCUMENT_BYTES + 1)  # sparse: refused on its size, never read
    with pytest.raises(HcdfTrustError) as info:
        resolver._read_blob(blob, sha(b"x"), file="robot.hcdf", line=7, url="https://h/x.hcdf")
    assert info.value.file == "https://h/x.hcdf" and "limit" in str(info.value)


def test_an_unexpected_exception_in_a_worker_thread_is_raised_in_the_caller():
    def boom(task):
        raise RuntimeError(f"bug on {task}")

    workers = resolver._Workers(boom, ["a", "b", "c"], 1)  # type: ignore[arg-type]
    workers.join()
    with pytest.raises(RuntimeError, match="bug on a"):
        workers.reraise()


def test_worker_threads_end_quietly(tmp_path, https_server, tls):
    """Every pool (network fetches, large local files) runs out of work without a
    thread dying of it: no traceback on stderr, in a real process."""
    import subprocess
    import sys

    refs = []
    for i in range(3):
        data = os.urandom(resolver.PARALLEL_MIN_BYTES + i)
        (tmp_path / f"big{i}.glb").write_bytes(data)
        refs.append(model(f"big{i}.glb", sha(data), name=f"b{i}"))
        small = os.urandom(100 + i)
        refs.append(model(https_server.add(f"/s{i}.glb", small), sha(small), name=f"s{i}"))
    doc = tmp_path / "robot.hcdf"
    doc.write_text(hcdf("\n".join(refs)))
    proc = subprocess.run(
        [sys.executable, "-m", "hcdf_trust.cli", "resolve", str(doc), "--jobs", "4", "--no-lock",
         "--ca-bundle", str(tls.ca_pem), "--cache-dir", str(tmp_path / "c")],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr and "Exception in thread" not in proc.stderr


def test_locked_names_an_unpinned_reference_the_lock_does_not_know(cli, tmp_path):
    (tmp_path / "m.glb").write_bytes(b"abc")
    (tmp_path / "n.glb").write_bytes(b"xyz")
    doc = tmp_path / "robot.hcdf"
    doc.write_text(hcdf(model("m.glb")))
    assert _resolve(cli, doc, tmp_path / "c").exit_code == 0
    doc.write_text(hcdf(model("m.glb") + "\n" + model("n.glb", name="d")))
    r = _resolve(cli, doc, tmp_path / "c", "--locked")
    assert r.exit_code == 1, r.stdout
    [err] = [e for e in r.json["errors"] if e["code"] == "unpinned"]
    assert Path(err["file"]).name == "robot.hcdf" and err["line"] == 4 and Path(err["url"]).name == "n.glb"
    assert err["expected"] == "a sha attribute or a lock entry" and err["actual"] == sha(b"xyz")


def test_locked_refetches_a_locked_remote_file_into_an_empty_cache(cli, remote_locked, tmp_path, tls):
    """Under --locked the lock is the pin: the fetched bytes are compared with the entry's
    digest and size, and the ones that match are taken."""
    doc, cache = remote_locked["docs"]["unpinned"], tmp_path / "new-cache"
    r = _resolve(cli, doc, cache, "--locked", "--ca-bundle", tls.ca_pem)
    assert r.exit_code == 0, r.stdout
    [art] = r.json["artifacts"]
    assert art["source"] == "network" and art["sha256"] == sha(remote_locked["body"])
    r = _resolve(cli, doc, cache, "--locked", "--offline")  # and it was kept in the cache
    assert r.exit_code == 0, r.stdout
    assert r.json["artifacts"][0]["source"] == "cache"


def test_write_lock_names_the_lock_file_when_it_cannot_be_written(tmp_path):
    from hcdf_trust.outputs import OutputError

    (tmp_path / "m.glb").write_bytes(b"abc")
    doc = tmp_path / "robot.hcdf"
    doc.write_text(hcdf(model("m.glb")))
    (tmp_path / "afile").write_bytes(b"")
    res = resolver.resolve(doc, resolver.ResolveOptions(lock_path=tmp_path / "afile" / "x.lock", offline=True))
    assert res.ok, res.errors
    with pytest.raises(OutputError, match=r": lock file .*x\.lock: .*afile is not a folder"):
        res.write_lock()


def test_strict_names_a_weak_pin_with_every_field(cli, tmp_path):
    (tmp_path / "m.glb").write_bytes(b"abc")
    doc = tmp_path / "robot.hcdf"
    doc.write_text(hcdf(model("m.glb", sha(b"abc")[:16])))
    r = _resolve(cli, doc, tmp_path / "c", "--strict")
    assert r.exit_code == 1, r.stdout
    [err] = r.json["errors"]
    assert err["code"] == "weak-pin" and Path(err["file"]).name == "robot.hcdf" and err["line"] == 3
    assert Path(err["url"]).name == "m.glb"
    assert err["expected"] == "a full 64-digit SHA-256" and err["actual"] == sha(b"abc")[:16]


def test_update_of_an_unknown_name_says_what_it_expected(cli, tmp_path):
    (tmp_path / "m.glb").write_bytes(b"abc")
    doc = tmp_path / "robot.hcdf"
    doc.write_text(hcdf(model("m.glb")))
    assert _resolve(cli, doc, tmp_path / "c").exit_code == 0
    r = _resolve(cli, doc, tmp_path / "c", "--update", "nope.glb")
    assert r.exit_code == 3, r.stdout
    [err] = r.json["errors"]
    assert err["code"] == "update-unknown"
    assert err["expected"] == "a uri as written, a lock url, a URL or a path of the tree"
    assert err["actual"] == "nope.glb" and Path(err["file"]).name == "robot.hcdf.lock"


def test_update_names_a_file_by_its_path_or_url(cli, tmp_path, monkeypatch):
    """resolve reads --update names as pin does: a path (as the shell names it) or the URL."""
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "m.glb").write_bytes(b"abc")
    doc = tmp_path / "robot.hcdf"
    doc.write_text(hcdf(model("sub/m.glb")))
    assert _resolve(cli, doc, tmp_path / "c").exit_code == 0
    (tmp_path / "sub" / "m.glb").write_bytes(b"abcd")
    monkeypatch.chdir(tmp_path)
    for name in ("m.glb", "sub/../m.glb"):  # neither the uri as written, nor a lock url, nor its path
        r = _resolve(cli, doc, tmp_path / "c", "--update", name)
        assert r.exit_code != 0 and "update-unknown" in {e["code"] for e in r.json["errors"]}, r.stdout
    r = _resolve(cli, doc, tmp_path / "c", "--update", (tmp_path / "sub" / "m.glb").as_uri())
    assert r.exit_code == 0, r.stdout
    (tmp_path / "sub" / "m.glb").write_bytes(b"abcde")
    monkeypatch.chdir(tmp_path / "sub")
    r = _resolve(cli, doc, tmp_path / "c", "--update", "./m.glb")  # its path, from where the shell is
    assert r.exit_code == 0, r.stdout


def test_two_distinct_include_cycles_are_both_reported(cli, tmp_path):
    for a, b in (("a", "a2"), ("b", "b2")):
        (tmp_path / f"{a}.hcdf").write_text(hcdf(include(f"{b}.hcdf", name="x"), name=a))
        (tmp_path / f"{b}.hcdf").write_text(hcdf(include(f"{a}.hcdf", name="y"), name=b))
    doc = tmp_path / "robot.hcdf"
    doc.write_text(hcdf(include("a.hcdf", name="a") + "\n" + include("b.hcdf", name="b")))
    r = _resolve(cli, doc, tmp_path / "c", "--no-lock")
    assert r.exit_code != 0, r.stdout
    cycles = sorted(e["message"] for e in r.json["errors"] if e["code"] == "include-cycle")
    assert len(cycles) == 2 and "a2.hcdf" in cycles[0] and "b2.hcdf" in cycles[1], cycles


@pytest.mark.parametrize("name", ["sub/real.hcdf", "sub\\\\real.hcdf", "..", "."])
def test_a_link_stub_is_never_followed_out_of_its_folder(cli, tmp_path, name):
    (tmp_path / "sub").mkdir()
    (tmp_path / "m.glb").write_bytes(b"m")
    (tmp_path / "sub" / "real.hcdf").write_text(hcdf(model("../m.glb")))
    stub = tmp_path / "robot.hcdf"
    stub.write_text(name.replace("\\\\", "\\") + "\n")
    r = _resolve(cli, stub, tmp_path / "c", "--no-lock")
    assert r.exit_code == 3, r.stdout  # the stub itself is the document: not XML
    assert r.json["errors"][0]["code"] in ("xml", "not-hcdf"), r.json["errors"]


def test_a_link_stub_that_is_not_utf8_is_just_not_a_document(cli, tmp_path):
    stub = tmp_path / "robot.hcdf"
    stub.write_bytes(b"\xff\xfe-not-a-name\n")
    r = _resolve(cli, stub, tmp_path / "c", "--no-lock")
    assert r.exit_code == 3, r.stdout
    assert r.json["errors"][0]["code"] in ("xml", "not-hcdf")


@pytest.mark.parametrize("uri", ["ftp://h/x.glb", "data:,x", "mailto:x@h"])
def test_a_reference_of_another_scheme_says_what_is_allowed(cli, tmp_path, uri):
    doc = tmp_path / "robot.hcdf"
    doc.write_text(hcdf(model(uri)))
    r = _resolve(cli, doc, tmp_path / "c", "--no-lock")
    assert r.exit_code == 3, r.stdout
    [err] = r.json["errors"]
    assert err["expected"] == "a relative path or an https URL", err


def test_drift_of_an_unpinned_file_says_how_to_accept_it(cli, tmp_path):
    (tmp_path / "m.glb").write_bytes(b"old")
    doc = tmp_path / "robot.hcdf"
    doc.write_text(hcdf(model("m.glb")))
    assert _resolve(cli, doc, tmp_path / "c").exit_code == 0
    (tmp_path / "m.glb").write_bytes(b"new")
    r = _resolve(cli, doc, tmp_path / "c")
    assert r.exit_code == 1, r.stdout
    [err] = r.json["errors"]
    assert "`resolve --update m.glb` accepts the new content" in err["message"], err


def test_folder_descriptors_stay_open_while_a_worker_still_runs(tmp_path):
    """After an interrupt the run is closed with workers still alive: their folder
    descriptors must not be closed (and their numbers reused) under them."""
    import threading

    (tmp_path / "m.glb").write_bytes(b"m")
    run = resolver._Run(resolver.ResolveOptions(), on_start=None, on_progress=None)
    run.folders.hash(str(tmp_path / "m.glb"), tmp_path)
    release = threading.Event()
    workers = resolver._Workers(lambda _task: release.wait(30), ["x"], 1)  # type: ignore[arg-type,return-value]
    run._pools.append(workers)
    run.close()
    assert run.folders.hash(str(tmp_path / "m.glb"), tmp_path).sha256 == sha(b"m")
    assert [fd for fd in run.folders._folders.values() if fd is not None]  # still open
    release.set()
    workers.join()
    run.close()
    assert run.folders._folders == {}
