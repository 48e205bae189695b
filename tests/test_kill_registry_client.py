"""Mutation killers for hcdf_trust/registry/client.py (see tests/MUTATION.md).

Each test pins behaviour a surviving mutant changed: where a client keeps its state when no
``--cache-dir`` is given, the order of versions, and the messages of the failures the
attack table does not name. Through the CLI, or the module's public functions.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from hcdf_trust.registry.client import latest
from tests._registry import PASSPHRASE, Registry, build
from tests.servers import LoopbackServer


@pytest.fixture(autouse=True)
def _passphrase(monkeypatch):
    monkeypatch.setenv("HCDF_TRUST_PASSPHRASE", PASSPHRASE)


@pytest.fixture
def reg(tmp_path, cli) -> Registry:
    return build(tmp_path / "reg", cli)


def _verify(reg: Registry, site: str | Path, *extra: object) -> object:
    """``registry verify SITE`` with the registry's root and no ``--cache-dir``: the default folder."""
    res = reg.cli("registry", "verify", site, "--trusted-root", reg.root_json, *extra)
    assert res.exit_code == 0, res.stderr
    return res


def _client_folders(cache: Path) -> list[Path]:
    """The per-site client folders under a cache home (each holds the trusted metadata)."""
    top = cache / "hcdf-trust" / "registry"
    found = sorted(top.iterdir()) if top.is_dir() else []
    for folder in found:
        assert (folder / "metadata" / "timestamp.json").is_file(), folder
    return found


# --- default_cache_dir: one folder per site and trusted root, under the user's cache --------


def test_without_cache_dir_the_client_keeps_its_state_under_xdg_cache_home(reg, tmp_path, monkeypatch):
    home, xdg = tmp_path / "home", tmp_path / "xdg"
    home.mkdir()
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.setenv("XDG_CACHE_HOME", str(xdg))
    _verify(reg, reg.site)
    assert len(_client_folders(xdg)) == 1
    assert list(home.iterdir()) == []  # nothing in ~/.cache when XDG_CACHE_HOME is set


def test_without_xdg_cache_home_the_client_keeps_its_state_in_home_cache(reg, tmp_path, monkeypatch):
    home = tmp_path / "home"
    home.mkdir()
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.delenv("XDG_CACHE_HOME")
    _verify(reg, reg.site)
    assert len(_client_folders(home / ".cache")) == 1
    assert [p.name for p in home.iterdir()] == [".cache"]


def test_a_site_folder_named_three_ways_shares_one_client_folder(reg, tmp_path, monkeypatch):
    xdg = tmp_path / "xdg"
    monkeypatch.setenv("XDG_CACHE_HOME", str(xdg))
    link = tmp_path / "site-link"
    link.symlink_to(reg.site)
    _verify(reg, reg.site)
    _verify(reg, link)
    monkeypatch.chdir(reg.base)
    _verify(reg, "site")
    assert len(_client_folders(xdg)) == 1


def test_the_default_client_folder_is_named_by_the_site_and_root_it_trusts(reg, tmp_path, monkeypatch):
    """The folder is the client's memory (what it trusted last): its name must stay the same from
    one release to the next, or an upgrade silently forgets it. Computed here independently: the
    first 24 hex digits of SHA-256 over the site's real path, a NUL and the trusted root's bytes."""
    import hashlib
    import os

    xdg = tmp_path / "xdg"
    monkeypatch.setenv("XDG_CACHE_HOME", str(xdg))
    _verify(reg, reg.site)
    key = hashlib.sha256(os.path.realpath(reg.site).encode() + b"\0" + reg.root_json.read_bytes()).hexdigest()
    assert _client_folders(xdg) == [xdg / "hcdf-trust" / "registry" / key[:24]]


def test_another_site_or_another_trusted_root_gets_its_own_client_folder(reg, tmp_path, monkeypatch):
    xdg = tmp_path / "xdg"
    monkeypatch.setenv("XDG_CACHE_HOME", str(xdg))
    _verify(reg, reg.site)
    copy = tmp_path / "copy"
    shutil.copytree(reg.site, copy)
    _verify(reg, copy)
    assert len(_client_folders(xdg)) == 2
    # the same site trusted from a copy of its root with other bytes (same signatures, one more newline)
    other_root = tmp_path / "root.json"
    other_root.write_bytes(reg.root_json.read_bytes() + b"\n")
    res = reg.cli("registry", "verify", reg.site, "--trusted-root", other_root)
    assert res.exit_code == 0, res.stderr
    assert len(_client_folders(xdg)) == 3


def test_a_registry_url_is_one_client_folder_whatever_the_working_folder(reg, tmp_path, monkeypatch):
    xdg = tmp_path / "xdg"
    monkeypatch.setenv("XDG_CACHE_HOME", str(xdg))
    with LoopbackServer(root=reg.site) as srv:
        for cwd in (tmp_path, reg.base):
            monkeypatch.chdir(cwd)
            _verify(reg, srv.base)
    assert len(_client_folders(xdg)) == 1
    assert not (tmp_path / "http:").exists() and not (reg.base / "http:").exists()


def test_a_client_without_cache_dir_remembers_what_it_trusted(reg, tmp_path, monkeypatch):
    """The default folder is the client's memory: a rollback to a timestamp it saw replaced is refused."""
    from tests._registry import IEEE_XSD

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    meta = reg.site / "metadata"
    old_ts = (meta / "timestamp.json").read_bytes()
    reg.add_domain("org.ros2", "1.1", IEEE_XSD)
    reg.publish()
    _verify(reg, reg.site)
    (meta / "timestamp.json").write_bytes(old_ts)
    res = reg.cli("registry", "verify", reg.site, "--trusted-root", reg.root_json)
    assert res.exit_code == 1 and "rollback attack" in res.stderr, res.stderr


# --- latest: numeric order of dotted versions ---------------------------------------------


@pytest.mark.parametrize(
    ("versions", "want"),
    [
        (["1.0"], "1.0"),
        (["1.2", "1.10", "1.9"], "1.10"),  # text order would pick 1.9
        (["10.0", "2.0", "9.9"], "10.0"),
        (["1.0.1", "1.0", "0.99"], "1.0.1"),
    ],
)
def test_latest_is_the_highest_version_in_numeric_order(versions, want):
    assert latest(dict.fromkeys(versions, object())) == want


# --- messages of the failures the attack table does not name ------------------------------


def test_a_site_folder_without_timestamp_is_exit_3_naming_the_missing_file(reg):
    (reg.site / "metadata" / "timestamp.json").unlink()
    res = reg.verify()
    assert res.exit_code == 3, res.stderr
    assert "top-level metadata: HTTP 404" in res.stderr, res.stderr
    assert f"{reg.site / 'metadata' / 'timestamp.json'}: not found" in res.stderr, res.stderr


def test_a_site_url_without_timestamp_is_exit_3_naming_the_status(reg):
    (reg.site / "metadata" / "timestamp.json").unlink()
    with LoopbackServer(root=reg.site) as srv:
        res = reg.verify(srv.base)
    assert res.exit_code == 3, res.stderr
    assert "top-level metadata: HTTP 404" in res.stderr, res.stderr


def test_metadata_that_is_not_tuf_metadata_is_exit_1_naming_the_role_set(reg):
    (reg.site / "metadata" / "timestamp.json").write_bytes(b"{}")
    res = reg.verify()
    assert res.exit_code == 1, res.stderr
    assert "the registry's metadata does not verify: top-level metadata:" in res.stderr, res.stderr
    assert "Traceback" not in res.stderr


# --- what the client reads from the signed roles: domains, versions, profiles and schemas --


def _versions_json(reg: Registry, tmp_path: Path, *what: str) -> object:
    return reg.cli("registry", "fetch", *what, "--from", reg.site, "--trusted-root", reg.root_json,
                   "--cache-dir", reg.base / "client", "-o", tmp_path / "out", "--json")  # fmt: skip


def test_an_unregistered_domain_is_not_found_naming_the_site(reg, tmp_path):
    res = _versions_json(reg, tmp_path, "org.nope")
    assert res.exit_code == 3, res.stdout
    [err] = res.json["errors"]
    assert (err["message"], err["url"]) == ("org.nope is not a registered domain", str(reg.site))


def test_a_domain_role_listing_paths_outside_its_folder_does_not_gain_versions(reg, tmp_path):
    """A bare ``2.0.xsd`` and a nested ``extensions/org.ros2/x/3.0.xsd`` are not versions of org.ros2."""

    def add(signed):
        for path in ("2.0.xsd", "extensions/org.ros2/x/3.0.xsd"):
            signed.targets[path] = reg.put_target(path, b"<evil/>")

    reg.forge("org.ros2", add, signer=reg.owner_signer("org.ros2"))
    res = _versions_json(reg, tmp_path, "org.ros2")
    assert res.exit_code == 0, res.stderr
    assert res.json["version"] == "1.0"
    assert (tmp_path / "out").read_bytes() == reg.target_file("extensions/org.ros2/1.0.xsd").read_bytes()


def test_top_level_paths_outside_profiles_and_schemas_are_not_artifacts(reg, tmp_path):
    """``stray/evil/1.0.xsd`` and a two-part ``schemas/evil.xsd`` name no core schema."""

    def add(signed):
        for path in ("stray/evil/1.0.xsd", "schemas/evil.xsd", "profiles/evil.streams.xml"):
            signed.targets[path] = reg.put_target(path, b"<evil/>")

    reg.forge("targets", add, signer=reg.top_signer("targets"))
    for kind in ("schema", "profile"):
        res = _versions_json(reg, tmp_path, kind, "evil")
        assert res.exit_code == 3 and res.json["errors"][0]["message"] == f"no {kind} evil in the registry", res.stdout
    res = reg.cli("registry", "verify", reg.site, "--trusted-root", reg.root_json, "--json")
    assert res.exit_code == 0, res.stderr
    assert (res.json["roles"], res.json["targets"]) == (2, 3)  # two domain schemas and the profile


def test_only_extensions_domain_patterns_of_top_level_targets_are_domains(reg, tmp_path):
    """A delegation for ``profiles/evil/*`` or ``profiles/*`` registers no domain."""
    from tuf.api.metadata import DelegatedRole

    def add(signed):
        for name, pattern in (("evil", "profiles/evil/*"), ("evil2", "profiles/*")):
            signed.delegations.roles[name] = DelegatedRole(name, [], 1, False, paths=[pattern])

    reg.forge("targets", add, signer=reg.top_signer("targets"))
    res = reg.cli("registry", "verify", reg.site, "--trusted-root", reg.root_json, "--json")
    assert res.exit_code == 0, res.stderr
    assert res.json["roles"] == 2
    res = _versions_json(reg, tmp_path, "evil")
    assert res.exit_code == 3 and res.json["errors"][0]["message"] == "evil is not a registered domain", res.stdout


def test_top_level_targets_without_delegations_has_no_domains(reg, tmp_path):
    def drop(signed):
        signed.delegations = None

    reg.forge("targets", drop, signer=reg.top_signer("targets"))
    res = reg.cli("registry", "verify", reg.site, "--trusted-root", reg.root_json, "--json")
    assert res.exit_code == 0, res.stderr
    assert (res.json["roles"], res.json["targets"]) == (0, 1)  # the profile only
    res = _versions_json(reg, tmp_path, "org.ros2")
    assert res.exit_code == 3, res.stdout
    assert res.json["errors"][0]["message"] == "org.ros2 is not a registered domain"


def test_a_replaced_version_names_both_contents_and_the_site(reg, tmp_path):
    import hashlib

    from tests._registry import IEEE_XSD

    assert reg.verify().exit_code == 0  # the client has seen org.ros2 1.0
    was = reg.target_file("extensions/org.ros2/1.0.xsd").read_bytes()
    evil = IEEE_XSD.read_bytes()

    def replace(signed):
        signed.targets["extensions/org.ros2/1.0.xsd"] = reg.put_target("extensions/org.ros2/1.0.xsd", evil)

    reg.forge("org.ros2", replace, signer=reg.owner_signer("org.ros2"))
    res = _versions_json(reg, tmp_path, "org.ros2@1.0")
    assert res.exit_code == 1, res.stdout
    [err] = res.json["errors"]
    assert err["message"] == (
        "replaced published version: extensions/org.ros2/1.0.xsd (org.ros2) "
        "changed content since this client last saw it"
    )
    assert err["expected"] == f"sha256:{hashlib.sha256(was).hexdigest()} ({len(was)} bytes)"
    assert err["actual"] == f"sha256:{hashlib.sha256(evil).hexdigest()} ({len(evil)} bytes)"
    assert err["url"] == str(reg.site)


def test_verify_downloads_and_checks_core_schemas_too(reg):
    from tests.conftest import HCDFORMAT

    reg.run("add", reg.src, "--core", "hcdf", "--version", "1.0", "--schema", HCDFORMAT / "hcdf.xsd",
            "--content", reg.content)  # fmt: skip
    reg.publish()
    res = reg.cli("registry", "verify", reg.site, "--trusted-root", reg.root_json, "--json")
    assert res.exit_code == 0, res.stdout
    assert (res.json["roles"], res.json["targets"]) == (2, 4)
    target = reg.target_file("schemas/hcdf/1.0.xsd")
    target.write_bytes(target.read_bytes().replace(b"<", b"[", 1))
    res = reg.cli("registry", "verify", reg.site, "--trusted-root", reg.root_json, "--cache-dir", reg.base / "c2")
    assert res.exit_code == 1 and "arbitrary content: target schemas/hcdf/1.0.xsd" in res.stderr, res.stderr


def test_top_level_targets_listing_a_domain_file_is_reported_by_name(reg):
    def shadow(signed):
        signed.targets["extensions/org.ros2/9.0.xsd"] = reg.put_target("extensions/org.ros2/9.0.xsd", b"<x/>")

    reg.forge("targets", shadow, signer=reg.top_signer("targets"))
    res = reg.cli("registry", "verify", reg.site, "--trusted-root", reg.root_json, "--json")
    assert res.exit_code == 1, res.stdout
    assert [e["message"] for e in res.json["errors"]] == [
        "targets lists extensions/org.ros2/9.0.xsd: only a domain's own role may list its files (it would shadow them)"
    ]
