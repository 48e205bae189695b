"""include/fetch.py: transport checks of the HTTPS fetcher, against real loopback servers.

Mutation-testing killers: status codes, redirect rules and counts, exact limits,
the environment not being trusted, content decoding, and the messages that name each.
"""

from __future__ import annotations

import gzip
import os
import ssl
import zlib

import pytest

from hcdf_trust.errors import FetchError
from hcdf_trust.include.fetch import (
    DEFAULT_DEADLINE,
    DEFAULT_MAX_BYTES,
    DEFAULT_TIMEOUT,
    MAX_REDIRECTS,
    HttpFetcher,
    _describe,
)


@pytest.fixture
def fetcher(tls):
    f = HttpFetcher(ca_bundle=str(tls.ca_pem), timeout=5.0)
    yield f
    f.close()


def get(fetcher: HttpFetcher, url: str, **kw) -> bytes:
    with fetcher.open(url, **kw) as chunks:
        return b"".join(chunks)


def test_defaults():
    f = HttpFetcher()
    assert (f.timeout, f.deadline, f.max_bytes, f.max_redirects) == (30.0, 600.0, 4 << 30, 5)
    assert (DEFAULT_TIMEOUT, DEFAULT_DEADLINE, DEFAULT_MAX_BYTES, MAX_REDIRECTS) == (30.0, 600.0, 4 << 30, 5)
    assert f.allow_http is False and f.ca_bundle is None


def test_a_body_is_yielded_in_bounded_chunks(fetcher, https_server):
    data = os.urandom(3 << 20)
    url = https_server.add("/a.glb", data)
    with fetcher.open(url) as chunks:
        parts = list(chunks)
    assert b"".join(parts) == data and max(len(p) for p in parts) <= 1 << 20


@pytest.mark.parametrize("status", [201, 203, 204, 206, 404, 500])
def test_any_status_but_200_is_refused_naming_it(fetcher, https_server, status):
    url = https_server.add("/s", b"partial", status=status)
    with pytest.raises(FetchError) as info:
        get(fetcher, url, file="d.hcdf", line=4)
    err = info.value
    assert f"HTTP {status}" in str(err) and err.file == "d.hcdf" and err.line == 4 and err.url == url


@pytest.mark.parametrize("status", [301, 302, 303, 307, 308])
def test_redirects_within_https_are_followed(fetcher, https_server, status):
    https_server.add("/real", b"body")
    url = https_server.redirect("/r", "/real", status=status)
    assert get(fetcher, url) == b"body"


def test_exactly_max_redirects_hops_are_followed_and_one_more_is_refused(fetcher, https_server):
    https_server.add("/end", b"end")
    for i in range(6):
        https_server.redirect(f"/h{i}", f"/h{i + 1}" if i < 5 else "/end")
    assert get(fetcher, https_server.url("/h1")) == b"end"  # 5 redirects
    with pytest.raises(FetchError) as info:
        get(fetcher, https_server.url("/h0"), file="d", line=1)  # 6 redirects
    assert "more than 5 redirects" in str(info.value) and info.value.url == https_server.url("/h0")
    assert https_server.hits["/end"] == 1


def test_a_redirect_without_location_is_refused(fetcher, https_server):
    url = https_server.redirect("/r", "")
    with pytest.raises(FetchError, match="HTTP 302 redirect without a Location"):
        get(fetcher, url)


def test_https_down_to_http_is_refused_even_with_allow_http(tls, https_server, http_server):
    http_server.add("/a", b"a")
    url = https_server.redirect("/r", http_server.url("/a"))
    for allow in (False, True):
        f = HttpFetcher(ca_bundle=str(tls.ca_pem), allow_http=allow)
        try:
            with pytest.raises(FetchError) as info:
                get(f, url)
        finally:
            f.close()
        assert "redirect from https down to http is refused" in str(info.value)
        assert info.value.actual == http_server.url("/a")
    assert http_server.hits["/a"] == 0


def test_plain_http_needs_allow_http(tls, http_server, https_server):
    url = http_server.add("/a", b"a")
    f = HttpFetcher(ca_bundle=str(tls.ca_pem))
    try:
        with pytest.raises(FetchError, match="plain http is refused without --allow-http"):
            get(f, url)
    finally:
        f.close()
    assert http_server.hits["/a"] == 0
    f = HttpFetcher(ca_bundle=str(tls.ca_pem), allow_http=True)
    try:
        assert get(f, url) == b"a"
        https_server.add("/b", b"b")
        up = http_server.redirect("/up", https_server.url("/b"))  # http up to https is fine
        assert get(f, up) == b"b"
        http_server.add("/c", b"c")
        assert get(f, http_server.redirect("/same", "/c")) == b"c"  # http to http under --allow-http
    finally:
        f.close()


def test_an_https_redirect_to_plain_http_is_refused_as_a_downgrade_not_as_plain_http(tls, https_server):
    url = https_server.redirect("/r", "http://127.0.0.1:1/x")
    f = HttpFetcher(ca_bundle=str(tls.ca_pem))
    try:
        with pytest.raises(FetchError, match="down to http"):
            get(f, url)
    finally:
        f.close()


def test_an_http_redirect_to_http_without_allow_http_names_the_redirect(tls, http_server):
    f = HttpFetcher(ca_bundle=str(tls.ca_pem), allow_http=True)
    g = HttpFetcher(ca_bundle=str(tls.ca_pem))
    try:
        with pytest.raises(FetchError, match="plain http is refused"):
            get(g, http_server.redirect("/r", "/x"))
        assert get(f, http_server.add("/ok", b"ok")) == b"ok"
    finally:
        f.close()
        g.close()


@pytest.mark.parametrize(
    ("location", "words"),
    [("ftp://127.0.0.1/x", "redirect to a ftp: URL"), ("file:///etc/passwd", "redirect to a file: URL")],
)
def test_a_redirect_to_another_scheme_is_refused(fetcher, https_server, location, words):
    url = https_server.redirect("/r", location)
    with pytest.raises(FetchError) as info:
        get(fetcher, url)
    assert words in str(info.value) and info.value.actual == location


def test_the_environment_is_not_trusted(fetcher, https_server, monkeypatch):
    """A proxy or CA bundle from the environment must not redirect or weaken a fetch."""
    for var in ("HTTPS_PROXY", "https_proxy", "ALL_PROXY", "all_proxy", "HTTP_PROXY", "http_proxy"):
        monkeypatch.setenv(var, "http://127.0.0.1:9")  # discard port: any proxied request fails
    for var in ("NO_PROXY", "no_proxy"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setenv("SSL_CERT_FILE", os.devnull)
    url = https_server.add("/a", b"direct")
    assert get(fetcher, url) == b"direct"


def test_content_length_at_the_limit_is_accepted_and_one_over_is_refused_before_the_body(tls, https_server):
    f = HttpFetcher(ca_bundle=str(tls.ca_pem), max_bytes=1000)
    try:
        assert get(f, https_server.add("/ok", b"x" * 1000)) == b"x" * 1000
        url = https_server.add("/big", b"x" * 1001)
        with pytest.raises(FetchError, match="Content-Length 1001 is over the 1000-byte limit"):
            get(f, url)
        chunked = https_server.stream("/c", 1001, chunked=True)
        with pytest.raises(FetchError, match="body is over the 1000-byte limit"):
            get(f, chunked)
        assert len(get(f, https_server.stream("/c2", 1000, chunked=True))) == 1000
    finally:
        f.close()


def test_a_non_numeric_content_length_is_not_trusted_as_a_size(fetcher, https_server):
    url = https_server.add("/a", b"body", headers={"X-Pad": "1"})
    assert get(fetcher, url) == b"body"


def test_a_timeout_names_the_timeout(tls, https_server):
    f = HttpFetcher(ca_bundle=str(tls.ca_pem), timeout=0.3)
    try:
        with pytest.raises(FetchError, match=r"timed out \(no data for 0.3 s\)") as info:
            get(f, https_server.stall("/s"), file="d", line=2)
        assert info.value.file == "d" and info.value.line == 2
    finally:
        f.close()


def test_the_deadline_bounds_the_whole_fetch(tls, https_server):
    f = HttpFetcher(ca_bundle=str(tls.ca_pem), timeout=5.0, deadline=0.3)
    try:
        with pytest.raises(FetchError, match="took longer than 0.3 s"):
            get(f, https_server.drip("/d", b"x" * 100, every=0.05))
    finally:
        f.close()


def test_an_untrusted_certificate_is_named(serve, tls):
    srv = serve("untrusted")
    f = HttpFetcher(ca_bundle=str(tls.ca_pem))
    try:
        with pytest.raises(FetchError, match="TLS certificate verification failed"):
            get(f, srv.add("/a", b"a"))
    finally:
        f.close()


def test_a_plain_server_on_an_https_url_is_a_tls_error(tls, http_server):
    f = HttpFetcher(ca_bundle=str(tls.ca_pem))
    http_server.add("/a", b"a")
    try:
        with pytest.raises(FetchError) as info:
            get(f, http_server.url("/a").replace("http://", "https://"))
        assert "TLS" in str(info.value) or "SSL" in str(info.value)
    finally:
        f.close()


def test_a_refused_connection_is_a_fetch_error(fetcher):
    with pytest.raises(FetchError) as info:
        get(fetcher, "https://127.0.0.1:9/a", file="d", line=1)
    assert info.value.url == "https://127.0.0.1:9/a"


def test_close_then_reuse(fetcher, https_server):
    url = https_server.add("/a", b"a")
    assert get(fetcher, url) == b"a"
    fetcher.close()
    fetcher.close()
    assert get(fetcher, url) == b"a"


# -- Content-Encoding ------------------------------------------------------------------


def _deflate(data: bytes, *, raw: bool) -> bytes:
    c = zlib.compressobj(wbits=-zlib.MAX_WBITS if raw else zlib.MAX_WBITS)
    return c.compress(data) + c.flush()


@pytest.mark.parametrize("encoding", ["gzip", "x-gzip", "GZIP", " gzip "])
def test_gzip_is_undone(fetcher, https_server, encoding):
    data = os.urandom(1000) * 50
    url = https_server.add("/g", gzip.compress(data), headers={"Content-Encoding": encoding})
    assert get(fetcher, url) == data


@pytest.mark.parametrize("raw", [False, True])
def test_deflate_zlib_wrapped_or_raw_is_undone(fetcher, https_server, raw):
    data = os.urandom(500) * 30
    url = https_server.add("/d", _deflate(data, raw=raw), headers={"Content-Encoding": "deflate"})
    assert get(fetcher, url) == data


def test_identity_encoding_is_the_body(fetcher, https_server):
    url = https_server.add("/i", b"plain", headers={"Content-Encoding": "identity"})
    assert get(fetcher, url) == b"plain"


def test_data_after_a_deflate_stream_is_refused(fetcher, https_server):
    url = https_server.add("/d", _deflate(b"x", raw=False) + b"junk", headers={"Content-Encoding": "deflate"})
    with pytest.raises(FetchError, match="Content-Encoding deflate: data after the end of the stream"):
        get(fetcher, url)


def test_zero_padding_after_a_deflate_stream_is_tolerated(fetcher, https_server):
    url = https_server.add("/d", _deflate(b"x", raw=False) + b"\0" * 10, headers={"Content-Encoding": "deflate"})
    assert get(fetcher, url) == b"x"


def test_corrupt_gzip_is_refused(fetcher, https_server):
    url = https_server.add("/g", b"\x1f\x8b" + b"\xff" * 30, headers={"Content-Encoding": "gzip"})
    with pytest.raises(FetchError, match="Content-Encoding gzip: corrupt data"):
        get(fetcher, url)


def test_corrupt_deflate_is_refused(fetcher, https_server):
    url = https_server.add("/d", b"\xff" * 30, headers={"Content-Encoding": "deflate"})
    with pytest.raises(FetchError, match="Content-Encoding deflate: corrupt data"):
        get(fetcher, url)


def test_truncated_deflate_is_refused(fetcher, https_server):
    body = _deflate(os.urandom(5000), raw=False)[:-20]
    url = https_server.add("/d", body, headers={"Content-Encoding": "deflate"})
    with pytest.raises(FetchError, match="truncated"):
        get(fetcher, url)


def test_decoded_size_is_bounded_exactly(tls, https_server):
    f = HttpFetcher(ca_bundle=str(tls.ca_pem), max_bytes=10_000)
    try:
        ok = https_server.add("/ok", gzip.compress(b"\0" * 10_000), headers={"Content-Encoding": "gzip"})
        assert len(get(f, ok)) == 10_000
        big = https_server.add("/big", gzip.compress(b"\0" * 10_001), headers={"Content-Encoding": "gzip"})
        with pytest.raises(FetchError, match="body is over the 10000-byte limit"):
            get(f, big)
    finally:
        f.close()


def test_an_unknown_encoding_is_refused_as_written(fetcher, https_server):
    url = https_server.add("/b", b"x", headers={"Content-Encoding": "br"})
    with pytest.raises(FetchError, match="unsupported Content-Encoding 'br'"):
        get(fetcher, url)


def test_decoding_errors_name_the_reference(fetcher, https_server):
    url = https_server.add("/g", b"\x1f\x8b" + b"\xff" * 30, headers={"Content-Encoding": "gzip"})
    with pytest.raises(FetchError) as info:
        get(fetcher, url, file="d.hcdf", line=7)
    err = info.value
    assert (err.file, err.line, err.url) == ("d.hcdf", 7, url)


def test_truncation_message(fetcher, https_server):
    body = gzip.compress(os.urandom(5000))[:-30]
    url = https_server.add("/t", body, headers={"Content-Encoding": "gzip"})
    with pytest.raises(FetchError) as info:
        get(fetcher, url)
    assert str(info.value).endswith("the body ends before the compressed stream does (truncated)")


def test_gzip_members_after_zero_padding_are_decoded(fetcher, https_server):
    body = gzip.compress(b"first ") + b"\0" * 7 + gzip.compress(b"second")
    url = https_server.add("/m", body, headers={"Content-Encoding": "gzip"})
    assert get(fetcher, url) == b"first second"


def test_only_zero_bytes_count_as_padding(fetcher, https_server):
    url = https_server.add("/d", _deflate(b"x", raw=False) + b"XXX", headers={"Content-Encoding": "deflate"})
    with pytest.raises(FetchError, match="data after the end of the stream"):
        get(fetcher, url)


# -- how transport failures are described (fetch._describe: pure, over exception chains) --


def _chain(depth: int, last: BaseException, *, via: str = "__cause__") -> BaseException:
    """An exception whose ``via`` chain reaches ``last`` after ``depth - 1`` links."""
    top: BaseException = last
    for i in range(depth - 1):
        outer = RuntimeError(f"layer {i}")
        setattr(outer, via, top)
        top = outer
    return top


def _cert_error(message: str | None = "self-signed certificate") -> ssl.SSLCertVerificationError:
    err = ssl.SSLCertVerificationError(1, "[SSL: CERTIFICATE_VERIFY_FAILED] certificate verify failed")
    err.verify_message = message
    return err


@pytest.mark.parametrize("via", ["__cause__", "__context__"])
@pytest.mark.parametrize("depth", [1, 2, 8])
def test_a_certificate_failure_is_found_up_to_eight_links_down(via, depth):
    text = _describe(_chain(depth, _cert_error(), via=via))
    assert text == "TLS certificate verification failed: self-signed certificate"


def test_a_certificate_failure_nine_links_down_is_not_looked_for():
    assert _describe(_chain(9, _cert_error())) == "layer 7"


def test_a_certificate_failure_without_a_verify_message_shows_the_error():
    err = _cert_error(None)
    assert _describe(err) == f"TLS certificate verification failed: {err}"


def test_failure_texts():
    assert _describe(RuntimeError("x [SSL: CERTIFICATE_VERIFY_FAILED] y")).startswith(
        "TLS certificate verification failed: x [SSL"
    )
    assert _describe(ssl.SSLError(1, "bad record")) == f"TLS handshake failed: {ssl.SSLError(1, 'bad record')}"
    assert _describe(OSError("SSL: wrong version")) == "TLS handshake failed: SSL: wrong version"
    assert _describe(OSError("ssl is lower case")) == "ssl is lower case"
    assert _describe(ConnectionRefusedError()) == "ConnectionRefusedError"
    assert _describe(OSError("connection refused")) == "connection refused"


def test_a_body_that_inflates_past_one_chunk_per_read_is_decoded_whole(fetcher, https_server):
    data = b"\0" * (5 << 20) + b"end"  # a few KB on the wire, far more than 1 MiB per network read
    url = https_server.add("/z", gzip.compress(data), headers={"Content-Encoding": "gzip"})
    with fetcher.open(url) as chunks:
        parts = list(chunks)
    assert b"".join(parts) == data and max(len(p) for p in parts) <= 1 << 20


def test_body_and_encoding_errors_name_the_reference(tls, https_server):
    f = HttpFetcher(ca_bundle=str(tls.ca_pem), timeout=5.0, max_bytes=10, deadline=0.2)
    try:
        cases = [
            https_server.stream("/big", 100, chunked=True),  # over the limit while streaming
            https_server.drip("/slow", b"x" * 8, every=0.1),  # past the deadline
            https_server.add("/br", b"x", headers={"Content-Encoding": "br"}),  # unsupported encoding
        ]
        for url in cases:
            with pytest.raises(FetchError) as info:
                get(f, url, file="d.hcdf", line=9)
            err = info.value
            assert (err.file, err.line, err.url) == ("d.hcdf", 9, url), url
            assert str(err).startswith(f"d.hcdf:9: {url}:") or url in str(err)
    finally:
        f.close()


def test_a_decoding_error_names_the_url_it_was_read_from(fetcher, https_server):
    https_server.add("/bad", b"\xff" * 20, headers={"Content-Encoding": "deflate"})
    url = https_server.redirect("/r", "/bad")
    with pytest.raises(FetchError) as info:
        get(fetcher, url, file="d", line=1)
    assert info.value.url == url and f"{https_server.url('/bad')}: Content-Encoding deflate" in str(info.value)
