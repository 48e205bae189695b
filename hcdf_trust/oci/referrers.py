"""Referrers of a release or bundle manifest: the SUIT envelope (releases), the provenance and
the SBOMs, each one small OCI 1.1 artifact whose ``subject`` is that manifest.

Pushed as an image manifest with its own ``artifactType``, the empty config and exactly one
layer; listed through the referrers API or, where the registry has none (distribution 2.8),
through the ``sha256-<hex>`` tag index this module keeps up to date (the OCI distribution
spec's referrers tag schema). On pull nothing in the listing is taken on trust: each referrer
manifest is fetched by its digest and hashed, its ``subject`` must be the release just
verified, its one layer must have the expected media type, size bound and (for blobs we
read) SHA-256. What the blob *says* is checked by the caller (the SUIT envelope: the
release's own; the provenance: ``ota verify --provenance``).
"""

from __future__ import annotations

import hashlib
import json
import re
from dataclasses import dataclass
from typing import Any

from ..errors import DigestMismatchError, IntegrityError
from .client import INDEX_TYPE, MANIFEST_TYPE, RegistryClient, fallback_tag, sha256_digest

SIGNATURE_TYPE = "application/vnd.hcdf.release.signature.v1"  # artifactType of the SUIT referrer
PROVENANCE_TYPE = "application/vnd.hcdf.release.provenance.v1"  # artifactType of the provenance referrer
SBOM_TYPE = "application/vnd.hcdf.release.sbom.v1"  # artifactType of an SBOM referrer
BUNDLE_PROVENANCE_TYPE = "application/vnd.hcdf.bundle.provenance.v1"  # a bundle's (bundle --provenance)
BUNDLE_SBOM_TYPE = "application/vnd.hcdf.bundle.sbom.v1"  # an SBOM of a bundle (sbom X.hcdfz)
DSSE_TYPE = "application/vnd.dsse.envelope.v1+json"  # the provenance layer: a DSSE envelope
CYCLONEDX_TYPE = "application/vnd.cyclonedx+json"  # IANA-registered
SPDX_TYPE = "application/spdx+json"  # IANA-registered
PREDICATE_ANNOTATION = "in-toto.io/predicate-type"
MAX_REFERRERS = 16  # per artifact type: more is a registry flooding the listing
EMPTY_TYPE = "application/vnd.oci.empty.v1+json"
EMPTY_DESCRIPTOR = {"mediaType": EMPTY_TYPE, "digest": sha256_digest(b"{}"), "size": 2}
_DIGEST = re.compile(r"sha256:[0-9a-f]{64}")


class ReferrerError(IntegrityError):
    code = "oci-referrer"


@dataclass(frozen=True)
class Referrer:
    """One referrer checked against its subject: its manifest digest, type and one layer."""

    digest: str
    artifact_type: str
    layer: dict[str, Any]


def attach(client: RegistryClient, subject: tuple[str, int], items: list[tuple[str, dict[str, Any]]]) -> list[str]:
    """Push one referrer manifest per ``(artifactType, layer descriptor)`` (the layer's blob
    already pushed) with ``subject`` = ``(digest, size)`` of the release manifest; then, unless
    the registry said it indexed the subject itself (``OCI-Subject``), add them all to the
    ``sha256-<hex>`` tag index in one update. Returns the referrer manifests' digests."""
    digest, size = subject
    pushed: list[dict[str, Any]] = []
    indexed = True
    for artifact_type, layer in items:
        doc = {
            "schemaVersion": 2,
            "mediaType": MANIFEST_TYPE,
            "artifactType": artifact_type,
            "config": EMPTY_DESCRIPTOR,
            "layers": [layer],
            "subject": {"mediaType": MANIFEST_TYPE, "digest": digest, "size": size},
        }
        body = json.dumps(doc, sort_keys=True, separators=(",", ":")).encode()
        headers = client.put_manifest(sha256_digest(body), body, MANIFEST_TYPE)
        indexed = indexed and any(k.lower() == "oci-subject" for k in headers)
        pushed.append(
            {
                "mediaType": MANIFEST_TYPE,
                "digest": sha256_digest(body),
                "size": len(body),
                "artifactType": artifact_type,
            }
        )
    if pushed and not indexed:
        _update_fallback(client, digest, pushed)
    return [str(x["digest"]) for x in pushed]


def _update_fallback(client: RegistryClient, subject: str, descriptors: list[dict[str, Any]]) -> None:
    """Read-modify-write the tag index: what it listed (but these digests), then these."""
    from ..localfile import MAX_JSON_BYTES, parse_json

    tag = fallback_tag(subject)
    got = client.get_manifest(tag, accept=INDEX_TYPE)
    new = {d["digest"] for d in descriptors}
    manifests: list[Any] = []
    if got is not None:
        doc = parse_json(got[0], source=tag, what="referrers tag", limit=MAX_JSON_BYTES)
        if isinstance(doc, dict) and isinstance(doc.get("manifests"), list):
            manifests = [m for m in doc["manifests"] if isinstance(m, dict) and m.get("digest") not in new]
    index = {"schemaVersion": 2, "mediaType": INDEX_TYPE, "manifests": [*manifests, *descriptors]}
    client.put_manifest(tag, json.dumps(index, sort_keys=True, separators=(",", ":")).encode(), INDEX_TYPE)


def push_small_blob(
    client: RegistryClient, data: bytes, media_type: str, annotations: dict[str, str]
) -> dict[str, Any]:
    """Push a blob held in memory (a provenance, an SBOM) and return its layer descriptor."""
    digest = sha256_digest(data)
    client.push_blob(digest, len(data), [data])
    return {"mediaType": media_type, "digest": digest, "size": len(data), "annotations": annotations}


def listed(
    client: RegistryClient, digest: str, layer_types: dict[str, frozenset[str]], *, what: str = "release"
) -> list[Referrer]:
    """The referrers of ``digest`` whose ``artifactType`` is a key of ``layer_types``, each
    fetched by digest and checked: subject, artifact type, exactly one layer of one of the
    allowed media types with a valid digest. Others (another tool's signatures) are ignored.
    ``what``: the subject's kind, for messages (``release``, ``bundle``).

    Raises:
        ReferrerError: a listed referrer that is missing, hashes otherwise, points at another
            manifest, or is not the one-layer artifact its type says (exit 1).
    """
    from ..localfile import MAX_JSON_BYTES, parse_json

    entries, _api = client.referrers(digest)
    counts: dict[str, int] = {}
    found: list[Referrer] = []
    for item in entries:
        kind = item.get("artifactType") if isinstance(item, dict) else None
        if not isinstance(kind, str) or kind not in layer_types:
            continue
        counts[kind] = counts.get(kind, 0) + 1
        if counts[kind] > MAX_REFERRERS:
            raise ReferrerError(f"referrers of {digest}: more than {MAX_REFERRERS} of type {kind} listed")
        rd = item.get("digest")
        if not isinstance(rd, str) or not _DIGEST.fullmatch(rd):
            raise ReferrerError(f"referrers of {digest}: a {kind} descriptor with no valid digest")
        got = client.get_manifest(rd)
        if got is None:
            raise ReferrerError(f"referrer {rd} ({kind}) is listed but the registry does not have it")
        body, actual, _ = got
        if actual != rd:
            raise ReferrerError(f"referrer {rd}: the manifest received hashes otherwise", expected=rd, actual=actual)
        doc = parse_json(body, source=rd, what="referrer manifest", limit=MAX_JSON_BYTES)
        subject = doc.get("subject") if isinstance(doc, dict) else None
        if not isinstance(subject, dict) or subject.get("digest") != digest:
            raise ReferrerError(
                f"referrer {rd} ({kind}) points at another {what}",
                expected=digest,
                actual=str(subject.get("digest") if isinstance(subject, dict) else None)[:100],
            )
        if doc.get("artifactType") != kind:
            raise ReferrerError(
                f"referrer {rd}: its artifactType is not the one listed",
                expected=kind,
                actual=str(doc.get("artifactType"))[:100],
            )
        layers = doc.get("layers")
        layer = layers[0] if isinstance(layers, list) and len(layers) == 1 else None
        if (
            not isinstance(layer, dict)
            or layer.get("mediaType") not in layer_types[kind]
            or not isinstance(layer.get("digest"), str)
            or not _DIGEST.fullmatch(layer["digest"])
            or type(layer.get("size")) is not int
            or layer["size"] < 0
        ):
            raise ReferrerError(f"referrer {rd} ({kind}) is not one layer of {' or '.join(sorted(layer_types[kind]))}")
        found.append(Referrer(rd, kind, layer))
    return found


def fetch_layer(client: RegistryClient, referrer: Referrer, *, limit: int) -> bytes:
    """The referrer's one blob, at most ``limit`` bytes, hashed against its descriptor.

    Raises:
        ReferrerError: larger than ``limit``. DigestMismatchError: not its digest (exit 1).
    """
    layer = referrer.layer
    if layer["size"] > limit:
        raise ReferrerError(
            f"referrer {referrer.digest}: its layer is larger than {limit} bytes",
            expected=f"<= {limit}",
            actual=str(layer["size"]),
        )
    h = hashlib.sha256()
    parts: list[bytes] = []
    with client.blob(layer["digest"], layer["size"]) as chunks:
        for chunk in chunks:
            h.update(chunk)
            parts.append(chunk)
    data = b"".join(parts)
    if "sha256:" + h.hexdigest() != layer["digest"] or len(data) != layer["size"]:
        raise DigestMismatchError(
            f"referrer {referrer.digest} ({referrer.artifact_type}): its blob is not its digest",
            expected=layer["digest"],
            actual="sha256:" + h.hexdigest(),
        )
    return data


def one_provenance(
    client: RegistryClient,
    found: list[Referrer],
    shown: str,
    *,
    artifact_type: str,
    limit: int,
    required: bool,
    why: str = "--require-provenance",
) -> tuple[Referrer, bytes] | None:
    """The provenance referrer among ``found`` (:func:`listed`, the referrers of ``shown``) and its blob
    (fetched, at most ``limit`` bytes, hashed against its descriptor); None when there is none
    and none is ``required``. What it says is the caller's to verify.

    Raises:
        ReferrerError: two with different envelopes (which one is meant?), or none when
            ``required`` (``why`` says who asked). DigestMismatchError: see :func:`fetch_layer`.
    """
    provenances = [r for r in found if r.artifact_type == artifact_type]
    if len({r.layer["digest"] for r in provenances}) > 1:
        raise ReferrerError(
            f"{shown}: {len(provenances)} provenance referrers with different envelopes: which one is meant?",
            expected="one provenance",
            actual=", ".join(r.digest for r in provenances),
        )
    if not provenances:
        if required:
            raise ReferrerError(
                f"{shown}: no provenance referrer is listed ({why})",
                expected=f"a referrer of type {artifact_type}",
                actual="none",
            )
        return None
    return provenances[0], fetch_layer(client, provenances[0], limit=limit)


def sbom_list(found: list[Referrer], artifact_type: str) -> list[dict[str, Any]]:
    """The SBOM referrers among ``found``, as ``--json`` lists them (checked, not fetched)."""
    return [
        {"digest": r.digest, "mediaType": r.layer["mediaType"], "blob": r.layer["digest"], "size": r.layer["size"]}
        for r in found
        if r.artifact_type == artifact_type
    ]
