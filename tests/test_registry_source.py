"""The registry source (registry/ and its TOML entries): the committed seed and strict validation."""

from __future__ import annotations

import hashlib
import os
import shutil
from pathlib import Path

import pytest

from hcdf_trust.errors import InputError
from hcdf_trust.registry.errors import SourceError
from hcdf_trust.registry.publish import check_source, read_content
from hcdf_trust.registry.source import is_reverse_dns, load_source
from tests._registry import PASSPHRASE
from tests.conftest import HCDFORMAT, PROJECT

SEED = PROJECT / "registry"


def test_seed_lists_the_corpus_domains_profile_and_schemas_with_their_digests():
    src = load_source(SEED)
    assert set(src.domains) == {"org.ros2", "org.gazebosim", "org.ieee.1722", "org.cognipilot.imu-stability"}
    assert set(src.profiles) == {"operational"}
    assert set(src.schemas) == {"hcdf", "hcdf-stream-profile"}
    expected = {
        "org.ros2": "extensions/hcdf-ext-ros2.xsd",
        "org.gazebosim": "extensions/hcdf-ext-gazebo.xsd",
        "org.ieee.1722": "extensions/hcdf-ext-1722.xsd",
    }
    for domain, file in expected.items():
        release = src.domains[domain].versions["1.0"]
        data = (HCDFORMAT / file).read_bytes()
        assert (release.file, release.sha256, release.length) == (file, hashlib.sha256(data).hexdigest(), len(data))
    assert src.domains["org.cognipilot.imu-stability"].versions == {}  # the corpus has no schema for it
    profile = src.profiles["operational"].versions["1.0"]
    data = (HCDFORMAT / "examples/profiles/operational.streams.xml").read_bytes()
    assert profile.sha256 == hashlib.sha256(data).hexdigest()
    # every version is owner-signed and every content file matches: the seed is publishable
    check_source(src)
    assert len(read_content(src, HCDFORMAT)) == 6


def test_every_seed_domain_extension_in_the_corpus_is_registered():
    """Independent oracle: the domains the corpus documents use are the seed's domains."""
    from lxml import etree

    used = set()
    for doc in HCDFORMAT.rglob("*.hcdf"):
        try:
            tree = etree.parse(str(doc))
        except etree.XMLSyntaxError:
            continue
        used |= {e.get("domain") for e in tree.iter("extension") if e.get("domain")}
    registered = set(load_source(SEED).domains)
    assert {d for d in used if is_reverse_dns(d)} <= registered
    assert "gazebo" in used and not is_reverse_dns("gazebo")  # the one non-reverse-DNS use stays unregistered


@pytest.mark.parametrize(
    ("domain", "ok"),
    [
        ("org.ros2", True),
        ("org.ieee.1722", True),
        ("org.cognipilot.imu-stability", True),
        ("gazebo", False),
        ("Org.ros2", False),
        ("org..ros2", False),
        ("org.ros2.", False),
        ("1org.ros2", False),
        ("org.-ros2", False),
        ("org.ros2/../x", False),
        ("org.ros*", False),
        ("org." + "a" * 64, False),
    ],
)
def test_reverse_dns(domain, ok):
    assert is_reverse_dns(domain) is ok


@pytest.fixture
def seed(tmp_path) -> Path:
    dest = tmp_path / "registry"
    shutil.copytree(SEED, dest)
    return dest


def _edit(path: Path, old: str, new: str) -> None:
    text = path.read_text()
    assert old in text, old
    path.write_text(text.replace(old, new, 1))


@pytest.mark.parametrize(
    ("file", "old", "new", "key"),
    [
        ("domains/org.ros2.toml", "length = 6862", 'length = "6862"', "versions.1.0.length"),
        ("domains/org.ros2.toml", 'sha256 = "830e', 'sha256 = "XYZ', "versions.1.0.sha256"),
        ("domains/org.ros2.toml", 'domain = "org.ros2"', 'domain = "org.ros3"', "domain"),
        ("domains/org.ros2.toml", "threshold = 1", "threshold = 2", "owner.threshold"),
        ("domains/org.ros2.toml", "description =", "descripton =", "descripton"),
        ("domains/org.ros2.toml", 'path = "extensions/org.ros2/1.0.xsd"', 'path = "../x.xsd"', "versions.1.0.path"),
        ("domains/org.ros2.toml", 'scheme = "ed25519"', 'scheme = "rsa"', "scheme"),
        ("domains/org.ros2.toml", 'public = "', 'public = "00', "public"),
        ("profiles/operational.toml", 'name = "operational"', 'name = "Operational"', "name"),
        ("root.toml", "[roles.timestamp]", "[roles.timestampx]", "roles.timestamp"),
    ],
)
def test_malformed_entries_name_the_file_and_key(seed, file, old, new, key):
    _edit(seed / file, old, new)
    with pytest.raises(SourceError) as info:
        load_source(seed)
    assert info.value.file == os.fspath(seed / file)
    assert f"{key}`" in str(info.value)
    assert "expected: None" not in str(info.value)
    assert info.value.exit_code == 3


def test_key_id_must_match_the_key(seed):
    path = seed / "domains" / "org.ros2.toml"
    text = path.read_text()
    keyid = text.split("[owner.keys.", 1)[1].split("]", 1)[0]
    path.write_text(text.replace(keyid, "0" * 64))
    with pytest.raises(SourceError, match="key id does not match the key") as info:
        load_source(seed)
    assert info.value.expected == keyid


def test_toml_syntax_error_has_a_line(seed):
    path = seed / "profiles" / "operational.toml"
    path.write_text(path.read_text() + "\n[versions\n")
    with pytest.raises(SourceError, match="not valid TOML") as info:
        load_source(seed)
    assert info.value.line is not None and info.value.line > 5


def test_hostile_entries_fifo_and_huge(seed):
    fifo = seed / "domains" / "org.fifo.toml"
    os.mkfifo(fifo)
    with pytest.raises(InputError, match="FIFO"):
        load_source(seed)
    fifo.unlink()
    (seed / "domains" / "org.huge.toml").write_bytes(b"#" * (2 << 20))
    with pytest.raises(InputError, match="limit"):
        load_source(seed)


def test_cli_add_refuses_a_domain_that_is_not_reverse_dns(seed, cli, tmp_path, monkeypatch):
    monkeypatch.setenv("HCDF_TRUST_PASSPHRASE", PASSPHRASE)
    assert cli("registry", "keygen", "--keys", tmp_path / "k", "-o", tmp_path / "o.pub").exit_code == 0
    res = cli("registry", "add", seed, "--domain", "gazebo", "--version", "1.0",
              "--schema", HCDFORMAT / "extensions/hcdf-ext-gazebo.xsd", "--content", HCDFORMAT,
              "--owner", "x", "--owner-key", tmp_path / "o.pub", "--keys", tmp_path / "k")  # fmt: skip
    assert res.exit_code == 3 and "not a reverse-DNS domain" in res.stderr
    assert not (seed / "domains" / "gazebo.toml").exists()


def test_cli_add_refuses_a_schema_outside_the_content_folder(seed, cli, tmp_path, monkeypatch):
    monkeypatch.setenv("HCDF_TRUST_PASSPHRASE", PASSPHRASE)
    res = cli("registry", "add", seed, "--profile", HCDFORMAT / "examples/profiles/operational.streams.xml",
              "--content", HCDFORMAT / "extensions")  # fmt: skip
    assert res.exit_code == 3 and "outside the root" in res.stderr


def test_no_passphrase_is_an_input_error(tmp_path, cli, monkeypatch):
    monkeypatch.delenv("HCDF_TRUST_PASSPHRASE", raising=False)
    res = cli("registry", "init", tmp_path / "src", "--keys", tmp_path / "keys")
    assert res.exit_code == 3 and "no passphrase" in res.stderr
    assert not (tmp_path / "keys").exists() and not (tmp_path / "src").exists()


def test_registry_help_does_not_import_tuf():
    import subprocess
    import sys

    code = "import sys; from hcdf_trust.cli import main; print('tuf' in sys.modules, 'securesystemslib' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False False"
