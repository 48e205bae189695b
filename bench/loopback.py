"""A loopback HTTP/1.1 file server for the benchmarks (127.0.0.1 only).

Unlike ``python -m http.server`` it listens with a backlog of 128 and sets
TCP_NODELAY (notes/env.md §4: a backlog of 5 turns 16 parallel connects into
1 s SYN retransmits, and Nagle stalls HTTP/1.1), keeps connections alive, sends
bodies with ``sendfile`` and can add a fixed delay before every response.
"""

from __future__ import annotations

import os
import socket
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import unquote, urlsplit


class _Server(ThreadingHTTPServer):
    request_queue_size = 128
    daemon_threads = True
    allow_reuse_address = True

    root: Path
    delay: float
    hits: int
    hits_lock: threading.Lock


class _Handler(BaseHTTPRequestHandler):
    protocol_version = "HTTP/1.1"
    server: _Server

    def setup(self) -> None:
        super().setup()
        self.connection.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    def log_message(self, format: str, *args: object) -> None:  # noqa: A002 - base signature
        pass

    def do_GET(self) -> None:  # noqa: N802 - http.server naming
        with self.server.hits_lock:
            self.server.hits += 1
        if self.server.delay:
            time.sleep(self.server.delay)
        rel = unquote(urlsplit(self.path).path).lstrip("/")
        path = (self.server.root / rel).resolve()
        if self.server.root not in path.parents or not path.is_file():
            self.send_error(404)
            return
        with open(path, "rb") as f:
            size = os.fstat(f.fileno()).st_size
            self.send_response(200)
            self.send_header("Content-Type", "application/octet-stream")
            self.send_header("Content-Length", str(size))
            self.end_headers()
            self.wfile.flush()
            self.connection.sendfile(f)


class LoopbackServer:
    """Serve ``root`` on 127.0.0.1:<free port> in a background thread.

    ``delay`` seconds are slept before each response (simulated latency).
    Use as a context manager; ``url`` is the base URL with a trailing slash.
    """

    def __init__(self, root: str | os.PathLike[str], *, delay: float = 0.0) -> None:
        self.httpd = _Server(("127.0.0.1", 0), _Handler)
        self.httpd.root = Path(root).resolve()
        self.httpd.delay = delay
        self.httpd.hits = 0
        self.httpd.hits_lock = threading.Lock()
        self.thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)

    @property
    def url(self) -> str:
        host, port = self.httpd.server_address[:2]
        return f"http://{host}:{port}/"

    @property
    def hits(self) -> int:
        return self.httpd.hits

    def __enter__(self) -> LoopbackServer:
        self.thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()
        self.thread.join()
