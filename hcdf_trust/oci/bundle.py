"""``bundle push`` / ``bundle pull``: one ``.hcdfz`` as one OCI 1.1 artifact, verified on every pull.

The artifact (docs/oci.md, "bundle push / pull"): an image manifest with ``artifactType``
:data:`BUNDLE_TYPE`, the empty config, and the bundle, byte for byte, as its one layer
(:data:`BUNDLE_LAYER_TYPE`, the file's name as ``org.opencontainers.image.title``); the
manifest's annotations name the root entry, its SHA-256 and the bundle's. The bundle is its own
lock: every file it holds is pinned by its document, so no signature is needed to check that
what was pulled is one consistent robot; *which* bundle is meant is the manifest digest a
fleet pins (``oci://…@sha256:…``), or, for a tag, the bundle's signed provenance. Beside it,
as ``ota push`` attaches a release's (:mod:`.referrers`, the same code): the provenance
``X.hcdfz.intoto.json`` (``bundle --provenance``) and each SBOM, as referrers whose
``subject`` is the bundle manifest.

``pull`` trusts nothing the registry says; in order:

1. The manifest's digest is the hash of the body received (a ``@sha256:`` reference must match;
   a tag is pulled only through a provenance that verifies, or when the caller trusts the tag).
2. The manifest is a bundle artifact: artifact type, empty config, exactly one layer of
   :data:`BUNDLE_LAYER_TYPE`, a size within a bundle's cap (``bundle.MAX_BYTES``), a plain title.
3. The blob comes from the content store (verified before: a repeated pull) or is fetched by
   digest, hashed while it streams (into the store and a file of a private staging folder)
   and refused past its declared size; only a blob whose SHA-256 and size are the manifest's
   enters the store or stays staged.
4. The referrers are listed once, each checked against its subject; the provenance is fetched
   (bounded, hashed) when keys were given to check it, and required when asked for.
5. In the staging folder the blob is read as ``verify X.hcdfz`` reads it: the same strict
   archive reader and the same walk, every pin re-hashed (exit 3 for the structure, 1 for the
   content), then the provenance as ``verify X.hcdfz --provenance`` checks it; the manifest's
   annotations must say what the verified bundle says. Messages name the reference and the
   entry (``oci://…@sha256:…/scout2.hcdfz/assets/…``), never the staging folder.
6. Only then is the bundle written to ``--out`` (and the verified provenance beside it) through
   the OutputPlan: the staged file, which this pull wrote from the bytes it hashed and held
   open since, is moved into place (:class:`~hcdf_trust.outputs.HeldFile`).

The staging folder and the content store are the ones ``ota pull`` uses (:mod:`.blobs`), so a
killed pull of either kind is swept by the next.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass, field
from typing import Any

from ..errors import DigestMismatchError, ErrorGroup, InputError, IntegrityError, Notice
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


@dataclass(frozen=True)
class Provenance:
    """A bundle's provenance envelope to verify (``verify X.hcdfz --provenance``'s checks):
    its bytes, where they came from (for messages), who may sign it and how many must."""

    data: bytes
    source: str
    keys: list[Any]
    threshold: int = 1


def verify_bundle(path: str, *, provenance: Provenance | None = None) -> Checked:
    """The verdict of ``hcdf-trust verify PATH`` on a ``.hcdfz``: the strict archive reader, then
    the resolver's walk over its entries (offline, writing nothing, every pin re-hashed); with
    ``provenance``, also ``verify PATH --provenance``'s, over the same bytes.

    Raises:
        BundleFormatError (exit 3), ErrorGroup of the walk's errors (exit 1 for a mismatch),
        MalformedProvenanceError / ProvenanceError (the envelope, its signatures, its statement).
    """
    from ..include.resolver import ResolveOptions, verify

    res = verify(path, ResolveOptions())
    if not res.ok:
        raise ErrorGroup(res.errors)
    assert res.bundle is not None  # a .hcdfz name is always read as a bundle
    archive = res.bundle.archive  # the bytes the walk checked (no second read)
    if provenance is not None:
        from ..provenance.bundle import verify_bundle_provenance

        errors = verify_bundle_provenance(
            archive, provenance.data, provenance.keys, threshold=provenance.threshold, source=provenance.source
        )
        if errors:
            raise ErrorGroup(errors)
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
    (pull checks it as a one-segment path; it never names where the bundle is written); the
    same for the provenance beside it (``X.hcdfz.intoto.json``, else ``bundle.hcdfz.intoto.json``)."""
    from ..provenance.bundle import SUFFIX
    from .blobs import SEGMENT

    name = os.path.basename(path)
    if name.endswith(SUFFIX):
        bundle = name[: -len(SUFFIX)]
        return (bundle if SEGMENT.fullmatch(name) else "bundle.hcdfz") + SUFFIX
    return name if SEGMENT.fullmatch(name) else "bundle.hcdfz"


def read_envelope(path: str) -> bytes | None:
    """The provenance beside the bundle ``path`` (``X.hcdfz.intoto.json``, ``bundle
    --provenance``), bounded; None without one."""
    from ..localfile import read_input
    from ..provenance.bundle import envelope_path
    from ..provenance.dsse import MAX_ENVELOPE_BYTES

    where = envelope_path(path)
    if not os.path.lexists(where):
        return None
    return read_input(where, limit=MAX_ENVELOPE_BYTES, what="provenance")


def push_bundle(
    path: str,
    ref: Reference,
    client: RegistryClient,
    *,
    sboms: list[Any] | None = None,
    provenance_keys: list[Any] | None = None,
    threshold: int = 1,
) -> dict[str, Any]:
    """Verify ``path`` (a hostile or broken bundle is never sent) and, given
    ``provenance_keys``, its provenance (which must then exist); then upload the empty config,
    the bundle's bytes (hashed again as they are sent: a file swapped since it was verified is
    refused and the manifest never pushed), the manifest under the tag, and the referrers: the
    provenance beside the bundle (``X.hcdfz.intoto.json``) when there is one, and each SBOM
    (:func:`.release.read_sbom`), attached as ``ota push`` attaches a release's."""
    from ..localfile import open_regular
    from ..provenance import PREDICATE_TYPE
    from ..provenance.bundle import envelope_path
    from .referrers import (
        BUNDLE_PROVENANCE_TYPE,
        BUNDLE_SBOM_TYPE,
        DSSE_TYPE,
        PREDICATE_ANNOTATION,
        attach,
        push_small_blob,
    )
    from .release import EMPTY

    envelope = read_envelope(path)
    check = None
    if provenance_keys is not None:
        if envelope is None:
            from ..errors import NotFoundError

            where = envelope_path(path)
            raise NotFoundError(
                f"{where}: no provenance beside the bundle to verify (--provenance-key)",
                file=where,
                expected="bundle --provenance's envelope",
                actual="none",
            )
        check = Provenance(envelope, envelope_path(path), provenance_keys, threshold)
    checked = verify_bundle(path, provenance=check)
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
    items: list[tuple[str, dict[str, Any]]] = []
    if envelope is not None:
        about = {TITLE: layer_title(envelope_path(path)), PREDICATE_ANNOTATION: PREDICATE_TYPE}
        items.append((BUNDLE_PROVENANCE_TYPE, push_small_blob(client, envelope, DSSE_TYPE, about)))
    for sbom in sboms or []:
        items.append((BUNDLE_SBOM_TYPE, push_small_blob(client, sbom.data, sbom.media_type, {TITLE: sbom.title})))
    referrers = attach(client, (digest, len(body)), items)
    warnings = list(checked.warnings)
    if envelope is not None and check is None:
        warnings.append(
            Notice(
                "unverified-provenance",
                f"attached {envelope_path(path)} without --provenance-key: not verified first "
                "(a pull with --provenance-key verifies it)",
                file=envelope_path(path),
            )
        )
    return {
        "digest": digest,
        "sha256": checked.sha256,
        "size": checked.size,
        "annotations": checked.annotations(),
        "referrers": [{"digest": d, "artifactType": t} for d, (t, _) in zip(referrers, items, strict=True)],
        "provenance_verified": check is not None,
        "warnings": warnings,
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
    provenance: str | None = None  # the provenance referrer verified and written beside --out, if any
    sboms: list[dict[str, Any]] = field(default_factory=list)  # SBOM referrers listed (checked, not fetched)
    notices: list[Notice] = field(default_factory=list)


def pull_bundle(
    ref: Reference,
    client: RegistryClient,
    *,
    out: str,
    cache_dir: str,
    provenance_keys: list[Any] | None = None,
    threshold: int = 1,
    require_provenance: bool = False,
    trust_tag: bool = False,
) -> BundlePullReport:
    """Steps 1-6 above. ``provenance_keys``: who may sign the bundle's provenance (none given:
    a provenance listed is not fetched, and a notice says so); ``threshold`` signatures needed;
    ``require_provenance``: none listed is an error. A tag (``ref`` without a digest) names
    whatever the registry says today: it is pulled only when its provenance verifies (keys
    given: then one is required), or with ``trust_tag``.

    Raises:
        InputError: a tag without keys or ``trust_tag``, or ``require_provenance`` without keys
            (exit 3; the CLI says so as a usage error before any request). IntegrityError
            (exit 1) or InputError (exit 3) before any write. Messages name ``oci://…@sha256:…``
            and the entry inside the bundle, never the staging folder.
    """
    from ..bundle import MAX_BYTES, is_bundle
    from ..errors import HcdfTrustError, relabel
    from ..outputs import BUNDLE, ORDINARY, OutputPlan
    from ..provenance.bundle import envelope_path
    from ..store import ContentStore
    from .blobs import Stage, fetch_blob

    keys = list(provenance_keys or [])
    if ref.digest is None and not trust_tag and not keys:
        raise InputError(
            f"{ref}: a tag names whatever the registry says today; pull by digest (@sha256:…), "
            "verify the bundle's provenance (--provenance-key), or take the tag as it is (--trust-tag)",
            url=str(ref),
        )
    if require_provenance and not keys:
        raise InputError("--require-provenance needs --provenance-key (a provenance no key checks proves nothing)")
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
    title = layer["annotations"][TITLE]
    # 3. the blob into the content store, only if it is the manifest's, and into a file of our
    # own in a private staging folder, under the name messages give it
    store = ContentStore(cache_dir)
    with Stage(cache_dir) as stage:
        try:
            held, cached, _ = fetch_blob(
                client,
                store,
                layer,
                title=title,
                where=f"{source}#/layers/0",
                stage=stage,
                rel=title if is_bundle(title) else "bundle.hcdfz",
            )
            # 4. the referrers: the provenance (fetched only when a key can check it), the SBOMs
            if require_provenance:
                why: str | None = "--require-provenance"
            elif ref.digest is None and not trust_tag:
                why = "a tag is trusted through its provenance"
            else:
                why = None
            provenance, sboms, notices = _referrers(client, digest, source, keys=keys, required=why)
            # 5. verify X.hcdfz (and its provenance) on the staged file; every message names the
            # reference and the entry (oci://…@sha256:…/scout2.hcdfz/assets/…), never that folder
            check = None
            if provenance is not None:
                check = Provenance(provenance[1], f"{source} ({provenance[0]})", keys, threshold)
            checked = verify_bundle(held.path, provenance=check)
            for notice in checked.warnings:
                relabel(notice, stage.path, source)
            if checked.sha256 != hex_:  # the staged file is not the one hashed
                raise DigestMismatchError(
                    f"{source}: the staged bundle is not the layer's blob",
                    expected=layer["digest"],
                    actual=checked.sha256,
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
            # 6. into --out (and the verified provenance beside it), all or nothing: the staged
            # file moved into place
            plan = OutputPlan()
            plan.protect_tree(cache_dir, what="the cache")
            plan.add(out, held, flag="--out", replaces=(ORDINARY, BUNDLE))
            if provenance is not None:
                plan.add(envelope_path(out), provenance[1], flag="--out", replaces=(ORDINARY,))
            wrote = [str(p) for p in plan.commit()]
        except HcdfTrustError as exc:
            relabel(exc, stage.path, source)
            raise
    return BundlePullReport(
        str(ref),
        digest,
        checked,
        cached,
        wrote,
        provenance[0] if provenance is not None else None,
        sboms,
        [*notices, *checked.warnings],
    )


def _referrers(
    client: RegistryClient, digest: str, source: str, *, keys: list[Any], required: str | None
) -> tuple[tuple[str, bytes] | None, list[dict[str, Any]], list[Notice]]:
    """The referrers of the bundle manifest ``digest`` (``source``: its reference, for
    messages), each checked against its subject (:func:`.referrers.listed`): the provenance
    (its referrer digest and envelope bytes; fetched only when ``keys`` can check it; when
    ``required`` says why, none is an error), the SBOMs as ``--json`` lists them, and a notice
    for a provenance listed that no key was given to check."""
    from ..provenance.dsse import MAX_ENVELOPE_BYTES
    from .referrers import (
        BUNDLE_PROVENANCE_TYPE,
        BUNDLE_SBOM_TYPE,
        CYCLONEDX_TYPE,
        DSSE_TYPE,
        SPDX_TYPE,
        listed,
        one_provenance,
        sbom_list,
    )

    types = {BUNDLE_PROVENANCE_TYPE: frozenset({DSSE_TYPE}), BUNDLE_SBOM_TYPE: frozenset({CYCLONEDX_TYPE, SPDX_TYPE})}
    found = listed(client, digest, types, what="bundle")
    sboms = sbom_list(found, BUNDLE_SBOM_TYPE)
    if not keys:
        unchecked = [r.digest for r in found if r.artifact_type == BUNDLE_PROVENANCE_TYPE]
        notices = []
        if unchecked:
            notices.append(
                Notice(
                    "oci-provenance-unchecked",
                    f"{source}: a provenance referrer is listed ({unchecked[0]}) but no --provenance-key was "
                    "given to check it: not verified, not written",
                )
            )
        return None, sboms, notices
    got = one_provenance(
        client,
        found,
        source,
        artifact_type=BUNDLE_PROVENANCE_TYPE,
        limit=MAX_ENVELOPE_BYTES,
        required=required is not None,
        why=required or "",
    )
    return ((got[0].digest, got[1]) if got is not None else None), sboms, []
