"""The official SPDX 3 validator (PyPI ``spdx3-validate``), run offline.

It checks a document against the 3.0.1 JSON Schema and the SHACL shapes of the 3.0.1 model,
which it normally downloads from spdx.org. Here those three URLs are answered from the copies in
``../shared/specs/spdx-3.0.1/`` (see its README) and every other URL is refused, so a document
that only passes because something was fetched from the network cannot pass.
"""

from __future__ import annotations

import contextlib
import email.message
import hashlib
import io
import json
import tempfile
import threading
import urllib.error
import urllib.request
import urllib.response
from collections.abc import Iterator
from pathlib import Path

from tests.conftest import SPECS

SPDX = SPECS / "spdx-3.0.1"
SERVED = {
    "https://spdx.org/rdf/3.0.1/spdx-context.jsonld": ("spdx-context.jsonld", "application/ld+json"),
    "https://spdx.org/rdf/3.0.1/spdx-model.ttl": ("spdx-model.ttl", "text/turtle"),
    "https://spdx.org/schema/3.0.1/spdx-json-schema.json": ("schema.json", "application/schema+json"),
}
_LOCK = threading.Lock()  # the opener is process-global


class _SpecFiles(urllib.request.BaseHandler):
    """Answers the three spec URLs from the local copies; any other URL is an error."""

    handler_order = 0

    def _serve(self, req: urllib.request.Request) -> urllib.response.addinfourl:
        url = req.full_url
        if url not in SERVED:
            raise urllib.error.URLError(f"offline SPDX validation: refusing to fetch {url}")
        name, ctype = SERVED[url]
        headers = email.message.Message()
        headers["Content-Type"] = ctype
        return urllib.response.addinfourl(io.BytesIO((SPDX / name).read_bytes()), headers, url, 200)

    http_open = https_open = _serve

    def unknown_open(self, req: urllib.request.Request) -> None:
        raise urllib.error.URLError(f"offline SPDX validation: refusing to fetch {req.full_url}")


@contextlib.contextmanager
def _offline() -> Iterator[None]:
    opener = urllib.request.OpenerDirector()
    opener.add_handler(_SpecFiles())
    with _LOCK:
        previous = urllib.request._opener  # type: ignore[attr-defined]
        urllib.request.install_opener(opener)
        try:
            yield
        finally:
            urllib.request._opener = previous  # type: ignore[attr-defined]


def spdx3_validate(data: bytes) -> list[str]:
    """Every finding of ``spdx3-validate`` on one SPDX 3.0.1 JSON-LD document (empty: valid).

    Its JSON Schema stage takes seconds per document, so a document already checked in this
    process (the same bytes) is not checked again."""
    digest = hashlib.sha256(data).hexdigest()
    if digest not in _FINDINGS:
        _FINDINGS[digest] = _run(data)
    return _FINDINGS[digest]


_FINDINGS: dict[str, list[str]] = {}


def _run(data: bytes) -> list[str]:
    assert SPDX.is_dir(), f"SPDX 3.0.1 spec files not found at {SPDX} (../shared/specs, or set HCDF_SPECS)"
    from spdx3_validate.core import validate

    with tempfile.TemporaryDirectory() as tmp, _offline():
        path = Path(tmp) / "sbom.spdx.json"
        path.write_bytes(data)
        result = validate(str(path), version="3.0.1")
    return [f"[{e.kind}] {e.message}" for e in result.errors]


def check_cli_run(argv: list[str], stdout: str) -> None:
    """After a successful ``hcdf-trust sbom ... --format spdx``: what it wrote passes the validator."""
    out = next((argv[i + 1] for i, a in enumerate(argv[:-1]) if a in ("-o", "--out")), None)
    out = next((a.split("=", 1)[1] for a in argv if a.startswith("--out=")), out)
    if out not in (None, "-"):
        data = Path(out).read_bytes()
    elif "--json" in argv:  # the document inside the summary object
        data = json.dumps(json.loads(stdout)["sbom"]).encode()
    else:
        data = stdout.encode()
    errors = spdx3_validate(data)
    assert not errors, f"spdx3-validate refuses the SPDX document: {errors}"[:4000]
