"""Fetchers: the only code that opens reference targets (local files or HTTPS).

Both yield the body as byte chunks, so callers hash while streaming in constant
memory. Checks made here are transport checks (root confinement, file type,
TLS, redirects, size, time); whether the bytes are the *right* bytes is decided
by the resolver against the pins.
"""

from __future__ import annotations

import contextlib
import os
import ssl
import stat
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING
from urllib.parse import urljoin, urlsplit

from ..digest import CHUNK, SMALL_FILE
from ..errors import FetchError, InputError, NotFoundError, PathEscapeError

if TYPE_CHECKING:
    import httpx

    from .locate import Location

DEFAULT_MAX_BYTES = 4 << 30
DEFAULT_TIMEOUT = 30.0
DEFAULT_DEADLINE = 600.0
MAX_REDIRECTS = 5


@contextlib.contextmanager
def open_local(path: Path, root: Path, *, file: str | None = None, line: int | None = None) -> Iterator[int]:
    """Open a regular file that really lies inside ``root`` and yield its descriptor.

    The symlink check is made on the opened descriptor (``/proc/self/fd``), so a
    link swapped in between check and use cannot lead outside the root.

    Raises:
        NotFoundError, PathEscapeError, InputError (not a regular file, unreadable).
    """
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except FileNotFoundError:
        raise NotFoundError(f"{path}: no such file", file=file, line=line, url=str(path)) from None
    except OSError as exc:
        # ELOOP: a symlink loop; EACCES etc.
        raise InputError(f"{path}: cannot open: {exc.strerror}", file=file, line=line) from None
    try:
        real = Path(os.readlink(f"/proc/self/fd/{fd}"))
        real_root = Path(os.path.realpath(root))
        if real != real_root and real_root not in real.parents:
            raise PathEscapeError(
                f"{path} resolves to {real}, outside the root {real_root} (symlink escape)",
                file=file,
                line=line,
                expected=f"a file inside {real_root}",
                actual=str(real),
            )
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            what = "a directory" if stat.S_ISDIR(mode) else "not a regular file"
            raise InputError(f"{path} is {what}", file=file, line=line)
        os.set_blocking(fd, True)
        yield fd
    finally:
        os.close(fd)


def read_chunks(fd: int) -> Iterator[bytes]:
    """Yield a regular file's content from ``fd``; one read for small files."""
    size = os.fstat(fd).st_size
    if size <= SMALL_FILE:
        chunks = []
        while data := os.read(fd, SMALL_FILE + 1):
            chunks.append(data)
        yield b"".join(chunks)
        return
    while data := os.read(fd, CHUNK):
        yield data


@dataclass
class HttpFetcher:
    """HTTPS through httpx: TLS verified, timeouts, size limit, redirect rules.

    Redirects are followed by hand so that every hop is checked: at most
    ``max_redirects``, never to another scheme than https (http only where
    ``allow_http``), never from https down to http.
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

    def _get_client(self) -> httpx.Client:
        if self._client is None:
            import httpx  # imported here: ~70 ms, only paid when a URL is fetched

            ctx = ssl.create_default_context(cafile=self.ca_bundle) if self.ca_bundle else True
            self._client = httpx.Client(
                verify=ctx,
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
        if self._client is not None:
            self._client.close()
            self._client = None

    @contextlib.contextmanager
    def open(self, url: str, *, file: str | None = None, line: int | None = None) -> Iterator[Iterator[bytes]]:
        """Yield the body of ``url`` as chunks; raises :class:`FetchError` on any transport fault."""
        import httpx

        client = self._get_client()
        started = time.monotonic()
        current = url
        original_scheme = urlsplit(url).scheme
        self._check_scheme(current, original_scheme, url, file=file, line=line)
        for _hop in range(self.max_redirects + 1):
            try:
                with client.stream("GET", current) as response:
                    if response.is_redirect:
                        location = response.headers.get("location", "")
                        current = urljoin(current, location)
                        self._check_scheme(current, original_scheme, url, file=file, line=line)
                        continue
                    if response.status_code != 200:
                        raise FetchError(
                            f"{current}: HTTP {response.status_code}", file=file, line=line, url=url
                        )
                    declared = response.headers.get("content-length")
                    if declared and declared.isdigit() and int(declared) > self.max_bytes:
                        raise FetchError(
                            f"{current}: Content-Length {declared} is over the "
                            f"{self.max_bytes}-byte limit",
                            file=file,
                            line=line,
                            url=url,
                        )
                    yield self._body(response, started, url, file, line)
                    return
            except FetchError:
                raise
            except httpx.TimeoutException:
                raise FetchError(
                    f"{current}: timed out (no data for {self.timeout:g} s)", file=file, line=line, url=url
                ) from None
            except (httpx.HTTPError, ssl.SSLError, OSError) as exc:
                raise FetchError(f"{current}: {_describe(exc)}", file=file, line=line, url=url) from None
        raise FetchError(
            f"{url}: more than {self.max_redirects} redirects", file=file, line=line, url=url
        )

    def _body(self, response: httpx.Response, started: float, url: str, file: str | None, line: int | None) -> Iterator[bytes]:
        size = 0
        # iter_bytes decodes any Content-Encoding the server forced on us, so the
        # limit applies to the decoded size and a gzip bomb stops at the limit.
        for chunk in response.iter_bytes(CHUNK):
            size += len(chunk)
            if size > self.max_bytes:
                raise FetchError(
                    f"{url}: body is over the {self.max_bytes}-byte limit", file=file, line=line, url=url
                )
            if time.monotonic() - started > self.deadline:
                raise FetchError(
                    f"{url}: took longer than {self.deadline:g} s", file=file, line=line, url=url
                )
            yield chunk

    def _check_scheme(self, current: str, original: str, url: str, *, file: str | None, line: int | None) -> None:
        scheme = urlsplit(current).scheme.lower()
        if scheme == "https":
            return
        if scheme == "http" and self.allow_http and original == "http":
            return
        if current == url:
            reason = "plain http is refused without --allow-http and a full SHA-256 pin"
        elif scheme == "http":
            reason = "redirect from https down to http is refused"
        else:
            reason = f"redirect to a {scheme or 'relative'}: URL is refused"
        raise FetchError(f"{url}: {reason} ({current})", file=file, line=line, url=url, actual=current)


def _describe(exc: BaseException) -> str:
    text = str(exc) or type(exc).__name__
    cause = exc.__context__ or exc.__cause__
    if isinstance(cause, ssl.SSLCertVerificationError):
        return f"TLS certificate verification failed: {cause.verify_message}"
    if "CERTIFICATE_VERIFY_FAILED" in text:
        return f"TLS certificate verification failed: {text}"
    return text
