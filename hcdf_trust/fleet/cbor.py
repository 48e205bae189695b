"""Bounded decoding of the CBOR a device sends: a device is hostile input.

cbor2 decodes whatever it is given: tags it knows are turned into Python objects
(bigfloats computed, shared references that make a small frame a huge graph), nesting
ends in RecursionError, and duplicate map keys silently keep the last. So every SMP body
is first walked here without building anything — one top-level item, at most
``MAX_ITEMS`` items and ``MAX_DEPTH`` nested containers, no tags, no indefinite-length
strings, map keys that are text or integers and unique, no trailing bytes — and only then
handed to cbor2, which can then build nothing surprising.
"""

from __future__ import annotations

from typing import Any

from ..errors import counted

MAX_ITEMS = 4096
MAX_DEPTH = 8
_INDEFINITE = -1


class CborError(ValueError):
    """The bytes are not CBOR this module accepts (the message says why and where)."""


class _Container:
    __slots__ = ("remaining", "is_map", "seen", "index")

    def __init__(self, remaining: int, is_map: bool) -> None:
        self.remaining = remaining  # items still expected; _INDEFINITE until a break
        self.is_map = is_map
        self.seen: set[tuple[int, Any]] = set()
        self.index = 0  # items read so far (even: a map key comes next)


def check(data: bytes, *, max_items: int = MAX_ITEMS, max_depth: int = MAX_DEPTH) -> None:
    """Raise :class:`CborError` unless ``data`` is exactly one well-formed item within the bounds."""
    n = len(data)
    i = 0
    items = 0
    stack: list[_Container] = [_Container(1, False)]
    while stack:
        top = stack[-1]
        if top.remaining == 0:
            stack.pop()
            continue
        if i >= n:
            raise CborError(f"truncated at byte {i}")
        start = i
        initial = data[i]
        i += 1
        if initial == 0xFF:
            if top.remaining != _INDEFINITE or len(stack) == 1:
                raise CborError(f"unexpected break at byte {start}")
            if top.is_map and top.index % 2:
                raise CborError(f"map without a value for its last key at byte {start}")
            stack.pop()
            continue
        major, info = initial >> 5, initial & 0x1F
        items += 1
        if items > max_items:
            raise CborError(f"more than {max_items} items")
        arg: int | None
        if info < 24:
            arg = info
        elif info <= 27:
            size = 1 << (info - 24)
            if i + size > n:
                raise CborError(f"truncated at byte {i}")
            arg = int.from_bytes(data[i : i + size], "big")
            i += size
        elif info == 31 and major in (4, 5):
            arg = None
        else:
            raise CborError(f"reserved or indefinite-length encoding (0x{initial:02x}) at byte {start}")
        if major == 6:
            raise CborError(f"tag {arg} at byte {start}: no tags are accepted")
        if major in (2, 3):
            assert arg is not None
            if arg > n - i:
                raise CborError(f"string of {arg} bytes at byte {start} runs past the end")
            i += arg
        is_key = top.is_map and top.index % 2 == 0
        top.index += 1
        if top.remaining != _INDEFINITE:
            top.remaining -= 1
        if is_key:
            if major not in (0, 1, 3) or arg is None:
                raise CborError(f"map key at byte {start} is neither text nor an integer")
            # by value, not by encoding: 0x61 'a' and 0x78 0x01 'a' are the same key to cbor2
            key = (major, data[i - arg : i] if major == 3 else arg)
            if key in top.seen:
                raise CborError(f"duplicate map key at byte {start}")
            top.seen.add(key)
        if major in (4, 5):
            if len(stack) > max_depth:
                raise CborError(f"nested deeper than {max_depth} at byte {start}")
            if arg is None:
                stack.append(_Container(_INDEFINITE, major == 5))
            else:
                count = arg * 2 if major == 5 else arg
                if count > n - i:  # every item takes at least one byte
                    raise CborError(f"container of {arg} items at byte {start} runs past the end")
                stack.append(_Container(count, major == 5))
    if i != n:
        raise CborError(f"{counted(n - i, 'byte')} after the item")


def loads(data: bytes, *, max_items: int = MAX_ITEMS, max_depth: int = MAX_DEPTH) -> Any:
    """The item ``data`` holds, checked by :func:`check` first.

    Raises:
        CborError: malformed, out of bounds, or rejected by cbor2 (invalid UTF-8, …).
    """
    import cbor2

    check(data, max_items=max_items, max_depth=max_depth)
    try:
        return cbor2.loads(data)
    except (cbor2.CBORDecodeError, ValueError, RecursionError, OverflowError) as exc:
        raise CborError(str(exc)) from None
