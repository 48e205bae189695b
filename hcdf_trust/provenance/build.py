"""Signing a provenance: :func:`sign_provenance` for any set of files (a release, a bundle),
:func:`release_provenance` for the release ``ota build --provenance`` is writing.

Public API (docs/api.md): :func:`sign_provenance` and :class:`Dependency`.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Mapping, Sequence
from typing import Any

from ..errors import ErrorGroup
from . import BUILD_TYPE, dsse
from .files import release_files
from .statement import FIRMWARE_DEPENDENCY, BuildFacts, Dependency, release_statement, serialize, statement

__all__ = ["Dependency", "sign_provenance"]


def sign_provenance(
    subjects: Mapping[str, str],
    dependencies: Sequence[Dependency],
    *,
    parameters: Mapping[str, Any],
    date: str,
    signers: Sequence[Any],
    build_type: str = BUILD_TYPE,
    builder_id: str | None = None,
) -> bytes:
    """The ``provenance.intoto.json`` bytes (a DSSE envelope, every signer's signature) over
    an in-toto Statement v1 / SLSA Provenance v1 whose subjects are ``subjects`` (relative
    name -> file SHA-256, hex) and whose ``resolvedDependencies`` are ``dependencies`` in
    that order; ``parameters`` are its ``externalParameters`` (what the build type
    ``build_type`` defines), ``date`` (RFC 3339, e.g. from ``SOURCE_DATE_EPOCH``) its start
    and finish. ``signers`` are ota signers (:class:`hcdf_trust.ota.signer.FileSigner`,
    :class:`hcdf_trust.ota.hsm.HsmSigner`). The statement is serialized once (compact,
    sorted keys); those bytes are what is signed and published.

    >>> import base64, hashlib, json
    >>> from hcdf_trust.ota.keys import generate
    >>> from hcdf_trust.ota.signer import FileSigner
    >>> from hcdf_trust.provenance.build import Dependency, sign_provenance
    >>> doc = open("examples/robot/robot.hcdf", "rb").read()
    >>> sha = hashlib.sha256(doc).hexdigest()
    >>> envelope = sign_provenance(
    ...     {"robot.hcdf": sha},
    ...     [Dependency("hcdf-root", sha, "robot.hcdf")],
    ...     parameters={"root": "robot.hcdf"},
    ...     date="2026-05-28T20:26:40Z",
    ...     signers=[FileSigner(generate("ed25519"))],
    ...     build_type="https://example.com/buildtypes/copy/v1",
    ... )
    >>> outer = json.loads(envelope)
    >>> outer["payloadType"], len(outer["signatures"])
    ('application/vnd.in-toto+json', 1)
    >>> statement = json.loads(base64.b64decode(outer["payload"]))
    >>> statement["subject"] == [{"name": "robot.hcdf", "digest": {"sha256": sha}}]
    True

    Raises:
        KeyFileError: a signer that cannot sign a provenance.
    """
    doc = statement(
        subjects,
        parameters=parameters,
        dependencies=dependencies,
        date=date,
        build_type=build_type,
        builder_id=builder_id,
    )
    return dsse.sign(serialize(doc), list(signers))


def release_provenance(
    *,
    out_dir: str,
    new_files: dict[str, bytes],
    release: Any,
    lock_name: str,
    lock_entries: list[Any],
    images: list[str],
    firmware: Mapping[str, tuple[str, str | None]],
    date: str,
    base_url: str | None,
    config_path: str | None,
    signers: list[Any],
    builder_id: str | None = None,
) -> bytes:
    """The envelope file for a release whose folder will hold ``new_files`` (relative
    path -> bytes) over whatever ``out_dir`` already holds (older images stay).
    ``firmware``: "board/app" -> (the binary's path under ``--firmware-dir``, its SHA-256).

    Raises:
        ErrorGroup: a symlink in the release folder. KeyFileError: a signer that cannot sign.
    """
    from ..localfile import read_input

    existing, errors = release_files(out_dir, skip=frozenset(new_files))
    if errors:
        raise ErrorGroup(errors)
    files = existing | {rel: hashlib.sha256(data).hexdigest() for rel, data in new_files.items()}
    deps = [Dependency(e.url, e.sha256, e.uri) for e in lock_entries]
    for image, (path, sha) in firmware.items():
        assert sha is not None, image  # hashed when the build makes a provenance
        deps.append(Dependency(FIRMWARE_DEPENDENCY + image, sha, path))
    config_name = None
    if config_path is not None:
        config_name = os.path.basename(config_path)
        data = read_input(config_path, limit=1 << 20, what="ota.toml")
        deps.append(Dependency("ota.toml", hashlib.sha256(data).hexdigest(), config_name))
    facts = BuildFacts(
        files=files,
        root=release.root,
        root_sha256=release.root_sha256,
        lock_sha256=release.lock_sha256,
        lock=lock_name,
        images=tuple(images),
        dependencies=tuple(deps),
        date=date,
        base_url=base_url,
        ota_config=config_name,
        builder_id=builder_id,
    )
    return dsse.sign(serialize(release_statement(facts)), signers)
