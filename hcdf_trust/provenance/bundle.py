"""Provenance of a ``.hcdfz`` (``bundle --provenance``, ``verify X.hcdfz --provenance``).

The envelope is ``X.hcdfz.intoto.json`` beside the bundle: the same DSSE envelope and in-toto
Statement v1 / SLSA Provenance v1 as a release's, with its own build type
(:data:`BUNDLE_BUILD_TYPE`):

- ``subject``: the bundle alone, by file name and SHA-256.
- ``externalParameters``: ``root`` (the root document's name) and ``bundle`` (the bundle's).
- ``resolvedDependencies``: the root document (``hcdf-root``), the lock (``hcdf-lock``, when
  the tree has one), then every file the lock lists, by its lock URL and SHA-256: each
  include as ``hcdf-include:<url>`` (flattened into the bundle's root, so not an entry of
  it), every other file as ``<url>`` (an ``assets/`` entry of the bundle).

Verifying checks the envelope as ``ota verify --provenance`` does (steps 1–4 of
:mod:`.verify`), then that the subject is this bundle's SHA-256 and that the non-include
dependencies are exactly the bundle's assets (by SHA-256, both ways). The root entry is the
flattened document, covered by the subject's digest; the source root, includes and lock
cannot be read back out of a bundle, so their digests are stated, not re-checked.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Sequence
from typing import Any

from ..errors import HcdfTrustError
from .errors import MalformedProvenanceError, ProvenanceError
from .statement import LOCK_DEPENDENCY, ROOT_DEPENDENCY, Dependency

BUNDLE_BUILD_TYPE = "https://hcdf.cognipilot.org/hcdf-trust/buildtypes/bundle/v1"
SUFFIX = ".intoto.json"  # the envelope of X.hcdfz is X.hcdfz.intoto.json
INCLUDE_DEPENDENCY = "hcdf-include:"  # + the lock URL of an include
BUNDLE_PARAMETERS = frozenset({"root", "bundle"})


def envelope_path(bundle: str) -> str:
    """Where the provenance of ``bundle`` is written and looked for: beside it."""
    return bundle + SUFFIX


def bundle_provenance(
    res: Any, *, bundle: str, data: bytes, date: str, signers: Sequence[Any], builder_id: str | None = None
) -> bytes:
    """The envelope over the bundle ``data`` (to be written as ``bundle``) built from the
    resolution ``res`` (clean, under its lock when it has one).

    Raises:
        InputError: the lock file cannot be read. KeyFileError: a signer that cannot sign.
    """
    from ..include.lockfile import MAX_LOCK_BYTES
    from .build import sign_provenance

    root = os.path.basename(res.root.source)
    deps = [Dependency(ROOT_DEPENDENCY, hashlib.sha256(res.root.data).hexdigest(), root)]
    if res.bundle is None and os.path.lexists(res.lock_path):
        deps.append(Dependency(LOCK_DEPENDENCY, res.pins_sha256(limit=MAX_LOCK_BYTES), res.lock_path.name))
    for e in sorted(res.lock_entries(), key=lambda e: (e.url, e.sha256)):
        name = INCLUDE_DEPENDENCY + e.url if e.kind == "include" else e.url
        deps.append(Dependency(name, e.sha256, e.uri))
    name = os.path.basename(bundle)
    return sign_provenance(
        {name: hashlib.sha256(data).hexdigest()},
        deps,
        parameters={"root": root, "bundle": name},
        date=date,
        signers=signers,
        build_type=BUNDLE_BUILD_TYPE,
        builder_id=builder_id,
    )


def verify_bundle_provenance(
    archive: Any, data: bytes, public_keys: list[Any], *, threshold: int, source: str
) -> list[HcdfTrustError]:
    """Every violation once the envelope ``data`` (read from ``source``) verified; the
    archive is the bundle, already checked (:func:`hcdf_trust.bundle.read_archive`).

    Raises:
        MalformedProvenanceError, ProvenanceError: the envelope, its signatures or its statement.
    """
    from ..bundle import ASSETS
    from .verify import check_build_type, open_statement

    subjects, build, where = open_statement(data, public_keys, threshold, source=source)
    bwhere = where + "/predicate/buildDefinition"
    errors = check_build_type(
        build, bwhere, build_type=BUNDLE_BUILD_TYPE, parameters=BUNDLE_PARAMETERS, whose="a bundle's"
    )
    # the subject: this bundle, and nothing else
    if len(subjects) != 1 or archive.sha256 not in subjects.values():
        errors.append(
            ProvenanceError(
                "the subject is not this bundle (edited after signing, or another bundle's provenance?)",
                file=where + "/subject",
                expected=f"one subject, sha256 {archive.sha256}",
                actual=", ".join(f"{n} {s}" for n, s in sorted(subjects.items())),
            )
        )
    # the dependencies: one root document, and the bundle's assets, both ways
    dwhere = bwhere + "/resolvedDependencies"
    deps = build.get("resolvedDependencies")
    if not isinstance(deps, list) or not all(isinstance(d, dict) for d in deps):
        raise MalformedProvenanceError("resolvedDependencies is not a list of objects", file=dwhere)
    roots = [d for d in deps if d.get("name") == ROOT_DEPENDENCY]
    if len(roots) != 1:
        errors.append(
            ProvenanceError(
                f"resolvedDependencies names {len(roots)} {ROOT_DEPENDENCY!r}",
                file=dwhere,
                expected="1",
                actual=str(len(roots)),
            )
        )
    stated: dict[str, int] = {}
    for i, d in enumerate(deps):
        name = d.get("name")
        if not isinstance(name, str) or name in (ROOT_DEPENDENCY, LOCK_DEPENDENCY):
            continue
        if name.startswith(INCLUDE_DEPENDENCY):
            continue
        digest = d.get("digest")
        sha = digest.get("sha256") if isinstance(digest, dict) else None
        if not isinstance(sha, str):
            raise MalformedProvenanceError("a dependency without digest.sha256", file=f"{dwhere}/{i}")
        stated.setdefault(sha, i)
    assets = {
        hashlib.sha256(archive.data(e)).hexdigest(): e.name
        for e in archive.entries[1:]
        if e.name.startswith(ASSETS + "/")
    }
    for sha, entry in sorted(assets.items(), key=lambda kv: kv[1]):
        if sha not in stated:
            errors.append(
                ProvenanceError(
                    f"{entry} is in the bundle but not a dependency of its provenance",
                    file=f"{archive.path}/{entry}",
                    expected="a resolvedDependencies entry with its sha256",
                    actual=sha,
                )
            )
    for sha, i in sorted(stated.items(), key=lambda kv: kv[1]):
        if sha not in assets:
            errors.append(
                ProvenanceError(
                    "a dependency that is not an asset of the bundle",
                    file=f"{dwhere}/{i}",
                    expected=f"an entry of {archive.path}",
                    actual=sha,
                )
            )
    return errors
