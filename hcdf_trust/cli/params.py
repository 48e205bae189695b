"""One click type per kind of number or time a user gives (a flag or an environment variable),
each range-checked when parsed: a value out of range is a usage error (exit 2) in every verb,
never a traceback or a silent default. Counts use ``click.IntRange`` with both bounds.
"""

from __future__ import annotations

import math
from datetime import datetime, timedelta
from typing import Any

import click


class _Clock(click.ParamType[Any]):
    """A :mod:`hcdf_trust.clock` parser as a click type (its ValueError: exit 2, its message)."""

    def parse(self, text: str) -> Any:
        raise NotImplementedError

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        if not isinstance(value, str):
            return value  # a default already converted
        try:
            return self.parse(value)
        except ValueError as exc:
            self.fail(str(exc), param, ctx)


class UtcTime(_Clock):
    """``--now``: an ISO 8601 time with a zone, 1970 to 2999."""

    name = "time"

    def parse(self, text: str) -> datetime:
        from ..clock import parse_time

        return parse_time(text)


class EpochTime(_Clock):
    """``SOURCE_DATE_EPOCH``: seconds since 1970, digits only, up to 2999."""

    name = "seconds"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        try:
            return super().convert(value, param, ctx)
        except click.BadParameter as exc:
            source = ctx.get_parameter_source(param.name) if ctx is not None and param and param.name else None
            if source is click.core.ParameterSource.ENVIRONMENT:
                exc.message = f"SOURCE_DATE_EPOCH: {exc.message}"  # type: ignore[misc]  # Final in the stubs
            raise

    def parse(self, text: str) -> datetime:
        from ..clock import parse_epoch

        return parse_epoch(text)


class Duration(_Clock):
    """``--overlap``, ``--expires``: seconds or 30m / 12h / 7d / 2w, from ``min`` to ``max``
    (at most 100 years)."""

    name = "duration"

    def __init__(self, *, min: timedelta = timedelta(0), max: timedelta | None = None) -> None:
        self.min = min
        self.max = max

    def parse(self, text: str) -> timedelta:
        from ..clock import parse_duration

        delta = parse_duration(text)
        if self.max is not None and delta > self.max:
            raise ValueError(f"{text!r} is longer than {_days(self.max)}")
        if delta < self.min:
            raise ValueError(f"{text!r} is shorter than {self.min}")
        return delta


class Seconds(click.ParamType[float]):
    """A timeout: a finite number of seconds in (0, ``max``]."""

    name = "seconds"

    def __init__(self, max: float = 3600.0) -> None:
        self.max = max

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> float:
        try:
            seconds = float(value)
        except (TypeError, ValueError):
            self.fail(f"{value!r} is not a number of seconds", param, ctx)
        if not math.isfinite(seconds) or not 0 < seconds <= self.max:
            self.fail(f"{value!r} is not a number of seconds in (0, {self.max:g}]", param, ctx)
        return seconds


def _days(delta: timedelta) -> str:
    years, days = divmod(delta.days, 365)
    return f"{years} years" if years >= 1 and days < 30 else f"{delta.days} days"


UTC_TIME = UtcTime()
EPOCH_TIME = EpochTime()
TIMEOUT = Seconds()


def source_date_epoch_option(func: Any) -> Any:
    """``--source-date-epoch`` [env: SOURCE_DATE_EPOCH] of the verbs that date what they write."""
    return click.option(
        "--source-date-epoch",
        "source_date",
        type=EPOCH_TIME,
        envvar="SOURCE_DATE_EPOCH",
        metavar="SECONDS",
        help="Date outputs with this time, in seconds since 1970, for reproducible builds [env: SOURCE_DATE_EPOCH].",
    )(func)
