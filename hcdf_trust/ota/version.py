"""HCDF ``<version>`` text → MCUboot's image-header version ``major.minor.revision+build``.

The header holds u8.u8.u16+u32 and no pre-release part. A leading ``v`` is dropped;
anything else that does not fit (``1.2.3-rc1``, ``v2024.03-rc1``, a calendar
``2026.11`` whose major is over 255) is refused with a message that says to give
``mcuboot_version`` in ``ota.toml``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any

from .errors import FirmwareError

_VERSION = re.compile(r"(0|[1-9][0-9]*)(?:\.(0|[1-9][0-9]*)(?:\.(0|[1-9][0-9]*))?)?(?:\+(0|[1-9][0-9]*))?")
_LIMITS = (("major", 0xFF), ("minor", 0xFF), ("revision", 0xFFFF), ("build", 0xFFFFFFFF))


@dataclass(frozen=True, order=True)
class McubootVersion:
    major: int
    minor: int
    revision: int
    build: int = 0

    def __str__(self) -> str:
        core = f"{self.major}.{self.minor}.{self.revision}"
        return f"{core}+{self.build}" if self.build else core

    def imgtool(self) -> Any:
        """imgtool's ``SemiSemVersion`` for ``Image(version=...)``."""
        from imgtool.version import SemiSemVersion

        return SemiSemVersion(self.major, self.minor, self.revision, self.build)

    @property
    def auto_security_counter(self) -> int:
        """imgtool's ``security_counter='auto'``: ``(major << 24) | (minor << 16) | revision`` (no build)."""
        return (self.major << 24) | (self.minor << 16) | self.revision


def parse_version(
    text: str | None,
    *,
    comp: str,
    app: str,
    file: str | None = None,
    line: int | None = None,
    source: str = "<version>",
) -> McubootVersion:
    """Normalise ``text`` (from ``source``) to an MCUboot version, or say how to fix it.

    Raises:
        FirmwareError: missing, a pre-release or other suffix, leading zeros, or a
            field too large for the header; names the comp and ``mcuboot_version``.
    """
    hint = f"; give mcuboot_version for {app!r} in ota.toml"
    if source != "<version>":
        hint = ""
    if text is None or not text.strip():
        raise FirmwareError(
            f"comp {comp!r}: <software name={app!r}> has no {source}{hint}",
            file=file,
            line=line,
            expected="major.minor.revision+build",
            actual="nothing",
        )
    raw = text.strip()
    body = raw[1:] if raw[:1] in ("v", "V") else raw
    m = _VERSION.fullmatch(body)
    if m is None:
        why = "a pre-release or other suffix has no place in the image header" if "-" in body else "not of that form"
        raise FirmwareError(
            f"comp {comp!r}: {source} {raw!r} does not fit MCUboot's major.minor.revision+build ({why}){hint}",
            file=file,
            line=line,
            expected="major.minor.revision+build (u8.u8.u16+u32)",
            actual=raw,
        )
    parts = [int(g) if g is not None else 0 for g in m.groups()]
    for value, (name, limit) in zip(parts, _LIMITS, strict=True):
        if value > limit:
            raise FirmwareError(
                f"comp {comp!r}: {source} {raw!r} does not fit MCUboot's major.minor.revision+build "
                f"({name} {value} > {limit}){hint}",
                file=file,
                line=line,
                expected=f"{name} at most {limit}",
                actual=raw,
            )
    return McubootVersion(*parts)
