"""The TUF registry site (``registry publish --oci``, ``registry verify|fetch oci://…``) as one
OCI artifact: every file of the published folder one layer, titled with its path in the site.

The registry only transports: trust is decided by the TUF client exactly as for an http(s)
or folder site (``hcdf_trust.registry.client``), through :func:`oci_fetcher`, a python-tuf
``FetcherInterface`` that serves the site's paths from the artifact's blobs, each fetched by
digest and hashed while streaming (a blob that is not its digest is a download error, so TUF
never even sees it).
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Iterator
from typing import Any
from urllib.parse import unquote, urlsplit

from ..digest import hash_fd
from ..errors import DigestMismatchError, HcdfTrustError, InputError
from ..localfile import open_checked
from .client import MANIFEST_TYPE, RegistryClient, connect, sha256_digest
from .reference import Reference
from .referrers import EMPTY_DESCRIPTOR
from .release import ArtifactError, _Layer, check_manifest, push_blobs

SITE_TYPE = "application/vnd.hcdf.registry.site.v1"
METADATA_TYPE = "application/vnd.hcdf.tuf.metadata.v1+json"
TARGET_TYPE = "application/vnd.hcdf.registry.target.v1"
SITE_LAYER_TYPES = frozenset({METADATA_TYPE, TARGET_TYPE})
MAX_SEGMENTS = 8
BASE = "oci-site:///"  # the TUF client's base URL for a site served by oci_fetcher


def site_layers(folder: str) -> list[_Layer]:
    """Every regular file under ``metadata/`` and ``targets/`` (a symlink is refused)."""
    layers = []
    for top, media_type in (("metadata", METADATA_TYPE), ("targets", TARGET_TYPE)):
        for dirpath, dirnames, filenames in os.walk(os.path.join(folder, top)):
            dirnames.sort()
            for name in sorted(filenames):
                path = os.path.join(dirpath, name)
                rel = os.path.relpath(path, folder).replace(os.sep, "/")
                if os.path.islink(path):
                    raise InputError(f"{rel}: a symlink in the site is refused", file=rel)
                fd, st = open_checked(path, folder, file=rel)
                try:
                    hashed = hash_fd(fd, size=st.st_size)
                finally:
                    os.close(fd)
                layers.append(_Layer(rel, media_type, hashed.sha256, hashed.size, {}))
    if not any(x.rel == "metadata/timestamp.json" for x in layers):
        raise InputError(f"{folder}: not a published registry site (no metadata/timestamp.json)", file=folder)
    return layers


def push_site(folder: str, ref: Reference, client: RegistryClient) -> dict[str, Any]:
    layers = site_layers(folder)
    push_blobs(client, folder, layers)
    doc = {
        "schemaVersion": 2,
        "mediaType": MANIFEST_TYPE,
        "artifactType": SITE_TYPE,
        "config": EMPTY_DESCRIPTOR,
        "layers": [x.descriptor() for x in layers],
    }
    body = json.dumps(doc, sort_keys=True, separators=(",", ":")).encode()
    digest = sha256_digest(body)
    client.put_manifest(ref.tag or digest, body, MANIFEST_TYPE)
    return {"digest": digest, "files": len(layers)}


def oci_fetcher(site: str, *, ca_bundle: str | None = None, insecure_registries: tuple[str, ...] = ()) -> Any:
    """A python-tuf fetcher serving the site artifact ``site`` (``oci://…:TAG|@sha256:…``),
    talking to the registry as ``ota pull`` does (``--ca-bundle``, ``--insecure-registry``).

    Raises:
        ArtifactError / RegistryError / DigestMismatchError: the manifest cannot be used.
    """
    from tuf.api.exceptions import DownloadError, DownloadHTTPError
    from tuf.ngclient import FetcherInterface

    ref, client = connect(site, ca_bundle=ca_bundle, insecure_registries=insecure_registries)
    got = client.get_manifest(ref.reference)
    if got is None:
        raise ArtifactError(f"{ref}: the registry has no such manifest", url=str(ref))
    body, digest, _ = got
    if ref.digest is not None and digest != ref.digest:
        raise DigestMismatchError(
            f"{ref}: the manifest received is not the one pinned", url=str(ref), expected=ref.digest, actual=digest
        )
    _, layers = check_manifest(
        body,
        source=str(ref.with_digest(digest)),
        artifact_type=SITE_TYPE,
        layer_types=SITE_LAYER_TYPES,
        max_segments=MAX_SEGMENTS,
        what="an hcdf-trust registry site",
    )
    by_title = {x["annotations"]["org.opencontainers.image.title"]: x for x in layers}

    class OciFetcher(FetcherInterface):
        """Site paths -> blobs by digest, each hashed; a path the artifact lacks is a 404."""

        def _fetch(self, url: str) -> Iterator[bytes]:
            title = unquote(urlsplit(url).path).lstrip("/")
            layer = by_title.get(title)
            if layer is None:
                raise DownloadHTTPError(f"{title}: not in the site artifact", 404)
            return self._stream(layer, title)

        def _stream(self, layer: dict[str, Any], title: str) -> Iterator[bytes]:
            h = hashlib.sha256()
            try:
                with client.blob(layer["digest"], layer["size"]) as chunks:
                    for chunk in chunks:
                        h.update(chunk)
                        yield chunk
            except HcdfTrustError as exc:
                raise DownloadError(str(exc)) from None
            if "sha256:" + h.hexdigest() != layer["digest"]:
                raise DownloadError(f"{title}: the blob's SHA-256 is not its digest in the site manifest")

    return OciFetcher()
