"""Mutation killers for how a registry client is opened and refreshed (hcdf_trust/registry/client.py:
``RegistryClient.__init__``, ``open``, ``_cached_roles``, ``refresh``; see tests/MUTATION.md).

Through ``registry verify --json``: the messages of a trusted root or a site that cannot be used,
where the client keeps its state when ``--cache-dir`` is given, and that a client's memory of a
top-level target (a core schema) is kept across runs like a domain's.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests._registry import PASSPHRASE, Registry, build
from tests.servers import LoopbackServer


@pytest.fixture(autouse=True)
def _passphrase(monkeypatch):
    monkeypatch.setenv("HCDF_TRUST_PASSPHRASE", PASSPHRASE)


@pytest.fixture
def reg(tmp_path, cli) -> Registry:
    return build(tmp_path / "reg", cli)


def _errors(reg: Registry, site: object, root: object, cache: Path, code: int) -> list[dict[str, object]]:
    res = reg.cli("registry", "verify", site, "--trusted-root", root, "--cache-dir", cache, "--json")
    assert res.exit_code == code, res.stdout + res.stderr
    return [{k: v for k, v in e.items() if v is not None} for e in res.json["errors"]]


def test_a_trusted_root_with_a_duplicate_key_is_refused_by_name(reg, tmp_path):
    root = tmp_path / "root.json"
    text = reg.root_json.read_text()
    root.write_text('{"signed": {}, ' + text.lstrip()[1:])  # two "signed" keys, the forged one first
    [err] = _errors(reg, reg.site, root, tmp_path / "c", 3)
    assert err["message"].startswith("the trusted root is not valid TUF root metadata: the trusted root: ")
    assert "key 'signed' appears twice" in err["message"] and err["code"] == "input"


def test_a_trusted_root_that_is_json_but_not_root_metadata_is_refused_by_name(reg, tmp_path):
    root = tmp_path / "root.json"
    root.write_text('{"signed": {"_type": "root"}, "signatures": []}')
    [err] = _errors(reg, reg.site, root, tmp_path / "c", 3)
    assert err["message"].startswith("the trusted root is not valid TUF root metadata: ")
    assert err["code"] == "input"


def test_a_trusted_root_over_the_limit_is_not_read(reg, tmp_path):
    root = tmp_path / "root.json"
    data = reg.root_json.read_bytes()
    root.write_bytes(data.rstrip() + b" " * (512_000 - len(data.rstrip())))
    assert len(root.read_bytes()) == 512_000
    assert _errors(reg, reg.site, root, tmp_path / "c", 0) == []  # at the limit: read
    root.write_bytes(root.read_bytes() + b" ")
    [err] = _errors(reg, reg.site, root, tmp_path / "c2", 3)
    assert (err["message"], err["file"]) == ("trusted root is over the 512000-byte limit", str(root))
    assert not (tmp_path / "c2").exists()  # refused before the client made its folder


def test_a_missing_site_folder_is_named(reg, tmp_path):
    missing = tmp_path / "no-site"
    [err] = _errors(reg, missing, reg.root_json, tmp_path / "c", 3)
    assert (err["message"], err["file"]) == (f"{missing}: no such registry site folder", str(missing))
    regular = tmp_path / "file-site"
    regular.write_text("x")
    [err] = _errors(reg, regular, reg.root_json, tmp_path / "c", 3)
    assert (err["message"], err["file"]) == (f"{regular}: no such registry site folder", str(regular))


@pytest.mark.parametrize("site", ["ftp://127.0.0.1/site", "oci+x://127.0.0.1/site"])
def test_a_site_url_of_another_scheme_is_refused_by_name(reg, tmp_path, site):
    [err] = _errors(reg, site, reg.root_json, tmp_path / "c", 3)
    assert (err["message"], err["file"]) == (f"{site}: a registry is an http(s) URL or a folder", site)


def test_a_cache_dir_whose_parents_do_not_exist_is_made_and_reused(reg, tmp_path):
    cache = tmp_path / "a" / "b" / "cache"
    for _ in range(2):  # the second run finds the folders made by the first
        assert _errors(reg, reg.site, reg.root_json, cache, 0) == []
    assert (cache / "metadata" / "timestamp.json").is_file()
    assert (cache / "targets").is_dir()


def test_a_site_url_with_a_trailing_slash_is_the_same_site(reg, tmp_path):
    with LoopbackServer(root=reg.site) as srv:
        assert _errors(reg, srv.base.rstrip("/") + "/", reg.root_json, tmp_path / "c", 0) == []
        assert _errors(reg, srv.base.rstrip("/"), reg.root_json, tmp_path / "c", 0) == []


def test_a_stale_timestamp_is_a_freeze_attack_on_the_top_level_metadata(reg, tmp_path):
    import datetime as dt

    from tuf.api.metadata import Metadata

    meta = reg.site / "metadata"
    version = Metadata.from_file(str(meta / "timestamp.json")).signed.snapshot_meta.version
    snap = Metadata.from_file(str(meta / f"{version}.snapshot.json"))
    reg.resign_snapshot_timestamp(snap, ts_expires=dt.datetime(2001, 1, 1, tzinfo=dt.UTC))
    [err] = _errors(reg, reg.site, reg.root_json, tmp_path / "c", 1)
    assert err["message"].startswith("freeze attack or stale mirror: top-level metadata: expired metadata ("), err


def _core_schema_seen(reg, cache: Path) -> Path:
    """The core schema hcdf 1.0 published, and seen once by a client caching in ``cache``."""
    from tests.conftest import HCDFORMAT

    reg.run("add", reg.src, "--core", "hcdf", "--version", "1.0", "--schema", HCDFORMAT / "hcdf.xsd",
            "--content", reg.content)  # fmt: skip
    reg.publish()
    assert _errors(reg, reg.site, reg.root_json, cache, 0) == []
    return cache


def _replace_core_schema(reg, cache: Path) -> dict:
    """Top-level targets re-signed with other bytes for that schema: the client refuses it."""
    evil = b"<xs:schema xmlns:xs='http://www.w3.org/2001/XMLSchema'/>"

    def replace(signed):
        signed.targets["schemas/hcdf/1.0.xsd"] = reg.put_target("schemas/hcdf/1.0.xsd", evil)

    reg.forge("targets", replace, signer=reg.top_signer("targets"))
    [err] = _errors(reg, reg.site, reg.root_json, cache, 1)
    assert err["message"] == (
        "replaced published version: schemas/hcdf/1.0.xsd (targets) changed content since this client last saw it"
    )
    return err


def test_a_replaced_core_schema_is_refused_on_the_next_run(reg, tmp_path):
    """Top-level targets is remembered like a domain role: a version seen once keeps its content."""
    cache = _core_schema_seen(reg, tmp_path / "c")
    err = _replace_core_schema(reg, cache)
    # the client keeps trusting what it saw: the next run refuses again
    [again] = _errors(reg, reg.site, reg.root_json, cache, 1)
    assert again["message"] == err["message"]
    assert json.loads((cache / "metadata" / "targets.json").read_text())["signed"]["targets"]["schemas/hcdf/1.0.xsd"]


def test_site_metadata_with_a_duplicate_key_is_named_by_file(reg, tmp_path):
    """``check_metadata`` on a download: the file (as the URL names it) and the parser's reason,
    whole. python-tuf alone would keep the last "signed" and verify."""
    path = reg.site / "metadata" / "timestamp.json"
    doc = json.loads(path.read_bytes())
    evil = json.dumps({**doc["signed"], "version": 999})
    path.write_text(path.read_text().replace('"signed":', f'"signed": {evil}, "signed":', 1))
    [err] = _errors(reg, reg.site, reg.root_json, tmp_path / "c", 1)
    assert (err["file"], err["code"]) == ("timestamp.json", "registry-attack"), err
    assert err["message"] == (
        "ambiguous or malformed metadata: timestamp.json: key 'signed' appears twice in the object at "
        "(the document) (parsers disagree on which one counts)"
    ), err


def test_site_metadata_that_is_not_json_is_named_by_file_and_line(reg, tmp_path):
    path = reg.site / "metadata" / "timestamp.json"
    path.write_text('{\n"signed":\n  {,\n')
    [err] = _errors(reg, reg.site, reg.root_json, tmp_path / "c", 1)
    assert (err["file"], err["line"], err["code"]) == ("timestamp.json", 3, "registry-attack"), err
    assert err["message"] == (
        "ambiguous or malformed metadata: timestamp.json is not JSON: "
        "Expecting property name enclosed in double quotes (column 4)"
    ), err


def test_a_client_cache_file_that_cannot_be_written_is_named_with_the_cache(reg, tmp_path):
    """The metadata python-tuf writes goes through the output planner, whose refusal names the file
    as the client's cache (a folder where timestamp.json belongs)."""
    cache = tmp_path / "c"
    blocked = cache / "metadata" / "timestamp.json"
    blocked.mkdir(parents=True)
    [err] = _errors(reg, reg.site, reg.root_json, cache, 3)
    assert (err["message"], err["file"], err["code"]) == (
        f"the registry client cache {blocked} is a directory",
        str(blocked),
        "output",
    )


def test_an_unreadable_cached_role_does_not_make_the_client_forget_the_others(reg, tmp_path):
    """A cached role file that fails the strict reader is skipped, and the client still remembers
    every other role it trusted: a core schema replaced in top-level targets is refused although an
    ambiguous cached file comes before ``targets.json`` in the folder's listing order."""
    import os

    cache = _core_schema_seen(reg, tmp_path / "c")
    meta = cache / "metadata"
    # ambiguous role files until one is listed before targets.json (the client reads the folder in
    # that order, os.scandir's, which the file system decides)
    for n in range(200):
        (meta / f"broken-{n}.json").write_text('{"signed": {}, "signed": {}}')
        order = [e.name for e in os.scandir(meta)]
        if any(name.startswith("broken-") for name in order[: order.index("targets.json")]):
            break
    else:
        pytest.skip("no file was listed before targets.json")
    _replace_core_schema(reg, cache)
