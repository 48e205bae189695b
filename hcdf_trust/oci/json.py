"""Strict JSON for what registries and credential helpers send.

A local stand-in until the one strict reader (``localfile.parse_json``, branch ``otaverify``)
is merged: same signature, so the merge replaces the imports and deletes this module.
Refused: duplicate keys (two parsers, two meanings), NaN/Infinity, non-UTF-8, over the limit,
nesting deeper than 64.
"""

from __future__ import annotations

import json
from typing import Any

from ..errors import InputError

MAX_JSON_BYTES = 4 << 20
MAX_DEPTH = 64


class JsonError(InputError):
    code = "json"


def parse_json(data: bytes, *, source: str, what: str = "document", limit: int = MAX_JSON_BYTES) -> Any:
    """Raises JsonError."""
    if len(data) > limit:
        raise JsonError(f"{what} is over the {limit}-byte limit", file=source)
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise JsonError(f"{what} is not UTF-8: {exc.reason} at byte {exc.start}", file=source) from None
    depth = 0
    for ch in text:  # a cheap upper bound of the nesting before json recurses
        if ch in "[{":
            depth += 1
            if depth > MAX_DEPTH:
                raise JsonError(f"{what} nests deeper than {MAX_DEPTH}", file=source)
        elif ch in "]}":
            depth -= 1

    def pairs(items: list[tuple[str, Any]]) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for k, v in items:
            if k in out:
                raise JsonError(f"{what}: key {k!r} appears twice", file=source)
            out[k] = v
        return out

    def constant(token: str) -> None:
        raise JsonError(f"{what}: {token} is not a JSON number", file=source)

    try:
        return json.loads(text, object_pairs_hook=pairs, parse_constant=constant)
    except JsonError:
        raise
    except (ValueError, RecursionError) as exc:
        raise JsonError(f"{what} is not JSON: {exc}", file=source) from None
