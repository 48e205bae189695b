"""Attack: remote references whose text is not an ``https://host/…`` URL.

``https:user:pw@host/x`` has no ``//``, so it carries no authority by the URL
grammar, but collapsing its path used to rebuild it as ``https://user:pw@host/x``:
the credentials check (which looks after ``//``) was passed, and the fetcher then
sent the secret to the host as Basic auth. ``https:\\\\host\\x`` (a form browsers read
as ``https://host/x``) reached httpx and died with a traceback. A malformed URL is
an input error (exit 3) before anything is fetched, however a server redirects.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest

SECRET = "s3cr3t-Passw0rd"
DATA = b"model bytes"


def _doc(tmp_path: Path, uri: str) -> Path:
    doc = tmp_path / "robot.hcdf"
    doc.write_text(
        '<?xml version="1.0"?>\n<hcdf version="1.0" name="r">\n<comp name="a"><visual>'
        f'<model uri="{uri}" sha="{hashlib.sha256(DATA).hexdigest()}"/></visual></comp>\n</hcdf>\n'
    )
    return doc


@pytest.mark.parametrize(
    "form",
    [
        "https:user:{secret}@127.0.0.1:{port}/a.glb",  # no //: the path used to become the authority
        "https:127.0.0.1:{port}/a.glb",
        "https:/127.0.0.1:{port}/a.glb",
        "https:///127.0.0.1:{port}/a.glb",
        "https:\\\\127.0.0.1:{port}\\a.glb",
        "https://127.0.0.1:{port}\\a.glb",
        "https:\\\\user:{secret}@127.0.0.1:{port}\\a.glb",
    ],
)
def test_a_remote_reference_without_a_plain_authority_is_refused_unfetched(cli, https_server, tls, tmp_path, form):
    https_server.add("/a.glb", DATA)
    doc = _doc(tmp_path, form.format(secret=SECRET, port=https_server.port))
    result = cli("resolve", doc, "--ca-bundle", tls.ca_pem, "--cache-dir", tmp_path / "c", "--json")
    assert result.exit_code == 3, result.stdout
    (error,) = result.json["errors"]
    assert error["line"] == 3
    assert (error["code"], "{secret}" in form) in (("input", False), ("url-credentials", True)), error
    assert https_server.total_hits == 0
    assert SECRET not in result.stdout + result.stderr
    assert not (tmp_path / "robot.hcdf.lock").exists()


def test_a_redirect_to_a_malformed_url_is_a_fetch_error(cli, https_server, tls, tmp_path):
    url = https_server.redirect("/r.glb", f"https://127.0.0.1:{https_server.port}\\a.glb")
    doc = _doc(tmp_path, url)
    result = cli("resolve", doc, "--ca-bundle", tls.ca_pem, "--cache-dir", tmp_path / "c", "--json")
    assert result.exit_code == 3, result.stdout
    (error,) = result.json["errors"]
    assert error["code"] == "fetch" and error["line"] == 3, error


@pytest.mark.parametrize(
    "url", ["https://127.0.0.1:9x/", "https://[::1/", "https:///x/", "https://h\\x/", "https://127.0.0.1:99999/"]
)
@pytest.mark.parametrize("flag", ["--base", "--mirror"])
def test_a_malformed_url_flag_is_a_usage_error(cli, tmp_path, flag, url):
    doc = _doc(tmp_path, "https://models.example/a.glb")
    value = f"https://models.example/={url}" if flag == "--mirror" else url
    result = cli("resolve", doc, flag, value, "--cache-dir", tmp_path / "c")
    assert result.exit_code == 2, result.stderr
    assert "is not a valid URL" in result.stderr


def test_the_fetcher_reports_a_url_httpx_cannot_parse_as_a_fetch_error():
    from hcdf_trust.errors import FetchError
    from hcdf_trust.include.fetch import HttpFetcher

    fetcher = HttpFetcher()
    try:
        with pytest.raises(FetchError, match="Invalid port"), fetcher.open("https://127.0.0.1:9x/a.glb", file="d"):
            pass
    finally:
        fetcher.close()
