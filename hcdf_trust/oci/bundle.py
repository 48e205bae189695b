"""``bundle push`` / ``bundle pull``: one ``.hcdfz`` as one OCI 1.1 artifact, verified on every pull.

The artifact (docs/oci.md, "bundle push / pull"): an image manifest with ``artifactType``
:data:`BUNDLE_TYPE`, the empty config, and the bundle, byte for byte, as its one layer
(:data:`BUNDLE_LAYER_TYPE`, the file's name as ``org.opencontainers.image.title``); the
manifest's annotations name the root entry, its SHA-256 and the bundle's. The bundle is its own
lock: every file it holds is pinned by its document, so no signature is needed to check that
what was pulled is one consistent robot; *which* bundle is meant is the manifest digest a
fleet pins (``oci://…@sha256:…``).

``pull`` trusts nothing the registry says; in order:

1. The manifest's digest is the hash of the body received (a ``@sha256:`` reference must match).
2. The manifest is a bundle artifact: artifact type, empty config, exactly one layer of
   :data:`BUNDLE_LAYER_TYPE`, a size within a bundle's cap (``bundle.MAX_BYTES``), a plain title.
3. The blob comes from the content store (verified before: a repeated pull) or is fetched by
   digest, hashed while it streams (into the store and a file of a private staging folder)
   and refused past its declared size; only a blob whose SHA-256 and size are the manifest's
   enters the store or stays staged.
4. In the staging folder the blob is read as ``verify X.hcdfz`` reads it: the same strict
   archive reader and the same walk, every pin re-hashed (exit 3 for the structure, 1 for the
   content); the manifest's annotations must say what the verified bundle says.
5. Only then is the bundle written to ``--out`` through the OutputPlan: the staged file, which
   this pull wrote from the bytes it hashed and held open since, is moved into place.

The staging folder and the content store are the ones ``ota pull`` uses (:mod:`.blobs`), so a
killed pull of either kind is swept by the next.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass, field
from typing import Any

from ..errors import DigestMismatchError, ErrorGroup, IntegrityError, Notice
from .client import MANIFEST_TYPE, RegistryClient, sha256_digest
from .reference import Reference
from .referrers import EMPTY_DESCRIPTOR
from .release import TITLE, A, ArtifactError, check_manifest

BUNDLE_TYPE = "application/vnd.hcdf.bundle.v1"  # the manifest's artifactType
BUNDLE_LAYER_TYPE = "application/vnd.hcdf.bundle.v1+zip"  # its one layer: the .hcdfz, as written
ROOT = A + "root"  # the root entry's name (scout2.hcdf)
ROOT_SHA256 = A + "root-sha256"  # that entry's SHA-256
BUNDLE_SHA256 = A + "bundle-sha256"  # the whole bundle's (also the layer's digest)
UPLOAD_CHUNK = 1 << 20


@dataclass(frozen=True)
class Checked:
    """A bundle verified as ``verify X.hcdfz`` verifies it: what its manifest says of it."""

    root: str
    root_sha256: str
    sha256: str
    size: int
    warnings: list[Notice]

    def annotations(self) -> dict[str, str]:
        return {ROOT: self.root, ROOT_SHA256: self.root_sha256, BUNDLE_SHA256: self.sha256}


def verify_bundle(path: str) -> Checked:
    """The verdict of ``hcdf-trust verify PATH`` on a ``.hcdfz``: the strict archive reader, then
    the resolver's walk over its entries (offline, writing nothing, every pin re-hashed).

    Raises:
        BundleFormatError (exit 3), ErrorGroup of the walk's errors (exit 1 for a mismatch).
    """
    from ..include.resolver import ResolveOptions, verify

    res = verify(path, ResolveOptions())
    if not res.ok:
        raise ErrorGroup(res.errors)
    assert res.bundle is not None  # a .hcdfz name is always read as a bundle
    archive = res.bundle.archive  # the bytes the walk checked (no second read)
    root = archive.root
    root_sha = hashlib.sha256(archive.data(root)).hexdigest()
    return Checked(root.name, root_sha, archive.sha256, archive.size, list(res.warnings))


def manifest_for(checked: Checked, title: str) -> bytes:
    """The bundle's OCI image manifest, deterministic (sorted keys, no spaces)."""
    import json

    doc = {
        "schemaVersion": 2,
        "mediaType": MANIFEST_TYPE,
        "artifactType": BUNDLE_TYPE,
        "config": EMPTY_DESCRIPTOR,
        "layers": [
            {
                "mediaType": BUNDLE_LAYER_TYPE,
                "digest": f"sha256:{checked.sha256}",
                "size": checked.size,
                "annotations": {TITLE: title},
            }
        ],
        "annotations": checked.annotations(),
    }
    return json.dumps(doc, sort_keys=True, separators=(",", ":")).encode()


def layer_title(path: str) -> str:
    """The layer's title: the bundle's file name when it is a plain one, else ``bundle.hcdfz``
    (pull checks it as a one-segment path; it never names where the bundle is written)."""
    from .blobs import SEGMENT

    name = os.path.basename(path)
    return name if SEGMENT.fullmatch(name) else "bundle.hcdfz"


def push_bundle(path: str, ref: Reference, client: RegistryClient) -> dict[str, Any]:
    """Verify ``path`` (a hostile or broken bundle is never sent), then upload the empty config,
    the bundle's bytes (hashed again as they are sent: a file swapped since it was verified is
    refused and the manifest never pushed) and the manifest under the tag."""
    from ..localfile import open_regular
    from .release import EMPTY

    checked = verify_bundle(path)
    body = manifest_for(checked, layer_title(path))
    digest = sha256_digest(body)
    client.check()
    client.push_blob(str(EMPTY_DESCRIPTOR["digest"]), 2, [EMPTY])
    fd, _ = open_regular(path, what="bundle")
    try:
        client.push_blob(f"sha256:{checked.sha256}", checked.size, _as_verified(fd, path, checked))
    finally:
        os.close(fd)
    client.put_manifest(ref.tag or digest, body, MANIFEST_TYPE)
    # Referrers: a bundle has none yet. When `bundle --provenance` writes a signed statement of
    # the bundle, attach it here as ota push attaches a release's (referrers.attach with subject
    # (digest, len(body))), and check it in pull_bundle after step 4 as check_referrers does.
    return {
        "digest": digest,
        "sha256": checked.sha256,
        "size": checked.size,
        "annotations": checked.annotations(),
        "warnings": checked.warnings,
    }


def _as_verified(fd: int, path: str, checked: Checked) -> Any:
    """The file's bytes as uploaded, refused at the end unless they are the bytes verified."""
    from ..localfile import read_chunks

    h = hashlib.sha256()
    size = 0
    for chunk in read_chunks(fd):
        for start in range(0, len(chunk), UPLOAD_CHUNK):
            part = chunk[start : start + UPLOAD_CHUNK]
            h.update(part)
            size += len(part)
            yield part
    if h.hexdigest() != checked.sha256 or size != checked.size:
        raise IntegrityError(
            f"{path} changed while it was being pushed",
            file=path,
            expected=checked.sha256,
            actual=h.hexdigest(),
        )


@dataclass
class BundlePullReport:
    reference: str
    digest: str
    checked: Checked
    from_cache: bool
    wrote: list[str] = field(default_factory=list)


def pull_bundle(ref: Reference, client: RegistryClient, *, out: str, cache_dir: str) -> BundlePullReport:
    """Steps 1-5 above. Raises IntegrityError (exit 1) or InputError (exit 3) before any write."""
    from ..bundle import MAX_BYTES, is_bundle
    from ..outputs import BUNDLE, ORDINARY, OutputPlan
    from ..store import ContentStore
    from .blobs import Stage, fetch_blob

    # 1. the manifest, pinned by the hash of its body
    got = client.get_manifest(ref.reference)
    if got is None:
        raise ArtifactError(f"{ref}: the registry has no such manifest", url=str(ref))
    body, digest, _ = got
    if ref.digest is not None and digest != ref.digest:
        raise DigestMismatchError(
            f"{ref}: the manifest received is not the one pinned", url=str(ref), expected=ref.digest, actual=digest
        )
    source = str(ref.with_digest(digest))
    # 2. a bundle artifact: one layer, within a bundle's cap
    doc, layers = check_manifest(
        body,
        source=source,
        artifact_type=BUNDLE_TYPE,
        layer_types=frozenset({BUNDLE_LAYER_TYPE}),
        max_segments=1,
        what="an hcdf-trust bundle",
        max_layer_bytes=MAX_BYTES,
    )
    if len(layers) != 1:
        raise ArtifactError(
            "a bundle artifact has exactly one layer", file=source, expected="1", actual=str(len(layers))
        )
    layer = layers[0]
    hex_ = layer["digest"].split(":", 1)[1]
    # 3. the blob into the content store, only if it is the manifest's, and into a file of our
    # own in a private staging folder, under --out's name (messages name it)
    store = ContentStore(cache_dir)
    with Stage(cache_dir) as stage:
        name = os.path.basename(out) if is_bundle(out) else "bundle.hcdfz"
        held, cached = fetch_blob(
            client, store, layer, title=layer["annotations"][TITLE], where=f"{source}#/layers/0", stage=stage, rel=name
        )
        # 4. verify X.hcdfz on the staged file
        checked = verify_bundle(held.path)
        if checked.sha256 != hex_:  # the staged file is not the one hashed
            raise DigestMismatchError(
                f"{source}: the staged bundle is not the layer's blob", expected=layer["digest"], actual=checked.sha256
            )
        said = doc.get("annotations")
        said = said if isinstance(said, dict) else {}
        for key, value in checked.annotations().items():
            if said.get(key) != value:
                raise IntegrityError(
                    f"{source}: manifest annotation {key} is not what the verified bundle says",
                    file=source,
                    expected=value,
                    actual=str(said.get(key))[:100],
                )
        # 5. into --out, all or nothing: the staged file moved into place
        plan = OutputPlan()
        plan.protect_tree(cache_dir, what="the cache")
        plan.add(out, held, flag="--out", replaces=(ORDINARY, BUNDLE))
        wrote = [str(p) for p in plan.commit()]
    return BundlePullReport(str(ref), digest, checked, cached, wrote)
