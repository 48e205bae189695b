"""The HTTPS fetcher: the only code that talks to servers (local files: ``localfile.py``).

It yields the body as byte chunks, so callers hash while streaming in constant
memory. Checks made here are transport checks (TLS, redirects, size, time);
whether the bytes are the *right* bytes is decided by the resolver against the pins.
"""

from __future__ import annotations

import contextlib
import ssl
import threading
import time
import zlib
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from types import ModuleType
from typing import TYPE_CHECKING
from urllib.parse import urljoin, urlsplit

from ..digest import CHUNK
from ..errors import FetchError, InputError
from ..localfile import read_input
from .locate import redact

if TYPE_CHECKING:
    import httpx


DEFAULT_MAX_BYTES = 4 << 30
DEFAULT_TIMEOUT = 30.0
DEFAULT_DEADLINE = 600.0
MAX_REDIRECTS = 5


def _import_httpx() -> ModuleType:
    """Import httpx only when a URL is fetched (~90 ms), without its command line.

    httpx's ``__init__`` imports its own CLI (``httpx._main``: click, rich,
    pygments) when those are installed, as they are here; it falls back to a stub
    when that import fails. Blocking it saves ~40 ms per run (measured: 160 -> 120 ms
    for ``python -c "import httpx"``) and changes nothing we use.
    """
    import sys

    sys.modules.setdefault("httpx._main", None)  # type: ignore[arg-type]  # None blocks an import; typeshed omits it
    import httpx

    return httpx


@dataclass
class HttpFetcher:
    """HTTPS through httpx: TLS verified, timeouts, size limit, redirect rules.

    Redirects are followed by hand so that every hop is checked: at most
    ``max_redirects``, never to another scheme than https (http only where
    ``allow_http`` and the original URL was http), never from https down to http.
    ``timeout`` bounds every wait for the server (connect, each read);
    ``deadline`` bounds the whole fetch, so a server that drips one byte at a
    time cannot hold a fetch open forever. ``max_bytes`` bounds the body both
    as sent and after any ``Content-Encoding`` is undone (a gzip bomb stops at
    the limit, in constant memory). One instance is safe to share between threads.
    """

    ca_bundle: str | None = None
    allow_http: bool = False
    timeout: float = DEFAULT_TIMEOUT
    deadline: float = DEFAULT_DEADLINE
    max_bytes: int = DEFAULT_MAX_BYTES
    max_redirects: int = MAX_REDIRECTS
    max_connections: int = 16

    def __post_init__(self) -> None:
        self._client: httpx.Client | None = None
        self._client_lock = threading.Lock()
        self._ssl: ssl.SSLContext | bool = load_ca_bundle(self.ca_bundle) if self.ca_bundle else True

    def _get_client(self) -> httpx.Client:
        with self._client_lock:  # resolver threads race to the first fetch
            if self._client is None:
                httpx = _import_httpx()

                self._client = httpx.Client(
                    verify=self._ssl,
                    timeout=httpx.Timeout(self.timeout),
                    follow_redirects=False,
                    trust_env=False,
                    limits=httpx.Limits(
                        max_connections=self.max_connections,
                        max_keepalive_connections=self.max_connections,
                    ),
                    headers={"Accept-Encoding": "identity", "User-Agent": "hcdf-trust"},
                )
            return self._client

    def close(self) -> None:
        with self._client_lock:
            if self._client is not None:
                self._client.close()
                self._client = None

    @contextlib.contextmanager
    def open(self, url: str, *, file: str | None = None, line: int | None = None) -> Iterator[Iterator[bytes]]:
        """Yield the body of ``url`` as chunks of at most :data:`CHUNK` bytes.

        Raises:
            FetchError: any transport fault (TLS, timeout, redirect rule, HTTP
            status, size limit, connection closed or reset before the end).
        """
        httpx = _import_httpx()
        client = self._get_client()
        started = time.monotonic()
        current = url
        original_scheme = urlsplit(url).scheme.lower()
        self._check_scheme(current, original_scheme, url, file=file, line=line)
        consuming = False
        for _hop in range(self.max_redirects + 1):
            try:
                with client.stream("GET", current) as response:
                    if response.is_redirect:
                        location = response.headers.get("location", "").strip()
                        if not location:
                            raise FetchError(
                                f"{current}: HTTP {response.status_code} redirect without a Location",
                                file=file,
                                line=line,
                                url=url,
                            )
                        current = urljoin(current, location)
                        self._check_scheme(current, original_scheme, url, file=file, line=line)
                        if "@" in urlsplit(current).netloc:  # httpx would send them as Basic auth
                            raise FetchError(
                                f"{url}: redirect to a URL with credentials is refused ({redact(current)})",
                                file=file,
                                line=line,
                                url=url,
                            )
                        continue
                    if response.status_code != 200:
                        raise FetchError(f"{current}: HTTP {response.status_code}", file=file, line=line, url=url)
                    declared = response.headers.get("content-length")
                    if declared and declared.isdigit() and int(declared) > self.max_bytes:
                        raise FetchError(
                            f"{current}: Content-Length {declared} is over the {self.max_bytes}-byte limit",
                            file=file,
                            line=line,
                            url=url,
                        )
                    decoder = _decoder(response.headers.get("content-encoding"), current, url, file, line)
                    framed = declared is not None or "chunked" in response.headers.get("transfer-encoding", "").lower()
                    if not framed and decoder is None and response.http_version != "HTTP/2":
                        # The body ends where the connection does: a connection cut
                        # short (and a TLS stream truncated without close_notify,
                        # which Python reports as a clean end) would look complete.
                        raise FetchError(
                            f"{current}: the response has neither Content-Length nor chunked "
                            "encoding, so a truncated body could not be told from a whole one",
                            file=file,
                            line=line,
                            url=url,
                        )
                    consuming = True
                    yield self._body(response, decoder, started, current, url, file, line)
                    return
            except FetchError:
                raise
            except (httpx.HTTPError, httpx.InvalidURL, ssl.SSLError, OSError) as exc:
                if consuming:
                    # Raised by the caller's handling of the body (its cache file, its
                    # descriptors): transport faults while reading are converted in _body.
                    raise InputError(
                        f"{current}: storing the body failed: {_describe(exc)}", file=file, line=line, url=url
                    ) from exc
                raise self._transport_error(exc, httpx, current, url, file, line) from None
        raise FetchError(
            f"{url}: more than {self.max_redirects} redirects (a redirect loop?)",
            file=file,
            line=line,
            url=url,
        )

    def _body(
        self,
        response: httpx.Response,
        decoder: _Decoder | None,
        started: float,
        current: str,
        url: str,
        file: str | None,
        line: int | None,
    ) -> Iterator[bytes]:
        # iter_raw yields each network read as it arrives (no re-chunking), so the
        # deadline and the limits are checked after every read, and the encoding
        # is undone here with a bounded output size instead of by httpx, whose
        # decoder inflates a whole network read at once (~1000x for a gzip bomb).
        raw_size = 0
        size = 0

        def over() -> FetchError:
            return FetchError(
                f"{current}: body is over the {self.max_bytes}-byte limit",
                file=file,
                line=line,
                url=url,
            )

        httpx = _import_httpx()
        raws = response.iter_raw()
        while True:
            try:
                raw = next(raws)
            except StopIteration:
                break
            except (httpx.HTTPError, ssl.SSLError, OSError) as exc:
                raise self._transport_error(exc, httpx, current, url, file, line) from None
            raw_size += len(raw)
            if raw_size > self.max_bytes:
                raise over()
            if time.monotonic() - started > self.deadline:
                raise FetchError(
                    f"{current}: took longer than {self.deadline:g} s",
                    file=file,
                    line=line,
                    url=url,
                )
            if decoder is None:
                chunks: Iterable[bytes] = (raw,)
            else:
                chunks = decoder.feed(raw, self.max_bytes - size + 1)
            for chunk in chunks:
                size += len(chunk)
                if size > self.max_bytes:
                    raise over()
                yield chunk
        if decoder is not None:
            decoder.finish()

    def _transport_error(
        self, exc: BaseException, httpx: ModuleType, current: str, url: str, file: str | None, line: int | None
    ) -> FetchError:
        """The fetch error for a transport fault raised by httpx, ssl or the socket."""
        if isinstance(exc, httpx.TimeoutException):
            text = f"{current}: timed out (no data for {self.timeout:g} s)"
        elif isinstance(exc, httpx.RemoteProtocolError):
            text = f"{current}: the server broke the HTTP exchange ({_describe(exc)})"
        else:
            text = f"{current}: {_describe(exc)}"
        return FetchError(text, file=file, line=line, url=url)

    def _check_scheme(self, current: str, original: str, url: str, *, file: str | None, line: int | None) -> None:
        scheme = urlsplit(current).scheme.lower()
        if scheme == "https":
            return
        if scheme == "http" and self.allow_http and original == "http":
            return
        if current == url:
            reason = "plain http is refused without --allow-http and a full SHA-256 pin"
        elif scheme == "http" and original == "https":
            reason = "redirect from https down to http is refused"
        elif scheme == "http":
            reason = "redirect to plain http is refused without --allow-http"
        else:
            reason = f"redirect to a {scheme or 'relative'}: URL is refused"
        allowed = "an https or http URL" if self.allow_http and original == "http" else "an https URL"
        raise FetchError(
            f"{url}: {reason} ({current})", file=file, line=line, url=url, expected=allowed, actual=current
        )


MAX_CA_BUNDLE_BYTES = 16 << 20


def load_ca_bundle(path: str) -> ssl.SSLContext:
    """A TLS client context that trusts the CA certificates of the PEM file ``path``.

    Read once, bounded and non-blocking like every local input (a FIFO or a huge
    file is refused, not waited on).

    Raises:
        InputError: missing or unreadable, or not a PEM file of certificates.
    """
    data = read_input(path, limit=MAX_CA_BUNDLE_BYTES, what="CA bundle", source=path)
    try:
        text = data.decode("ascii")
    except UnicodeDecodeError:
        text = ""
    if "-----BEGIN CERTIFICATE-----" not in text:
        raise InputError(
            f"--ca-bundle {path} is not a PEM file of CA certificates (no BEGIN CERTIFICATE block)",
            file=path,
        )
    try:
        return ssl.create_default_context(cadata=text)
    except (ssl.SSLError, ValueError) as exc:
        raise InputError(f"--ca-bundle {path}: its certificates cannot be loaded: {exc}", file=path) from None


class _Decoder:
    """Undo a gzip or deflate ``Content-Encoding`` with bounded output per step."""

    def __init__(self, encoding: str, current: str, url: str, file: str | None, line: int | None) -> None:
        self.encoding = encoding
        self.where = (current, url, file, line)
        self.gzip = encoding in ("gzip", "x-gzip")
        self.started = False
        self.raw_deflate = False
        self._d = self._new()

    def _new(self) -> zlib._Decompress:
        if self.gzip:
            return zlib.decompressobj(zlib.MAX_WBITS | 16)
        return zlib.decompressobj(-zlib.MAX_WBITS if self.raw_deflate else zlib.MAX_WBITS)

    def _error(self, what: str) -> FetchError:
        current, url, file, line = self.where
        return FetchError(f"{current}: Content-Encoding {self.encoding}: {what}", file=file, line=line, url=url)

    def feed(self, data: bytes, budget: int) -> Iterator[bytes]:
        """Yield the decoded bytes of ``data``, at most ``min(CHUNK, budget)`` at a time."""
        step = max(1, min(CHUNK, budget))
        while data:
            if self._d.eof:
                # Past the end of a stream: zero padding (tolerated, as gzip(1)
                # does, and dropped as it comes, so it costs no memory), or the
                # next member of a multi-member gzip. Anything else is an error.
                data = data.lstrip(b"\0")
                if not data:
                    return
                if not self.gzip:
                    raise self._error("data after the end of the stream")
                self._d = self._new()
            try:
                out = self._d.decompress(data, step)
            except zlib.error as exc:
                if not self.gzip and not self.started and not self.raw_deflate:
                    # "deflate" is meant to be zlib-wrapped; some servers send it raw.
                    self.raw_deflate = True
                    self._d = self._new()
                    continue
                raise self._error(f"corrupt data ({exc})") from None
            self.started = True
            # Input not yet inflated (output was capped), or, at the end of the
            # stream, whatever followed it.
            data = self._d.unused_data if self._d.eof else self._d.unconsumed_tail
            if out:
                yield out

    def finish(self) -> None:
        if self.started and not self._d.eof:
            raise self._error("the body ends before the compressed stream does (truncated)")


def _decoder(header: str | None, current: str, url: str, file: str | None, line: int | None) -> _Decoder | None:
    """The decoder for a response's ``Content-Encoding`` (we asked for identity)."""
    encoding = (header or "").strip().lower()
    if encoding in ("", "identity"):
        return None
    if encoding in ("gzip", "x-gzip", "deflate"):
        return _Decoder(encoding, current, url, file, line)
    raise FetchError(
        f"{current}: unsupported Content-Encoding {header!r} (asked for identity)",
        file=file,
        line=line,
        url=url,
    )


def _describe(exc: BaseException) -> str:
    """A one-line reason, naming TLS certificate failures as such."""
    seen: BaseException | None = exc
    depth = 0
    while seen is not None and depth < 8:
        if isinstance(seen, ssl.SSLCertVerificationError):
            return f"TLS certificate verification failed: {seen.verify_message or seen}"
        seen = seen.__cause__ or seen.__context__
        depth += 1
    text = str(exc) or type(exc).__name__
    if "CERTIFICATE_VERIFY_FAILED" in text:
        return f"TLS certificate verification failed: {text}"
    if isinstance(exc, ssl.SSLError) or "SSL" in text:
        return f"TLS handshake failed: {text}"
    return text
