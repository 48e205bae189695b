"""A real CNCF distribution server (Debian ``docker-registry``) on 127.0.0.1 for the OCI tests.

Started with its own configuration file (never the package's, which listens on every
interface), on a port the kernel picks (read back from its log), storing into a temporary
folder the tests can edit to play a compromised registry; with ``htpasswd`` it asks for
Basic credentials (a bcrypt line, as distribution requires).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
import shutil
import subprocess
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import pytest

BINARY = shutil.which("docker-registry") or "/usr/bin/docker-registry"


@dataclass
class Registry:
    root: Path  # storage root
    port: int
    process: subprocess.Popen[bytes]
    user: str | None = None
    password: str | None = None

    @property
    def netloc(self) -> str:
        return f"127.0.0.1:{self.port}"

    def ref(self, repo: str = "robots/scout", tag: str = "r1") -> str:
        return f"oci://{self.netloc}/{repo}:{tag}"

    def http(self) -> httpx.Client:
        auth = (self.user, self.password) if self.user and self.password else None
        return httpx.Client(base_url=f"http://{self.netloc}", auth=auth, timeout=10)

    def blob_path(self, digest: str) -> Path:
        hex_ = digest.split(":", 1)[1]
        return self.root / "docker/registry/v2/blobs/sha256" / hex_[:2] / hex_ / "data"

    def tag_link(self, repo: str, tag: str) -> Path:
        return self.root / f"docker/registry/v2/repositories/{repo}/_manifests/tags/{tag}/current/link"

    def manifest(self, repo: str, reference: str) -> tuple[bytes, str]:
        with self.http() as c:
            r = c.get(
                f"/v2/{repo}/manifests/{reference}",
                headers={
                    "Accept": "application/vnd.oci.image.manifest.v1+json,application/vnd.oci.image.index.v1+json"
                },
            )
            r.raise_for_status()
            return r.content, "sha256:" + hashlib.sha256(r.content).hexdigest()

    def put_manifest(
        self, repo: str, reference: str, body: bytes, media_type: str = "application/vnd.oci.image.manifest.v1+json"
    ) -> str:
        with self.http() as c:
            r = c.put(f"/v2/{repo}/manifests/{reference}", content=body, headers={"Content-Type": media_type})
            assert r.status_code == 201, r.text
        return "sha256:" + hashlib.sha256(body).hexdigest()

    def put_blob(self, repo: str, data: bytes) -> str:
        digest = "sha256:" + hashlib.sha256(data).hexdigest()
        with self.http() as c:
            r = c.post(f"/v2/{repo}/blobs/uploads/")
            assert r.status_code == 202, r.text
            loc = r.headers["location"]
            sep = "&" if "?" in loc else "?"  # the upload URL's own query (_state) stays
            r = c.put(f"{loc}{sep}digest={digest}", content=data, headers={"Content-Type": "application/octet-stream"})
            assert r.status_code == 201, r.text
        return digest


def start_registry(
    folder: Path, *, user: str | None = None, password: str | None = None, tls: tuple[Path, Path] | None = None
) -> Registry:
    folder.mkdir(parents=True, exist_ok=True)
    storage = folder / "storage"
    config = {
        "version": 0.1,
        "log": {"level": "info"},
        "storage": {"filesystem": {"rootdirectory": str(storage)}, "delete": {"enabled": True}},
        "http": {"addr": "127.0.0.1:0", "secret": "test-secret-not-a-credential"},
    }
    if user is not None:
        import bcrypt

        assert password is not None
        line = f"{user}:{bcrypt.hashpw(password.encode(), bcrypt.gensalt(rounds=4)).decode()}\n"
        (folder / "htpasswd").write_text(line)
        config["auth"] = {"htpasswd": {"realm": "hcdf-test", "path": str(folder / "htpasswd")}}
    if tls is not None:
        config["http"]["tls"] = {"certificate": str(tls[0]), "key": str(tls[1])}  # type: ignore[index]
    # JSON is YAML: no YAML writer needed
    (folder / "config.yml").write_text(json.dumps(config))
    log = open(folder / "registry.log", "wb")  # noqa: SIM115 -- the process writes it until stopped
    env = {k: v for k, v in os.environ.items() if not k.startswith("REGISTRY_")}
    proc = subprocess.Popen([BINARY, "serve", str(folder / "config.yml")], stdout=log, stderr=log, env=env)
    log.close()
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:
        m = re.search(rb"listening on 127\.0\.0\.1:(\d+)", (folder / "registry.log").read_bytes())
        if m:
            return Registry(storage, int(m.group(1)), proc, user, password)
        if proc.poll() is not None:
            break
        time.sleep(0.02)
    proc.kill()
    raise RuntimeError("docker-registry did not start: " + (folder / "registry.log").read_text()[-2000:])


def stop_registry(reg: Registry) -> None:
    reg.process.terminate()
    with contextlib.suppress(subprocess.TimeoutExpired):
        reg.process.wait(5)
    if reg.process.poll() is None:
        reg.process.kill()
        reg.process.wait()


@pytest.fixture(scope="module")
def registry(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Registry]:
    if not os.path.exists(BINARY):
        pytest.fail("docker-registry is not installed (.ci/apt-packages lists it)")
    reg = start_registry(tmp_path_factory.mktemp("registry"))
    yield reg
    stop_registry(reg)


USER = "robot-ci"
PASSWORD = "s3cret-Registry-Passw0rd"


@pytest.fixture(scope="module")
def auth_registry(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Registry]:
    reg = start_registry(tmp_path_factory.mktemp("registry-auth"), user=USER, password=PASSWORD)
    yield reg
    stop_registry(reg)


MANIFEST_TYPE = "application/vnd.oci.image.manifest.v1+json"
INDEX_TYPE = "application/vnd.oci.image.index.v1+json"


def mirror(srv, registry: Registry, repo: str, tag: str, *, referrers_api: bool = False) -> tuple[str, dict]:
    """Serve what ``registry`` holds under ``repo:tag`` from the loopback test server ``srv``
    (a registry the test can make misbehave path by path); returns the manifest digest and doc.
    ``referrers_api``: answer ``/referrers/<digest>`` (OCI 1.1) instead of the fallback tag."""
    srv.add("/v2/", b"{}", headers={"Content-Type": "application/json"})
    body, digest = registry.manifest(repo, tag)
    doc = json.loads(body)
    for ref in (tag, digest):
        srv.add(f"/v2/{repo}/manifests/{ref}", body, headers={"Content-Type": MANIFEST_TYPE})
    for layer in [doc["config"], *doc["layers"]]:
        srv.add(f"/v2/{repo}/blobs/{layer['digest']}", registry.blob_path(layer["digest"]).read_bytes())
    index, _ = registry.manifest(repo, digest.replace(":", "-"))
    for entry in json.loads(index)["manifests"]:
        sig, _ = registry.manifest(repo, entry["digest"])
        srv.add(f"/v2/{repo}/manifests/{entry['digest']}", sig, headers={"Content-Type": MANIFEST_TYPE})
        for layer in json.loads(sig)["layers"]:  # the provenance and SBOM blobs
            srv.add(f"/v2/{repo}/blobs/{layer['digest']}", registry.blob_path(layer["digest"]).read_bytes())
    if referrers_api:
        srv.add(f"/v2/{repo}/referrers/{digest}", index, headers={"Content-Type": INDEX_TYPE})
    else:
        srv.add(f"/v2/{repo}/manifests/{digest.replace(':', '-')}", index, headers={"Content-Type": INDEX_TYPE})
    return digest, doc


class TokenFront:
    """A bearer-token registry on 127.0.0.1: ``/token`` hands a token for the right Basic
    credentials (the Docker token protocol); every ``/v2/`` request without that token gets
    401 with ``WWW-Authenticate: Bearer realm=…``; the rest is passed to a real registry."""

    def __init__(self, backend: Registry, user: str, password: str) -> None:
        import base64
        import http.server
        import secrets
        import threading

        self.token = "tok-" + secrets.token_hex(16)
        self.seen_auth: list[str] = []
        front = self
        good = "Basic " + base64.b64encode(f"{user}:{password}".encode()).decode()

        class Handler(http.server.BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"

            def log_message(self, *a):  # noqa: ANN002
                pass

            def _reply(self, status, body=b"", headers=()):
                self.send_response(status)
                for k, v in headers:
                    self.send_header(k, v)
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                if self.command != "HEAD":
                    self.wfile.write(body)

            def _any(self):
                auth = self.headers.get("Authorization", "")
                front.seen_auth.append(auth)
                if self.path.startswith("/token"):
                    if auth != good:
                        return self._reply(401)
                    return self._reply(200, json.dumps({"token": front.token}).encode())
                if auth != f"Bearer {front.token}":
                    realm = f'Bearer realm="http://127.0.0.1:{front.port}/token",service="test"'
                    return self._reply(401, b"{}", [("WWW-Authenticate", realm)])
                length = int(self.headers.get("Content-Length") or 0)
                body = self.rfile.read(length) if length else None
                keep = {k: v for k, v in self.headers.items() if k.lower() in ("accept", "content-type")}
                with httpx.Client(base_url=f"http://{backend.netloc}", timeout=30) as c:
                    r = c.request(self.command, self.path, content=body, headers=keep)
                hdrs = [
                    (k, v.replace(backend.netloc, f"127.0.0.1:{front.port}"))
                    for k, v in r.headers.items()
                    if k.lower() in ("content-type", "location", "docker-content-digest", "oci-subject")
                ]
                self._reply(r.status_code, r.content, hdrs)

            do_GET = do_HEAD = do_PUT = do_POST = do_PATCH = _any  # noqa: N815

        self.httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.port = self.httpd.server_address[1]
        threading.Thread(target=self.httpd.serve_forever, daemon=True).start()

    def ref(self, repo: str = "robots/scout", tag: str = "r1") -> str:
        return f"oci://127.0.0.1:{self.port}/{repo}:{tag}"

    def close(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()


@contextlib.contextmanager
def running_registry(folder: Path, **kw: Any) -> Iterator[Registry]:
    """:func:`start_registry` for one ``with`` block (stopped whatever happens)."""
    reg = start_registry(folder, **kw)
    try:
        yield reg
    finally:
        stop_registry(reg)


def module_cli() -> Any:
    """The CLI in-process, for module-scoped fixtures (conftest's ``cli`` is function-scoped)."""
    from click.testing import CliRunner

    from hcdf_trust.cli import main
    from tests.conftest import CliResult

    def run(*args: Any) -> CliResult:
        r = CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)
        return CliResult(r.exit_code, r.stdout, r.stderr)

    return run
