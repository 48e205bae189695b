"""The network side of ``resolve``, against real servers on 127.0.0.1 (tests/servers.py).

Every test drives the real CLI (or the fetcher directly where memory or a
deadline is measured) and checks what the tool guarantees: the exit code, an
error that says what went wrong, and a cache that never holds a wrong blob.
"""

from __future__ import annotations

import gzip
import hashlib
import os
import socket
import time
import tracemalloc
from pathlib import Path

import pytest

from hcdf_trust.errors import FetchError
from hcdf_trust.include.fetch import HttpFetcher

from .servers import Route

# -- helpers ------------------------------------------------------------------------------


def sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def blob(n: int, seed: int = 0) -> bytes:
    """``n`` deterministic, incompressible-looking bytes."""
    out = bytearray()
    block = hashlib.sha256(f"{seed}".encode()).digest()
    while len(out) < n:
        block = hashlib.sha256(block).digest()
        out += block
    return bytes(out[:n])


def model(uri: str, pin: str | None = None) -> str:
    sha_attr = f' sha="{pin}"' if pin else ""
    return f'<visual><model uri="{uri}"{sha_attr}/></visual>'


def hcdf(*parts: str) -> str:
    body = "\n".join(f'  <comp name="c{i}">{p}</comp>' for i, p in enumerate(parts))
    return f'<?xml version="1.0"?>\n<hcdf version="1.0">\n{body}\n</hcdf>\n'


def write_doc(folder: Path, *parts: str, name: str = "robot.hcdf") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    doc = folder / name
    doc.write_text(hcdf(*parts))
    return doc


def line_of(doc: Path, needle: str) -> int:
    for i, text in enumerate(doc.read_text().splitlines(), 1):
        if needle in text:
            return i
    raise AssertionError(f"{needle!r} not in {doc}")


def cache_blobs(cache: Path) -> dict[str, bytes]:
    """Every blob in the cache; asserts each one hashes to its name and no temp file is left."""
    found = {}
    for path in (cache / "sha256").rglob("*") if (cache / "sha256").exists() else []:
        if path.is_file():
            data = path.read_bytes()
            assert sha(data) == path.name, f"cache blob {path} does not hash to its name"
            found[path.name] = data
    leftovers = [p for p in (cache / "tmp").rglob("*")] if (cache / "tmp").exists() else []
    assert leftovers == [], f"temporary files left in the cache: {leftovers}"
    return found


@pytest.fixture
def work(tmp_path: Path) -> Path:
    return tmp_path / "work"


@pytest.fixture
def cache(tmp_path: Path) -> Path:
    return tmp_path / "cache"


@pytest.fixture
def resolve(cli, tls, cache):
    """``resolve(doc, *extra)``: the CLI with the test CA and the test's own cache."""

    def run(doc: Path, *extra: str | os.PathLike[str]):
        return cli("resolve", doc, "--ca-bundle", tls.ca_pem, "--cache-dir", cache, *extra)

    return run


@pytest.fixture
def no_sockets(monkeypatch):
    """Make every outgoing connection in this process fail, and record the attempts."""
    attempts: list[object] = []

    def refuse(self, address, *args):
        attempts.append(address)
        raise OSError("test: sockets are forbidden here")

    monkeypatch.setattr(socket.socket, "connect", refuse)
    monkeypatch.setattr(socket.socket, "connect_ex", refuse)
    return attempts


# -- TLS ------------------------------------------------------------------------------------


def test_fetch_over_tls_verifies_sha256_caches_and_locks(https_server, resolve, work, cache):
    data = blob(300_000, seed=1)
    url = https_server.add("/models/arm.glb", data)
    doc = write_doc(work, model(url, sha(data)))

    result = resolve(doc, "--json")

    assert result.exit_code == 0, result.stderr + result.stdout
    (art,) = result.json["artifacts"]
    assert art["url"] == url
    assert art["sha256"] == sha(data)
    assert art["size"] == len(data)
    assert art["source"] == "network"
    assert cache_blobs(cache) == {sha(data): data}
    assert url in (work / "robot.hcdf.lock").read_text()
    assert https_server.hits["/models/arm.glb"] == 1


@pytest.mark.parametrize(
    ("kind", "words"),
    [("untrusted", ("tls", "certificate")), ("expired", ("certificate", "expired"))],
)
def test_bad_certificate_is_refused(serve, resolve, work, cache, kind, words):
    srv = serve(kind)
    data = blob(1000)
    doc = write_doc(work, model(srv.add("/a.glb", data), sha(data)))

    result = resolve(doc)

    assert result.exit_code == 3, result.stderr
    message = result.stderr.lower()
    for word in words:
        assert word in message, result.stderr
    assert srv.hits["/a.glb"] == 0  # no request was ever sent over the rejected channel
    assert cache_blobs(cache) == {}
    assert not (work / "robot.hcdf.lock").exists()


def test_system_trust_store_does_not_trust_the_test_ca(https_server, cli, work, cache, monkeypatch):
    """Without --ca-bundle the default trust store applies (and knows nothing of our CA)."""
    monkeypatch.delenv("HCDF_TRUST_CA_BUNDLE", raising=False)
    monkeypatch.delenv("SSL_CERT_FILE", raising=False)
    data = blob(100)
    doc = write_doc(work, model(https_server.add("/a.glb", data), sha(data)))

    result = cli("resolve", doc, "--cache-dir", cache)

    assert result.exit_code == 3
    assert "certificate" in result.stderr.lower()


def test_http_error_status_is_an_input_error(https_server, resolve, work, cache):
    doc = write_doc(work, model(https_server.url("/missing.glb"), "ab" * 32))

    result = resolve(doc)

    assert result.exit_code == 3
    assert "HTTP 404" in result.stderr
    assert https_server.hits["/missing.glb"] == 1


# -- redirects --------------------------------------------------------------------------------


def test_redirect_within_https_is_followed(https_server, resolve, work):
    """The control for the refusals below: a same-scheme redirect works."""
    data = blob(5000, seed=2)
    https_server.add("/real/a.glb", data)
    url = https_server.redirect("/a.glb", "/real/a.glb")
    doc = write_doc(work, model(url, sha(data)))

    result = resolve(doc, "--json")

    assert result.exit_code == 0, result.stdout
    assert result.json["artifacts"][0]["url"] == url  # the lock keeps the URL as referenced
    assert https_server.hits["/real/a.glb"] == 1


@pytest.mark.parametrize("allow_http", [False, True])
def test_redirect_to_http_is_refused(https_server, http_server, resolve, work, cache, allow_http):
    data = blob(5000, seed=3)
    target = http_server.add("/a.glb", data)
    url = https_server.redirect("/a.glb", target)
    doc = write_doc(work, model(url, sha(data)))

    result = resolve(doc, *(["--allow-http"] if allow_http else []))

    assert result.exit_code == 3, result.stderr
    assert "redirect from https down to http is refused" in result.stderr
    assert http_server.total_hits == 0  # the downgrade target was never contacted
    assert cache_blobs(cache) == {}
    assert not (work / "robot.hcdf.lock").exists()


def test_redirect_to_file_url_is_refused(https_server, resolve, tmp_path, work, cache):
    # A local file whose digest *is* the pin: following the redirect would "succeed".
    secret = tmp_path / "secret.glb"
    secret.write_bytes(blob(2000, seed=4))
    url = https_server.redirect("/a.glb", secret.as_uri())
    doc = write_doc(work, model(url, sha(secret.read_bytes())))

    result = resolve(doc, "--json")

    assert result.exit_code == 3
    (err,) = result.json["errors"]
    assert err["code"] == "fetch"
    assert "redirect to a file: URL is refused" in err["message"]
    assert err["actual"] == secret.as_uri()
    assert cache_blobs(cache) == {}


@pytest.mark.parametrize("loop", ["self", "pair"])
def test_redirect_loop_is_refused_after_a_bounded_number_of_hops(https_server, resolve, work, cache, loop):
    if loop == "self":
        url = https_server.redirect("/loop", "/loop")
    else:
        url = https_server.redirect("/ping", "{base}/pong")
        https_server.redirect("/pong", "/ping")
    doc = write_doc(work, model(url, "ab" * 32))

    result = resolve(doc)

    assert result.exit_code == 3
    assert "redirects" in result.stderr
    assert 2 <= https_server.total_hits <= 6  # at most 5 redirects followed, then stop


# -- bodies that are too big, lie, or break off -----------------------------------------------


@pytest.mark.parametrize("chunked", [False, True], ids=["content-length", "chunked"])
def test_oversize_body_is_aborted_and_nothing_is_cached(https_server, resolve, work, cache, chunked):
    url = https_server.stream("/big.glb", 20 << 20, chunked=chunked)
    doc = write_doc(work, model(url))  # unpinned: only the limit can stop it

    result = resolve(doc, "--max-size", str(1 << 20))

    assert result.exit_code == 3, result.stderr
    assert "limit" in result.stderr
    assert cache_blobs(cache) == {}
    assert not (work / "robot.hcdf.lock").exists()


def test_body_exactly_at_the_limit_is_accepted(https_server, resolve, work, cache):
    data = blob(1 << 20, seed=5)
    doc = write_doc(work, model(https_server.add("/a.glb", data), sha(data)))

    result = resolve(doc, "--max-size", str(1 << 20))

    assert result.exit_code == 0, result.stderr
    assert set(cache_blobs(cache)) == {sha(data)}


def test_content_length_longer_than_the_body_is_an_error(https_server, resolve, work, cache):
    data = blob(50_000, seed=6)
    url = https_server.lie("/a.glb", data[:30_000], declared=len(data))
    doc = write_doc(work, model(url))  # unpinned: only the transport check can catch it

    result = resolve(doc, "--json")

    assert result.exit_code == 3, result.stdout
    (err,) = result.json["errors"]
    assert err["code"] == "fetch"
    assert cache_blobs(cache) == {}
    assert not (work / "robot.hcdf.lock").exists()


def test_content_length_shorter_than_the_body_truncates_and_the_pin_catches_it(https_server, resolve, work, cache):
    """HTTP says the body ends where Content-Length says: the tool reads that many
    bytes, hashes them, and the pin (of the full file) does not match."""
    data = blob(50_000, seed=7)
    url = https_server.lie("/a.glb", data, declared=30_000)
    doc = write_doc(work, model(url, sha(data)))

    result = resolve(doc, "--json")

    assert result.exit_code == 1, result.stdout
    (err,) = result.json["errors"]
    assert err["code"] == "digest-mismatch"
    assert err["expected"] == sha(data)
    assert err["actual"] == sha(data[:30_000])
    assert cache_blobs(cache) == {}  # neither the full nor the truncated content
    assert not (work / "robot.hcdf.lock").exists()


@pytest.mark.parametrize("scheme", ["https", "http"])
def test_connection_reset_mid_body_is_a_network_error(serve, resolve, work, cache, scheme):
    """Over TLS Python reports the reset as an early end of stream (Content-Length
    catches it); over plain http the client sees ECONNRESET itself."""
    srv = serve("good" if scheme == "https" else None)
    data = blob(400_000, seed=8)
    url = srv.reset("/a.glb", data, after=100_000)
    doc = write_doc(work, model(url, sha(data)))

    result = resolve(doc, "--json", "--allow-http")

    assert result.exit_code == 3, result.stdout
    (err,) = result.json["errors"]
    assert err["code"] == "fetch"
    assert err["file"].endswith("robot.hcdf") and isinstance(err["line"], int)  # names the reference
    assert cache_blobs(cache) == {}
    assert not (work / "robot.hcdf.lock").exists()


@pytest.mark.parametrize("cut", [False, True], ids=["whole", "truncated"])
def test_body_delimited_only_by_connection_close_is_refused(https_server, resolve, work, cache, cut):
    """Without Content-Length or chunking, a cut connection looks like the end of the
    body (Python treats TLS EOF without close_notify as clean): refuse such bodies,
    whole or not, rather than lock a truncated file."""
    data = blob(200_000, seed=21)
    if cut:
        https_server.routes["/a.glb"] = Route(body=data, close_delimited=True, reset_after=50_000)
    else:
        https_server.routes["/a.glb"] = Route(body=data, close_delimited=True)
    doc = write_doc(work, model(https_server.url("/a.glb")))  # unpinned: trust on first use

    result = resolve(doc)

    assert result.exit_code == 3, result.stderr
    assert "Content-Length" in result.stderr
    assert cache_blobs(cache) == {}
    assert not (work / "robot.hcdf.lock").exists()


def test_gzip_encoded_body_is_decoded_and_hashed_as_the_file(https_server, resolve, work, cache):
    """The control for the bomb: Content-Encoding is undone, the pin is of the file."""
    data = blob(100_000, seed=9) + bytes(100_000)
    https_server.add("/a.glb", gzip.compress(data), headers={"Content-Encoding": "gzip"})
    doc = write_doc(work, model(https_server.url("/a.glb"), sha(data)))

    result = resolve(doc, "--json")

    assert result.exit_code == 0, result.stdout
    assert result.json["artifacts"][0]["size"] == len(data)
    assert cache_blobs(cache) == {sha(data): data}


def test_gzip_bomb_stops_at_the_limit(https_server, resolve, work, cache):
    url = https_server.gzip_bomb("/bomb.glb", expanded=64 << 20)
    doc = write_doc(work, model(url))

    result = resolve(doc, "--max-size", str(1 << 20))

    assert result.exit_code == 3, result.stderr
    assert "limit" in result.stderr
    assert cache_blobs(cache) == {}


def test_gzip_bomb_is_inflated_in_bounded_memory(https_server, tls):
    """64 MiB of zeros in ~64 KB on the wire; the limit is 1 MiB. Memory stays small
    (httpx's own decoder would inflate a whole 64 KiB read to ~64 MiB at once)."""
    url = https_server.gzip_bomb("/bomb.glb", expanded=64 << 20)
    fetcher = HttpFetcher(ca_bundle=str(tls.ca_pem), max_bytes=1 << 20, timeout=5)
    received = 0
    tracemalloc.start()
    try:
        with pytest.raises(FetchError, match="limit"):
            with fetcher.open(url) as chunks:
                for chunk in chunks:
                    received += len(chunk)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
        fetcher.close()
    assert received <= 1 << 20
    assert peak < 8 << 20, f"peak {peak} bytes while inflating a gzip bomb"


def test_padding_after_a_gzip_body_counts_against_the_limit(https_server, resolve, work, cache):
    """Zero bytes after the end of a gzip stream are tolerated, but not without bound."""
    data = blob(1000, seed=19)
    https_server.add(
        "/a.glb",
        gzip.compress(data) + bytes(4 << 20),
        headers={"Content-Encoding": "gzip"},
        chunked=True,  # no Content-Length for the early check to catch
    )
    doc = write_doc(work, model(https_server.url("/a.glb"), sha(data)))

    result = resolve(doc, "--max-size", str(1 << 20))

    assert result.exit_code == 3, result.stderr
    assert "limit" in result.stderr
    assert cache_blobs(cache) == {}


@pytest.mark.parametrize("members", [1, 3])
def test_gzip_with_padding_or_several_members_decodes(https_server, resolve, work, members):
    parts = [blob(20_000, seed=40 + i) for i in range(members)]
    body = b"".join(gzip.compress(p) for p in parts) + bytes(100)
    https_server.add("/a.glb", body, headers={"Content-Encoding": "gzip"})
    doc = write_doc(work, model(https_server.url("/a.glb"), sha(b"".join(parts))))

    result = resolve(doc)

    assert result.exit_code == 0, result.stderr


def test_truncated_gzip_body_is_an_error(https_server, resolve, work, cache):
    data = blob(50_000, seed=20)
    https_server.add("/a.glb", gzip.compress(data)[:-100], headers={"Content-Encoding": "gzip"})
    doc = write_doc(work, model(https_server.url("/a.glb")))  # unpinned

    result = resolve(doc)

    assert result.exit_code == 3, result.stderr
    assert "truncated" in result.stderr
    assert cache_blobs(cache) == {}


def test_unknown_content_encoding_is_refused(https_server, resolve, work):
    data = blob(1000)
    https_server.add("/a.glb", data, headers={"Content-Encoding": "br"})
    doc = write_doc(work, model(https_server.url("/a.glb"), sha(data)))

    result = resolve(doc)

    assert result.exit_code == 3
    assert "Content-Encoding" in result.stderr


# -- time -------------------------------------------------------------------------------------


@pytest.mark.parametrize("after", [-1, 10_000], ids=["no-headers", "mid-body"])
def test_stalled_server_times_out(https_server, resolve, work, cache, after):
    data = blob(50_000, seed=10)
    url = https_server.stall("/a.glb", after=after, body=data)
    doc = write_doc(work, model(url, sha(data)))

    started = time.monotonic()
    result = resolve(doc, "--timeout", "1")
    elapsed = time.monotonic() - started

    assert result.exit_code == 3, result.stderr
    assert "timed out" in result.stderr
    assert elapsed < 10, f"a 1 s timeout took {elapsed:.1f} s"
    assert cache_blobs(cache) == {}


def test_dripping_server_is_cut_off_by_the_deadline(https_server, tls):
    """One byte every 0.1 s never trips a 1 s read timeout; the whole-fetch deadline stops it."""
    url = https_server.drip("/a.glb", blob(40), every=0.1)  # would take 4 s
    fetcher = HttpFetcher(ca_bundle=str(tls.ca_pem), timeout=1, deadline=0.5)
    started = time.monotonic()
    try:
        with pytest.raises(FetchError, match="longer than"):
            with fetcher.open(url) as chunks:
                for _ in chunks:
                    pass
    finally:
        fetcher.close()
    assert time.monotonic() - started < 5


# -- the cache and fetch-once -----------------------------------------------------------------


def test_each_file_is_fetched_once_and_a_second_resolve_fetches_nothing(https_server, resolve, work, cache):
    glb = blob(120_000, seed=11)
    profile = b"<stream-profile/>"
    https_server.add("/models/arm.glb", glb)
    https_server.add("/profiles/p.xml", profile)
    # The sub-assembly is remote: its relative references resolve against its URL.
    sub = hcdf(model("models/arm.glb"), model("./models/../models/arm.glb"), model("models/arm.glb"))
    https_server.add("/sub.hcdf", sub.encode())
    sub_url = https_server.url("/sub.hcdf")
    work.mkdir(parents=True)
    doc = work / "robot.hcdf"
    doc.write_text(
        '<?xml version="1.0"?>\n<hcdf version="1.0">\n'
        f'  <include uri="{sub_url}" sha="{sha(sub.encode())}" name="left" pose="0 0.1 0 0 0 0"/>\n'
        f'  <include uri="{sub_url}" sha="{sha(sub.encode())}" name="right" pose="0 -0.1 0 0 0 0"/>\n'
        f'  <comp name="base">{model(https_server.url("/models/arm.glb"), sha(glb))}</comp>\n'
        f'  <comp name="head">{model(https_server.url("/x/../models/arm.glb"))}</comp>\n'
        f'  <stream-profile uri="{https_server.url("/profiles/p.xml")}"/>\n'
        "</hcdf>\n"
    )

    first = resolve(doc, "--json")

    assert first.exit_code == 0, first.stdout
    lock = (work / "robot.hcdf.lock").read_bytes()
    assert dict(https_server.hits) == {"/sub.hcdf": 1, "/models/arm.glb": 1, "/profiles/p.xml": 1}
    arm = next(a for a in first.json["artifacts"] if a["url"].endswith("/models/arm.glb"))
    assert len(arm["referenced_from"]) == 5  # two lines of robot.hcdf, three of sub.hcdf
    assert first.json["summary"]["fetched"] == 3

    second = resolve(doc, "--json")

    assert second.exit_code == 0, second.stdout
    assert https_server.total_hits == 3  # nothing new: everything came from the cache
    assert second.json["summary"]["fetched"] == 0
    assert second.json["summary"]["from_cache"] == 3
    assert (work / "robot.hcdf.lock").read_bytes() == lock  # same tree, same lock, byte for byte


def test_cached_blob_that_was_tampered_with_is_fetched_again(https_server, resolve, work, cache):
    data = blob(10_000, seed=12)
    doc = write_doc(work, model(https_server.add("/a.glb", data), sha(data)))
    assert resolve(doc).exit_code == 0
    (path,) = [p for p in (cache / "sha256").rglob("*") if p.is_file()]
    path.chmod(0o644)
    path.write_bytes(b"evil")

    result = resolve(doc, "--json")

    assert result.exit_code == 0, result.stdout
    assert https_server.hits["/a.glb"] == 2
    assert cache_blobs(cache) == {sha(data): data}


# -- offline ----------------------------------------------------------------------------------


def test_offline_with_an_empty_cache_fails_clearly_and_opens_no_socket(https_server, resolve, work, cache, no_sockets):
    data = blob(1000, seed=13)
    doc = write_doc(work, model(https_server.add("/a.glb", data), sha(data)))

    result = resolve(doc, "--offline", "--json")

    assert result.exit_code == 3
    (err,) = result.json["errors"]
    assert err["code"] == "offline"
    assert "--offline" in err["message"] and "cache" in err["message"]
    assert err["line"] == line_of(doc, "a.glb")
    assert no_sockets == []
    assert https_server.total_hits == 0
    assert not (work / "robot.hcdf.lock").exists()


def test_offline_resolves_from_a_warm_cache_without_a_socket(https_server, resolve, work, monkeypatch):
    data = blob(1000, seed=14)
    doc = write_doc(work, model(https_server.add("/a.glb", data)))  # unpinned: found via the lock
    assert resolve(doc).exit_code == 0
    attempts: list[object] = []

    def refuse(self, address, *args):
        attempts.append(address)
        raise OSError("test: sockets are forbidden here")

    monkeypatch.setattr(socket.socket, "connect", refuse)

    result = resolve(doc, "--offline", "--json")

    assert result.exit_code == 0, result.stdout
    assert result.json["summary"]["from_cache"] == 1
    assert attempts == []
    assert https_server.hits["/a.glb"] == 1


# -- plain http -------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("flags", "pin", "ok"),
    [
        ((), "full", False),
        (("--allow-http",), None, False),
        (("--allow-http",), "weak", False),
        (("--allow-http",), "full", True),
    ],
    ids=["no-flag", "flag-unpinned", "flag-weak-pin", "flag-full-pin"],
)
def test_plain_http_needs_allow_http_and_a_full_pin(http_server, resolve, work, cache, flags, pin, ok):
    data = blob(3000, seed=15)
    url = http_server.add("/a.glb", data)
    written = {None: None, "weak": sha(data)[:8], "full": sha(data)}[pin]
    doc = write_doc(work, model(url, written))

    result = resolve(doc, *flags)

    if ok:
        assert result.exit_code == 0, result.stderr
        assert http_server.hits["/a.glb"] == 1
        assert cache_blobs(cache) == {sha(data): data}
    else:
        assert result.exit_code == 3, result.stderr
        assert "--allow-http" in result.stderr and "full SHA-256 pin" in result.stderr
        assert http_server.total_hits == 0  # refused before any request
        assert cache_blobs(cache) == {}


def test_plain_http_with_a_full_pin_still_catches_a_mismatch(http_server, resolve, work, cache):
    url = http_server.add("/a.glb", b"tampered on the wire")
    doc = write_doc(work, model(url, sha(b"the real file")))

    result = resolve(doc, "--allow-http")

    assert result.exit_code == 1
    assert cache_blobs(cache) == {}


# -- mirrors ----------------------------------------------------------------------------------


def test_mirror_to_a_loopback_server(serve, resolve, tmp_path, work, monkeypatch):
    data = blob(4000, seed=16)
    site = tmp_path / "site"
    (site / "models").mkdir(parents=True)
    (site / "models" / "a.glb").write_bytes(data)
    https_server = serve("good", root=site)  # this one serves a folder
    logical = "https://example.invalid/models/a.glb"
    doc = write_doc(work, model(logical, sha(data)))
    looked_up: list[str] = []
    real_getaddrinfo = socket.getaddrinfo

    def getaddrinfo(host, *args, **kw):
        looked_up.append(host)
        return real_getaddrinfo(host, *args, **kw)

    monkeypatch.setattr(socket, "getaddrinfo", getaddrinfo)

    result = resolve(doc, "--mirror", f"https://example.invalid/={https_server.base}/", "--json")

    assert result.exit_code == 0, result.stdout
    assert https_server.hits["/models/a.glb"] == 1
    assert "example.invalid" not in looked_up
    assert result.json["artifacts"][0]["url"] == logical  # the lock keeps the logical URL
    assert logical in (work / "robot.hcdf.lock").read_text()


def test_mirror_to_a_folder_needs_no_network(resolve, tmp_path, work, no_sockets):
    data = blob(4000, seed=17)
    mirror = tmp_path / "mirror"
    (mirror / "models").mkdir(parents=True)
    (mirror / "models" / "a.glb").write_bytes(data)
    doc = write_doc(work, model("https://example.invalid/models/a.glb", sha(data)))

    result = resolve(doc, "--mirror", f"https://example.invalid/={mirror}", "--json")

    assert result.exit_code == 0, result.stdout
    assert result.json["artifacts"][0]["source"] == "mirror"
    assert no_sockets == []


# -- digest mismatch --------------------------------------------------------------------------


def test_digest_mismatch_over_https_names_file_line_expected_actual(https_server, resolve, work, cache):
    served = blob(8000, seed=18)
    pinned = sha(b"what the author meant")
    url = https_server.add("/models/wrong.glb", served)
    doc = write_doc(work, model(https_server.add("/ok.glb", b"fine"), sha(b"fine")), model(url, pinned))

    as_json = resolve(doc, "--json")
    human = resolve(doc)

    assert as_json.exit_code == 1 and human.exit_code == 1
    (err,) = as_json.json["errors"]
    assert err["code"] == "digest-mismatch"
    assert Path(err["file"]).resolve() == doc.resolve()
    assert err["line"] == line_of(doc, "wrong.glb")
    assert err["expected"] == pinned
    assert err["actual"] == sha(served)
    assert url in err["url"]
    assert f"{doc.name}:{err['line']}" in human.stderr
    assert pinned in human.stderr and sha(served) in human.stderr
    assert sha(served) not in cache_blobs(cache)  # the good file may be cached; the bad never
    assert not (work / "robot.hcdf.lock").exists()


# -- parallel fetch ---------------------------------------------------------------------------


def test_fetches_run_in_parallel_up_to_jobs(https_server, resolve, work, cache):
    """--jobs 16 keeps many requests in flight at once, each file fetched once. Counted by the
    server (not timed: the speed-up itself is measured in bench/, as a ratio)."""
    n, latency = 200, 0.02
    files = {f"/m/{i:03}.glb": blob(2000, seed=1000 + i) for i in range(n)}
    for path, data in files.items():
        https_server.add(path, data)
    https_server.latency = latency
    doc = write_doc(work, *(model(https_server.url(p), sha(d)) for p, d in files.items()))

    result = resolve(doc, "--jobs", "16")

    assert result.exit_code == 0, result.stderr
    assert all(https_server.hits[p] == 1 for p in files)
    assert 8 <= https_server.max_in_flight <= 16, https_server.max_in_flight


def test_jobs_1_fetches_one_at_a_time(https_server, resolve, work, cache):
    files = {f"/s/{i:02}.glb": blob(500, seed=2000 + i) for i in range(10)}
    for path, data in files.items():
        https_server.add(path, data)
    https_server.latency = 0.02
    doc = write_doc(work, *(model(https_server.url(p), sha(d)) for p, d in files.items()))
    assert resolve(doc, "--jobs", "1").exit_code == 0
    assert https_server.max_in_flight == 1


def test_an_error_of_the_body_consumer_is_not_reported_as_a_transport_fault(https_server, tls):
    """The caller's own failure while it stores the body (its cache file, a descriptor) is an
    input error that says so, not a fetch error blaming the server."""
    import errno

    from hcdf_trust.errors import InputError

    url = https_server.add("/c.glb", blob(3000, seed=7))
    fetcher = HttpFetcher(ca_bundle=str(tls.ca_pem), timeout=5)
    try:
        with pytest.raises(InputError) as info:
            with fetcher.open(url) as chunks:
                next(chunks)
                raise OSError(errno.EBADF, "Bad file descriptor")
    finally:
        fetcher.close()
    assert not isinstance(info.value, FetchError)
    assert "storing the body failed" in info.value.message and url in info.value.message


def test_a_connection_reset_while_reading_the_body_is_still_a_fetch_error(https_server, tls):
    url = https_server.reset("/r.glb", blob(200_000, seed=8), after=1000)
    fetcher = HttpFetcher(ca_bundle=str(tls.ca_pem), timeout=5)
    try:
        with pytest.raises(FetchError):
            with fetcher.open(url) as chunks:
                for _ in chunks:
                    pass
    finally:
        fetcher.close()
