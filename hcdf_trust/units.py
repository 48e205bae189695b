"""Reading quantities with units from HCDF: one function per kind, used by every reader.

:func:`bit_rate` reads every way a data rate is written in HCDF files: the 1.0 schema's
``<speed unit="Mbps">1000</speed>`` (default unit Mb/s), upstream's newer
``<rate nominal="25000000000" unit="bit/s"/>`` and ``<nominal value unit/>``, and what people
write by hand (``unit="Gb/s"``, ``10G``, ``2.5G``, ``10 Gbps``). Anything it cannot read
exactly is a :class:`UnitError`, never "unknown": a caller that needs the rate (the MACsec
packet-number rule) must not skip its check because the unit was spelled differently.
"""

from __future__ import annotations

import functools
import math
import re

# SI prefixes of a rate. Lower-case "m" is mega here: a millibit per second is no link speed,
# and "mbps" is a common spelling of Mb/s.
_PREFIX = {"": 1.0, "k": 1e3, "K": 1e3, "m": 1e6, "M": 1e6, "g": 1e9, "G": 1e9, "t": 1e12, "T": 1e12}
# Bits per second, then bytes per second (an upper-case B): "MB/s" is 8 × "Mb/s".
_BITS = ("bit/s", "bits/s", "b/s", "bps", "bit/sec", "bits/sec")
_BYTES = ("B/s", "Bps", "byte/s", "bytes/s")
_UNIT = re.compile(r"(?P<prefix>[kKmMgGtT]?)(?P<per>" + "|".join(re.escape(u) for u in (*_BITS, *_BYTES)) + ")")
# A value written with its unit in the text: "10G", "2.5G", "10 Gb/s", "100Mbps".
_TEXT = re.compile(r"(?P<value>[0-9]+(?:\.[0-9]+)?(?:[eE][+-]?[0-9]+)?)\s*(?P<unit>[A-Za-z/]*)")


class UnitError(ValueError):
    """A rate that cannot be read: unknown unit, not a positive finite number, or two units."""


def _unit_factor(unit: str) -> float:
    """Bits per second in one ``unit``; a bare prefix (``G`` of ``10G``) is that many bit/s."""
    if unit in _PREFIX and unit:
        return _PREFIX[unit]
    m = _UNIT.fullmatch(unit)
    if m is None:
        raise UnitError(f"unknown data-rate unit {unit!r}")
    factor = _PREFIX[m["prefix"]]
    return factor * 8 if m["per"] in _BYTES else factor


@functools.lru_cache(maxsize=1024)  # a description writes a handful of distinct rates, many times
def bit_rate(text: str | None, unit: str | None, *, default_unit: str = "Mb/s") -> float:
    """The data rate ``text`` (an element's text or an attribute) in ``unit`` (its ``unit``
    attribute, None when absent), in bit/s. Without a unit anywhere, ``default_unit``.

    Raises:
        UnitError: no number, a number that is not positive and finite, an unknown unit, or
            a unit in the text and another in the attribute.
    """
    m = _TEXT.fullmatch((text or "").strip())
    if m is None:
        raise UnitError(f"{(text or '').strip()[:40]!r} is not a data rate")
    value = float(m["value"])
    inline = m["unit"]
    written = (unit or "").strip()
    if inline and written:
        raise UnitError(f"{text!r} carries a unit and unit={written!r} another")
    factor = _unit_factor(inline or written or default_unit)
    rate = value * factor
    if not math.isfinite(rate) or rate <= 0:
        raise UnitError(f"{text!r} is not a positive data rate")
    return rate


def mbps(text: str | None, unit: str | None, *, default_unit: str = "Mb/s") -> float:
    """:func:`bit_rate` in Mb/s."""
    return bit_rate(text, unit, default_unit=default_unit) / 1e6
