"""``ota.toml``: how each ``<software>`` entry becomes an image, and per-board image settings.

```toml
[release]
base_url = "https://firmware.example.com/"   # --base-url wins
changelog = "default changelog"             # --changelog wins
sequence_number = 12                        # default: the previous release's + 1, else 1

[boards.default]         # every board, unless its own table says otherwise
header_size = 0x200      # MCUboot header (imgtool -H); the binary gets it prepended
slot_size = 0            # 0: no slot-size check (imgtool -S)
align = 4                # flash write alignment (imgtool --align): 1, 2, 4, 8, 16 or 32
max_align = 8            # optional (imgtool --max-align)

[images.arm-ctrl]        # keyed by <software name>
type = "mcuboot"         # or "raw": listed in the manifest, no MCUboot header
file = "arm/app.hex"     # relative to --firmware-dir; default {board}/{app}.bin|.hex, then {app}.bin|.hex
mcuboot_version = "1.4.2+7"   # instead of the normalised <version>
security_counter = 9     # or "auto" (default): (major << 24) | (minor << 16) | revision
changelog = "..."
dependencies = [{ image = 1, version = "2.0.0" }]   # MCUboot dependency TLVs (multi-core)
exclude = true           # not part of the release (reported as excluded)
```
Unknown keys are refused: a typo must not silently fall back to a default.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, replace
from typing import Any

from ..localfile import read_toml
from .errors import OtaConfigError

MAX_CONFIG_BYTES = 1 << 20
ALIGNMENTS = (1, 2, 4, 8, 16, 32)


@dataclass(frozen=True)
class BoardSettings:
    header_size: int = 0x200
    slot_size: int = 0
    align: int = 4
    max_align: int | None = None


@dataclass(frozen=True)
class Dependency:
    image: int
    version: str


@dataclass(frozen=True)
class ImageSettings:
    type: str = "mcuboot"
    file: str | None = None
    mcuboot_version: str | None = None
    security_counter: int | str = "auto"
    changelog: str | None = None
    dependencies: tuple[Dependency, ...] = ()
    exclude: bool = False


@dataclass(frozen=True)
class OtaConfig:
    source: str | None = None
    base_url: str | None = None
    changelog: str | None = None
    sequence_number: int | None = None
    boards: dict[str, BoardSettings] = field(default_factory=dict)
    images: dict[str, ImageSettings] = field(default_factory=dict)

    def board(self, name: str) -> BoardSettings:
        return self.boards.get(name) or self.boards.get("default") or BoardSettings()

    def image(self, app: str) -> ImageSettings:
        return self.images.get(app) or ImageSettings()


def load_config(path: str | os.PathLike[str] | None) -> OtaConfig:
    """Read and check ``ota.toml``; ``None`` gives the defaults.

    Raises:
        OtaConfigError: not TOML, an unknown key, a wrong type or an impossible value.
        NotFoundError / InputError: unreadable or not a regular file.
    """
    if path is None:
        return OtaConfig()
    shown = os.fspath(path)
    doc = read_toml(shown, limit=MAX_CONFIG_BYTES, what="ota.toml", error=OtaConfigError)
    _keys(doc, {"release", "boards", "images"}, shown, "the top level")
    release = _table(doc, "release", shown)
    _keys(release, {"base_url", "changelog", "sequence_number"}, shown, "[release]")
    seq = _opt(release, "sequence_number", int, shown, "[release]")
    if seq is not None and not 0 <= seq < 2**63:
        raise OtaConfigError("[release] sequence_number must be ≥ 0", file=shown, actual=str(seq))
    defaults = BoardSettings()
    boards: dict[str, BoardSettings] = {}
    raw_boards = _table(doc, "boards", shown)
    if "default" in raw_boards:
        defaults = _board(_table(raw_boards, "default", shown), defaults, shown, "[boards.default]")
        boards["default"] = defaults
    for name in raw_boards:
        if name != "default":
            boards[name] = _board(_table(raw_boards, name, shown), defaults, shown, f"[boards.{name}]")
    images = {
        name: _image(_table(_table(doc, "images", shown), name, shown), shown, f"[images.{name}]")
        for name in _table(doc, "images", shown)
    }
    return OtaConfig(
        source=shown,
        base_url=_opt(release, "base_url", str, shown, "[release]"),
        changelog=_opt(release, "changelog", str, shown, "[release]"),
        sequence_number=seq,
        boards=boards,
        images=images,
    )


def _board(t: dict[str, Any], base: BoardSettings, shown: str, where: str) -> BoardSettings:
    _keys(t, {"header_size", "slot_size", "align", "max_align"}, shown, where)
    out = base
    for key in ("header_size", "slot_size", "align", "max_align"):
        value = _opt(t, key, int, shown, where)
        if value is not None:
            out = replace(out, **{key: value})
    if not 0 <= out.header_size <= 0xFFFF or out.header_size % 4:
        raise OtaConfigError(
            f"{where} header_size must be a multiple of 4 below 65536", file=shown, actual=str(out.header_size)
        )
    if out.slot_size < 0:
        raise OtaConfigError(f"{where} slot_size must be ≥ 0", file=shown, actual=str(out.slot_size))
    for key in ("align", "max_align"):
        value = getattr(out, key)
        if value is not None and value not in ALIGNMENTS:
            raise OtaConfigError(f"{where} {key} must be one of {ALIGNMENTS}", file=shown, actual=str(value))
    return out


def _image(t: dict[str, Any], shown: str, where: str) -> ImageSettings:
    allowed = {"type", "file", "mcuboot_version", "security_counter", "changelog", "dependencies", "exclude"}
    _keys(t, allowed, shown, where)
    kind = _opt(t, "type", str, shown, where) or "mcuboot"
    if kind not in ("mcuboot", "raw"):
        raise OtaConfigError(f'{where} type must be "mcuboot" or "raw"', file=shown, actual=kind)
    counter: int | str = "auto"
    if "security_counter" in t:
        value = t["security_counter"]
        if value != "auto" and (type(value) is not int or not 0 <= value < 2**32):
            raise OtaConfigError(
                f'{where} security_counter must be "auto" or an integer 0..2^32-1', file=shown, actual=repr(value)
            )
        counter = value
    deps = []
    raw_deps = t.get("dependencies", [])
    if not isinstance(raw_deps, list):
        raise OtaConfigError(f"{where} dependencies must be a list of tables", file=shown)
    for dep in raw_deps:
        if not isinstance(dep, dict):
            raise OtaConfigError(f"{where} dependencies must be a list of tables", file=shown)
        _keys(dep, {"image", "version"}, shown, f"{where} dependencies")
        image = _opt(dep, "image", int, shown, where)
        version = _opt(dep, "version", str, shown, where)
        if image is None or version is None or not 0 <= image <= 255:
            raise OtaConfigError(
                f"{where} each dependency needs image (0..255) and version", file=shown, actual=repr(dep)
            )
        deps.append(Dependency(image, version))
    exclude = t.get("exclude", False)
    if type(exclude) is not bool:
        raise OtaConfigError(f"{where} exclude must be true or false", file=shown, actual=repr(exclude))
    return ImageSettings(
        type=kind,
        file=_opt(t, "file", str, shown, where),
        mcuboot_version=_opt(t, "mcuboot_version", str, shown, where),
        security_counter=counter,
        changelog=_opt(t, "changelog", str, shown, where),
        dependencies=tuple(deps),
        exclude=exclude,
    )


def _table(doc: dict[str, Any], key: str, shown: str) -> dict[str, Any]:
    value = doc.get(key, {})
    if not isinstance(value, dict):
        raise OtaConfigError(f"{key} must be a table", file=shown, actual=type(value).__name__)
    return value


def _keys(t: dict[str, Any], allowed: set[str], shown: str, where: str) -> None:
    unknown = sorted(set(t) - allowed)
    if unknown:
        raise OtaConfigError(
            f"unknown key {unknown[0]!r} in {where}", file=shown, expected=", ".join(sorted(allowed)), actual=unknown[0]
        )


def _opt(t: dict[str, Any], key: str, kind: type, shown: str, where: str) -> Any:
    if key not in t:
        return None
    value = t[key]
    if type(value) is not kind:
        raise OtaConfigError(
            f"{where} {key} must be a {kind.__name__}",
            file=shown,
            expected=kind.__name__,
            actual=f"{type(value).__name__} {value!r}",
        )
    return value
