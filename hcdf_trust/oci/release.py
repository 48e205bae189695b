"""``ota push`` / ``ota pull``: one release folder as one OCI 1.1 artifact, verified on every pull.

The artifact (docs/oci.md): an image manifest with ``artifactType``
:data:`RELEASE_TYPE`, the empty config, one layer per release file (its media type below and
its path in the release folder as ``org.opencontainers.image.title``), annotations naming each
image's board, app, version and MCUboot hash, and the lock and root digests on the manifest.
The signed SUIT envelope, the provenance (when the folder has one) and each SBOM given are
attached as referrers (``subject`` = the release manifest, :mod:`.referrers`), listed through
the referrers API or, where the registry has none, the ``sha256-<hex>`` tag.

``pull`` trusts nothing the registry says; in order:

1. The manifest's digest is the hash of the body received (a ``@sha256:`` reference must match).
2. The manifest is ours and well-formed: artifact type, empty config, every layer a known media
   type, a size within bounds, a title that is a plain relative path (no ``..``, no absolute
   path, no duplicate, not even by case).
3. Each blob comes from the content store (a blob verified before: a resumed pull) or is
   fetched by digest, hashed while streaming and refused past its declared size; only a blob
   whose SHA-256 and size are the manifest's enters the store. The same bytes go into a file
   of a private staging folder (:mod:`.blobs`), where the release is laid out as in ``--out``;
   a blob refused leaves nothing there either.
4. ``ota verify`` runs on the staging folder with the public key (signature, every image,
   latest.json, ``--previous``): a title the signed manifest does not account for is refused;
   the layer annotations must say what the signed manifest says. imgtool checks each MCUboot
   image as soon as it is staged, while the other blobs still arrive.
5. The referrers must point at this release: the SUIT ones hold this release's envelope, a
   provenance is fetched, hashed and verified as ``ota verify --provenance`` does (required
   with ``require_provenance``), SBOMs are listed.
6. Only then is the release written into ``--out`` through one OutputPlan (all or nothing):
   the staged files, written from the bytes hashed and held open since, are moved into place
   (:class:`~hcdf_trust.outputs.HeldFile`), not copied.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

from ..digest import hash_fd
from ..errors import DigestMismatchError, HcdfTrustError, InputError, IntegrityError, Notice
from ..localfile import open_checked, read_chunks
from ..outputs import HeldFile
from .blobs import SEGMENT
from .client import MANIFEST_TYPE, RegistryClient, sha256_digest
from .reference import Reference
from .referrers import EMPTY_DESCRIPTOR, ReferrerError

RELEASE_TYPE = "application/vnd.hcdf.release.v1"
MCUBOOT_TYPE = "application/vnd.hcdf.mcuboot.image.v1"
RAW_TYPE = "application/vnd.hcdf.raw.image.v1"
LATEST_TYPE = "application/vnd.hcdf.dendrite.latest.v1+json"
SUIT_TYPE = "application/suit-envelope+cose"
RENDERING_TYPE = "application/vnd.hcdf.release.suit.v1+json"
HISTORY_TYPE = "application/vnd.hcdf.release.history.v1+cbor"  # the earlier signed envelopes
LAYER_TYPES = frozenset({MCUBOOT_TYPE, RAW_TYPE, LATEST_TYPE, SUIT_TYPE, RENDERING_TYPE, HISTORY_TYPE})
EMPTY = b"{}"
TITLE = "org.opencontainers.image.title"
A = "dev.hcdf."  # our annotation prefix
MAX_LAYERS = 1024
FETCH_THREADS = 4
MAX_TOTAL_BYTES = 8 << 30
MAX_LAYER_BYTES = 256 << 20  # one release file (a bundle layer has the bundle's own cap)
_DIGEST = re.compile(r"sha256:[0-9a-f]{64}")


class ArtifactError(InputError):
    """The registry's manifest is not a release artifact we can read (exit 3)."""

    code = "oci-artifact"


@dataclass
class PullReport:
    reference: str
    digest: str
    release: Any
    files: list[dict[str, Any]]
    from_cache: int
    referrers: list[str]
    notices: list[Notice] = field(default_factory=list)
    wrote: list[str] = field(default_factory=list)
    provenance: str | None = None  # the provenance referrer verified and written, if any
    sboms: list[dict[str, Any]] = field(default_factory=list)  # SBOM referrers listed (checked, not fetched)


# -- push ------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Layer:
    rel: str
    media_type: str
    sha256: str
    size: int
    annotations: dict[str, str]

    def descriptor(self) -> dict[str, Any]:
        return {
            "mediaType": self.media_type,
            "digest": f"sha256:{self.sha256}",
            "size": self.size,
            "annotations": {TITLE: self.rel, **self.annotations},
        }


def release_layers(folder: str, release: Any) -> list[_Layer]:
    """The files ``ota verify`` reads in ``folder``, with their media types and annotations."""
    from ..ota.read import HISTORY_NAME, MANIFEST_JSON_NAME, MANIFEST_NAME
    from ..ota.verify import image_path

    wanted: list[tuple[str, str, dict[str, str]]] = [(MANIFEST_NAME, SUIT_TYPE, {})]
    if os.path.lexists(os.path.join(folder, MANIFEST_JSON_NAME)):
        wanted.append((MANIFEST_JSON_NAME, RENDERING_TYPE, {}))
    if os.path.lexists(os.path.join(folder, HISTORY_NAME)):  # what vouches for latest.json's previous[]
        wanted.append((HISTORY_NAME, HISTORY_TYPE, {}))
    for c in release.components:
        about = {A + "board": c.board, A + "app": c.app, A + "version": c.version}
        if c.mcuboot_hash:
            about[A + "mcuboot-hash"] = c.mcuboot_hash
        wanted.append((image_path(c), MCUBOOT_TYPE if c.type == "mcuboot" else RAW_TYPE, about))
        latest = f"{c.board}/{c.app}/latest.json"
        if c.type == "mcuboot" and os.path.lexists(os.path.join(folder, latest)):
            wanted.append((latest, LATEST_TYPE, {A + "board": c.board, A + "app": c.app}))
    layers = []
    for rel, media_type, about in wanted:
        fd, st = open_checked(os.path.join(folder, rel), folder, file=rel)
        try:
            hashed = hash_fd(fd, size=st.st_size)
        finally:
            os.close(fd)
        layers.append(_Layer(rel, media_type, hashed.sha256, hashed.size, about))
    return layers


def manifest_for(release: Any, layers: list[_Layer]) -> bytes:
    """The release's OCI image manifest, deterministic (sorted keys, no spaces)."""
    doc = {
        "schemaVersion": 2,
        "mediaType": MANIFEST_TYPE,
        "artifactType": RELEASE_TYPE,
        "config": EMPTY_DESCRIPTOR,
        "layers": [layer.descriptor() for layer in layers],
        "annotations": {
            A + "sequence-number": str(release.sequence_number),
            A + "lock-sha256": release.lock_sha256,
            A + "root": release.root,
            A + "root-sha256": release.root_sha256,
        },
    }
    return json.dumps(doc, sort_keys=True, separators=(",", ":")).encode()


def push_release(
    folder: str, ref: Reference, client: RegistryClient, release: Any, *, sboms: list[Sbom] | None = None
) -> dict[str, Any]:
    """Upload every blob (streamed), the manifest under the tag, and its referrers: the SUIT
    envelope, the provenance when the folder has one, and each SBOM given."""
    from .referrers import (
        DSSE_TYPE,
        PREDICATE_ANNOTATION,
        PROVENANCE_TYPE,
        SBOM_TYPE,
        SIGNATURE_TYPE,
        attach,
        push_small_blob,
    )

    layers = release_layers(folder, release)
    push_blobs(client, folder, layers)
    body = manifest_for(release, layers)
    digest = sha256_digest(body)
    client.put_manifest(ref.tag or digest, body, MANIFEST_TYPE)
    envelope = next(layer for layer in layers if layer.media_type == SUIT_TYPE)
    items: list[tuple[str, dict[str, Any]]] = [(SIGNATURE_TYPE, envelope.descriptor())]
    provenance = read_provenance(folder)
    if provenance is not None:
        from ..provenance import FILE_NAME, PREDICATE_TYPE

        about = {TITLE: FILE_NAME, PREDICATE_ANNOTATION: PREDICATE_TYPE}
        items.append((PROVENANCE_TYPE, push_small_blob(client, provenance, DSSE_TYPE, about)))
    for sbom in sboms or []:
        items.append((SBOM_TYPE, push_small_blob(client, sbom.data, sbom.media_type, {TITLE: sbom.title})))
    referrers = attach(client, (digest, len(body)), items)
    return {
        "digest": digest,
        "layers": [x.descriptor() for x in layers],
        "referrers": [{"digest": d, "artifactType": t} for d, (t, _) in zip(referrers, items, strict=True)],
    }


def read_provenance(folder: str) -> bytes | None:
    """The folder's ``provenance.intoto.json`` (ota build --provenance), bounded; None without one."""
    from ..localfile import read_bounded
    from ..provenance import FILE_NAME
    from ..provenance.dsse import MAX_ENVELOPE_BYTES

    if not os.path.lexists(os.path.join(folder, FILE_NAME)):
        return None
    fd, _ = open_checked(os.path.join(folder, FILE_NAME), folder, file=FILE_NAME)
    try:
        return read_bounded(fd, MAX_ENVELOPE_BYTES, source=FILE_NAME, what="provenance")
    finally:
        os.close(fd)


MAX_SBOM_BYTES = 64 << 20


@dataclass(frozen=True)
class Sbom:
    """An SBOM file for ``ota push --sbom``: its bytes, its IANA media type, its file name."""

    data: bytes
    media_type: str
    title: str


def read_sbom(path: str) -> Sbom:
    """A CycloneDX or SPDX 3 JSON SBOM (``hcdf-trust sbom``), told apart by its content.

    Raises:
        InputError: unreadable, not strict JSON, or neither CycloneDX nor SPDX (exit 3).
    """
    from ..localfile import parse_json, read_input
    from .referrers import CYCLONEDX_TYPE, SPDX_TYPE

    data = read_input(path, limit=MAX_SBOM_BYTES, what="SBOM")
    doc = parse_json(data, source=path, what="SBOM", limit=MAX_SBOM_BYTES)
    context = doc.get("@context") if isinstance(doc, dict) else None
    if isinstance(doc, dict) and doc.get("bomFormat") == "CycloneDX":
        media_type = CYCLONEDX_TYPE
    elif isinstance(context, str) and context.startswith("https://spdx.org/rdf/3."):
        media_type = SPDX_TYPE
    else:
        raise InputError(
            f"{path}: not a CycloneDX (bomFormat) or SPDX 3 (@context) JSON SBOM",
            file=path,
            expected='"bomFormat": "CycloneDX" or an spdx.org/rdf/3 @context',
        )
    name = os.path.basename(path)
    if not SEGMENT.fullmatch(name):
        name = "sbom.cdx.json" if media_type == CYCLONEDX_TYPE else "sbom.spdx.json"
    return Sbom(data, media_type, name)


def push_blobs(client: RegistryClient, folder: str, layers: list[_Layer]) -> None:
    """The empty config and every layer's file, streamed from ``folder``."""
    client.check()
    client.push_blob(str(EMPTY_DESCRIPTOR["digest"]), 2, [EMPTY])  # the config of every manifest here
    for layer in layers:
        fd, _ = open_checked(os.path.join(folder, layer.rel), folder, file=layer.rel)
        try:
            client.push_blob(f"sha256:{layer.sha256}", layer.size, _checked(read_chunks(fd), layer))
        finally:
            os.close(fd)


def _checked(chunks: Iterator[bytes], layer: _Layer) -> Iterator[bytes]:
    """The file's bytes as uploaded, refused when they are not what was hashed a moment ago."""
    import hashlib

    h = hashlib.sha256()
    size = 0
    for chunk in chunks:
        h.update(chunk)
        size += len(chunk)
        yield chunk
    if h.hexdigest() != layer.sha256 or size != layer.size:
        raise InputError(f"{layer.rel} changed while it was being pushed", file=layer.rel)


# -- pull ------------------------------------------------------------------------------


def check_manifest(
    body: bytes,
    *,
    source: str,
    artifact_type: str = RELEASE_TYPE,
    layer_types: frozenset[str] = LAYER_TYPES,
    max_segments: int = 3,
    what: str = "an hcdf-trust release",
    max_layer_bytes: int = MAX_LAYER_BYTES,
) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """Step 2: the manifest document and its layers, each checked. Pure.

    Raises:
        ArtifactError: not an artifact of ``artifact_type``, or a layer we would not write.
    """
    from ..localfile import MAX_JSON_BYTES, parse_json

    doc = parse_json(body, source=source, what="OCI manifest", limit=MAX_JSON_BYTES)
    if not isinstance(doc, dict) or doc.get("schemaVersion") != 2 or doc.get("mediaType") != MANIFEST_TYPE:
        raise ArtifactError("not an OCI image manifest (schemaVersion 2, mediaType)", file=source)
    if doc.get("artifactType") != artifact_type:
        raise ArtifactError(
            f"not {what}", file=source, expected=artifact_type, actual=str(doc.get("artifactType"))[:100]
        )
    if doc.get("config") != EMPTY_DESCRIPTOR:
        raise ArtifactError("the config is not the OCI empty descriptor", file=source)
    layers = doc.get("layers")
    if not isinstance(layers, list) or not layers or len(layers) > MAX_LAYERS:
        raise ArtifactError(f"layers: a list of 1 to {MAX_LAYERS} descriptors is expected", file=source)
    seen: dict[str, str] = {}
    total = 0
    for i, layer in enumerate(layers):
        where = f"/layers/{i}"
        if not isinstance(layer, dict):
            raise ArtifactError(f"{where}: not a descriptor", file=source)
        if not isinstance(layer.get("mediaType"), str) or layer["mediaType"] not in layer_types:
            raise ArtifactError(f"{where}: unknown media type {str(layer.get('mediaType'))[:100]!r}", file=source)
        if not isinstance(layer.get("digest"), str) or not _DIGEST.fullmatch(layer["digest"]):
            raise ArtifactError(f"{where}: digest is not sha256: and 64 lower-case hex digits", file=source)
        size = layer.get("size")
        if type(size) is not int or size < 0 or size > max_layer_bytes:
            raise ArtifactError(f"{where}: size is not an integer from 0 to {max_layer_bytes} bytes", file=source)
        total += size
        annotations = layer.get("annotations")
        title = annotations.get(TITLE) if isinstance(annotations, dict) else None
        if not isinstance(title, str):
            raise ArtifactError(f"{where}: no {TITLE} annotation", file=source)
        parts = title.split("/")
        if len(parts) > max_segments or not all(SEGMENT.fullmatch(p) and p not in (".", "..") for p in parts):
            raise ArtifactError(
                f"{where}: title {title[:200]!r} is not a plain relative path "
                f"(1-{max_segments} segments of A-Z a-z 0-9 . _ + -)",
                file=source,
            )
        if title.lower() in seen:
            raise ArtifactError(f"{where}: title {title!r} is also the title of {seen[title.lower()]}", file=source)
        seen[title.lower()] = where
    for title, where in seen.items():  # "a" and "a/b": a file where a folder must be
        parts = title.split("/")
        for n in range(1, len(parts)):
            prefix = "/".join(parts[:n])
            if prefix in seen:
                raise ArtifactError(f"{where}: title {title!r} lies below the file of {seen[prefix]}", file=source)
    if total > MAX_TOTAL_BYTES:
        raise ArtifactError(f"the layers add up to more than {MAX_TOTAL_BYTES} bytes", file=source)
    return doc, layers


def pull_release(
    ref: Reference,
    client: RegistryClient,
    *,
    public_key: Any,
    out_dir: str,
    cache_dir: str,
    key_path: str,
    previous: Any = None,
    provenance_keys: tuple[Any, ...] = (),
    threshold: int = 1,
    require_provenance: bool = False,
) -> PullReport:
    """Steps 1–6 above. ``provenance_keys``: who else may sign the provenance (``--key``
    always may), ``threshold`` signatures needed; ``require_provenance``: none is an error.
    Raises IntegrityError (exit 1) or InputError (exit 3) before any write."""
    from ..errors import relabel
    from ..outputs import FileContent, OutputPlan
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
    # 2. ours, and well-formed
    doc, layers = check_manifest(body, source=source)
    store = ContentStore(cache_dir)
    # 3. every blob into the content store and into a file of our own in a private staging
    # folder (the release laid out as in --out), hashed as it streams; a few blobs at a time
    # (each request waits on the registry, not on us). An image's bytes are hashed once, by an
    # ImageStream, which takes MCUboot's image hash from the same pass; the verify stack is
    # imported meanwhile.
    stage = Stage(cache_dir)
    staged = os.path.join(stage.path, "release")
    try:
        from ..ota.mcuboot import ImageStream

        pool = ThreadPoolExecutor(max_workers=FETCH_THREADS)
        jobs = []
        try:
            jobs = [
                pool.submit(
                    fetch_blob,
                    client,
                    store,
                    x,
                    title=t,
                    where=f"{source}#/layers/{i}",
                    stage=stage,
                    rel=f"release/{t}",
                    sha256=ImageStream if x["mediaType"] in (MCUBOOT_TYPE, RAW_TYPE) else hashlib.sha256,
                )
                for i, x in enumerate(layers)
                for t in [x["annotations"][TITLE]]
            ]
            # while they arrive: the verify stack loads (COSE, CBOR)
            from ..ota import read, verify  # noqa: F401

            held: dict[str, HeldFile] = {}
            images: dict[str, ImageStream] = {}
            cached = 0
            for x, job in zip(layers, jobs, strict=True):  # in order, each as soon as it is in
                title = x["annotations"][TITLE]
                held[title], hit, hashed = job.result()
                cached += hit
                if isinstance(hashed, ImageStream):
                    images[title] = hashed
        except BaseException:
            for job in jobs:
                job.cancel()
            raise
        finally:
            pool.shutdown(wait=True)
        # 4. ota verify of the staged release, with the public key
        release, errors = _verify_staged(staged, public_key, previous, set(held), layers, images)
        if errors:
            raise _group(errors)
        # 5. the referrers: SUIT envelopes, the provenance (verified here), SBOMs
        envelope = next(x for x in layers if x["mediaType"] == SUIT_TYPE)
        checked = check_referrers(
            client,
            digest,
            envelope["digest"],
            staged=staged,
            release=release,
            keys=(public_key, *provenance_keys),
            threshold=threshold,
            require_provenance=require_provenance,
        )
        # 6. into --out, all or nothing: each staged file moved into place (never all in
        # memory, never copied), the provenance copied and hashed against its digest
        plan = OutputPlan()
        plan.protect(key_path, what="the public key")
        plan.protect_tree(cache_dir, what="the cache")
        outputs: dict[str, HeldFile | FileContent] = dict(held)
        if checked.provenance is not None:
            blob, size = checked.provenance_blob
            outputs[PROVENANCE_NAME] = FileContent(os.path.join(staged, PROVENANCE_NAME), size, blob.split(":", 1)[1])
        for title, data in sorted(outputs.items()):
            plan.add(os.path.join(out_dir, *title.split("/")), data, flag="--out", under=out_dir)
        wrote = [str(p) for p in plan.commit()]
    except HcdfTrustError as exc:  # named as the user named it: oci://…@sha256:…/FILE, never the stage
        relabel(exc, staged, source)
        raise
    finally:
        stage.close()
    files = [
        {"title": x["annotations"][TITLE], "mediaType": x["mediaType"], "digest": x["digest"], "size": x["size"]}
        for x in layers
    ]
    return PullReport(
        str(ref),
        digest,
        release,
        files,
        cached,
        checked.signatures,
        checked.notices,
        wrote,
        checked.provenance,
        checked.sboms,
    )


PROVENANCE_NAME = "provenance.intoto.json"  # == provenance.FILE_NAME (not imported: that package loads lazily)


def _verify_staged(
    stage: str,
    public_key: Any,
    previous: Any,
    titles: set[str],
    layers: list[dict[str, Any]],
    images: dict[str, Any],
) -> tuple[Any, list[HcdfTrustError]]:
    import dataclasses

    from ..ota.read import HISTORY_NAME, MANIFEST_JSON_NAME, MANIFEST_NAME, read_release
    from ..ota.verify import check_release, image_path

    release, files = read_release(stage, public_key)
    # each image was hashed as it was written into the staged file that lands in --out (the same
    # file, held open since it was created), by the ImageStream that also has its image hash
    files = dataclasses.replace(files, scanned=images)
    errors = check_release(release, files, public_key, previous=previous)
    accounted = {MANIFEST_NAME, *files.latest}
    if files.rendering is not None:
        accounted.add(MANIFEST_JSON_NAME)
    if files.history:
        accounted.add(HISTORY_NAME)
    by_title: dict[str, Any] = {}
    for c in release.components:
        accounted.add(image_path(c))
        by_title[image_path(c)] = c
    for title in sorted(titles - accounted):
        errors.append(
            IntegrityError(f"layer {title!r} is not a file of the signed release (refused: unverified)", file=title)
        )
    for layer in layers:
        title = layer["annotations"][TITLE]
        comp = by_title.get(title)
        if comp is None:
            continue
        want = {A + "board": comp.board, A + "app": comp.app, A + "version": comp.version}
        if comp.mcuboot_hash:
            want[A + "mcuboot-hash"] = comp.mcuboot_hash
        want_type = MCUBOOT_TYPE if comp.type == "mcuboot" else RAW_TYPE
        for key, value in [("mediaType", want_type)]:
            if layer.get(key) != value:
                errors.append(
                    IntegrityError(
                        f"{title}: layer {key} differs from the signed manifest",
                        file=title,
                        expected=value,
                        actual=str(layer.get(key)),
                    )
                )
        for key, value in want.items():
            got = layer["annotations"].get(key)
            if got != value:
                errors.append(
                    IntegrityError(
                        f"{title}: layer annotation {key} differs from the signed manifest",
                        file=title,
                        expected=value,
                        actual=str(got),
                    )
                )
    return release, errors


@dataclass
class CheckedReferrers:
    signatures: list[str]  # the SUIT envelope referrers, each carrying this release's envelope
    provenance: str | None  # the provenance referrer, verified and staged as provenance.intoto.json
    sboms: list[dict[str, Any]]
    notices: list[Notice]
    provenance_blob: tuple[str, int] = ("", 0)  # its layer's digest and size


def check_referrers(
    client: RegistryClient,
    digest: str,
    envelope_digest: str,
    *,
    staged: str,
    release: Any,
    keys: tuple[Any, ...],
    threshold: int = 1,
    require_provenance: bool = False,
) -> CheckedReferrers:
    """Step 5, over one listing of the referrers of ``digest``: every SUIT referrer carries
    this release's envelope; the provenance (at most one envelope) is fetched, hashed, staged
    beside the release in ``staged`` and checked as ``ota verify --provenance`` checks it;
    an SBOM referrer is checked for its subject and type only. A missing SUIT referrer is a
    notice (the release itself verified); a missing provenance is an error when required
    (else the report's ``provenance`` is None).

    Raises:
        ReferrerError / DigestMismatchError / ProvenanceError: see :mod:`.referrers` (exit 1).
    """
    from .referrers import (
        CYCLONEDX_TYPE,
        DSSE_TYPE,
        PROVENANCE_TYPE,
        SBOM_TYPE,
        SIGNATURE_TYPE,
        SPDX_TYPE,
        listed,
        one_provenance,
        sbom_list,
    )

    types = {
        SIGNATURE_TYPE: frozenset({SUIT_TYPE}),
        PROVENANCE_TYPE: frozenset({DSSE_TYPE}),
        SBOM_TYPE: frozenset({CYCLONEDX_TYPE, SPDX_TYPE}),
    }
    found = listed(client, digest, types)
    notices: list[Notice] = []
    signatures = [r.digest for r in found if r.artifact_type == SIGNATURE_TYPE]
    for r in found:
        if r.artifact_type == SIGNATURE_TYPE and r.layer["digest"] != envelope_digest:
            raise ReferrerError(
                f"referrer {r.digest} does not carry this release's SUIT envelope",
                expected=envelope_digest,
                actual=str(r.layer["digest"]),
            )
    if not signatures:
        notices.append(
            Notice("oci-no-referrer", f"{digest}: no SUIT envelope referrer is listed (the release itself verified)")
        )
    provenance = None
    blob = ("", 0)
    from ..provenance.dsse import MAX_ENVELOPE_BYTES

    got = one_provenance(
        client, found, digest, artifact_type=PROVENANCE_TYPE, limit=MAX_ENVELOPE_BYTES, required=require_provenance
    )
    if got is not None:
        from ..provenance.verify import verify_provenance  # (imported only for a release that has one)

        chosen, data = got
        with open(os.path.join(staged, PROVENANCE_NAME), "xb") as f:  # our private staging folder
            f.write(data)
        errors = verify_provenance(staged, release, list(keys), threshold=threshold)
        if errors:
            raise _group(errors)
        provenance = chosen.digest
        blob = (chosen.layer["digest"], chosen.layer["size"])
    return CheckedReferrers(signatures, provenance, sbom_list(found, SBOM_TYPE), notices, blob)


def _group(errors: list[HcdfTrustError]) -> HcdfTrustError:
    from ..errors import ErrorGroup

    return ErrorGroup(errors)
