"""``ota verify --provenance``: a release folder's ``provenance.intoto.json``, step by step
(as sigstore's ``verify_artifact``: each step trusts only what the steps before it checked).

1. The file is there, one strict JSON DSSE envelope (else exit 3).
2. ``payloadType`` is exactly ``application/vnd.in-toto+json``.
3. At least ``threshold`` of the given keys signed the PAE of the exact payload bytes.
4. Those bytes, never re-serialized, are one strict JSON in-toto Statement whose
   ``_type`` and ``predicateType`` are exactly Statement v1 and SLSA Provenance v1.
5. ``buildType`` is ours; ``externalParameters`` holds only the fields we define, and its
   root and images are the signed manifest's (SLSA: refuse unexpected parameters).
6. ``resolvedDependencies`` names exactly one root document and one lock, with the
   digests the SUIT manifest binds (a statement of another robot is refused).
7. Every subject is a file of the folder with that SHA-256, and every file of the folder
   is a subject (a file added after signing, or an older release's statement, is refused).
"""

from __future__ import annotations

import os
from typing import Any

from ..errors import HcdfTrustError
from ..localfile import open_checked, read_bounded
from . import BUILD_TYPE, FILE_NAME, PAYLOAD_TYPE, PREDICATE_TYPE, STATEMENT_TYPE, dsse
from .errors import MalformedProvenanceError, ProvenanceError
from .files import release_files
from .statement import EXTERNAL_PARAMETERS, LOCK_DEPENDENCY, ROOT_DEPENDENCY


def verify_provenance(folder: str, release: Any, public_keys: list[Any], *, threshold: int = 1) -> list[HcdfTrustError]:
    """Every violation of steps 5–7 (steps 1–4 raise: nothing after them can be trusted).

    ``release`` is the SUIT manifest, already verified. Raises:
        MalformedProvenanceError: steps 1 and 4's parsing. ProvenanceError: steps 1–4.
    """
    # 1. the envelope
    path = os.path.join(folder, FILE_NAME)
    if not os.path.lexists(path):
        raise ProvenanceError("the release has no provenance", file=FILE_NAME, expected=FILE_NAME, actual="none")
    fd, _ = open_checked(path, folder, file=FILE_NAME)
    try:
        data = read_bounded(fd, dsse.MAX_ENVELOPE_BYTES, source=FILE_NAME, what="provenance")
    finally:
        os.close(fd)
    env = dsse.parse(data, source=FILE_NAME)
    # 2. payloadType
    if env.payload_type != PAYLOAD_TYPE:
        raise ProvenanceError(
            "payloadType is not an in-toto statement's",
            file=FILE_NAME + "#/payloadType",
            expected=PAYLOAD_TYPE,
            actual=env.payload_type,
        )
    # 3. signatures over the PAE
    dsse.verify(env, [dsse.sslib_key(k) for k in public_keys], threshold, source=FILE_NAME)
    # 4. the statement, from the bytes that were verified
    where = FILE_NAME + "#/payload"
    stmt = dsse.strict_json(env.payload, source=where, what="statement")
    if not isinstance(stmt, dict):
        raise MalformedProvenanceError("the statement is not a JSON object", file=where)
    for key, want in (("_type", STATEMENT_TYPE), ("predicateType", PREDICATE_TYPE)):
        if stmt.get(key) != want:
            raise ProvenanceError(
                f"statement {key} is not ours", file=f"{where}/{key}", expected=want, actual=str(stmt.get(key))
            )
    subjects = _subjects(stmt.get("subject"), where)
    build = _object(_object(stmt.get("predicate"), where + "/predicate").get("buildDefinition"), where)
    errors: list[HcdfTrustError] = []
    errors += _check_build(build, release, where + "/predicate/buildDefinition")
    errors += _check_dependencies(build.get("resolvedDependencies"), release, where)
    errors += _check_subjects(subjects, folder)
    return errors


def _check_build(build: dict[str, Any], release: Any, where: str) -> list[HcdfTrustError]:
    # 5. buildType and externalParameters
    errors: list[HcdfTrustError] = []
    if build.get("buildType") != BUILD_TYPE:
        errors.append(
            ProvenanceError(
                "buildType is not hcdf-trust's",
                file=where + "/buildType",
                expected=BUILD_TYPE,
                actual=str(build.get("buildType")),
            )
        )
    params = _object(build.get("externalParameters"), where + "/externalParameters")
    for key in sorted(set(params) - EXTERNAL_PARAMETERS):
        errors.append(
            ProvenanceError(
                f"unexpected externalParameters field {key!r}",
                file=f"{where}/externalParameters/{key}",
                expected=", ".join(sorted(EXTERNAL_PARAMETERS)),
                actual=key,
            )
        )
    images = sorted(f"{c.board}/{c.app}" for c in release.components)
    for key, want in (("root", release.root), ("images", images)):
        if params.get(key) != want:
            errors.append(
                ProvenanceError(
                    f"externalParameters.{key} is not the signed manifest's",
                    file=f"{where}/externalParameters/{key}",
                    expected=str(want),
                    actual=str(params.get(key)),
                )
            )
    return errors


def _check_dependencies(deps: Any, release: Any, where: str) -> list[HcdfTrustError]:
    # 6. the root document and the lock the SUIT manifest binds
    where += "/predicate/buildDefinition/resolvedDependencies"
    if not isinstance(deps, list):
        raise MalformedProvenanceError("resolvedDependencies is not a list", file=where)
    errors: list[HcdfTrustError] = []
    for name, want in ((ROOT_DEPENDENCY, release.root_sha256), (LOCK_DEPENDENCY, release.lock_sha256)):
        found = [(i, d) for i, d in enumerate(deps) if isinstance(d, dict) and d.get("name") == name]
        if len(found) != 1:
            errors.append(
                ProvenanceError(
                    f"resolvedDependencies names {len(found)} {name!r}",
                    file=where,
                    expected="1",
                    actual=str(len(found)),
                )
            )
            continue
        i, dep = found[0]
        digest = dep.get("digest")
        actual = digest.get("sha256") if isinstance(digest, dict) else None
        if actual != want:
            errors.append(
                ProvenanceError(
                    f"{name} digest is not the one the signed manifest binds (another robot's description?)",
                    file=f"{where}/{i}/digest/sha256",
                    expected=want,
                    actual=str(actual),
                )
            )
    return errors


def _check_subjects(subjects: dict[str, str], folder: str) -> list[HcdfTrustError]:
    # 7. subjects against the files on disk, both ways
    on_disk, errors = release_files(folder)
    for name, want in sorted(subjects.items()):
        actual = on_disk.get(name)
        if actual != want:
            errors.append(
                ProvenanceError(
                    f"subject {name}: " + ("missing from the release" if actual is None else "SHA-256 differs"),
                    file=name,
                    expected=want,
                    actual=actual or "missing",
                )
            )
    for name in sorted(set(on_disk) - set(subjects)):
        errors.append(
            ProvenanceError(
                f"{name} is in the release but not a subject of its provenance (added after signing?)",
                file=name,
                expected="a subject",
                actual="not covered",
            )
        )
    return errors


def _subjects(value: Any, where: str) -> dict[str, str]:
    where += "/subject"
    if not isinstance(value, list) or not value:
        raise MalformedProvenanceError("subject is not a non-empty list", file=where)
    out: dict[str, str] = {}
    for i, s in enumerate(value):
        name = s.get("name") if isinstance(s, dict) else None
        digest = s.get("digest") if isinstance(s, dict) else None
        sha = digest.get("sha256") if isinstance(digest, dict) else None
        if not isinstance(name, str) or not isinstance(sha, str) or name in out:
            raise MalformedProvenanceError(
                "a subject is not a unique {name, digest: {sha256}}", file=f"{where}/{i}", actual=str(s)[:200]
            )
        out[name] = sha
    return out


def _object(value: Any, where: str) -> dict[str, Any]:
    if not isinstance(value, dict):
        raise MalformedProvenanceError("not a JSON object", file=where)
    return value
