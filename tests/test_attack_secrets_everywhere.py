"""Attack: make the tool print a secret, or a line of our own, through any verb.

An attacker (or a tired operator) puts a token in a URL's query string, pastes an age
identity where the recipient goes, writes a key-ref with a newline to forge a CI log line,
or leaves a passphrase file readable by everyone. Every message, ``--json`` object and
click usage error passes through one filter (``hcdf_trust/scrub.py``); every key,
passphrase and PIN file through ``localfile.read_secret``; every passphrase through
``hcdf_trust/passphrase.py``.
"""

from __future__ import annotations

import hashlib
import json
import os
import stat
from pathlib import Path

import pytest

from ._macsec import comp, hcdf, link, port, tree

TOKEN = "tok-9f8e7d6c5b4a"
AGE_IDENTITY = "AGE-SECRET-KEY-1GQ9778VQXMMJVE8SK7J6VT8UJ4HDQAJUVSFCWCM02D8GEWQ72PVQ2Y5J33"
PEM_BODY = "MC4CAQAwBQYDK2VwBCIEIJ+ZbQ3L1mV4f1p3t6ZcqJ1dW0Y7Gm8f2u9rXo3kLhQx"
PEM = f"-----BEGIN PRIVATE KEY-----\n{PEM_BODY}\n-----END PRIVATE KEY-----\n"
PASS = b"correct horse battery staple"
T0 = "2026-01-01T00:00:00Z"


def _doc_with_query(tmp_path: Path, url: str, pin: str | None = None) -> Path:
    sha = f' sha="{pin}"' if pin else ""
    doc = tmp_path / "robot.hcdf"
    doc.write_text(
        f'<?xml version="1.0"?>\n<hcdf version="1.0" name="r"><comp name="c"><visual name="v">'
        f'<model uri="{url}"{sha}/></visual></comp></hcdf>\n'
    )
    return doc


# --- query strings -------------------------------------------------------------------------


@pytest.mark.parametrize("verb", ["resolve", "verify", "pin", "validate"])
def test_a_token_in_a_query_string_is_in_no_message(cli, tmp_path, verb):
    doc = _doc_with_query(tmp_path, f"https://127.0.0.1:9/m.glb?token={TOKEN}", pin="ab" * 2)
    extra = ("--offline",) if verb in ("resolve", "pin") else ()
    for as_json in ((), ("--json",)):
        r = cli(verb, doc, *extra, *as_json)
        assert TOKEN not in r.stdout + r.stderr, (verb, as_json)
        if verb != "validate":
            assert r.exit_code != 0 and "127.0.0.1:9/m.glb?***" in r.stdout + r.stderr


def test_the_lock_keeps_the_url_as_written_and_json_shows_it_redacted(cli, tmp_path, https_server, tls):
    data = b"model bytes"
    url = https_server.add("/m.glb", data) + f"?token={TOKEN}"
    doc = _doc_with_query(tmp_path, url, pin=hashlib.sha256(data).hexdigest())
    r = cli("resolve", doc, "--ca-bundle", tls.ca_pem, "--json")
    assert r.exit_code == 0, r.stderr
    assert TOKEN not in r.stdout + r.stderr
    assert r.json["artifacts"][0]["url"].endswith("/m.glb?***")
    lock = json.loads((tmp_path / "robot.hcdf.lock").read_text())
    assert TOKEN in json.dumps(lock)  # the lock records what the document says
    r = cli("verify", doc)
    assert r.exit_code == 0 and TOKEN not in r.stderr


def test_a_flag_url_with_a_token_is_redacted_in_clicks_own_error(cli, tmp_path):
    r = cli("resolve", tmp_path / "x.hcdf", "--base", f"ftp://host/x?token={TOKEN}")
    assert r.exit_code == 2 and TOKEN not in r.stderr and "?***" in r.stderr


# --- a secret in the wrong place -------------------------------------------------------------


@pytest.fixture
def store(tmp_path, cli):
    """A two-device robot with its keys generated; ``run(verb, *args)`` with the store flags."""
    body = [
        comp("a", port("p0", "gcm-aes-128")) + comp("b", port("p0", "gcm-aes-128")),
        '<network name="n">',
        link("l0", "a/p0", "b/p0", '<macsec policy="must-secure" cipher="gcm-aes-128" key-ref="k0"/>'),
        "</network>",
    ]
    (tmp_path / "doc").mkdir()
    doc = tree(tmp_path / "doc", {"robot.hcdf": hcdf(*body)})
    pp = tmp_path / "pass"
    pp.write_bytes(PASS + b"\n")
    pp.chmod(0o600)
    flags = ["--store", tmp_path / "keys", "--passphrase-file", pp]
    assert cli("macsec", "generate", doc, *flags, "--now", T0).exit_code == 0

    def run(verb: str, *args):
        return cli("macsec", verb, doc, *flags, *args)

    return doc, tmp_path, run


def test_an_age_identity_given_as_the_recipient_is_not_echoed(store):
    pytest.importorskip("pyrage")
    _doc, tmp, run = store
    for as_json in ((), ("--json",)):
        r = run("export", "--device", "a", "--format", "json", "--out", tmp / "out", "--age-recipient",
                AGE_IDENTITY, *as_json)  # fmt: skip
        assert r.exit_code == 3, r.stderr
        assert AGE_IDENTITY[16:] not in r.stdout + r.stderr
        assert "AGE-SECRET-KEY-1***" in r.stdout + r.stderr


@pytest.mark.parametrize(
    "args",
    [
        ("resolve", "{doc}", "--mirror", "{secret}"),  # click.BadParameter of our own
        ("resolve", "{doc}", "--{secret}"),  # click's "No such option"
        (
            "macsec",
            "export",
            "{doc}",
            "--store",
            "{tmp}/none",
            "--device",
            "a",
            "--format",
            "{secret}",
            "--out",
            "{tmp}/o",
        ),  # click.Choice  # fmt: skip
    ],
    ids=["bad-parameter", "no-such-option", "choice"],
)
@pytest.mark.parametrize("secret", [AGE_IDENTITY, PEM, "mka_cak=" + "0f" * 16], ids=["age", "pem", "cak"])
def test_a_private_key_pasted_into_any_option_is_not_echoed_by_click(cli, tmp_path, args, secret):
    doc = _doc_with_query(tmp_path, "m.glb")
    r = cli(*(a.format(doc=doc, tmp=tmp_path, secret=secret) for a in args))
    assert r.exit_code == 2, r.stderr
    for part in (AGE_IDENTITY[16:], PEM_BODY, "0f" * 16):
        assert part not in r.stdout + r.stderr


def test_digests_are_not_mistaken_for_keys(cli, tmp_path):
    """The filter hides hex only after a key word: a digest mismatch still names both digests."""
    (tmp_path / "m.glb").write_bytes(b"x")
    doc = _doc_with_query(tmp_path, "m.glb", pin="0" * 64)
    r = cli("resolve", doc)
    actual = hashlib.sha256(b"x").hexdigest()
    assert r.exit_code == 1 and "0" * 64 in r.stderr and actual in r.stderr


def test_a_passphrase_read_by_the_run_is_in_no_message(cli, tmp_path):
    """A passphrase pasted into the wrong option (here, an output path) is hidden once read."""
    pp = tmp_path / "pass"
    pp.write_bytes(PASS)
    pp.chmod(0o600)
    (tmp_path / "file").write_text("not a folder")
    r = cli("ota", "keygen", "-o", tmp_path / "file" / PASS.decode(), "--passphrase-file", pp)
    assert r.exit_code == 3 and PASS.decode() not in r.stdout + r.stderr and "***" in r.stderr


# --- names with control characters ---------------------------------------------------------------


def test_a_key_ref_with_a_newline_forges_no_log_line(cli, tmp_path):
    forged = "error: forged line"
    body = [
        comp("a", port("p0", "gcm-aes-128")) + comp("b", port("p0", "gcm-aes-128")),
        '<network name="n">',
        link("l0", "a/p0", "b/p0",
             f'<macsec policy="must-secure" cipher="gcm-aes-128" key-ref="k0&#10;{forged}&#13;&#8238;x"/>'),
        "</network>",
    ]  # fmt: skip
    doc = tree(tmp_path, {"robot.hcdf": hcdf(*body)})
    pp = tmp_path / "pass"
    pp.write_bytes(PASS)
    pp.chmod(0o600)
    flags = ("--store", tmp_path / "keys", "--passphrase-file", pp)
    runs = [cli("macsec", "plan", doc), cli("macsec", "generate", doc, *flags), cli("macsec", "status", doc, *flags)]
    for r in runs:
        assert r.exit_code == 0, r.stderr
        lines = (r.stdout + r.stderr).splitlines()
        assert not [line for line in lines if line.startswith(forged)], lines
        assert "\r" not in r.stdout + r.stderr and "\u202e" not in r.stdout + r.stderr
        assert f"k0\\n{forged}\\r\\u202ex" in r.stdout + r.stderr


# --- key, passphrase and PIN files others can read --------------------------------------------------


def _open_to_others(path: Path) -> None:
    path.chmod(0o644)


def test_ota_refuses_a_key_or_passphrase_file_others_can_read(cli, tmp_path):
    from ._ota import make_robot
    from ._ota import tree as files_of

    robot = make_robot(tmp_path, cli)
    pp = tmp_path / "pw"
    pp.write_bytes(PASS)
    pp.chmod(0o600)
    enc = tmp_path / "enc.pem"
    assert cli("ota", "keygen", "-o", enc, "--passphrase-file", pp).exit_code == 0
    assert stat.S_IMODE(enc.stat().st_mode) == 0o600  # created private
    out = tmp_path / "rel"
    for path, args in ((robot.key, ("--key", robot.key)), (pp, ("--key", enc, "--passphrase-file", pp))):
        _open_to_others(path)
        r = cli("ota", "build", robot.doc, "--firmware-dir", robot.fw, "--out", out, *args)
        assert r.exit_code == 3, r.stderr
        assert "too open" in r.stderr and f"chmod 600 {path}" in r.stderr
        assert not out.exists()
        path.chmod(0o600)
        r = cli("ota", "build", robot.doc, "--firmware-dir", robot.fw, "--out", out, *args)
        assert r.exit_code == 0, r.stderr
        assert files_of(out)
        out.rename(tmp_path / f"rel-{path.name}")
    _open_to_others(pp)
    assert cli("ota", "keygen", "-o", tmp_path / "k2.pem", "--passphrase-file", pp).exit_code == 3


def test_macsec_refuses_a_passphrase_file_others_can_read(store):
    doc, tmp, run = store
    pp = tmp / "pass"
    _open_to_others(pp)
    r = run("status")
    assert r.exit_code == 3 and "too open" in r.stderr and "chmod 600" in r.stderr
    store_file = next((tmp / "keys").glob("*.json"))
    assert stat.S_IMODE(store_file.stat().st_mode) == 0o600


def test_registry_refuses_a_key_or_passphrase_file_others_can_read(cli, tmp_path, monkeypatch):
    monkeypatch.delenv("HCDF_TRUST_PASSPHRASE", raising=False)
    pp = tmp_path / "pw"
    pp.write_bytes(PASS)
    pp.chmod(0o644)
    keys = tmp_path / "keys"
    r = cli("registry", "init", tmp_path / "src", "--keys", keys, "--passphrase-file", pp)
    assert r.exit_code == 3 and "too open" in r.stderr and not (tmp_path / "src").exists()
    pp.chmod(0o600)
    assert cli("registry", "init", tmp_path / "src", "--keys", keys, "--passphrase-file", pp).exit_code == 0
    key_files = sorted(keys.glob("*.key"))
    assert key_files and all(stat.S_IMODE(k.stat().st_mode) == 0o600 for k in key_files)
    for key in key_files:
        key.chmod(0o640)
    (tmp_path / "content").mkdir()
    r = cli("registry", "publish", tmp_path / "src", "--keys", keys, "--passphrase-file", pp,
            "--content", tmp_path / "content", "--out", tmp_path / "site")  # fmt: skip
    assert r.exit_code == 3 and "too open" in r.stderr and "chmod 600" in r.stderr, r.stderr
    assert not (tmp_path / "site").exists()


def test_a_pin_file_others_can_read_is_refused(cli, tmp_path):
    pin = tmp_path / "pin"
    pin.write_text("1234\n")
    pin.chmod(0o604)
    from hcdf_trust.errors import SecretFileError
    from hcdf_trust.passphrase import read_pin

    with pytest.raises(SecretFileError, match="chmod 600"):
        read_pin(pin)
    pin.chmod(0o400)
    assert read_pin(pin) == b"1234"


# --- one passphrase rule -----------------------------------------------------------------------


@pytest.mark.parametrize(
    "verb",
    [
        ("ota", "keygen", "-o", "{tmp}/k.pem"),
        ("registry", "keygen", "--keys", "{tmp}/keys", "-o", "{tmp}/k.pub"),
        ("macsec", "generate", "{doc}", "--store", "{tmp}/store"),
    ],
    ids=["ota", "registry", "macsec"],
)
def test_every_verb_takes_the_same_passphrase_rule(cli, tmp_path, monkeypatch, verb):
    monkeypatch.delenv("HCDF_TRUST_PASSPHRASE", raising=False)
    body = [comp("a", port("p0", "gcm-aes-128")) + comp("b", port("p0", "gcm-aes-128")), '<network name="n">',
            link("l0", "a/p0", "b/p0", '<macsec policy="must-secure" cipher="gcm-aes-128" key-ref="k0"/>'),
            "</network>"]  # fmt: skip
    (tmp_path / "d").mkdir()
    doc = tree(tmp_path / "d", {"robot.hcdf": hcdf(*body)})

    def run(case: str, *extra):
        folder = tmp_path / case
        folder.mkdir()
        return cli(*(a.format(tmp=folder, doc=doc) for a in verb), *extra)

    pp = tmp_path / "pw"
    pp.write_bytes(PASS + b"\nsecond line\n")  # the registry took the first line, ota and macsec all of it
    r = run("two-lines", "--passphrase-file", pp)
    assert r.exit_code == 3 and "several lines" in r.stderr, r.stderr
    for content in (PASS + b"\r\n\n", b"", b"\n"):
        pp.write_bytes(content)
        assert run(f"bad-{len(content)}", "--passphrase-file", pp).exit_code == 3
    pp.write_bytes(PASS + b"\n")  # one final newline is not part of it
    assert run("file", "--passphrase-file", pp).exit_code == 0
    monkeypatch.setenv("HCDF_TRUST_PASSPHRASE", PASS.decode())  # the one variable of every verb
    assert run("env").exit_code == 0
    if verb[0] == "macsec":  # the store made from the file opens with the variable: the same passphrase
        assert cli("macsec", "status", doc, "--store", tmp_path / "file" / "store").exit_code == 0
    if verb[0] == "ota":
        from hcdf_trust.ota.keys import load_private

        assert load_private(tmp_path / "file" / "k.pem") is not None  # encrypted: the variable opens it
        monkeypatch.setenv("HCDF_TRUST_PASSPHRASE", "another passphrase")
        with pytest.raises(Exception, match="wrong passphrase"):
            load_private(tmp_path / "file" / "k.pem")
    assert os.environ["HCDF_TRUST_PASSPHRASE"]


# --- the filter itself ---------------------------------------------------------------------------

SHA = hashlib.sha256(b"x").hexdigest()


@pytest.mark.parametrize(
    ("text", "shown"),
    [
        (f"https://u:pw@h/p?token={TOKEN}#frag", "https://***@h/p?***#frag"),
        (f"'https:u:pw@h/p?t={TOKEN}'", "'https:***@h/p?***'"),
        (f"pkcs11:token=t;object=k?pin-value={TOKEN}", "pkcs11:token=t;object=k?***"),
        (f"got {PEM} after", "got [PRIVATE KEY redacted]\\n after"),
        (f"actual: {PEM[:60]!r}", "actual: '[PRIVATE KEY redacted]'"),
        (f"x {AGE_IDENTITY} y", "x AGE-SECRET-KEY-1*** y"),
        ("mka_cak=" + "0f" * 16, "mka_cak=***"),
        ('"cak": "' + "0f" * 32 + '"', '"cak": "***"'),
        ("Key=" + "AB" * 16, "Key=***"),
        ("passphrase: " + "0f" * 16, "passphrase: ***"),
        ("cak =  '" + "0f" * 16 + "'", "cak =  '***'"),
        ("ip macsec add m0 tx sa 0 pn 1 on key 01 " + "ab" * 16, "ip macsec add m0 tx sa 0 pn 1 on key 01 ***"),
        # what must stay: digests, key ids of public keys, file:line, ordinary punctuation
        (f"expected: {SHA}", f"expected: {SHA}"),
        (f"root: key {SHA}", f"root: key {SHA}"),
        ("robot.hcdf:12: is this ok? sha256:abc", "robot.hcdf:12: is this ok? sha256:abc"),
        ("name\twith\nnewline \x1b[31m \u2028", "name\\twith\\nnewline \\x1b[31m \\u2028"),
    ],
)
def test_the_filter(text, shown):
    from hcdf_trust.scrub import scrub

    assert scrub(text) == shown
    assert scrub(shown) == shown  # idempotent: a message filtered twice reads the same
