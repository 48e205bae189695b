"""The lock file: every artifact of a document tree, its digest and size.

JSON, sorted keys, one artifact per object, sorted by URL: deterministic and
diff-friendly. Local URLs are written relative to the lock file's folder so the
lock survives moving the checkout. ``lock_version`` changes on any format change.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..digest import is_full_sha256
from ..errors import LockDriftError, LockFileError
from ..store import atomic_write

LOCK_VERSION = 1
DEFAULT_NAME = "hcdf.lock"


@dataclass(frozen=True)
class LockEntry:
    kind: str
    uri: str
    url: str
    sha256: str
    size: int
    referenced_from: tuple[str, ...] = field(default=())

    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "uri": self.uri,
            "url": self.url,
            "sha256": self.sha256,
            "size": self.size,
            "referenced_from": list(self.referenced_from),
        }


def render(entries: list[LockEntry], *, root: str) -> bytes:
    doc = {
        "lock_version": LOCK_VERSION,
        "root": root,
        "artifacts": [e.to_dict() for e in sorted(entries, key=lambda e: (e.url, e.kind))],
    }
    return (json.dumps(doc, indent=2, sort_keys=True, ensure_ascii=False) + "\n").encode()


def write(path: str | os.PathLike[str], entries: list[LockEntry], *, root: str) -> None:
    atomic_write(path, render(entries, root=root))


def load(path: str | os.PathLike[str]) -> dict[str, LockEntry]:
    """Read a lock file, keyed by URL.

    Raises:
        LockFileError: missing, unreadable, not JSON, or an unknown format version.
    """
    p = Path(path)
    try:
        raw = p.read_bytes()
    except FileNotFoundError:
        raise LockFileError(f"lock file {p} does not exist (run resolve without --locked first)", file=str(p)) from None
    except OSError as exc:
        raise LockFileError(f"cannot read lock file: {exc.strerror}", file=str(p)) from None
    try:
        doc = json.loads(raw)
        version = doc["lock_version"]
        if version != LOCK_VERSION:
            raise LockFileError(
                f"unsupported lock_version {version!r}", file=str(p), expected=str(LOCK_VERSION), actual=str(version)
            )
        entries = {}
        for item in doc["artifacts"]:
            entry = LockEntry(
                kind=str(item["kind"]),
                uri=str(item["uri"]),
                url=str(item["url"]),
                sha256=str(item["sha256"]).lower(),
                size=int(item["size"]),
                referenced_from=tuple(str(r) for r in item.get("referenced_from", [])),
            )
            if not is_full_sha256(entry.sha256):
                raise LockFileError(f"artifact {entry.url}: sha256 is not a full digest", file=str(p))
            entries[entry.url] = entry
        return entries
    except LockFileError:
        raise
    except (ValueError, KeyError, TypeError) as exc:
        raise LockFileError(f"malformed lock file: {exc}", file=str(p)) from None


def compare(locked: dict[str, LockEntry], actual: dict[str, LockEntry], *, lock_path: str) -> list[LockDriftError]:
    """Every difference between the lock and what the tree resolves to now. Pure."""
    errors: list[LockDriftError] = []
    for url, now in sorted(actual.items()):
        before = locked.get(url)
        where = now.referenced_from[0] if now.referenced_from else None
        file, line = _split_where(where)
        if before is None:
            errors.append(
                LockDriftError(f"{now.uri} is not in the lock file {lock_path}", file=file, line=line, url=url)
            )
        elif before.sha256 != now.sha256:
            errors.append(
                LockDriftError(
                    f"{now.uri} changed since it was locked",
                    file=file,
                    line=line,
                    url=url,
                    expected=before.sha256,
                    actual=now.sha256,
                )
            )
    for url in sorted(set(locked) - set(actual)):
        errors.append(LockDriftError(f"{url} is in the lock file but no longer referenced", file=lock_path, url=url))
    return errors


def _split_where(where: str | None) -> tuple[str | None, int | None]:
    if not where:
        return None, None
    file, _, line = where.rpartition(":")
    return (file, int(line)) if line.isdigit() else (where, None)
