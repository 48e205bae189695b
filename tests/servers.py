"""A real, misbehaving-on-request HTTP(S) server on 127.0.0.1 for the network tests.

It binds to 127.0.0.1 only, serves each connection on its own thread (HTTP/1.1
keep-alive), listens with a backlog of 128 and sets TCP_NODELAY: with the
standard library's backlog of 5, parallel connects overflow the accept queue
and each dropped SYN costs a 1 s retransmit (../shared/notes/env.md §4).

Files come from a dict (:meth:`LoopbackServer.add`) or a folder (``root=``).
Any path can instead be told to misbehave::

    srv.redirect("/r", "/a.glb")                 # 302 to a path, http://, file://, itself
    srv.stall("/s")                              # headers never come
    srv.stall("/s2", after=1000, body=data)      # headers and 1000 bytes, then silence
    srv.lie("/l", data, declared=len(data) + 9)  # Content-Length that lies (either way)
    srv.reset("/x", data, after=4096)            # TCP RST in the middle of the body
    srv.gzip_bomb("/b", expanded=256 << 20)      # Content-Encoding: gzip, tiny on the wire
    srv.stream("/big", size, chunked=True)       # a generated body of any size
    srv.drip("/d", data, every=0.2)              # one byte at a time
    srv.latency = 0.02                           # added before every response

``srv.hits[path]`` counts requests per path (``srv.total_hits`` all of them);
``srv.max_in_flight`` is the most requests answered at once (while the latency sleeps).
TLS certificates come from ``trustme``: see the fixtures at the bottom, which
this suite registers as a plugin from ``tests/conftest.py``.
"""

from __future__ import annotations

import datetime as dt
import functools
import http.server
import mimetypes
import os
import socket
import ssl
import struct
import threading
import time
import zlib
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import unquote, urlsplit

import pytest

HOST = "127.0.0.1"  # never anything else


@dataclass
class Route:
    """How one path answers. ``body`` None with no other behaviour means 404."""

    body: bytes | None = None
    status: int = 200
    headers: dict[str, str] = field(default_factory=dict)
    redirect: str | None = None  # Location header; "{base}" is replaced by the server's URL
    stall_after: int | None = None  # send headers + this many body bytes, then hang (-1: no headers)
    declared_length: int | None = None  # Content-Length to announce instead of the true one
    reset_after: int | None = None  # send this many body bytes, then RST the connection
    stream_size: int | None = None  # generate this many bytes instead of sending ``body``
    chunked: bool = False  # Transfer-Encoding: chunked (no Content-Length)
    close_delimited: bool = False  # no Content-Length, no chunking: the body ends at close
    drip_every: float | None = None  # seconds between single bytes
    latency: float = 0.0


class LoopbackServer:
    """A threaded HTTP/1.1 server on 127.0.0.1; HTTPS when given a TLS context."""

    def __init__(self, *, tls: ssl.SSLContext | None = None, root: str | os.PathLike[str] | None = None) -> None:
        self.tls = tls
        self.root = Path(root) if root is not None else None
        self.routes: dict[str, Route] = {}
        self.hits: Counter[str] = Counter()
        self.latency = 0.0
        self.in_flight = 0  # requests being answered now, and the most at once
        self.max_in_flight = 0
        self.closing = threading.Event()
        self._lock = threading.Lock()
        self._httpd = _Server((HOST, 0), _Handler, owner=self)
        self.port = self._httpd.server_address[1]
        self.scheme = "https" if tls is not None else "http"
        self.base = f"{self.scheme}://{HOST}:{self.port}"
        self._thread = threading.Thread(target=self._httpd.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
        self._thread.start()

    # -- configuration --------------------------------------------------------------

    def url(self, path: str = "/") -> str:
        return self.base + (path if path.startswith("/") else "/" + path)

    def add(self, path: str, body: bytes, **kw: Any) -> str:
        """Serve ``body`` at ``path``; returns its URL."""
        self.routes[_norm(path)] = Route(body=body, **kw)
        return self.url(path)

    def redirect(self, path: str, location: str, *, status: int = 302) -> str:
        """Answer ``path`` with a redirect; ``location`` may be a path or any URL."""
        self.routes[_norm(path)] = Route(status=status, redirect=location)
        return self.url(path)

    def stall(self, path: str, *, after: int = -1, body: bytes = b"") -> str:
        """Never answer (``after=-1``), or send headers and ``after`` bytes then hang."""
        self.routes[_norm(path)] = Route(body=body, stall_after=after)
        return self.url(path)

    def lie(self, path: str, body: bytes, *, declared: int) -> str:
        """Announce ``Content-Length: declared`` and send ``body``, then close."""
        self.routes[_norm(path)] = Route(body=body, declared_length=declared)
        return self.url(path)

    def reset(self, path: str, body: bytes, *, after: int) -> str:
        """Send headers for all of ``body`` but only ``after`` bytes, then reset (RST)."""
        self.routes[_norm(path)] = Route(body=body, reset_after=after)
        return self.url(path)

    def stream(self, path: str, size: int, *, chunked: bool = False) -> str:
        """A generated body of ``size`` bytes (not held in memory)."""
        self.routes[_norm(path)] = Route(stream_size=size, chunked=chunked)
        return self.url(path)

    def gzip_bomb(self, path: str, *, expanded: int = 256 << 20) -> str:
        """``Content-Encoding: gzip`` whose body inflates to ``expanded`` zero bytes."""
        self.routes[_norm(path)] = Route(body=gzip_zeros(expanded), headers={"Content-Encoding": "gzip"})
        return self.url(path)

    def drip(self, path: str, body: bytes, *, every: float) -> str:
        """Send ``body`` one byte every ``every`` seconds (under any read timeout)."""
        self.routes[_norm(path)] = Route(body=body, drip_every=every)
        return self.url(path)

    @property
    def total_hits(self) -> int:
        return sum(self.hits.values())

    # -- lifecycle ------------------------------------------------------------------

    def close(self) -> None:
        self.closing.set()  # releases stalled handlers
        self._httpd.shutdown()
        self._httpd.server_close()
        self._thread.join(timeout=5)

    def __enter__(self) -> LoopbackServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- used by the handler --------------------------------------------------------

    def _count(self, path: str) -> None:
        with self._lock:
            self.hits[path] += 1

    def _route(self, path: str) -> Route | None:
        route = self.routes.get(path)
        if route is not None or self.root is None:
            return route
        file = (self.root / unquote(path).lstrip("/")).resolve()
        root = self.root.resolve()
        if root not in file.parents or not file.is_file():
            return None
        return Route(
            body=file.read_bytes(),
            headers={"Content-Type": mimetypes.guess_type(file.name)[0] or "application/octet-stream"},
        )


class _Server(http.server.ThreadingHTTPServer):
    request_queue_size = 128
    daemon_threads = True
    block_on_close = False
    allow_reuse_address = True

    def __init__(self, address: tuple[str, int], handler: type, *, owner: LoopbackServer) -> None:
        self.owner = owner
        super().__init__(address, handler)

    def finish_request(self, request: Any, client_address: Any) -> None:
        tls = self.owner.tls
        if tls is None:
            super().finish_request(request, client_address)
            return
        # Handshake on the connection's own thread, so one slow or failing client
        # (e.g. one that rejects our certificate) never blocks the accept loop.
        request.settimeout(10)
        try:
            conn = tls.wrap_socket(request, server_side=True)
        except (ssl.SSLError, OSError):
            return
        try:
            super().finish_request(conn, client_address)
        finally:
            conn.close()

    def handle_error(self, request: Any, client_address: Any) -> None:
        pass  # clients that hang up on us are the point of most tests


class _Handler(http.server.BaseHTTPRequestHandler):
    protocol_version = "HTTP/1.1"
    disable_nagle_algorithm = True  # TCP_NODELAY
    server: _Server

    def log_message(self, format: str, *args: Any) -> None:  # noqa: A002
        pass

    def do_HEAD(self) -> None:  # noqa: N802
        self.do_GET()

    def do_GET(self) -> None:  # noqa: N802
        owner = self.server.owner
        path = _norm(urlsplit(self.path).path)
        owner._count(path)
        route = owner._route(path)
        delay = owner.latency + (route.latency if route else 0.0)
        if delay:
            with owner._lock:
                owner.in_flight += 1
                owner.max_in_flight = max(owner.max_in_flight, owner.in_flight)
            time.sleep(delay)
            with owner._lock:
                owner.in_flight -= 1
        if route is None:
            self._send_simple(404, b"not found\n")
            return
        if route.stall_after is not None and route.stall_after < 0:
            owner.closing.wait()
            self.close_connection = True
            return
        if route.redirect is not None:
            self.send_response(route.status)
            self.send_header("Location", route.redirect.replace("{base}", owner.base))
            self.send_header("Content-Length", "0")
            self.end_headers()
            return
        self._send_body(route)

    def _send_simple(self, status: int, body: bytes) -> None:
        self.send_response(status)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def _send_body(self, route: Route) -> None:
        owner = self.server.owner
        size = route.stream_size if route.stream_size is not None else len(route.body or b"")
        self.send_response(route.status)
        for name, value in route.headers.items():
            self.send_header(name, value)
        if route.chunked:
            self.send_header("Transfer-Encoding", "chunked")
        elif route.close_delimited:
            self.send_header("Connection", "close")
            self.close_connection = True
        else:
            declared = route.declared_length if route.declared_length is not None else size
            self.send_header("Content-Length", str(declared))
        if route.declared_length is not None:
            self.send_header("Connection", "close")
            self.close_connection = True
        self.end_headers()
        if self.command == "HEAD":
            return
        sent = 0
        for chunk in self._chunks(route):
            if route.reset_after is not None and sent + len(chunk) >= route.reset_after:
                self.wfile.write(chunk[: route.reset_after - sent])
                self.wfile.flush()
                self._reset()
                return
            if route.stall_after is not None and sent + len(chunk) >= route.stall_after:
                self.wfile.write(chunk[: route.stall_after - sent])
                self.wfile.flush()
                owner.closing.wait()
                self.close_connection = True
                return
            if route.chunked:
                self.wfile.write(b"%x\r\n%s\r\n" % (len(chunk), chunk))
            else:
                self.wfile.write(chunk)
            sent += len(chunk)
            if route.drip_every is not None:
                self.wfile.flush()
                if owner.closing.wait(route.drip_every):
                    self.close_connection = True
                    return
        if route.chunked:
            self.wfile.write(b"0\r\n\r\n")
        self.wfile.flush()

    @staticmethod
    def _chunks(route: Route) -> Iterator[bytes]:
        if route.drip_every is not None:
            body = route.body or b""
            for i in range(len(body)):
                yield body[i : i + 1]
            return
        if route.stream_size is not None:
            block = b"\xa5" * (64 << 10)
            left = route.stream_size
            while left > 0:
                n = min(left, len(block))
                yield block[:n]
                left -= n
            return
        body = route.body or b""
        for i in range(0, len(body), 64 << 10):
            yield body[i : i + (64 << 10)]

    def _reset(self) -> None:
        """Close with SO_LINGER 0: the kernel sends RST instead of FIN."""
        sock = self.connection
        raw = sock
        if isinstance(sock, ssl.SSLSocket):
            # Reset the TCP connection under TLS too: no close_notify is sent.
            raw = socket.socket(fileno=sock.detach())
        raw.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        raw.close()
        self.close_connection = True
        self.wfile = _Discard()  # StreamRequestHandler.finish() flushes it


class _Discard:
    closed = False

    def write(self, data: bytes) -> int:
        return len(data)

    def flush(self) -> None:
        pass

    def close(self) -> None:
        pass


def _norm(path: str) -> str:
    return "/" + path.lstrip("/")


@functools.lru_cache(maxsize=4)
def gzip_zeros(expanded: int) -> bytes:
    """A gzip member that inflates to ``expanded`` zero bytes (about 1000:1)."""
    comp = zlib.compressobj(9, zlib.DEFLATED, zlib.MAX_WBITS | 16)
    block = bytes(1 << 20)
    parts = []
    left = expanded
    while left > 0:
        n = min(left, len(block))
        parts.append(comp.compress(block[:n]))
        left -= n
    parts.append(comp.flush())
    return b"".join(parts)


# -- TLS material -----------------------------------------------------------------------


@dataclass
class TlsMaterial:
    """A test CA (trusted via ``ca_pem``) and server contexts of several kinds."""

    ca: Any  # trustme.CA
    ca_pem: Path
    other_ca: Any  # a CA the client is never told about

    def server_context(self, kind: str = "good") -> ssl.SSLContext:
        """A server context: ``good`` (issued by ``ca``), ``untrusted`` (by ``other_ca``)
        or ``expired`` (by ``ca``, validity ended yesterday)."""
        if kind == "good":
            cert = self.ca.issue_cert(HOST, "localhost")
        elif kind == "untrusted":
            cert = self.other_ca.issue_cert(HOST, "localhost")
        elif kind == "expired":
            now = dt.datetime.now(dt.UTC)
            cert = self.ca.issue_cert(
                HOST,
                "localhost",
                not_before=now - dt.timedelta(days=30),
                not_after=now - dt.timedelta(days=1),
            )
        else:
            raise ValueError(kind)
        ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
        cert.configure_cert(ctx)
        return ctx


# -- pytest fixtures (registered as a plugin from tests/conftest.py) --------------------


@pytest.fixture(scope="session")
def tls(tmp_path_factory: pytest.TempPathFactory) -> TlsMaterial:
    trustme = pytest.importorskip("trustme")
    ca = trustme.CA()
    pem = tmp_path_factory.mktemp("tls") / "ca.pem"
    ca.cert_pem.write_to_path(str(pem))
    return TlsMaterial(ca=ca, ca_pem=pem, other_ca=trustme.CA())


@pytest.fixture
def serve(tls: TlsMaterial) -> Iterator[Any]:
    """Factory: ``serve(tls="good"|"untrusted"|"expired"|None, root=DIR)`` → a started server."""
    servers: list[LoopbackServer] = []

    def start(kind: str | None = "good", *, root: str | os.PathLike[str] | None = None) -> LoopbackServer:
        ctx = tls.server_context(kind) if kind is not None else None
        srv = LoopbackServer(tls=ctx, root=root)
        servers.append(srv)
        return srv

    yield start
    for srv in servers:
        srv.close()


@pytest.fixture
def https_server(serve: Any) -> LoopbackServer:
    """An HTTPS server whose certificate ``tls.ca_pem`` trusts."""
    return serve("good")


@pytest.fixture
def http_server(serve: Any) -> LoopbackServer:
    """A plain-http server."""
    return serve(None)
