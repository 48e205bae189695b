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
   digests the SUIT manifest binds (a statement of another robot is refused), and exactly
   one firmware input per image of the manifest: a raw image's is the image itself; an
   MCUboot image built from a ``.bin`` holds that binary between its header and its TLVs
   (an Intel HEX input is converted by imgtool: its digest cannot be checked here).
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
from .statement import EXTERNAL_PARAMETERS, FIRMWARE_DEPENDENCY, LOCK_DEPENDENCY, ROOT_DEPENDENCY


def read_envelope(folder: str) -> bytes | None:
    """The bytes of ``folder``'s ``provenance.intoto.json`` (bounded, confined), None when
    there is none.

    Raises:
        InputError: it is a symlink, not a regular file, or too large.
    """
    path = os.path.join(folder, FILE_NAME)
    if not os.path.lexists(path):
        return None
    fd, _ = open_checked(path, folder, file=FILE_NAME)
    try:
        return read_bounded(fd, dsse.MAX_ENVELOPE_BYTES, source=FILE_NAME, what="provenance")
    finally:
        os.close(fd)


def verify_provenance(
    folder: str, release: Any, public_keys: list[Any], *, threshold: int = 1, data: bytes | None = None
) -> list[HcdfTrustError]:
    """Every violation of steps 5–7 (steps 1–4 raise: nothing after them can be trusted).

    ``release`` is the SUIT manifest, already verified; ``data`` the envelope's bytes when
    the caller read them (:func:`read_envelope`: checked and then used, never read twice).

    Raises:
        MalformedProvenanceError: steps 1 and 4's parsing. ProvenanceError: steps 1–4.
    """
    # 1. the envelope
    if data is None:
        data = read_envelope(folder)
    if data is None:
        raise ProvenanceError("the release has no provenance", file=FILE_NAME, expected=FILE_NAME, actual="none")
    subjects, build, where = open_statement(data, public_keys, threshold, source=FILE_NAME)
    errors: list[HcdfTrustError] = []
    errors += _check_build(build, release, where + "/predicate/buildDefinition")
    errors += _check_dependencies(build.get("resolvedDependencies"), release, where)
    errors += _check_firmware(build.get("resolvedDependencies"), release, folder, where)
    errors += _check_subjects(subjects, folder)
    return errors


def open_statement(
    data: bytes, public_keys: list[Any], threshold: int, *, source: str
) -> tuple[dict[str, str], dict[str, Any], str]:
    """Steps 2–4 for any of our envelopes (a release's, a bundle's): payloadType, the signatures
    over the PAE, then the statement parsed from the very bytes that were verified, its
    ``_type`` and ``predicateType``. Returns its subjects (name -> sha256), its
    ``buildDefinition`` and the JSON Pointer prefix of the statement (``source#/payload``).

    Raises:
        MalformedProvenanceError, ProvenanceError: nothing after a failed step can be trusted.
    """
    env = dsse.parse(data, source=source)
    if env.payload_type != PAYLOAD_TYPE:
        raise ProvenanceError(
            "payloadType is not an in-toto statement's",
            file=source + "#/payloadType",
            expected=PAYLOAD_TYPE,
            actual=env.payload_type,
        )
    dsse.verify(env, [dsse.sslib_key(k) for k in public_keys], threshold, source=source)
    where = source + "#/payload"
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
    return subjects, build, where


def check_build_type(
    build: dict[str, Any], where: str, *, build_type: str, parameters: frozenset[str] | set[str], whose: str
) -> list[HcdfTrustError]:
    """``buildType`` is ``build_type`` and ``externalParameters`` holds no field outside
    ``parameters`` (SLSA's advice: refuse what you do not expect). ``where`` is the
    ``buildDefinition``'s pointer; ``whose`` names the build type in the message."""
    errors: list[HcdfTrustError] = []
    if build.get("buildType") != build_type:
        errors.append(
            ProvenanceError(
                f"buildType is not {whose}",
                file=where + "/buildType",
                expected=build_type,
                actual=str(build.get("buildType")),
            )
        )
    params = _object(build.get("externalParameters"), where + "/externalParameters")
    for key in sorted(set(params) - set(parameters)):
        errors.append(
            ProvenanceError(
                f"unexpected externalParameters field {key!r}",
                file=f"{where}/externalParameters/{key}",
                expected=", ".join(sorted(parameters)),
                actual=key,
            )
        )
    return errors


def _check_build(build: dict[str, Any], release: Any, where: str) -> list[HcdfTrustError]:
    # 5. buildType and externalParameters
    errors = check_build_type(build, where, build_type=BUILD_TYPE, parameters=EXTERNAL_PARAMETERS, whose="hcdf-trust's")
    params = _object(build.get("externalParameters"), where + "/externalParameters")
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


def _check_firmware(deps: Any, release: Any, folder: str, where: str) -> list[HcdfTrustError]:
    # 6. every image's input, and nothing else, with a digest the image can vouch for
    where += "/predicate/buildDefinition/resolvedDependencies"
    assert isinstance(deps, list)  # _check_dependencies refused anything else
    found: dict[str, tuple[int, Any]] = {}
    errors: list[HcdfTrustError] = []
    for i, dep in enumerate(deps):
        name = dep.get("name") if isinstance(dep, dict) else None
        if not isinstance(name, str) or not name.startswith(FIRMWARE_DEPENDENCY):
            continue
        image = name[len(FIRMWARE_DEPENDENCY) :]
        if image in found:
            errors.append(ProvenanceError(f"two firmware inputs for {image}", file=f"{where}/{i}", actual=name))
        found[image] = (i, dep)
    for c in release.components:
        image = f"{c.board}/{c.app}"
        if image not in found:
            errors.append(
                ProvenanceError(
                    f"resolvedDependencies has no firmware input for {image}",
                    file=where,
                    expected=FIRMWARE_DEPENDENCY + image,
                    actual="none",
                )
            )
            continue
        i, dep = found.pop(image)
        digest = dep.get("digest")
        stated = digest.get("sha256") if isinstance(digest, dict) else None
        uri = dep.get("uri")
        if c.type == "raw":
            inside: str | None = c.sha256
        elif isinstance(uri, str) and uri.lower().endswith(".hex"):
            continue  # imgtool converted it: the image holds its binary, not its text
        else:
            inside = _mcuboot_payload_sha256(folder, f"{c.board}/{c.app}/{c.version}.bin")
            if inside is None:
                continue  # not on disk: a missing subject, reported by step 7
        if stated != inside:
            errors.append(
                ProvenanceError(
                    f"the firmware input of {image} is not the binary its signed image holds",
                    file=f"{where}/{i}/digest/sha256",
                    expected=inside,
                    actual=str(stated),
                )
            )
    for image, (i, _dep) in sorted(found.items()):
        errors.append(
            ProvenanceError(
                f"a firmware input for {image}, an image the signed manifest lacks",
                file=f"{where}/{i}",
                expected=", ".join(sorted(f"{c.board}/{c.app}" for c in release.components)),
                actual=image,
            )
        )
    return errors


def _mcuboot_payload_sha256(folder: str, rel: str) -> str | None:
    """SHA-256 of the bytes between an MCUboot image's header and its TLVs (what ``ota
    build`` gave imgtool), or None when the file is not there."""
    import hashlib

    from ..ota.images import read_info
    from ..ota.release import MAX_FIRMWARE_BYTES

    path = os.path.join(folder, rel)
    if not os.path.lexists(path):
        return None
    fd, _ = open_checked(path, folder, file=rel)
    try:
        data = read_bounded(fd, MAX_FIRMWARE_BYTES, source=rel, what="firmware image")
    finally:
        os.close(fd)
    info = read_info(data, source=rel)
    return hashlib.sha256(data[info.header_size : info.header_size + info.image_size]).hexdigest()


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
