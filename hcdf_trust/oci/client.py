"""A thin client over the OCI distribution-spec endpoints, through httpx.

Why not oras-py (0.2.43, ../shared/notes/distribution.md §2.7) for the protocol: its ``pull()``
does not check blob digests and extracts tar layers with a path traversal; its default auth
backend cannot talk to Basic-auth registries (and resolves the realm as a host name); its
``login()`` stores the password without checking it; it has no ``artifactType``, referrers or
fallback-tag support; its monolithic upload reads a whole file into memory; and it brings a
second HTTP stack (requests) beside the httpx every other fetch here uses. The endpoints we
need are eight requests; writing them over httpx keeps one transport with one set of rules:

- TLS verified always (``--ca-bundle`` for a private CA); plain http only to a loopback host
  or one named by ``--insecure-registry``.
- Redirects followed by hand, each hop checked: never from https to http, never to another
  origin, except a blob download (registries hand those to a CDN), which then carries no
  ``Authorization`` header and is still hashed against its digest.
- Every body bounded (manifests 4 MiB, blobs their declared size), every wait bounded.
- Credentials (:mod:`.auth`) sent only to the registry's own origin, or to the token realm
  it names over https; never printed.
"""

from __future__ import annotations

import contextlib
import hashlib
import ipaddress
import re
import time
from collections.abc import Iterable, Iterator
from types import ModuleType
from typing import TYPE_CHECKING, Any
from urllib.parse import urlencode, urljoin, urlsplit

from ..errors import FetchError, InputError
from ..include.fetch import DEFAULT_DEADLINE, DEFAULT_TIMEOUT, MAX_REDIRECTS, _import_httpx, load_ca_bundle
from .auth import Credentials
from .reference import Reference

if TYPE_CHECKING:
    import httpx

MAX_MANIFEST_BYTES = 4 << 20  # the distribution spec's recommended limit
MAX_TOKEN_BYTES = 1 << 20
CHUNK_BYTES = 16 << 20  # larger blobs are uploaded as PATCHes of this size
MANIFEST_TYPE = "application/vnd.oci.image.manifest.v1+json"
INDEX_TYPE = "application/vnd.oci.image.index.v1+json"


class RegistryError(FetchError):
    """The registry refused a request or broke the protocol (transport: exit 3)."""

    code = "oci-registry"


class RegistryAuthError(RegistryError):
    code = "oci-auth"


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def _private_channel(url: str) -> bool:
    """Credentials go over https, or plain http to this machine only."""
    parts = urlsplit(url)
    return parts.scheme == "https" or (parts.scheme == "http" and is_loopback(parts.hostname or ""))


def sha256_digest(data: bytes) -> str:
    return "sha256:" + hashlib.sha256(data).hexdigest()


class RegistryClient:
    """One repository of one registry. ``push``: ask for push rights when a token is needed."""

    def __init__(
        self,
        ref: Reference,
        *,
        credentials: Credentials | None = None,
        ca_bundle: str | None = None,
        insecure_registries: Iterable[str] = (),
        push: bool = False,
        timeout: float = DEFAULT_TIMEOUT,
        deadline: float = DEFAULT_DEADLINE,
    ) -> None:
        self.ref = ref
        self.credentials = credentials
        self.plain_http = {h.lower() for h in insecure_registries}
        plain = (ref.loopback and ca_bundle is None) or ref.netloc in self.plain_http or ref.host in self.plain_http
        self.scheme = "http" if plain else "https"
        self.origin = f"{self.scheme}://{ref.netloc}"
        self.scope = f"repository:{ref.repository}:{'pull,push' if push else 'pull'}"
        self.timeout = timeout
        self.deadline = deadline
        self._auth: str | None = None  # the Authorization header, once a challenge said which
        self._ssl: Any = load_ca_bundle(ca_bundle) if ca_bundle else True
        self._httpx: ModuleType = _import_httpx()
        # https goes through a transport made at the first https request: loading the system's
        # CA certificates into a TLS context costs ~80 ms, which a plain-http (loopback) registry
        # never needs unless it redirects to https. Plain http gets a context with no CA at all:
        # it never speaks TLS, and would accept no certificate if it did.
        import ssl

        httpx_ = self._httpx
        self._client: httpx.Client = httpx_.Client(
            transport=httpx_.HTTPTransport(verify=ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)),
            mounts={"https://": _LazyTransport(lambda: httpx_.HTTPTransport(verify=self._ssl))},
            timeout=httpx_.Timeout(timeout),
            follow_redirects=False,
            trust_env=False,  # no proxy or .netrc credentials picked up behind our back
            headers={"Accept-Encoding": "identity", "User-Agent": "hcdf-trust"},
        )

    def close(self) -> None:
        self._client.close()

    def __enter__(self) -> RegistryClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- transport -------------------------------------------------------------------

    def _url(self, path: str) -> str:
        return f"{self.origin}/v2/{self.ref.repository}/{path}"

    def _allowed_scheme(self, url: str) -> bool:
        parts = urlsplit(url)
        if parts.scheme == "https":
            return True
        host = parts.netloc.rsplit("@", 1)[-1]
        return parts.scheme == "http" and (
            is_loopback(parts.hostname or "") or host in self.plain_http or (parts.hostname or "") in self.plain_http
        )

    @contextlib.contextmanager
    def request(
        self,
        method: str,
        url: str,
        *,
        headers: dict[str, str] | None = None,
        content: bytes | Iterable[bytes] | None = None,
        any_origin: bool = False,
        what: str = "",
    ) -> Iterator[httpx.Response]:
        """Send one request (answering one auth challenge, following checked redirects);
        yield the final response, streaming (the caller reads it within the block).

        Raises:
            RegistryError / RegistryAuthError: transport faults, a refused redirect, 401 after auth.
        """
        httpx = self._httpx
        current = url
        sent_auth = False
        retried = False
        started = time.monotonic()
        for _hop in range(MAX_REDIRECTS + 1):
            same = current.startswith(self.origin + "/")
            hdrs = dict(headers or {})
            if self._auth and same:
                hdrs["Authorization"] = self._auth
                sent_auth = True
            try:
                req = self._client.build_request(method, current, headers=hdrs, content=content)
                response = self._client.send(req, stream=True)
            except (httpx.HTTPError, httpx.InvalidURL, OSError) as exc:
                raise RegistryError(f"{what or method} {current}: {_describe(exc)}", url=current) from None
            try:
                if response.status_code == 401 and same and not retried and not isinstance(content, Iterator):
                    challenge = response.headers.get("www-authenticate", "")
                    response.close()
                    self._answer(challenge, current)
                    retried = True
                    continue
                if response.status_code == 401:
                    why = "the credentials were refused" if sent_auth else "it needs credentials (none were found)"
                    raise RegistryAuthError(
                        f"{what or method} {current}: HTTP 401: {why}", url=current, expected="HTTP 2xx", actual="401"
                    )
                if response.is_redirect and method in ("GET", "HEAD"):
                    location = response.headers.get("location", "").strip()
                    target = urljoin(current, location)
                    self._check_redirect(current, target, any_origin=any_origin, what=what or method)
                    current = target
                    response.close()
                    continue
                if time.monotonic() - started > self.deadline:
                    raise RegistryError(f"{what or method} {current}: took longer than {self.deadline:g} s")
                yield response
                return
            finally:
                response.close()
        raise RegistryError(f"{what or method} {url}: more than {MAX_REDIRECTS} redirects", url=url)

    def _check_redirect(self, current: str, target: str, *, any_origin: bool, what: str) -> None:
        src, dst = urlsplit(current), urlsplit(target)
        if "@" in dst.netloc:
            raise RegistryError(f"{what}: redirect to a URL with credentials is refused", url=current)
        if src.scheme == "https" and dst.scheme != "https":
            raise RegistryError(
                f"{what}: redirect from https down to {dst.scheme or 'a relative URL'} is refused ({target})",
                url=current,
                expected="an https URL",
                actual=target,
            )
        if not self._allowed_scheme(target):
            raise RegistryError(
                f"{what}: redirect to plain http is refused outside loopback and --insecure-registry ({target})",
                url=current,
            )
        if (src.scheme, src.netloc) != (dst.scheme, dst.netloc) and not any_origin:
            raise RegistryError(
                f"{what}: redirect to another host is refused ({target})",
                url=current,
                expected=f"{src.scheme}://{src.netloc}",
                actual=f"{dst.scheme}://{dst.netloc}",
            )

    def _answer(self, challenge: str, url: str) -> None:
        """Set the Authorization header that answers a ``WWW-Authenticate`` challenge."""
        scheme, params = _parse_challenge(challenge)
        creds = self.credentials
        if creds is not None and not _private_channel(url):
            raise RegistryAuthError(
                f"{url}: refusing to send credentials over plain http to a host that is not loopback", url=url
            )
        if scheme == "basic":
            if creds is None or creds.identity_token:
                raise RegistryAuthError(
                    f"{url}: HTTP 401: it needs a user name and password (none were found)", url=url
                )
            self._auth = creds.basic_header()
            return
        if scheme != "bearer" or "realm" not in params:
            raise RegistryAuthError(f"{url}: HTTP 401 with an authentication scheme we do not speak ({scheme!r})")
        realm = params["realm"]
        if not _private_channel(realm):
            raise RegistryAuthError(f"{url}: token realm {realm} is not https (nor loopback http)", url=url)
        query = {"service": params.get("service", ""), "scope": params.get("scope") or self.scope}
        headers: dict[str, str] = {}
        if creds is not None and not creds.identity_token:
            headers["Authorization"] = creds.basic_header()
        try:
            if creds is not None and creds.identity_token:
                form = {"grant_type": "refresh_token", "refresh_token": creds.password, "client_id": "hcdf-trust"}
                request = self._client.build_request("POST", realm, data={**form, **query})
            else:
                request = self._client.build_request("GET", f"{realm}?{urlencode(query)}", headers=headers)
            response = self._client.send(request, stream=True)
        except (self._httpx.HTTPError, self._httpx.InvalidURL, OSError) as exc:
            raise RegistryAuthError(f"token realm {realm}: {_describe(exc)}", url=realm) from None
        try:
            if response.status_code != 200:
                why = (
                    ""
                    if response.status_code != 401
                    else ": the credentials were refused"
                    if creds is not None
                    else ": it needs credentials (none were found)"
                )
                raise RegistryAuthError(f"token realm {realm}: HTTP {response.status_code}{why}", url=realm)
            body = self._read_bounded(response, MAX_TOKEN_BYTES, realm)
        finally:
            response.close()
        from ..localfile import MAX_JSON_BYTES, parse_json
        from ..scrub import remember

        doc = parse_json(body, source=realm, what="token response", limit=MAX_JSON_BYTES)
        token = doc.get("token") or doc.get("access_token") if isinstance(doc, dict) else None
        if not isinstance(token, str) or not token:
            raise RegistryAuthError(f"token realm {realm}: no token in the answer", url=realm)
        remember(token)
        self._auth = f"Bearer {token}"

    # -- endpoints -------------------------------------------------------------------

    def check(self) -> None:
        """``GET /v2/``: the registry speaks the distribution API (and we may talk to it)."""
        with self.request("GET", f"{self.origin}/v2/", what="GET /v2/") as r:
            if r.status_code != 200:
                raise RegistryError(f"{self.origin}/v2/: HTTP {r.status_code}: not an OCI registry?")

    def get_manifest(self, reference: str, *, accept: str = MANIFEST_TYPE) -> tuple[bytes, str, str] | None:
        """The manifest's bytes, its digest (hashed from the body, never the header) and its
        ``Content-Type``; None when the registry has none under ``reference``."""
        url = self._url(f"manifests/{reference}")
        with self.request("GET", url, headers={"Accept": accept}, what="GET manifest") as r:
            if r.status_code == 404:
                return None
            if r.status_code != 200:
                raise RegistryError(f"{url}: HTTP {r.status_code}", url=url)
            body = self._read_bounded(r, MAX_MANIFEST_BYTES, url)
            return body, sha256_digest(body), r.headers.get("content-type", "")

    def put_manifest(self, reference: str, body: bytes, media_type: str) -> dict[str, str]:
        """PUT a manifest under a tag or its digest; the response headers."""
        url = self._url(f"manifests/{reference}")
        with self.request("PUT", url, headers={"Content-Type": media_type}, content=body, what="PUT manifest") as r:
            if r.status_code != 201:
                raise RegistryError(f"{url}: HTTP {r.status_code}: {_error_text(r)}", url=url)
            got = r.headers.get("docker-content-digest")
            if got and got != sha256_digest(body):
                raise RegistryError(
                    f"{url}: the registry stored another manifest than the one sent",
                    url=url,
                    expected=sha256_digest(body),
                    actual=got,
                )
            return dict(r.headers)

    def has_blob(self, digest: str, size: int) -> bool:
        url = self._url(f"blobs/{digest}")
        with self.request("HEAD", url, any_origin=True, what="HEAD blob") as r:
            return r.status_code == 200 and r.headers.get("content-length") == str(size)

    def push_blob(self, digest: str, size: int, chunks: Iterable[bytes]) -> None:
        """Upload one blob, streamed: POST a session, then PUT the body with ``?digest=``; a blob
        larger than :data:`CHUNK_BYTES` goes as PATCHes of that size (``Content-Range``) and a
        closing PUT, so no request body is larger (proxies and registries cap them) and no part
        is ever held whole in memory."""
        if self.has_blob(digest, size):
            return
        url = self._url("blobs/uploads/")
        with self.request("POST", url, content=b"", what="POST blob upload") as r:
            if r.status_code != 202 or not r.headers.get("location"):
                raise RegistryError(f"{url}: HTTP {r.status_code}: {_error_text(r)}", url=url)
            location = self._upload_location(url, r)
        body = iter(chunks)
        if size > CHUNK_BYTES:
            parts = _Parts(body)
            for start in range(0, size, CHUNK_BYTES):
                n = min(CHUNK_BYTES, size - start)
                headers = {
                    "Content-Type": "application/octet-stream",
                    "Content-Length": str(n),
                    "Content-Range": f"{start}-{start + n - 1}",
                }
                with self.request("PATCH", location, headers=headers, content=parts.next(n), what="PATCH blob") as r:
                    if r.status_code != 202:
                        where = f"PATCH blob {digest} bytes {start}-{start + n - 1}"
                        raise RegistryError(f"{where}: HTTP {r.status_code}: {_error_text(r)}", url=url)
                    location = self._upload_location(url, r)
            parts.end()
            body, size = iter([b""]), 0
        sep = "&" if urlsplit(location).query else "?"
        put = f"{location}{sep}{urlencode({'digest': digest})}"
        headers = {"Content-Type": "application/octet-stream", "Content-Length": str(size)}
        with self.request("PUT", put, headers=headers, content=body, what="PUT blob") as r:
            if r.status_code != 201:
                raise RegistryError(f"PUT blob {digest}: HTTP {r.status_code}: {_error_text(r)}", url=url)

    def _upload_location(self, url: str, r: httpx.Response) -> str:
        """The upload session's next URL (``Location``), on this registry only."""
        location: str = urljoin(url, r.headers.get("location", ""))
        if not r.headers.get("location") or not location.startswith(self.origin + "/"):
            raise RegistryError(f"{url}: upload location missing or on another host ({location})", url=url)
        return location

    @contextlib.contextmanager
    def blob(self, digest: str, size: int) -> Iterator[Iterator[bytes]]:
        """The blob's bytes as chunks, refused past ``size`` (declared by the manifest); the
        caller hashes them (the registry's ``Docker-Content-Digest`` header proves nothing)."""
        url = self._url(f"blobs/{digest}")
        with self.request("GET", url, any_origin=True, what="GET blob") as r:
            if r.status_code != 200:
                raise RegistryError(f"{url}: HTTP {r.status_code}", url=url)
            declared = r.headers.get("content-length")
            if declared is not None and declared.isdigit() and int(declared) != size:
                raise RegistryError(
                    f"blob {digest}: the registry announces another size than the manifest's",
                    url=url,
                    expected=str(size),
                    actual=declared,
                )
            yield self._chunks(r, size, url)

    def _read_bounded(self, r: httpx.Response, limit: int, url: str) -> bytes:
        """A small body (a manifest, an index), whole: at most ``limit`` bytes and the deadline."""
        return b"".join(self._chunks(r, limit, url, what="body"))

    def _chunks(self, r: httpx.Response, size: int, url: str, *, what: str = "blob") -> Iterator[bytes]:
        got = 0
        started = time.monotonic()
        try:
            for chunk in r.iter_raw():  # each network read as it comes (a chunk size would buffer)
                got += len(chunk)
                if got > size:
                    limit = f"the manifest's {size} bytes" if what == "blob" else f"the {size}-byte limit"
                    raise RegistryError(f"{url}: {what} is longer than {limit}", url=url)
                if time.monotonic() - started > self.deadline:
                    raise RegistryError(f"{url}: took longer than {self.deadline:g} s", url=url)
                yield chunk
        except (self._httpx.HTTPError, OSError) as exc:
            raise RegistryError(f"{url}: {_describe(exc)}", url=url) from None

    def referrers(self, digest: str, *, artifact_type: str | None = None) -> tuple[list[Any], bool]:
        """The descriptors of the manifests whose ``subject`` is ``digest``, and whether the
        registry answered them through the referrers API (else the ``sha256-<hex>`` tag)."""
        from ..localfile import MAX_JSON_BYTES, parse_json

        url = self._url(f"referrers/{digest}")
        if artifact_type:
            url += "?" + urlencode({"artifactType": artifact_type})
        with self.request("GET", url, headers={"Accept": INDEX_TYPE}, what="GET referrers") as r:
            if r.status_code == 200 and r.headers.get("content-type", "").startswith(INDEX_TYPE):
                doc = parse_json(
                    self._read_bounded(r, MAX_MANIFEST_BYTES, url),
                    source=url,
                    what="referrers index",
                    limit=MAX_JSON_BYTES,
                )
                return _manifests(doc, url), True
            if r.status_code not in (200, 404):
                raise RegistryError(f"{url}: HTTP {r.status_code}", url=url)
        got = self.get_manifest(fallback_tag(digest), accept=INDEX_TYPE)
        if got is None:
            return [], False
        body, _, _ = got
        source = self._url(f"manifests/{fallback_tag(digest)}")
        return _manifests(parse_json(body, source=source, what="referrers tag", limit=MAX_JSON_BYTES), source), False


class _Parts:
    """A stream of chunks cut into consecutive parts of given sizes, each a generator of the
    stream's own chunks (split at a part's end): nothing is joined or held."""

    def __init__(self, chunks: Iterator[bytes]) -> None:
        self._chunks = chunks
        self._rest = b""

    def next(self, n: int) -> Iterator[bytes]:
        while n > 0:
            chunk = self._rest or next(self._chunks, b"")
            if not chunk:
                raise RegistryError(f"the blob ended {n} bytes before its declared size")
            self._rest = chunk[n:]
            yield chunk[:n]
            n -= min(n, len(chunk))

    def end(self) -> None:
        if self._rest or next(self._chunks, b""):
            raise RegistryError("the blob is longer than its declared size")


def connect(
    target: str | Reference,
    *,
    ca_bundle: str | None = None,
    insecure_registries: Iterable[str] = (),
    push: bool = False,
    need_tag: bool = False,
) -> tuple[Reference, RegistryClient]:
    """The reference ``target`` (``oci://…``, parsed unless it already is) and a client for its
    repository with the credentials :mod:`.auth` finds for its host: how every verb that talks
    to an OCI registry opens one (``ca_bundle``, ``insecure_registries``: ``--ca-bundle``,
    ``--insecure-registry``; ``push``: ask for push rights; ``need_tag``: refuse a digest).

    Raises:
        InputError: a reference we cannot use (credentials or a query in it, no tag when needed).
    """
    from .auth import find_credentials
    from .reference import parse_reference

    ref = parse_reference(target, need_tag=need_tag) if isinstance(target, str) else target
    client = RegistryClient(
        ref,
        credentials=find_credentials(ref.netloc),
        ca_bundle=ca_bundle,
        insecure_registries=insecure_registries,
        push=push,
    )
    return ref, client


def fallback_tag(digest: str) -> str:
    """The referrers tag schema: ``sha256:<hex>`` -> ``sha256-<hex>``."""
    return digest.replace(":", "-", 1)


def _manifests(doc: Any, source: str) -> list[Any]:
    if not isinstance(doc, dict) or doc.get("schemaVersion") != 2 or not isinstance(doc.get("manifests"), list):
        raise RegistryError(f"{source}: not an OCI image index", url=source)
    return list(doc["manifests"])


def _error_text(r: httpx.Response) -> str:
    """The first error code of a distribution-spec error body (short, no echo of our input)."""
    body = b""
    try:
        for chunk in r.iter_raw():
            body += chunk
            if len(body) >= 4096:
                break
    except Exception:  # noqa: BLE001 -- only a message
        return "no body"
    m = re.search(rb'"code"\s*:\s*"([A-Z_]{1,40})"', body)
    return m.group(1).decode() if m else "no error code"


_PARAM = re.compile(r'([A-Za-z]+)="([^"]*)"')


def _parse_challenge(text: str) -> tuple[str, dict[str, str]]:
    scheme, _, rest = text.strip().partition(" ")
    return scheme.lower(), {k.lower(): v for k, v in _PARAM.findall(rest)}


def _describe(exc: BaseException) -> str:
    text = str(exc) or exc.__class__.__name__
    return text[:300]


__all__ = ["InputError", "RegistryClient", "RegistryError", "fallback_tag", "sha256_digest"]


class _LazyTransport:  # an httpx.BaseTransport (httpx is imported lazily, so not its subclass)
    """An httpx transport made by ``make`` when the first request needs it (see RegistryClient)."""

    def __init__(self, make: Any) -> None:
        import threading

        self._make = make
        self._made: Any = None
        self._lock = threading.Lock()  # the fetch pool's threads may all start at once

    def handle_request(self, request: Any) -> Any:
        with self._lock:
            if self._made is None:
                self._made = self._make()
        return self._made.handle_request(request)

    def close(self) -> None:
        if self._made is not None:
            self._made.close()

    def __enter__(self) -> _LazyTransport:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
