"""Helpers shared by the tests/test_kill_*.py files (mutation-testing killers)."""

from __future__ import annotations

import hashlib


def sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def hcdf(body: str, *, name: str = "t") -> str:
    return f'<?xml version="1.0"?>\n<hcdf version="1.0" name="{name}">\n{body}\n</hcdf>\n'


def model(uri: str, pin: str | None = None, *, name: str = "c") -> str:
    sha_attr = f' sha="{pin}"' if pin is not None else ""
    return f'<comp name="{name}"><visual><model uri="{uri}"{sha_attr}/></visual></comp>'


def include(uri: str, pin: str | None = None, *, name: str = "i") -> str:
    sha_attr = f' sha="{pin}"' if pin is not None else ""
    return f'<include uri="{uri}"{sha_attr} name="{name}"/>'


def other_digest(real: str, keep: int) -> str:
    """A full digest that shares ``keep`` leading hex digits with ``real`` and differs after."""
    flipped = "0" if real[keep] != "0" else "1"
    return real[:keep] + flipped + real[keep + 1 :]


def flip_last_byte(data: bytes) -> bytes:
    """Same size, different content."""
    return data[:-1] + bytes([data[-1] ^ 0xFF])
