"""``ota build --provenance``: the signed statement of the release being written."""

from __future__ import annotations

import hashlib
import os
from typing import Any

from ..errors import ErrorGroup
from . import dsse
from .files import release_files
from .statement import BuildFacts, Dependency, serialize, statement


def release_provenance(
    *,
    out_dir: str,
    new_files: dict[str, bytes],
    release: Any,
    lock_name: str,
    lock_entries: list[Any],
    images: list[str],
    date: str,
    base_url: str | None,
    config_path: str | None,
    signers: list[Any],
    builder_id: str | None = None,
) -> bytes:
    """The envelope file for a release whose folder will hold ``new_files`` (relative
    path -> bytes) over whatever ``out_dir`` already holds (older images stay).

    Raises:
        ErrorGroup: a symlink in the release folder. KeyFileError: a signer that cannot sign.
    """
    from ..localfile import read_input

    existing, errors = release_files(out_dir, skip=frozenset(new_files))
    if errors:
        raise ErrorGroup(errors)
    files = existing | {rel: hashlib.sha256(data).hexdigest() for rel, data in new_files.items()}
    deps = [Dependency(e.url, e.sha256, e.uri) for e in lock_entries]
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
    return dsse.sign(serialize(statement(facts)), signers)
