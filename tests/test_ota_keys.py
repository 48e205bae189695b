"""``hcdf-trust ota keygen`` and key loading: imgtool's own loader is the oracle."""

from __future__ import annotations

import os
import stat

import pytest
from imgtool import keys as imgtool_keys

from hcdf_trust.ota.errors import KeyFileError
from hcdf_trust.ota.keys import load_private, load_public


@pytest.mark.parametrize("kind", ["ecdsa-p256", "ed25519", "rsa-2048", "rsa-3072"])
def test_keygen_writes_a_0600_private_key_and_its_public_key_beside_it(cli, tmp_path, kind):
    out = tmp_path / "fw.pem"
    r = cli("ota", "keygen", "--type", kind, "-o", out, "--json")
    assert r.exit_code == 0, r.stderr
    assert r.json["type"] == kind
    assert stat.S_IMODE(os.stat(out).st_mode) == 0o600
    pub = tmp_path / "fw.pub.pem"
    assert r.json["public"] == str(pub)
    # imgtool's own loader reads both files, and the public file is the private key's public half
    priv = imgtool_keys.load(str(out))
    assert priv.get_public_bytes() == imgtool_keys.load(str(pub)).get_public_bytes()
    assert load_private(out).get_public_bytes() == load_public(pub).get_public_bytes()


def test_passphrase_protected_key_needs_the_right_passphrase(cli, tmp_path):
    pw = tmp_path / "pw"
    pw.write_text("correct horse\n")
    out = tmp_path / "fw.pem"
    assert cli("ota", "keygen", "-o", out, "--passphrase-file", pw).exit_code == 0
    assert b"ENCRYPTED PRIVATE KEY" in out.read_bytes()
    assert imgtool_keys.load(str(out)) is None  # imgtool's pitfall: None, no exception
    assert imgtool_keys.load(str(out), b"correct horse") is not None  # the final newline is not part of it
    with pytest.raises(KeyFileError, match="passphrase-protected"):
        load_private(out)
    with pytest.raises(KeyFileError, match="wrong passphrase"):
        load_private(out, b"wrong")
    assert load_private(out, b"correct horse") is not None


def test_keygen_refuses_to_replace_a_key_or_write_over_its_passphrase_file(cli, tmp_path):
    out = tmp_path / "fw.pem"
    assert cli("ota", "keygen", "-o", out).exit_code == 0
    before = out.read_bytes()
    r = cli("ota", "keygen", "-o", out)
    assert r.exit_code == 3 and "exists" in r.stderr
    assert out.read_bytes() == before
    assert cli("ota", "keygen", "-o", out, "--force").exit_code == 0
    assert out.read_bytes() != before
    pw = tmp_path / "pw.pem"
    pw.write_text("secret\n")
    r = cli("ota", "keygen", "-o", pw, "--passphrase-file", pw, "--force")
    assert r.exit_code == 3 and "passphrase file" in r.stderr
    assert pw.read_text() == "secret\n"


def test_empty_or_special_passphrase_file_is_an_input_error(cli, tmp_path):
    empty = tmp_path / "empty"
    empty.write_text("\n")
    r = cli("ota", "keygen", "-o", tmp_path / "a.pem", "--passphrase-file", empty)
    assert r.exit_code == 3 and "empty" in r.stderr
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    r = cli("ota", "keygen", "-o", tmp_path / "b.pem", "--passphrase-file", fifo)
    assert r.exit_code == 3 and "FIFO" in r.stderr
    assert not (tmp_path / "a.pem").exists() and not (tmp_path / "b.pem").exists()


def test_a_public_key_is_not_a_signing_key(cli, tmp_path):
    out = tmp_path / "fw.pem"
    cli("ota", "keygen", "-o", out)
    with pytest.raises(KeyFileError, match="public key"):
        load_private(tmp_path / "fw.pub.pem")
    with pytest.raises(KeyFileError, match="not the private key"):
        load_public(out)


def test_the_ota_group_loads_under_python_dash_m(tmp_path):
    """``python -m hcdf_trust.cli`` runs cli.py as __main__: the ota module must not import it back."""
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, "-m", "hcdf_trust.cli", "ota", "--help"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert "keygen" in proc.stdout and "build" in proc.stdout and "verify" in proc.stdout
    proc = subprocess.run(
        [sys.executable, "-m", "hcdf_trust.cli", "ota", "keygen", "-o", tmp_path / "k.pem", "--json"],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 0, proc.stderr
