"""Mutation killers for how a registry URL that cannot be reached is reported
(hcdf_trust/registry/client.py: ``_unreachable`` and ``_attack``'s transport branch; see tests/MUTATION.md).

Each failure is made for real on 127.0.0.1 (a refused port, a server that never answers the
TLS handshake, one whose certificate the client does not trust, one that answers garbage) and
checked through ``registry verify --json``: the whole message, so the host, the reason, what
was being fetched and the advice are each pinned.
"""

from __future__ import annotations

import contextlib
import re
import socket
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests._oci import module_cli, registry  # noqa: F401 -- fixture
from tests._registry import PASSPHRASE, build
from tests.servers import LoopbackServer

ADVICE = "and the network, or give a folder holding a copy of the site"


@pytest.fixture(scope="module")
def root(tmp_path_factory) -> Path:
    """A published registry's first root: a valid trust anchor for any site URL."""
    base = tmp_path_factory.mktemp("reg")
    cli = module_cli()
    (base / "content").mkdir()
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("HCDF_TRUST_PASSPHRASE", PASSPHRASE)
        for args in (
            ("init", base / "src", "--keys", base / "keys"),
            ("publish", base / "src", "--keys", base / "keys", "--content", base / "content", "--out", base / "site"),
        ):
            res = cli("registry", *args)
            assert res.exit_code == 0, res.stderr
    return base / "site" / "metadata" / "1.root.json"


def _message(cli, root: Path, tmp_path: Path, site: str, *extra: object) -> str:
    res = cli("registry", "verify", site, "--trusted-root", root, "--cache-dir", tmp_path / "c", "--json", *extra)
    assert res.exit_code == 3, res.stdout + res.stderr
    [err] = res.json["errors"]
    assert err["code"] == "registry-transport", err
    message: str = err["message"]
    return message


@contextlib.contextmanager
def _raw_server(reply: bytes | None) -> Iterator[int]:
    """A TCP server on 127.0.0.1 that answers every connection with ``reply`` then closes it,
    or (``None``) accepts and never says anything."""
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    sock.listen(16)
    held: list[socket.socket] = []

    def serve() -> None:
        while True:
            try:
                conn, _ = sock.accept()
            except OSError:
                return
            held.append(conn)
            if reply is not None:
                with contextlib.suppress(OSError):
                    conn.recv(65536)
                    conn.sendall(reply)
                    conn.close()

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    try:
        yield sock.getsockname()[1]
    finally:
        sock.close()
        for conn in held:
            conn.close()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
    return port


def test_a_refused_connection_names_host_port_reason_role_and_site(cli, root, tmp_path):
    port = _free_port()
    site = f"http://127.0.0.1:{port}/"
    assert _message(cli, root, tmp_path, site) == (
        f"cannot reach the registry at 127.0.0.1:{port} (Connection refused) to fetch top-level metadata; "
        f"check SITE {site} {ADVICE}"
    )


def test_a_url_without_a_port_names_the_host_alone(cli, root, tmp_path):
    with socket.socket() as probe:
        if probe.connect_ex(("127.0.0.1", 80)) == 0:
            pytest.skip("something listens on 127.0.0.1:80")
    assert _message(cli, root, tmp_path, "http://127.0.0.1/") == (
        f"cannot reach the registry at 127.0.0.1 (Connection refused) to fetch top-level metadata; "
        f"check SITE http://127.0.0.1/ {ADVICE}"
    )


def test_a_url_without_a_host_is_named_as_given(cli, root, tmp_path):
    assert _message(cli, root, tmp_path, "http:///site") == (
        f"cannot reach the registry at http:///site (No host specified.) to fetch top-level metadata; "
        f"check SITE http:///site {ADVICE}"
    )


def test_credentials_in_the_url_are_not_repeated(cli, root, tmp_path):
    port = _free_port()
    message = _message(cli, root, tmp_path, f"http://user:secret@127.0.0.1:{port}/")
    assert message == (
        f"cannot reach the registry at 127.0.0.1:{port} (Connection refused) to fetch top-level metadata; "
        f"check SITE http://***@127.0.0.1:{port}/ {ADVICE}"
    )


def test_a_tls_handshake_that_never_completes_is_a_timeout(cli, root, tmp_path):
    """The handshake's own timeout ("The handshake operation timed out") arrives wrapped in
    urllib3's ProtocolError: the reason is found in its text, not its type."""
    with _raw_server(None) as port:
        site = f"https://127.0.0.1:{port}/"
        assert _message(cli, root, tmp_path, site, "--timeout", "0.5") == (
            f"cannot reach the registry at 127.0.0.1:{port} (timed out) to fetch top-level metadata; "
            f"check SITE {site} {ADVICE}"
        )


def test_an_untrusted_certificate_is_a_tls_failure(cli, root, tmp_path, serve):
    srv = serve("untrusted")
    message = _message(cli, root, tmp_path, srv.base)
    head = f"cannot reach the registry at 127.0.0.1:{srv.port} (TLS failed: [SSL: CERTIFICATE_VERIFY_FAILED] "
    tail = f") to fetch top-level metadata; check SITE {srv.base} {ADVICE}"
    assert message.startswith(head) and message.endswith(tail), message
    assert re.fullmatch(r"certificate verify failed: [^()]+ \(_ssl\.c:\d+\)", message[len(head) : -len(tail)]), message


def test_a_garbage_answer_is_named_by_its_first_200_characters(cli, root, tmp_path):
    with _raw_server(b"GARBAGE" + b"x" * 400 + b"\r\n\r\n") as port:
        site = f"http://127.0.0.1:{port}/"
        reason = "('Connection aborted.', BadStatusLine('GARBAGE" + "x" * 400
        assert _message(cli, root, tmp_path, site) == (
            f"cannot reach the registry at 127.0.0.1:{port} ({reason[:200]}) to fetch top-level metadata; "
            f"check SITE {site} {ADVICE}"
        )


def test_a_domain_role_that_cannot_be_fetched_names_the_role_and_the_site(cli, tmp_path, monkeypatch):
    """The top-level metadata loads; the domain's role (loaded on demand) then times out."""
    monkeypatch.setenv("HCDF_TRUST_PASSPHRASE", PASSPHRASE)
    reg = build(tmp_path / "reg", cli)
    with LoopbackServer(root=reg.site) as srv:
        srv.stall("/metadata/1.org.ros2.json")
        site = srv.base + "/"
        assert _message(cli, reg.root_json, tmp_path, site, "--timeout", "0.5") == (
            f"cannot reach the registry at 127.0.0.1:{srv.port} (timed out) to fetch org.ros2.json; "
            f"check SITE {site} {ADVICE}"
        )


def test_a_target_that_cannot_be_fetched_names_the_target_and_the_site(cli, tmp_path, monkeypatch):
    """Every role loads; the first schema download then times out."""
    monkeypatch.setenv("HCDF_TRUST_PASSPHRASE", PASSPHRASE)
    reg = build(tmp_path / "reg", cli)
    with LoopbackServer(root=reg.site) as srv:
        srv.stall("/" + reg.target_file("extensions/org.gazebosim/1.0.xsd").relative_to(reg.site).as_posix())
        site = srv.base + "/"
        assert _message(cli, reg.root_json, tmp_path, site, "--timeout", "0.5") == (
            f"cannot reach the registry at 127.0.0.1:{srv.port} (timed out) to fetch target "
            f"extensions/org.gazebosim/1.0.xsd; check SITE {site} {ADVICE}"
        )


def test_with_a_ca_bundle_the_client_names_itself_to_the_server(cli, tmp_path, monkeypatch, tls):
    """``--ca-bundle`` replaces python-tuf's connection pool; the replacement keeps a User-Agent
    naming this tool. Seen by a real TLS server on 127.0.0.1 that records every request's header
    and path (a site URL given with its final slash asks for ``/metadata/...``, not ``//metadata/...``)."""
    import functools
    import http.server

    monkeypatch.setenv("HCDF_TRUST_PASSPHRASE", PASSPHRASE)
    reg = build(tmp_path / "reg", cli)
    agents: list[str | None] = []
    paths: list[str] = []

    class Recording(http.server.SimpleHTTPRequestHandler):
        def do_GET(self) -> None:  # noqa: N802
            agents.append(self.headers.get("User-Agent"))
            paths.append(self.requestline.split(" ")[1])  # as sent (http.server collapses a leading //)
            super().do_GET()

        def log_message(self, format: str, *args: object) -> None:  # noqa: A002
            pass

    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(Recording, directory=str(reg.site)))
    httpd.socket = tls.server_context("good").wrap_socket(httpd.socket, server_side=True)
    thread = threading.Thread(target=httpd.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
    thread.start()
    try:
        site = f"https://127.0.0.1:{httpd.server_address[1]}/"
        res = cli("registry", "verify", site, "--trusted-root", reg.root_json, "--cache-dir", tmp_path / "c",
                  "--ca-bundle", tls.ca_pem)  # fmt: skip
        assert res.exit_code == 0, res.stderr
    finally:
        httpd.shutdown()
        httpd.server_close()
    assert agents and set(agents) == {"hcdf-trust python-tuf"}, agents
    # the site's final slash is not doubled: every request is /metadata/... or /targets/...
    assert all(p.split("/")[1] in ("metadata", "targets") and "//" not in p for p in paths), paths


def test_an_oci_site_named_insecure_is_reached_over_plain_http_despite_a_ca_bundle(
    cli,
    tmp_path,
    monkeypatch,
    tls,
    registry,  # noqa: F811
):
    """``--insecure-registry`` reaches the OCI transport of a TUF site: with a ``--ca-bundle`` a
    loopback registry is spoken to over TLS, unless it is named insecure (the test registry is
    plain http: over TLS the refresh fails)."""
    monkeypatch.setenv("HCDF_TRUST_PASSPHRASE", PASSPHRASE)
    reg = build(tmp_path / "reg", cli)
    ref = registry.ref("hcdf/insecure-site", "v1")
    assert reg.publish("--oci", ref).exit_code == 0
    common = ("registry", "verify", ref, "--trusted-root", reg.root_json, "--ca-bundle", tls.ca_pem)
    res = cli(*common, "--cache-dir", tmp_path / "c1")
    assert res.exit_code == 3, res.stderr  # TLS to a plain-http registry
    res = cli(*common, "--cache-dir", tmp_path / "c2", "--insecure-registry", registry.netloc)
    assert res.exit_code == 0, res.stderr


def test_a_site_url_whose_path_ends_in_x_is_used_as_written(cli, tmp_path, monkeypatch):
    """Only the final slashes of a site URL are dropped (``/siteX`` stays ``/siteX``)."""
    import shutil

    monkeypatch.setenv("HCDF_TRUST_PASSPHRASE", PASSPHRASE)
    reg = build(tmp_path / "reg", cli)
    served = tmp_path / "served"
    shutil.copytree(reg.site, served / "siteX")
    with LoopbackServer(root=served) as srv:
        for site in (srv.url("/siteX"), srv.url("/siteX/")):
            res = cli("registry", "verify", site, "--trusted-root", reg.root_json, "--cache-dir", tmp_path / "c")
            assert res.exit_code == 0, res.stderr
