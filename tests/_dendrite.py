"""What the Dendrite fleet daemon accepts as a ``latest.json``, written from its source, not from ours.

Read in CogniPilot/dendrite (Cargo.lock: serde 1.0.228, serde_json 1.0.149, chrono 0.4.42):
``crates/dendrite-core/src/firmware.rs`` (``FirmwareManifest``, ``FirmwareRelease``) and
``crates/dendrite-daemon/src/firmware_fetch.rs`` (``response.json()``, ``download_firmware``,
``compute_mcuboot_hash``)::

    #[derive(Deserialize)] struct FirmwareManifest { board: String, app: String,
        latest: FirmwareRelease, #[serde(default)] previous: Vec<FirmwareRelease> }
    #[derive(Deserialize)] struct FirmwareRelease { version: String, date: DateTime<Utc>,
        mcuboot_hash: String, size: u64, url: String, #[serde(default)] changelog: Option<String> }

What follows from serde's derive and serde_json (no ``deny_unknown_fields``, no ``flatten``):
- the body is UTF-8 JSON, one value, only JSON whitespace after it; NaN/Infinity are not JSON;
  a string with a raw control character or a lone surrogate escape is refused;
- a struct is an object (or, serde's other form, an array of its fields in order whose missing
  tail may only be ``#[serde(default)]`` fields); unknown keys are ignored; a known key twice is
  "duplicate field"; a missing key without ``default`` is "missing field";
- ``String`` takes a JSON string only (not null); ``u64`` an integer 0 ≤ n < 2**64 written
  without fraction or exponent (a float is "invalid type: floating point"); ``Option<String>``
  a string or null; ``Vec`` an array (not null);
- ``DateTime<Utc>``: a string parsed by chrono's ``DateTime<FixedOffset>::from_str``
  (``parse_rfc3339_relaxed``, ported below), then converted to UTC.
``mcuboot_hash`` is any string to the parser; the download compares it, ASCII case-insensitively,
with the lowercase hex SHA-256 over header + protected TLVs + payload, after checking the body
length equals ``size``, and ``reqwest`` needs an absolute URL.
"""

from __future__ import annotations

import hashlib
import json
import re
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any


class Refused(Exception):
    """The daemon would log "Failed to parse firmware manifest" (or fail the download)."""


@dataclass(frozen=True)
class Release:
    version: str
    date: tuple[int, int, int, int, int, int, int]  # UTC: year, month, day, h, m, s, ns
    mcuboot_hash: str
    size: int
    url: str
    changelog: str | None


@dataclass(frozen=True)
class Manifest:
    board: str
    app: str
    latest: Release
    previous: tuple[Release, ...]


class _Float(float):
    """A JSON number written with a fraction or exponent (serde_json gives visit_f64)."""


def _no_constant(name: str) -> Any:
    raise Refused(f"{name} is not JSON")


def _lone_surrogate(text: str) -> bool:
    return any(0xD800 <= ord(c) <= 0xDFFF for c in text)


def parse(data: bytes) -> Manifest:
    """A ``FirmwareManifest`` as the daemon deserialises it, or :class:`Refused`."""
    try:
        text = data.decode("utf-8")  # from_slice: UTF-8 only (Python's json would sniff UTF-16/32)
    except UnicodeDecodeError as exc:
        raise Refused(f"not UTF-8: {exc}") from None
    if text.startswith("\ufeff"):
        raise Refused("a byte order mark is not JSON")
    try:
        value = json.loads(
            text,
            object_pairs_hook=_Pairs,  # keep duplicates: serde sees every key
            parse_float=_Float,
            parse_constant=_no_constant,
        )
    except json.JSONDecodeError as exc:  # also: control characters in strings, trailing data
        raise Refused(f"not JSON: {exc}") from None
    return _struct(value, "$", _MANIFEST)


def _string(value: Any, where: str) -> str:
    if not isinstance(value, str):
        raise Refused(f"{where}: invalid type {_kind(value)}, expected a string")
    if _lone_surrogate(value):
        raise Refused(f"{where}: lone surrogate in hex escape")
    return value


def _u64(value: Any, where: str) -> int:
    if isinstance(value, _Float):
        raise Refused(f"{where}: invalid type: floating point `{value}`, expected u64")
    if type(value) is not int:
        raise Refused(f"{where}: invalid type {_kind(value)}, expected u64")
    if not 0 <= value < 2**64:
        raise Refused(f"{where}: invalid value: integer `{value}`, expected u64")
    return value


def _option_string(value: Any, where: str) -> str | None:
    return None if value is None else _string(value, where)


def _date(value: Any, where: str) -> tuple[int, int, int, int, int, int, int]:
    return chrono_datetime_utc(_string(value, where), where)


def _releases(value: Any, where: str) -> tuple[Release, ...]:
    if not isinstance(value, list) or isinstance(value, _Pairs):
        raise Refused(f"{where}: invalid type {_kind(value)}, expected a sequence")
    return tuple(_struct(v, f"{where}[{i}]", _RELEASE) for i, v in enumerate(value))


def _release(value: Any, where: str) -> Release:
    return _struct(value, where, _RELEASE)


# field name -> (reader, default when absent or None for a required field); in declaration order
_RELEASE_FIELDS: dict[str, tuple[Any, Any]] = {
    "version": (_string, None),
    "date": (_date, None),
    "mcuboot_hash": (_string, None),
    "size": (_u64, None),
    "url": (_string, None),
    "changelog": (_option_string, lambda: None),
}
_MANIFEST_FIELDS: dict[str, tuple[Any, Any]] = {
    "board": (_string, None),
    "app": (_string, None),
    "latest": (_release, None),
    "previous": (_releases, tuple),
}
_RELEASE = (Release, _RELEASE_FIELDS)
_MANIFEST = (Manifest, _MANIFEST_FIELDS)


class _Pairs(list):  # type: ignore[type-arg]
    """A JSON object as its (key, value) pairs, in order, duplicates kept."""


def _struct(value: Any, where: str, spec: tuple[type, dict[str, tuple[Any, Any]]]) -> Any:
    """serde derive's visit_map (an object) and visit_seq (an array of the fields in order)."""
    cls, fields = spec
    out: dict[str, Any] = {}
    if isinstance(value, _Pairs):
        for key, raw in value:
            if key not in fields:
                continue  # no deny_unknown_fields: ignored
            if key in out:
                raise Refused(f"{where}: duplicate field `{key}`")
            out[key] = fields[key][0](raw, f"{where}.{key}")
    elif isinstance(value, list):
        if len(value) > len(fields):
            raise Refused(f"{where}: invalid length {len(value)}, expected fewer elements in array")
        for (key, (read, _)), raw in zip(fields.items(), value, strict=False):
            out[key] = read(raw, f"{where}[{key}]")
    else:
        raise Refused(f"{where}: invalid type {_kind(value)}, expected struct {cls.__name__}")
    for key, (_, default) in fields.items():
        if key not in out:
            if default is None:
                kind = "missing field" if isinstance(value, _Pairs) else "invalid length, no element for"
                raise Refused(f"{where}: {kind} `{key}`")
            out[key] = default()
    return cls(**out)


def _kind(value: Any) -> str:
    if value is None:
        return "null"
    if isinstance(value, bool):
        return f"boolean `{str(value).lower()}`"
    if isinstance(value, _Float):
        return "floating point"
    if isinstance(value, int):
        return "integer"
    if isinstance(value, str):
        return "string"
    if isinstance(value, _Pairs):
        return "map"
    return "sequence"


# --- chrono 0.4.42: DateTime<FixedOffset>::from_str = parse_rfc3339_relaxed (src/format/parse.rs) ---

# Rust's char::is_whitespace (Unicode White_Space), which str::trim_start uses
_RUST_WS = set("\t\n\x0b\x0c\r \x85\xa0\u1680\u2028\u2029\u202f\u205f\u3000") | {chr(c) for c in range(0x2000, 0x200B)}


def _trim(s: str) -> str:
    i = 0
    while i < len(s) and s[i] in _RUST_WS:
        i += 1
    return s[i:]


def _number(s: str, lo: int, hi: int, where: str) -> tuple[str, int]:
    """scan::number: between lo and hi ASCII digits."""
    if len(s.encode()) < lo:
        raise Refused(f"{where}: premature end of input")
    n, i = 0, 0
    while i < len(s) and i < hi and "0" <= s[i] <= "9":
        n = n * 10 + int(s[i])
        i += 1
    if i < lo:
        raise Refused(f"{where}: input contains invalid characters")
    if n >= 2**63:
        raise Refused(f"{where}: input is out of range")
    return s[i:], n


def _literal(s: str, lit: str, where: str) -> str:
    if len(s) < len(lit):
        raise Refused(f"{where}: premature end of input")
    if not s.startswith(lit):
        raise Refused(f"{where}: input contains invalid characters")
    return s[len(lit) :]


def _numeric(s: str, width: int, where: str, *, signed: bool = False) -> tuple[str, int]:
    s = _trim(s)  # parse_internal trims before every Numeric item
    if signed and s.startswith("-"):
        s, v = _number(s[1:], 1, 2**63, where)
        return s, -v
    if signed and s.startswith("+"):
        return _number(s[1:], 1, 2**63, where)
    return _number(s, 1, width, where)


def _days_in_month(year: int, month: int) -> int:
    leap = year % 4 == 0 and (year % 100 != 0 or year % 400 == 0)
    return [31, 29 if leap else 28, 31, 30, 31, 30, 31, 31, 30, 31, 30, 31][month - 1]


def chrono_datetime_utc(s: str, where: str = "date") -> tuple[int, int, int, int, int, int, int]:
    """``s.parse::<DateTime<FixedOffset>>()`` then ``with_timezone(&Utc)``, as (y, m, d, H, M, S, ns)."""
    s, year = _numeric(s, 4, where, signed=True)
    s = _literal(_trim(s), "-", where)
    s, month = _numeric(s, 2, where)
    s = _literal(_trim(s), "-", where)
    s, day = _numeric(s, 2, where)
    if not s:
        raise Refused(f"{where}: premature end of input")  # a date without a time
    if s[0] not in "tT ":
        raise Refused(f"{where}: input contains invalid characters")
    s, hour = _numeric(s[1:], 2, where)
    s = _literal(_trim(s), ":", where)
    s, minute = _numeric(s, 2, where)
    s = _literal(_trim(s), ":", where)
    s, second = _numeric(s, 2, where)
    nano = 0
    if s.startswith("."):  # Fixed::Nanosecond: 1..9 digits kept, further digits dropped
        rest, digits = s[1:], 0
        while digits < len(rest) and "0" <= rest[digits] <= "9":
            digits += 1
        if digits == 0:
            raise Refused(f"{where}: input contains invalid characters")
        kept = rest[: min(digits, 9)]
        nano = int(kept) * 10 ** (9 - len(kept))
        s = rest[digits:]
    s = _trim(s)
    if len(s) >= 3 and s[:3].upper() == "UTC":
        s, offset = s[3:], 0
    else:
        s, offset = _offset(s, where)
    if _trim(s):
        raise Refused(f"{where}: trailing input")
    # Parsed setters and to_datetime
    if not 1 <= month <= 12 or not 1 <= day <= 31 or not 0 <= hour <= 23 or not 0 <= minute <= 59:
        raise Refused(f"{where}: input is out of range")
    if not 0 <= second <= 60:
        raise Refused(f"{where}: input is out of range")
    if not -262143 <= year <= 262142 or day > _days_in_month(year, month):
        raise Refused(f"{where}: input is out of range")
    if not -86400 < offset < 86400:
        raise Refused(f"{where}: input is out of range")
    if second == 60:  # a leap second: 59 s + 1e9 ns
        second, nano = 59, nano + 1_000_000_000
    # to UTC (the range check at the far ends of chrono's calendar is not modelled)
    total = ((hour * 60 + minute) * 60 + second) - offset
    day_shift, secs = divmod(total, 86400)
    y, m, d = year, month, day + day_shift
    if d < 1:
        m -= 1
        if m == 0:
            y, m = y - 1, 12
        d = _days_in_month(y, m)
    elif d > _days_in_month(y, m):
        d, m = 1, m + 1
        if m == 13:
            y, m = y + 1, 1
    return (y, m, d, secs // 3600, secs // 60 % 60, secs % 60, nano)


def _offset(s: str, where: str) -> tuple[str, int]:
    """scan::timezone_offset(s, colon_or_space, allow_zulu=true, allow_missing_minutes=false, minus=true)."""
    if s[:1] in ("Z", "z"):
        return s[1:], 0
    if not s:
        raise Refused(f"{where}: premature end of input")
    if s[0] not in "+-\u2212":
        raise Refused(f"{where}: input contains invalid characters")
    negative = s[0] != "+"
    s = s[1:]
    if len(s.encode()) < 2:
        raise Refused(f"{where}: premature end of input")
    if not ("0" <= s[0] <= "9" and "0" <= s[1] <= "9"):
        raise Refused(f"{where}: input contains invalid characters")
    hours = int(s[:2])
    s = s[2:]
    while s and (s[0] == ":" or s[0] in _RUST_WS):
        s = s[1:]
    if len(s.encode()) < 2:
        raise Refused(f"{where}: premature end of input")
    if not ("0" <= s[0] <= "9" and "0" <= s[1] <= "9"):
        raise Refused(f"{where}: input contains invalid characters")
    if s[0] > "5":
        raise Refused(f"{where}: input is out of range")
    minutes = int(s[:2])
    seconds = hours * 3600 + minutes * 60
    return s[2:], -seconds if negative else seconds


# --- download_firmware / compute_mcuboot_hash ---

_ABSOLUTE = re.compile(r"[A-Za-z][A-Za-z0-9+.-]*://[^/?#\s]+")


def check_download(release: Release, body: bytes) -> None:
    """What ``download_firmware`` checks once the body of ``release.url`` is read."""
    if not _ABSOLUTE.match(release.url):
        raise Refused(f"url {release.url!r} is not an absolute URL (reqwest: relative URL without a base)")
    if len(body) != release.size:
        raise Refused(f"Firmware size mismatch: expected {release.size} bytes, got {len(body)} bytes")
    if len(body) < 32:
        raise Refused(f"Binary too small to be MCUboot image ({len(body)} bytes)")
    magic, _load, hdr_size, ptlv_size, img_size = struct.unpack_from("<IIHHI", body)
    if magic != 0x96F3B83D:
        raise Refused(f"Not an MCUboot image (magic=0x{magic:08x}, expected 0x96f3b83d)")
    end = hdr_size + ptlv_size + img_size
    if len(body) < end:
        raise Refused(f"Binary truncated: need {end} bytes for hash, have {len(body)} bytes")
    computed = hashlib.sha256(body[:end]).hexdigest()
    if computed != release.mcuboot_hash.lower() or not release.mcuboot_hash.isascii():
        raise Refused(f"Firmware MCUboot hash mismatch: expected {release.mcuboot_hash}, got {computed}")


# --- every latest.json a release folder holds ---


def check_release(out: Path, base_url: str | None) -> int:
    """Parse every ``{board}/{app}/latest.json`` under ``out`` as the daemon does; with a base
    URL, also download-check every entry whose binary the folder holds. Returns how many
    latest.json files were read; raises AssertionError naming the file."""
    count = 0
    for path in sorted(out.glob("*/*/latest.json")):
        count += 1
        try:
            manifest = parse(path.read_bytes())
            assert (manifest.board, manifest.app) == (path.parent.parent.name, path.parent.name)
            if base_url is not None:
                prefix = base_url.rstrip("/") + "/"
                assert manifest.latest.url.startswith(prefix), manifest.latest.url
                for i, release in enumerate((manifest.latest, *manifest.previous)):
                    binary = out / release.url[len(prefix) :] if release.url.startswith(prefix) else None
                    # older binaries may live in an older release (or on the fleet's server) only
                    if i == 0 or (binary is not None and binary.is_file()):
                        assert binary is not None
                        check_download(release, binary.read_bytes())
        except Refused as exc:
            raise AssertionError(f"the fleet daemon refuses {path}: {exc}") from None
    return count


def check_cli_run(args: tuple[str, ...]) -> None:
    """After a successful ``hcdf-trust ota build ARGS``: what it wrote is what Dendrite reads."""

    def value(*flags: str) -> str | None:
        for i, a in enumerate(args):
            for flag in flags:
                if a == flag and i + 1 < len(args):
                    return args[i + 1]
                if a.startswith(flag + "="):
                    return a[len(flag) + 1 :]
        return None

    out = value("--out", "-o")
    if out is not None and Path(out).is_dir():
        check_release(Path(out), value("--base-url"))
