"""The files of a release folder, by relative path and SHA-256: what the subjects cover."""

from __future__ import annotations

import os

from ..errors import HcdfTrustError
from ..localfile import open_checked
from . import FILE_NAME
from .errors import ProvenanceError


def release_files(folder: str, *, skip: frozenset[str] = frozenset()) -> tuple[dict[str, str], list[HcdfTrustError]]:
    """Every regular file under ``folder`` (but ``provenance.intoto.json`` and ``skip``):
    relative POSIX path -> SHA-256, read through the confined reader. A symlink or any
    other non-regular entry is an error (a release holds files only)."""
    from ..digest import hash_fd

    found: dict[str, str] = {}
    errors: list[HcdfTrustError] = []
    if not os.path.isdir(folder):
        return found, errors
    for top, dirs, names in os.walk(folder):
        for name in sorted(dirs + names):
            path = os.path.join(top, name)
            rel = os.path.relpath(path, folder).replace(os.sep, "/")
            if rel == FILE_NAME or rel in skip:
                continue
            if os.path.islink(path):
                errors.append(ProvenanceError(f"{rel} is a symlink in the release folder", file=rel))
                continue
            if name in dirs:
                continue
            fd, _ = open_checked(path, folder, file=rel)
            try:
                found[rel] = hash_fd(fd).sha256
            finally:
                os.close(fd)
        dirs[:] = sorted(d for d in dirs if not os.path.islink(os.path.join(top, d)))
    return found, errors
