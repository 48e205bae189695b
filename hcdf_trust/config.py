"""The per-project configuration file, ``hcdf-trust.toml``: the tree options a project would
otherwise repeat on every call (``--base``, ``--mirror``, ``--root``, ``--cache-dir``, a registry,
an audit policy) and the warnings it has acknowledged.

Found the way ``.cargo/config.toml`` and ``pyproject.toml`` are: in the document's folder, else in
the nearest parent folder, stopping after the first folder that is a repository root (holds
``.git``, ``.hg`` or ``.svn``), the home folder, or the filesystem root. So a checkout never
picks up a file from the folder above it or from a shared ``/tmp``. Flags override it; the CLI
applies it (:mod:`hcdf_trust.cli.params`); the library never reads it on its own.

Because it decides where content comes from and what is trusted, the file is refused (exit 3)
when someone other than the user could have written it: owned by another user (root excepted),
writable by others, in a folder others may write into (unless sticky, like ``/tmp``), or a
symbolic link (a link's target is somewhere else, whose folder is not the one it governs).
"""

from __future__ import annotations

import os
import stat
from dataclasses import dataclass, field
from typing import Any

from .errors import InputError, display_path

NAME = "hcdf-trust.toml"
# The environment variable that turns the search off (any non-empty value), as --no-project-config does.
NO_CONFIG_ENV = "HCDF_TRUST_NO_CONFIG"
MAX_CONFIG_BYTES = 64 * 1024
_VCS_MARKERS = (".git", ".hg", ".svn")

# key -> what it holds; "path": a local path, resolved against the config file's folder;
# "location": a folder or an http(s) URL (only the folder is resolved); "mirrors": PREFIX=DIR|URL.
_TOP = {"base": "location", "root": "path", "cache-dir": "path", "mirror": "mirrors"}
_CONFINED = ("base", "root")  # local folders that decide which files local references may read
_TABLES = {
    "registry": {"site": "location", "trusted-root": "path"},
    "audit": {"policy": "path"},
    "warnings": {"acknowledge": "codes"},
}


class ConfigError(InputError):
    """``hcdf-trust.toml`` is unsafe to trust, not TOML, or holds a key or value we do not know."""

    code = "config"


@dataclass(frozen=True)
class ProjectConfig:
    """One ``hcdf-trust.toml``, checked. ``values``: option key (``base``, ``registry.site``, ...)
    -> its value with local paths resolved against :attr:`folder`; ``acknowledge``: warning codes
    the project has acknowledged (not printed; ``--json`` still lists them)."""

    path: str
    values: dict[str, Any] = field(default_factory=dict)
    acknowledge: frozenset[str] = frozenset()

    @property
    def folder(self) -> str:
        return os.path.dirname(self.path) or "."

    @property
    def shown(self) -> str:
        return display_path(self.path)


def find(start: str) -> str | None:
    """The ``hcdf-trust.toml`` that governs folder ``start``, or ``None``. ``start`` itself is
    checked first, then each parent up to the first repository root, the home folder or ``/``."""
    folder = os.path.abspath(start)
    home = os.path.abspath(os.path.expanduser("~"))
    while True:
        candidate = os.path.join(folder, NAME)
        if os.path.lexists(candidate):
            return candidate
        if folder == home or any(os.path.lexists(os.path.join(folder, m)) for m in _VCS_MARKERS):
            return None
        parent = os.path.dirname(folder)
        if parent == folder:
            return None
        folder = parent


def load(path: str) -> ProjectConfig:
    """Read and check the config file at ``path`` (through the bounded TOML reader).

    Raises:
        ConfigError: a symbolic link, writable by someone else, not TOML, an unknown key or a
            value of the wrong type (the message names the file and the key).
        NotFoundError / InputError: unreadable or not a regular file.
    """
    from .localfile import read_toml

    shown = display_path(path)
    _check_owner(path, shown)
    doc = read_toml(path, limit=MAX_CONFIG_BYTES, what=NAME, source=shown, error=ConfigError)
    folder = os.path.dirname(path) or "."
    values: dict[str, Any] = {}
    acknowledge: frozenset[str] = frozenset()
    for key, value in doc.items():
        if key in _TABLES:
            if not isinstance(value, dict):
                raise ConfigError(f"{key!r} must be a table ([{key}])", file=shown, actual=type(value).__name__)
            for sub, subvalue in value.items():
                kind = _TABLES[key].get(sub)
                if kind is None:
                    raise _unknown(shown, f"{key}.{sub}", sorted(_TABLES[key]))
                if kind == "codes":
                    acknowledge = frozenset(_strings(subvalue, shown, f"{key}.{sub}"))
                else:
                    values[f"{key}.{sub}"] = _value(kind, subvalue, folder, shown, f"{key}.{sub}")
        elif key in _TOP:
            values[key] = _value(_TOP[key], value, folder, shown, key)
            if key in _CONFINED:
                _inside_own_folder(values[key], folder, shown, key)
        else:
            raise _unknown(shown, key, sorted([*_TOP, *_TABLES]))
    return ProjectConfig(path=path, values=values, acknowledge=acknowledge)


def _inside_own_folder(value: str, folder: str, shown: str, key: str) -> None:
    """``root`` and a local ``base`` (which ``root`` defaults to) may not lie above the file's
    folder: the file comes with the tree it sits in (perhaps someone else's checkout), so it may
    confine that tree's local references further, never open files above it."""
    if "://" in value:
        return
    real, top = os.path.realpath(value), os.path.realpath(folder)
    if real != top and not real.startswith(top.rstrip(os.sep) + os.sep):
        raise ConfigError(
            f"{key} = {display_path(value)!r} lies outside the folder this file governs ({display_path(top)}): "
            f"a project's config may only keep references inside it; give --{key} on the command line to go wider",
            file=shown,
            expected=f"a folder inside {display_path(top)}",
            actual=display_path(real),
        )


def _unknown(shown: str, key: str, known: list[str]) -> ConfigError:
    return ConfigError(
        f"unknown key {key!r} (known here: {', '.join(known)})", file=shown, expected="a known key", actual=key
    )


def _check_owner(path: str, shown: str) -> None:
    """Refuse a config another user could have written or swapped (see the module docstring)."""
    try:
        st = os.lstat(path)
    except OSError:
        return  # the reader names what is wrong
    if stat.S_ISLNK(st.st_mode):
        raise ConfigError(
            f"{NAME} is a symbolic link ({shown} -> {os.readlink(path)}): the file that decides what is "
            "trusted must be a regular file in the folder it governs (copy it, or pass --no-project-config)",
            file=shown,
        )
    folder = os.path.dirname(os.path.abspath(path))
    dst = os.stat(folder)
    uid = os.getuid()
    why = None
    if st.st_uid not in (uid, 0):
        why = f"it is owned by another user (uid {st.st_uid})"
    elif st.st_mode & stat.S_IWOTH:
        why = f"it is writable by others (mode {stat.S_IMODE(st.st_mode):04o}; run: chmod o-w {shown})"
    elif dst.st_mode & stat.S_IWOTH and not dst.st_mode & stat.S_ISVTX:
        why = f"its folder {display_path(folder)} is writable by others, who could replace it"
    if why is not None:
        raise ConfigError(
            f"{NAME} refused: {why}; it sets where content comes from and what is trusted "
            "(fix its ownership or mode, or pass --no-project-config)",
            file=shown,
        )


def _strings(value: Any, shown: str, key: str) -> list[str]:
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        raise ConfigError(f"{key!r} must be a list of strings", file=shown, actual=repr(value)[:80])
    return list(value)


def _value(kind: str, value: Any, folder: str, shown: str, key: str) -> Any:
    if kind == "mirrors":
        out = []
        for item in _strings(value, shown, key):
            prefix, sep, target = item.partition("=")
            out.append(f"{prefix}={_local(target, folder)}" if sep else item)  # the flag's check names a bad one
        return tuple(out)
    if not isinstance(value, str) or not value:
        raise ConfigError(f"{key!r} must be a non-empty string", file=shown, actual=repr(value)[:80])
    if kind == "location" and "://" in value:
        return value
    return _local(value, folder)


def _local(value: str, folder: str) -> str:
    """A path named relative to the config file's folder (``~`` is the home folder); a URL as it is."""
    return value if "://" in value else os.path.normpath(os.path.join(folder, os.path.expanduser(value)))
