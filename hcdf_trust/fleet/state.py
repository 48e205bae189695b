"""What a device reports, and the verdict against the signed release and the description.

Pure: :func:`judge` takes what was read (slots, the HCDF group's answer) and what should
be (the release component, earlier signed releases, the description's digest) and says
one verdict per comp. The device side is unauthenticated: a verdict says what the device
*claims*, checked against what was signed.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Any

from ..ota import suit

# Verdicts (docs/fleet.md). Integrity verdicts exit 1, the unreadable ones 3.
CURRENT = "current"
OUTDATED = "outdated"
PENDING = "pending"
UNCONFIRMED = "unconfirmed"
UNKNOWN_IMAGE = "unknown-image"
WRONG_DESCRIPTION = "wrong-description"
NO_HCDF_GROUP = "no-hcdf-group"
UNREACHABLE = "unreachable"
MALFORMED = "malformed-answer"
VERDICTS = (
    CURRENT,
    OUTDATED,
    PENDING,
    UNCONFIRMED,
    UNKNOWN_IMAGE,
    WRONG_DESCRIPTION,
    NO_HCDF_GROUP,
    UNREACHABLE,
    MALFORMED,
)
INTEGRITY = frozenset({UNKNOWN_IMAGE, WRONG_DESCRIPTION})
UNREADABLE = frozenset({UNREACHABLE, MALFORMED})

HASH_BYTES = 32  # MCUboot's SHA-256 image hash
MAX_VERSION_CHARS = 64
MAX_URL_CHARS = 2048


@dataclass(frozen=True)
class Slot:
    """One entry of the img group's image state, as the device reported it."""

    image: int
    slot: int
    version: str
    hash: str  # hex, checked to be 32 bytes
    active: bool
    confirmed: bool
    pending: bool
    permanent: bool
    bootable: bool

    def to_json(self) -> dict[str, Any]:
        return {
            "image": self.image,
            "slot": self.slot,
            "version": self.version,
            "hash": self.hash,
            "active": self.active,
            "confirmed": self.confirmed,
            "pending": self.pending,
            "permanent": self.permanent,
            "bootable": self.bootable,
        }


@dataclass(frozen=True)
class Description:
    """The HCDF group's answer: the description fragment the firmware was built with."""

    url: str
    sha: str


class BadAnswer(ValueError):
    """A well-formed SMP answer whose content cannot be right (a hash of the wrong length, …)."""


def slots_from(images: list[Any]) -> list[Slot]:
    """Image 0's (or a single-image device's) slots from ``ImageStatesReadResponse.images``.

    Raises:
        BadAnswer: a hash that is not 32 bytes, a version too long, a slot twice.
    """
    out: list[Slot] = []
    seen: set[tuple[int, int]] = set()
    for st in images:
        image = st.image or 0
        if st.hash is None or len(st.hash) != HASH_BYTES:
            got = "none" if st.hash is None else f"{len(st.hash)} bytes"
            raise BadAnswer(f"image {image} slot {st.slot}: image hash of {got}, not {HASH_BYTES} bytes")
        if len(st.version) > MAX_VERSION_CHARS or not st.version.isprintable():
            raise BadAnswer(f"image {image} slot {st.slot}: unreadable version {st.version[:MAX_VERSION_CHARS]!r}")
        if (image, st.slot) in seen:
            raise BadAnswer(f"image {image} slot {st.slot} reported twice")
        seen.add((image, st.slot))
        out.append(
            Slot(
                image,
                st.slot,
                st.version,
                bytes(st.hash).hex(),
                bool(st.active),
                bool(st.confirmed),
                bool(st.pending),
                bool(st.permanent),
                bool(st.bootable),
            )
        )
    return out


def description_from(url: str, sha: str) -> Description:
    """Raises BadAnswer unless ``sha`` is 64 hex digits and ``url`` a printable, bounded text."""
    if len(url) > MAX_URL_CHARS or not url.isprintable():
        raise BadAnswer("HCDF group: unreadable url")
    text = sha.strip().lower()
    if len(text) != 64 or any(ch not in "0123456789abcdef" for ch in text):
        raise BadAnswer(f"HCDF group: sha is not 64 hex digits ({len(sha)} characters)")
    return Description(url, text)


@dataclass
class Verdict:
    verdict: str
    reason: str
    expected: str | None = None
    actual: str | None = None
    notes: list[str] = field(default_factory=list)


def judge(
    slots: list[Slot],
    component: suit.Component,
    earlier: list[tuple[int, suit.Component]],
    description: Description | None,
    description_sha: str | None,
) -> Verdict:
    """The verdict for one comp. ``earlier``: (sequence number, component) of the same
    board/app in previous signed releases; ``description_sha``: the SHA-256 the robot
    description holds for the document this comp is in (None: not checked)."""
    want = component.mcuboot_hash
    active = [s for s in slots if s.image == 0 and s.active]
    if len(active) != 1:
        return Verdict(MALFORMED, f"{len(active)} active images reported for image 0")
    run = active[0]
    others = [s for s in slots if s.image == 0 and not s.active]
    old = {c.mcuboot_hash: seq for seq, c in earlier if c.mcuboot_hash}
    if run.hash == want:
        if version_tuple(run.version) != version_tuple(component.version):
            return Verdict(
                UNKNOWN_IMAGE,
                "the release's image hash, reported with another version (the device is lying or broken)",
                expected=component.version,
                actual=run.version,
            )
        for s in others:
            if s.pending and s.hash != want:
                return _pending_other(s, want, old)
        if not run.confirmed:
            return Verdict(
                UNCONFIRMED,
                "runs the release but has not confirmed it: it reverts to the previous image on the next reset",
            )
        if description_sha is None:
            return Verdict(CURRENT, "runs the release's image, confirmed")
        if description is None:
            return Verdict(
                NO_HCDF_GROUP, "runs the release's image, confirmed; cannot say which description it was built for"
            )
        if description.sha != description_sha:
            return Verdict(
                WRONG_DESCRIPTION,
                f"built for another description than the one pinned (device says {description.url})",
                expected=description_sha,
                actual=description.sha,
            )
        return Verdict(CURRENT, "runs the release's image, confirmed, built for the pinned description")
    pending = [s for s in others if s.pending]
    if run.hash in old:
        if pending and pending[0].hash == want:
            return Verdict(PENDING, "the release's image is in slot 1, marked to run on the next reset")
        if pending:
            return _pending_other(pending[0], want, old)
        return Verdict(
            OUTDATED,
            f"runs the image of signed release {old[run.hash]}",
            expected=want,
            actual=run.hash,
        )
    return Verdict(
        UNKNOWN_IMAGE,
        "runs an image that no release signed by this key lists",
        expected=want,
        actual=run.hash,
    )


def _pending_other(s: Slot, want: str | None, old: dict[str, int]) -> Verdict:
    if s.hash in old:
        return Verdict(OUTDATED, f"slot {s.slot} holds the image of signed release {old[s.hash]}, marked to run next")
    return Verdict(
        UNKNOWN_IMAGE,
        f"slot {s.slot} holds an image no signed release lists, marked to run on the next reset",
        expected=want,
        actual=s.hash,
    )


_VERSION = re.compile(r"(\d{1,10})\.(\d{1,10})\.(\d{1,10})(?:[.+](\d{1,10}))?")


def version_tuple(text: str) -> tuple[int, ...] | str:
    """``major.minor.revision`` and the build number, as MCUboot's header holds them; the
    text as written when it is not of that form. Zephyr writes the build as a fourth
    dotted field (``1.2.3.4``), imgtool as ``+4``; a build of 0 may be left out."""
    m = _VERSION.fullmatch(text.strip())
    if m is None:
        return text
    return tuple(int(g) if g is not None else 0 for g in m.groups())
