"""The PKCS#11 backend: the store's wrapping key lives in SoftHSM2 (started here, in a temporary SOFTHSM2_CONF)."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from ._macsec import comp, hcdf, link, port, tree

MODULE = Path("/usr/lib/softhsm/libsofthsm2.so")
pkcs11 = pytest.importorskip("pkcs11")
pytestmark = pytest.mark.skipif(
    not MODULE.exists() or shutil.which("softhsm2-util") is None, reason="SoftHSM2 (Debian softhsm2) not installed"
)
PIN = "12345678"


def _init_token(label: str) -> None:
    subprocess.run(
        ["softhsm2-util", "--init-token", "--free", "--label", label, "--so-pin", "87654321", "--pin", PIN],
        check=True,
        capture_output=True,
    )


@pytest.fixture
def hsm(tmp_path, monkeypatch):
    """A fresh SoftHSM2 token store with tokens ``hcdf`` and ``other``; returns the PIN file."""
    tokens = tmp_path / "tokens"
    tokens.mkdir()
    conf = tmp_path / "softhsm2.conf"
    conf.write_text(f"directories.tokendir = {tokens}\nobjectstore.backend = file\nlog.level = ERROR\n")
    monkeypatch.setenv("SOFTHSM2_CONF", str(conf))
    monkeypatch.delenv("HCDF_TRUST_PASSPHRASE", raising=False)
    _init_token("hcdf")
    _init_token("other")
    pin = tmp_path / "pin"
    pin.write_text(PIN + "\n")
    return pin


@pytest.fixture
def doc(tmp_path):
    caps = ("gcm-aes-128",)
    body = [comp("a", port("p0", *caps)), comp("b", port("p0", *caps)), '<network name="n">']
    body += [link("l0", "a/p0", "b/p0", '<macsec policy="must-secure" key-ref="k"/>'), "</network>"]
    return tree(tmp_path / "d", {"robot.hcdf": hcdf(*body)})


def _args(store: Path, pin: Path, label: str = "hcdf") -> list:
    return ["--store", store, "--pkcs11-module", MODULE, "--token-label", label, "--pin-file", pin]


def test_store_wrapped_by_a_token_key(hsm, doc, tmp_path, cli):
    store = tmp_path / "keys"
    r = cli("macsec", "generate", doc, *_args(store, hsm), "--json")
    assert r.exit_code == 0, r.stderr
    assert r.json["created"] == ["key-ref:k"]
    text = (store / "macsec-keys.json").read_text()
    assert '"method":"pkcs11"' in text and '"token_label":"hcdf"' in text
    r = cli("macsec", "status", doc, *_args(store, hsm), "--json")
    assert r.exit_code == 0, r.stderr
    assert r.json["associations"][0]["generations"][0]["kcv"]
    r = cli("macsec", "export", doc, *_args(store, hsm), "--device", "a", "--format", "json", "--out", tmp_path / "o")
    assert r.exit_code == 0, r.stderr
    # the wrapping key is in the token, sensitive and not extractable
    from pkcs11 import Attribute, KeyType, ObjectClass

    token = pkcs11.lib(str(MODULE)).get_token(token_label="hcdf")
    with token.open(user_pin=PIN) as session:
        key = session.get_key(
            label="hcdf-trust-macsec-store", key_type=KeyType.AES, object_class=ObjectClass.SECRET_KEY
        )
        assert key[Attribute.SENSITIVE] and not key[Attribute.EXTRACTABLE]
        with pytest.raises(pkcs11.exceptions.AttributeSensitive):
            key[Attribute.VALUE]


def test_wrong_pin_wrong_token_wrong_backend(hsm, doc, tmp_path, cli):
    store = tmp_path / "keys"
    assert cli("macsec", "generate", doc, *_args(store, hsm)).exit_code == 0
    before = (store / "macsec-keys.json").read_bytes()
    bad_pin = tmp_path / "bad-pin"
    bad_pin.write_text("00000000")
    r = cli("macsec", "rotate", doc, *_args(store, bad_pin))
    assert r.exit_code == 3 and "wrong PIN" in r.stderr
    r = cli("macsec", "rotate", doc, *_args(store, hsm, label="other"))
    assert r.exit_code == 3 and "not the token this store was made with" in r.stderr
    pp = tmp_path / "pass"
    pp.write_text("a passphrase")
    r = cli("macsec", "rotate", doc, "--store", store, "--passphrase-file", pp)
    assert r.exit_code == 3 and "another backend" in r.stderr
    r = cli("macsec", "rotate", doc, *_args(store, hsm, label="nope"))
    assert r.exit_code == 3 and "no single PKCS#11 token" in r.stderr
    assert (store / "macsec-keys.json").read_bytes() == before
    r = cli("macsec", "status", doc, "--store", store, "--pkcs11-module", MODULE, "--pin-file", hsm)
    assert r.exit_code == 2
