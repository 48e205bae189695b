"""``{board}/{app}/latest.json``: the per-device manifest the fleet daemon reads.

The format is the CogniPilot Dendrite one (``../shared/corpus/firmware_releases``):
``{board, app, latest: {version, date, mcuboot_hash, size, url, changelog?}, previous: [...]}``.
It is unsigned; the signed release manifest (:mod:`.suit`) is what binds it. A new
release moves the previous ``latest`` to the front of ``previous``: history is never lost.
"""

from __future__ import annotations

import datetime
import json
import re
from dataclasses import dataclass
from typing import Any

from .errors import FirmwareError, MalformedReleaseError, RollbackError

_HEX64 = re.compile(r"[0-9a-f]{64}")
MAX_BYTES = 4 << 20  # a latest.json (the fleet's have a few entries; ours one per release)
# RFC 3339 date-time: what the fleet daemon's chrono parser needs (a subset of what it accepts).
# A date without a time makes it refuse the whole file, history included.
_RFC3339 = re.compile(r"(\d{4})-(\d{2})-(\d{2})[Tt ](\d{2}):(\d{2}):(\d{2})(?:\.\d{1,9})?(?:[Zz]|[+-](\d{2}):(\d{2}))")
_U64 = 2**64


@dataclass(frozen=True)
class Entry:
    version: str
    date: str
    mcuboot_hash: str
    size: int
    url: str
    changelog: str | None = None

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "version": self.version,
            "date": self.date,
            "mcuboot_hash": self.mcuboot_hash,
            "size": self.size,
            "url": self.url,
        }
        if self.changelog is not None:
            out["changelog"] = self.changelog
        return out


@dataclass(frozen=True)
class Latest:
    board: str
    app: str
    latest: Entry
    previous: tuple[Entry, ...] = ()

    def to_dict(self) -> dict[str, Any]:
        return {
            "board": self.board,
            "app": self.app,
            "latest": self.latest.to_dict(),
            "previous": [e.to_dict() for e in self.previous],
        }


def render(manifest: Latest) -> bytes:
    """The corpus layout: that key order, two-space indent, UTF-8."""
    return (json.dumps(manifest.to_dict(), indent=2, ensure_ascii=False) + "\n").encode()


def parse(data: bytes, *, source: str) -> Latest:
    """Read a ``latest.json`` (ours or the fleet's).

    Raises:
        MalformedReleaseError: not JSON, a missing or mistyped field, a bad hash.
    """
    from ..localfile import JsonError, parse_json

    try:
        doc = parse_json(data, source=source, what="latest.json", limit=MAX_BYTES)
    except JsonError as exc:
        raise MalformedReleaseError(exc.message, file=source, line=exc.line, expected=exc.expected) from None
    if not isinstance(doc, dict):
        raise MalformedReleaseError("latest.json is not an object", file=source, actual=type(doc).__name__)
    board = _field(doc, "board", str, source, "")
    app = _field(doc, "app", str, source, "")
    latest = _entry(doc.get("latest"), source, "latest")
    previous = doc.get("previous", [])
    if not isinstance(previous, list):
        raise MalformedReleaseError("previous is not a list", file=source, actual=type(previous).__name__)
    return Latest(board, app, latest, tuple(_entry(e, source, f"previous[{i}]") for i, e in enumerate(previous)))


def _entry(raw: Any, source: str, where: str) -> Entry:
    if not isinstance(raw, dict):
        raise MalformedReleaseError(f"{where} is not an object", file=source, actual=type(raw).__name__)
    mcuboot_hash = _field(raw, "mcuboot_hash", str, source, where).lower()
    if not _HEX64.fullmatch(mcuboot_hash):
        raise MalformedReleaseError(
            f"{where}.mcuboot_hash is not a SHA-256", file=source, expected="64 hex digits", actual=mcuboot_hash
        )
    size = _field(raw, "size", int, source, where)
    if not 0 <= size < _U64:
        raise MalformedReleaseError(f"{where}.size is not a u64", file=source, actual=str(size))
    changelog = raw.get("changelog")
    if changelog is not None and not isinstance(changelog, str):
        raise MalformedReleaseError(f"{where}.changelog is not a string", file=source)
    return Entry(
        version=_field(raw, "version", str, source, where),
        date=_date(_field(raw, "date", str, source, where), source, where),
        mcuboot_hash=mcuboot_hash,
        size=size,
        url=_field(raw, "url", str, source, where),
        changelog=changelog,
    )


def _date(value: str, source: str, where: str) -> str:
    """An RFC 3339 date and time (leap second allowed), as the fleet daemon needs; else refused."""
    m = _RFC3339.fullmatch(value)
    valid = m is not None
    if m is not None:
        year, month, day, hour, minute, second = (int(g) for g in m.groups()[:6])
        off_h, off_m = (int(g) if g else 0 for g in m.groups()[6:])
        try:
            datetime.date(year, month, day)
        except ValueError:
            valid = False
        valid = valid and hour < 24 and minute < 60 and second <= 60 and off_h < 24 and off_m < 60
    if not valid:
        raise MalformedReleaseError(
            f"latest.json {where}.date is not an RFC 3339 date and time: the fleet daemon refuses the whole file",
            file=source,
            expected="YYYY-MM-DDTHH:MM:SSZ",
            actual=value,
        )
    return value


def _field(raw: dict[str, Any], key: str, kind: type, source: str, where: str) -> Any:
    name = f"{where}.{key}" if where else key
    if key not in raw:
        raise MalformedReleaseError(f"latest.json has no {name}", file=source, expected=kind.__name__, actual="nothing")
    value = raw[key]
    if type(value) is not kind:
        raise MalformedReleaseError(
            f"latest.json {name} is not a {kind.__name__}",
            file=source,
            expected=kind.__name__,
            actual=type(value).__name__,
        )
    return value


def advance(previous: Latest | None, *, board: str, app: str, new: Entry, source: str | None = None) -> Latest:
    """The next ``latest.json``: ``new`` is latest, the old latest moves to the front of previous.

    Rebuilding the same version with the same image keeps the history as it was.

    Raises:
        RollbackError: ``new`` is an older version than the previous latest.
        FirmwareError: the previous release is for another board/app, or already has
            this version with a different image.
    """
    if previous is None:
        return Latest(board, app, new, ())
    if (previous.board, previous.app) != (board, app):
        raise FirmwareError(
            f"the previous latest.json is for {previous.board}/{previous.app}",
            file=source,
            expected=f"{board}/{app}",
            actual=f"{previous.board}/{previous.app}",
        )
    if previous.latest.version == new.version:
        if previous.latest.mcuboot_hash != new.mcuboot_hash:
            raise FirmwareError(
                f"{board}/{app} version {new.version} was already released with another image: bump the version",
                file=source,
                expected=previous.latest.mcuboot_hash,
                actual=new.mcuboot_hash,
            )
        return Latest(board, app, new, previous.previous)
    before, after = _ordered(previous.latest.version), _ordered(new.version)
    if before is not None and after is not None and after < before:
        raise RollbackError(
            f"{board}/{app}: version {new.version} is older than the previous release's {previous.latest.version}",
            file=source,
            expected=f"> {previous.latest.version}",
            actual=new.version,
        )
    history = (previous.latest, *previous.previous)
    return Latest(board, app, new, tuple(e for e in history if e.version != new.version))


def _ordered(version: str) -> tuple[int, ...] | None:
    """A ``major.minor.revision[+build]`` version as a comparable tuple; None if it is not one."""
    core, _, build = version.strip().lstrip("vV").partition("+")
    parts = core.split(".")
    if not all(p.isdigit() for p in parts) or (build and not build.isdigit()) or len(parts) > 3:
        return None
    return (*(int(p) for p in parts), *([0] * (3 - len(parts))), int(build or 0))
