"""Flags are checked when parsed (click usage error, exit 2), network settings belong to
the verbs that fetch, and URLs with credentials are refused without echoing the secret."""

from __future__ import annotations

import hashlib
import os
import shutil
import threading
from pathlib import Path

import pytest

from hcdf_trust.errors import display_path

from .conftest import PROJECT

SECRET = "s3cr3t-Passw0rd"


@pytest.fixture
def robot(tmp_path, monkeypatch) -> Path:
    """A copy of the example robot; the cwd is its parent."""
    shutil.copytree(PROJECT / "examples" / "robot", tmp_path / "robot")
    monkeypatch.chdir(tmp_path)
    return tmp_path / "robot" / "robot.hcdf"


def resolve(cli, doc, *extra):
    return cli("resolve", doc, "--cache-dir", "cache", "--no-lock", *extra)


def test_the_defaults_are_accepted(cli, robot):
    result = resolve(cli, robot)
    assert result.exit_code == 0, result.stderr


@pytest.mark.parametrize(
    "args",
    [
        ("--timeout", "0"),
        ("--timeout", "-1"),
        ("--timeout", "inf"),
        ("--timeout", "nan"),
        ("--max-size", "0"),
        ("--max-size", "-5"),
        ("--max-depth", "0"),
        ("--max-depth", "-1"),
    ],
)
def test_numbers_out_of_range_are_usage_errors(cli, robot, args):
    result = resolve(cli, robot, *args)
    assert result.exit_code == 2, result.stderr
    assert args[0] in result.stderr


def test_numbers_in_range_are_accepted(cli, robot):
    result = resolve(cli, robot, "--timeout", "0.5", "--max-size", "1", "--max-depth", "2")
    assert result.exit_code == 0, result.stderr


@pytest.mark.parametrize(
    ("target", "says"),
    [
        ("missing-folder", "does not exist"),
        ("robot/robot.hcdf", "is not a folder"),
        ("ftp://mirror.example/", "is not an https:// URL"),
        ("http://mirror.example/", "needs --allow-http"),
        ("file:///srv/mirror", "is not an https:// URL"),
    ],
)
def test_mirror_targets_are_checked(cli, robot, target, says):
    result = resolve(cli, robot, "--mirror", f"https://models.example/={target}")
    assert result.exit_code == 2, result.stderr
    assert says in result.stderr


@pytest.mark.parametrize("prefix", ["models.example/", "models/", "=", "ftp://models.example/", "s3://bucket/"])
def test_a_mirror_prefix_must_be_a_url(cli, robot, prefix):
    Path("m").mkdir()
    result = resolve(cli, robot, "--mirror", f"{prefix}=m")
    assert result.exit_code == 2, result.stderr


@pytest.mark.parametrize("order", ["before", "after"])
def test_an_http_mirror_is_accepted_with_allow_http_in_any_order(cli, robot, order):
    mirror = ("--mirror", "https://models.example/=http://127.0.0.1:9/")
    args = (*mirror, "--allow-http") if order == "after" else ("--allow-http", *mirror)
    result = resolve(cli, robot, *args)
    assert result.exit_code == 0, result.stderr


def test_mirror_to_an_existing_folder_and_an_https_url_is_accepted(cli, robot, tmp_path):
    (tmp_path / "m").mkdir()
    result = resolve(
        cli, robot, "--mirror", "https://a.example/=m", "--mirror", "https://b.example/=https://c.example/"
    )
    assert result.exit_code == 0, result.stderr


@pytest.mark.parametrize(
    ("base", "says"),
    [
        ("missing-folder", "does not exist"),
        ("robot/robot.hcdf", "is not a folder"),
        ("ftp://models.example/", "is not an https:// URL"),
    ],
)
def test_base_is_checked(cli, robot, base, says):
    result = resolve(cli, robot, "--base", base)
    assert result.exit_code == 2, result.stderr
    assert says in result.stderr


def test_base_may_be_a_url_or_an_existing_folder(cli, robot, tmp_path):
    (tmp_path / "site").mkdir()
    (tmp_path / "site" / "a.glb").write_bytes(b"model bytes")
    doc = _doc_with(tmp_path, "a.glb")
    assert resolve(cli, doc, "--base", "site").exit_code == 0
    # a URL base: the example's relative references now point at it; offline and
    # uncached, that is an input error about the references, not about the flag
    result = resolve(cli, robot, "--base", "https://models.example/robot/", "--offline", "--json")
    assert result.exit_code == 3 and {e["code"] for e in result.json["errors"]} == {"offline"}


@pytest.mark.parametrize("root", ["missing-folder", "robot/robot.hcdf"])
def test_root_must_be_an_existing_folder(cli, robot, root):
    result = resolve(cli, robot, "--root", root)
    assert result.exit_code == 2, result.stderr
    assert "--root" in result.stderr


# --- --ca-bundle ------------------------------------------------------------------------


def _not_pem(tmp_path: Path, kind: str) -> Path:
    path = tmp_path / f"ca-{kind}"
    if kind == "text":
        path.write_text("this is not a certificate\n")
    elif kind == "der":
        path.write_bytes(bytes(range(256)) * 4)
    elif kind == "key":
        path.write_text("-----BEGIN PRIVATE KEY-----\nMC4CAQAwBQYDK2VwBCIEIA==\n-----END PRIVATE KEY-----\n")
    elif kind == "broken":
        path.write_text("-----BEGIN CERTIFICATE-----\nnot base64 at all!\n-----END CERTIFICATE-----\n")
    elif kind == "empty":
        path.write_bytes(b"")
    elif kind == "fifo":
        os.mkfifo(path)
    return path


@pytest.mark.parametrize("kind", ["text", "der", "key", "broken", "empty", "fifo"])
def test_a_ca_bundle_that_is_not_pem_is_an_input_error(cli, robot, tmp_path, kind):
    bundle = _not_pem(tmp_path, kind)
    result: list = []
    worker = threading.Thread(target=lambda: result.append(resolve(cli, robot, "--ca-bundle", bundle, "--json")))
    worker.start()
    worker.join(timeout=20)
    if worker.is_alive():  # a FIFO read as a CA file blocks for a writer; unblock it to end the test
        with open(bundle, "wb"):
            pass
        worker.join()
        pytest.fail("--ca-bundle on a FIFO blocked")
    [r] = result
    assert r.exit_code == 3, r.stdout + r.stderr
    [error] = r.json["errors"]
    assert "ca-" + kind in error["message"]
    assert error["file"] == display_path(bundle)


def test_a_pem_ca_bundle_is_accepted(cli, robot, tls):
    result = resolve(cli, robot, "--ca-bundle", tls.ca_pem)
    assert result.exit_code == 0, result.stderr


def test_a_bad_ca_bundle_in_the_environment_fails_resolve(cli, robot, tmp_path, monkeypatch):
    monkeypatch.setenv("HCDF_TRUST_CA_BUNDLE", str(_not_pem(tmp_path, "text")))
    assert resolve(cli, robot).exit_code == 3


# --- verify is offline: it neither offers nor reads network settings --------------------


@pytest.fixture
def locked(cli, robot) -> Path:
    assert cli("resolve", robot, "--cache-dir", "cache", "--offline").exit_code == 0
    return robot


@pytest.mark.parametrize("value", ["missing.pem", "not-pem.txt"])
def test_verify_ignores_a_bad_ca_bundle_in_the_environment(cli, locked, monkeypatch, value):
    Path("not-pem.txt").write_text("garbage\n")
    monkeypatch.setenv("HCDF_TRUST_CA_BUNDLE", value)
    result = cli("verify", locked, "--cache-dir", "cache")
    assert result.exit_code == 0, result.stderr


@pytest.mark.parametrize(
    "args",
    [("--ca-bundle", "x.pem"), ("--timeout", "5"), ("--max-size", "10"), ("--allow-http",), ("--jobs", "2")],
)
def test_verify_has_no_network_flags(cli, locked, args):
    result = cli("verify", locked, *args)
    assert result.exit_code == 2 and "No such option" in result.stderr, result.stderr


def test_verify_help_lists_no_network_flags(cli):
    text = cli("verify", "--help").stdout
    for flag in ("--ca-bundle", "--timeout", "--max-size", "--allow-http", "--offline"):
        assert flag not in text
    assert "--mirror" in text and "--max-depth" in text


# --- URLs with credentials --------------------------------------------------------------


def _doc_with(tmp_path: Path, uri: str) -> Path:
    data = b"model bytes"
    doc = tmp_path / "creds.hcdf"
    doc.write_text(
        '<?xml version="1.0"?>\n<hcdf version="1.0" name="c">\n<comp name="a"><visual>'
        f'<model uri="{uri}" sha="{hashlib.sha256(data).hexdigest()}"/></visual></comp>\n</hcdf>\n'
    )
    return doc


def _assert_no_secret(result, *paths: Path) -> None:
    assert SECRET not in result.stdout and SECRET not in result.stderr
    for path in paths:
        assert not path.exists() or SECRET not in path.read_text()


@pytest.mark.parametrize(
    "uri",
    [
        f"https://user:{SECRET}@models.example/a.glb",
        f"https://{SECRET}@models.example/a.glb",
        f"HTTPS://user:{SECRET}@models.example/a.glb",
        f"http://user:{SECRET}@models.example/a.glb",
    ],
)
def test_a_reference_with_credentials_is_refused(cli, tmp_path, monkeypatch, uri):
    monkeypatch.chdir(tmp_path)
    doc = _doc_with(tmp_path, uri)
    out, lock = tmp_path / "flat.hcdf", tmp_path / "creds.lock"
    for extra in ((), ("--allow-http",)):
        result = cli(
            "resolve", doc, "--offline", "--cache-dir", "cache", "--lock", lock, "--out", out, "--json", *extra
        )
        assert result.exit_code == 3, result.stdout
        [error] = result.json["errors"]
        assert error["code"] == "url-credentials" and error["line"] == 3
        assert "***@models.example" in error["message"]
        _assert_no_secret(result, out, lock)
        assert not out.exists() and not lock.exists()


@pytest.mark.parametrize(
    "uri",
    [f"ftp://user:{SECRET}@host/a.glb", f"//user:{SECRET}@host/a.glb", f"file://user:{SECRET}@host/a.glb"],
)
def test_other_refusals_do_not_echo_credentials_either(cli, tmp_path, uri):
    doc = _doc_with(tmp_path, uri)
    result = cli("resolve", doc, "--offline", "--cache-dir", tmp_path / "c", "--no-lock", "--json")
    assert result.exit_code == 3
    _assert_no_secret(result)


def test_a_malformed_url_is_an_input_error(cli, tmp_path):
    doc = _doc_with(tmp_path, "https://[::1/a.glb")
    result = cli("resolve", doc, "--offline", "--cache-dir", tmp_path / "c", "--no-lock", "--json")
    assert result.exit_code == 3 and "malformed URL" in result.json["errors"][0]["message"]
    assert isinstance(result.json["errors"][0]["line"], int)  # names the reference's line


@pytest.mark.parametrize(
    ("args", "named"),
    [
        (("--base", f"https://user:{SECRET}@models.example/"), "--base"),
        (("--mirror", f"https://models.example/=https://user:{SECRET}@mirror.example/"), "--mirror target"),
        (("--mirror", f"https://user:{SECRET}@models.example/=mirror"), "--mirror prefix"),
    ],
)
def test_a_flag_with_credentials_is_refused(cli, robot, args, named):
    Path("mirror").mkdir()
    result = resolve(cli, robot, *args, "--json")
    assert result.exit_code == 3, result.stdout + result.stderr
    [error] = result.json["errors"]
    assert error["code"] == "url-credentials" and "***@" in error["message"]
    assert error["message"].startswith(f"{named} https://"), error["message"]  # says which flag
    _assert_no_secret(result)


def test_a_usage_error_about_a_credentialed_url_is_redacted(cli, robot):
    result = resolve(cli, robot, "--mirror", f"https://models.example/=http://user:{SECRET}@mirror.example/")
    assert result.exit_code == 2 and "***@mirror.example" in result.stderr
    _assert_no_secret(result)


def test_a_redirect_to_a_url_with_credentials_is_refused(cli, https_server, tls, tmp_path):
    data = b"model bytes"
    https_server.add("/a.glb", data)
    url = https_server.redirect("/r.glb", f"https://user:{SECRET}@127.0.0.1:{https_server.port}/a.glb")
    doc = _doc_with(tmp_path, url)
    result = cli("resolve", doc, "--ca-bundle", tls.ca_pem, "--cache-dir", tmp_path / "c", "--no-lock", "--json")
    assert result.exit_code == 3, result.stdout
    assert "redirect to a URL with credentials is refused" in result.json["errors"][0]["message"]
    assert https_server.hits["/a.glb"] == 0
    _assert_no_secret(result)
