"""Streaming SHA-256 and pin parsing (full digest vs weak prefix)."""

from __future__ import annotations

import hashlib
import os
import re
import threading
from collections.abc import Iterable
from dataclasses import dataclass, field
from enum import Enum
from typing import Protocol

from .errors import MalformedDigestError, redact

FULL_HEX = 64
# The shortest prefix accepted as a (weak) pin: the 8 hex digits (32 bits) that
# CogniPilot devices report for their firmware and that hcdf_models puts in file names.
MIN_WEAK_HEX = 8
CHUNK = 1 << 20
# Below this size one read() beats a chunk loop (no buffer set-up; notes/env.md §2).
SMALL_FILE = 64 << 10

_HEX = frozenset("0123456789abcdef")
_CANONICAL_PIN = re.compile(rf"[0-9a-f]{{{MIN_WEAK_HEX},{FULL_HEX}}}\Z")
#: What a malformed ``sha`` should have been, for ``expected`` in its error.
PIN_FORMAT = f"{FULL_HEX} hex digits (a SHA-256), or {MIN_WEAK_HEX} to {FULL_HEX - 1} for a weak prefix"


class PinStrength(str, Enum):
    FULL = "full"
    WEAK = "weak"


@dataclass(frozen=True)
class Pin:
    """A digest written in a document: a full SHA-256 or a hex prefix of one."""

    hex: str  # lower case

    @property
    def strength(self) -> PinStrength:
        return PinStrength.FULL if len(self.hex) == FULL_HEX else PinStrength.WEAK

    @property
    def is_full(self) -> bool:
        return len(self.hex) == FULL_HEX

    def matches(self, sha256_hex: str) -> bool:
        return sha256_hex.startswith(self.hex)


def parse_pin(
    text: str | None,
    *,
    file: str | None = None,
    line: int | None = None,
    uri: str | None = None,
    element: str | None = None,
) -> Pin | None:
    """Parse a ``sha`` attribute (or, with ``element="hash"``, the text of ``<hash>``, which
    messages then name as the element it is). ``None`` or blank means unpinned.

    ``uri`` names the reference the digest pins, for the message; ``actual`` is the
    attribute exactly as written.

    Raises:
        MalformedDigestError: not hex, longer than 64 digits or shorter than 8.
    """
    if text is None:
        return None
    if _CANONICAL_PIN.match(text):  # as render and pin write it: nothing to strip or lower
        return Pin(text)
    value = text.strip().lower()
    if not value:
        return None
    if value.startswith("sha256:"):
        value = value[len("sha256:") :]
    about = f"{redact(uri)}: " if uri else ""
    written = f"<{element}>{text}</{element}>" if element else f'sha="{text}"'
    if not set(value) <= _HEX:
        raise MalformedDigestError(
            f"{about}{written} is not a hex SHA-256 digest",
            file=file,
            line=line,
            expected=PIN_FORMAT,
            actual=text,
        )
    if len(value) > FULL_HEX or len(value) < MIN_WEAK_HEX:
        raise MalformedDigestError(
            f"{about}{written} has {len(value)} hex digits: a SHA-256 pin has 64 "
            f"(or at least {MIN_WEAK_HEX} for a weak prefix)",
            file=file,
            line=line,
            expected=PIN_FORMAT,
            actual=text,
        )
    return Pin(value)


PREFIX = "sha256:"


def prefixed_style(pins: Iterable[str | None]) -> bool:
    """Whether new pins of a document are written ``sha256:<hex>`` (else bare hex).

    The rule of ``pin --write``: a document whose existing pins (``sha`` attributes, blank
    ones ignored) are *all* ``sha256:``-prefixed gets prefixed new pins, as upstream's
    ``hcdf`` writes them; a document with no pin, or with some bare ones, gets bare hex,
    the form the 1.0 schema documents and every reader accepts. A replaced pin keeps its
    own style.
    """
    written = [p.strip().lower() for p in pins if p is not None and p.strip()]
    return bool(written) and all(p.startswith(PREFIX) for p in written)


def include_mismatch_hint(uri: str, root: str = "ROBOT.hcdf") -> str:
    """What an ``<include sha>`` mismatch may mean, and how to re-pin the bytes.

    Upstream's ``hcdf`` (hcdformat 05d27b58, ``content_sha_of_module``) accepts as an
    include pin either the SHA-256 of the file's bytes or that of its own canonical
    re-serialization of the module, and may write the latter. hcdf-trust pins bytes only:
    a canonical-form pin is a mismatch here, on purpose (the re-serialization is not a
    stable function of the bytes).
    """
    return (
        f"the included file changed since it was pinned; if the change is intended, re-pin it with "
        f"`hcdf-trust pin --write --update {redact(uri)} {redact(root)}` (a pin written by upstream `hcdf` may "
        "be a canonical-form pin, the SHA-256 of its re-serialization rather than of the bytes: re-pin it the same way)"
    )


def is_full_sha256(text: str) -> bool:
    return len(text) == FULL_HEX and set(text) <= _HEX


@dataclass(frozen=True)
class Hashed:
    sha256: str
    size: int
    # (st_dev, st_ino) of the local file the bytes were read from, when known: lets
    # output planning compare a destination with this input without another stat.
    inode: tuple[int, int] | None = field(default=None, compare=False)


def hash_bytes(data: bytes) -> Hashed:
    return Hashed(hashlib.sha256(data).hexdigest(), len(data))


_tls = threading.local()


def _buffer() -> memoryview:
    """This thread's reusable read buffer.

    Allocating (and zeroing) a fresh 1 MiB buffer per file costs more than hashing
    a small file, and it is done while holding the GIL; one buffer per thread is
    safe because nothing here keeps a view of it past a call.
    """
    view: memoryview | None = getattr(_tls, "view", None)
    if view is None:
        view = _tls.view = memoryview(bytearray(CHUNK))
    return view


class ByteSink(Protocol):
    """Where :func:`hash_chunks` copies the bytes: a binary file, a buffer."""

    def write(self, data: bytes, /) -> object: ...


class Sha256(Protocol):
    """A SHA-256 being fed: ``hashlib.sha256()``, or an object that hashes the same bytes and
    learns more from them on the way (:class:`~hcdf_trust.ota.mcuboot.ImageStream`)."""

    def update(self, data: bytes, /) -> None: ...

    def hexdigest(self) -> str: ...


def hash_chunks(
    chunks: Iterable[bytes], *, sink: ByteSink | None = None, limit: int | None = None, sha256: Sha256 | None = None
) -> Hashed:
    """Hash an iterator of byte chunks (e.g. an HTTP body) in constant memory, optionally copying
    them to ``sink``; ValueError past ``limit`` bytes (the caller names the file). ``sha256``:
    the hash to feed (default: a new ``hashlib.sha256()``)."""
    h = sha256 if sha256 is not None else hashlib.sha256()
    size = 0
    for chunk in chunks:
        size += len(chunk)
        if limit is not None and size > limit:
            raise ValueError(f"larger than the {limit}-byte limit")
        h.update(chunk)
        if sink is not None:
            sink.write(chunk)
    return Hashed(h.hexdigest(), size)


def read_small(fd: int, size: int) -> bytes:
    """Read a regular file of about ``size`` bytes to its end, usually in one call.

    A short read from a regular file means end of file on Linux, so asking for one
    byte more than the expected size saves the extra read that would return b"".
    A file that grew meanwhile is read on to its (new) end.
    """
    data = os.read(fd, size + 1)
    if len(data) <= size:
        return data
    parts = [data]
    while more := os.read(fd, CHUNK):
        parts.append(more)
    return b"".join(parts)


def hash_fd(fd: int, *, size: int | None = None, inode: tuple[int, int] | None = None) -> Hashed:
    """Hash an open file descriptor from its current position to end of file.

    Reads straight from ``fd`` (no duplicate descriptor, no file object): small
    files in one read, larger ones with ``readv`` into this thread's buffer. Both
    the reads and the hash updates run without the GIL, so threads hash in parallel.
    ``inode`` is recorded in the result (see :class:`Hashed`).
    """
    if size is None:
        size = os.fstat(fd).st_size
    if size <= SMALL_FILE:
        data = read_small(fd, size)
        return Hashed(hashlib.sha256(data).hexdigest(), len(data), inode)
    h = hashlib.sha256()
    view = _buffer()
    size = 0
    while n := os.readv(fd, [view]):
        size += n
        h.update(view[:n])
    return Hashed(h.hexdigest(), size, inode)
