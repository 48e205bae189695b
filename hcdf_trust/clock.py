"""Times and durations given by a user (a flag, ``SOURCE_DATE_EPOCH``): one parser per kind,
each with the range it accepts, so that every verb takes the same values and refuses the
same ones (``hcdf_trust.cli.params`` wraps them as click types: exit 2).

A time lies in [1970-01-01, 3000-01-01) UTC and a duration is at most 100 years, so that any
time plus any duration is still a date Python can hold (no ``OverflowError``).
"""

from __future__ import annotations

import os
import re
from datetime import UTC, datetime, timedelta

EARLIEST = datetime(1970, 1, 1, tzinfo=UTC)
LATEST = datetime(3000, 1, 1, tzinfo=UTC)  # exclusive
MAX_DURATION = timedelta(days=36525)  # 100 years
SOURCE_DATE_EPOCH = "SOURCE_DATE_EPOCH"

_DURATION = re.compile(r"([0-9]{1,12})\s*([smhdw]?)")
_UNITS = {"": 1, "s": 1, "m": 60, "h": 3600, "d": 86400, "w": 604800}


def parse_time(text: str) -> datetime:
    """An ISO 8601 time with a zone (``2026-01-01T00:00:00Z``), in the accepted range.

    Raises:
        ValueError: not such a time, no zone, or out of range (the message says which).
    """
    try:
        t = datetime.fromisoformat(text.strip())
    except ValueError:
        raise ValueError(f"{text!r} is not an ISO 8601 time (e.g. 2026-01-01T00:00:00Z)") from None
    if t.tzinfo is None:
        raise ValueError(f"{text!r} has no time zone: an ISO 8601 time with a zone is needed (add Z for UTC)")
    return _in_range(t, text)


def parse_epoch(text: str) -> datetime:
    """Seconds since 1970-01-01T00:00:00Z (``SOURCE_DATE_EPOCH``): digits only, in range.

    Raises:
        ValueError: not a non-negative integer, or out of range.
    """
    value = text.strip()
    if not value.isascii() or not value.isdigit() or len(value) > 12:
        raise ValueError(f"{text!r} is not a number of seconds since 1970 (digits only)")
    seconds = int(value)
    if seconds >= (LATEST - EARLIEST).total_seconds():
        raise ValueError(f"{text!r} is outside 1970-01-01 to 2999-12-31")
    return EARLIEST + timedelta(seconds=seconds)


def parse_duration(text: str) -> timedelta:
    """A duration: seconds (``3600``) or a number with a unit (``90s``, ``30m``, ``12h``, ``7d``,
    ``2w``), at most :data:`MAX_DURATION`.

    Raises:
        ValueError: not such a duration, or longer than 100 years.
    """
    m = _DURATION.fullmatch(text.strip())
    if m is None:
        raise ValueError(f"{text!r} is not a duration (3600, 90s, 30m, 12h, 7d, 2w)")
    seconds = int(m.group(1)) * _UNITS[m.group(2)]
    if seconds > MAX_DURATION.total_seconds():
        raise ValueError(f"{text!r} is longer than 100 years")
    return timedelta(seconds=seconds)


def source_date_epoch() -> datetime | None:
    """``$SOURCE_DATE_EPOCH`` (reproducible builds) as a time, or None when unset or empty.

    Raises:
        ValueError: set to something :func:`parse_epoch` refuses.
    """
    value = os.environ.get(SOURCE_DATE_EPOCH)
    return parse_epoch(value) if value else None


def _in_range(t: datetime, text: str) -> datetime:
    try:
        inside = EARLIEST <= t < LATEST
    except OverflowError:  # 0001-01-01T00:00+01:00 is before year 1 in UTC
        inside = False
    if not inside:
        raise ValueError(f"{text!r} is outside 1970-01-01 to 2999-12-31")
    return t
