"""``fleet update`` and ``fleet confirm``: put the verified release's image in each
device's secondary slot and mark it; confirm the ones that run it.

Only bytes of the verified release are ever sent (the caller passes them after ``ota
verify``'s checks). The upload resumes where the device says it stopped (SMP answers each
chunk with the offset it wants next; Zephyr answers a first chunk carrying the same
``sha`` with the offset of an interrupted upload); offsets are bounded and must move
forward. After the upload the device must report the release's MCUboot hash in slot 1
before it is marked for test (``--confirm``: permanent).
"""

from __future__ import annotations

import asyncio
import hashlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from ..errors import HcdfTrustError
from . import state
from .smp import DeviceError, DeviceMalformed, DeviceRefused, DeviceUnreachable, Session, connect
from .status import FleetIntegrityError, Target

DEFAULT_UPLOAD_JOBS = 4
DEFAULT_UPLOAD_TIMEOUT = 30.0
MAX_STALLS = 8  # answers in a row that do not move the offset forward

# Outcomes per device
UPDATED = "updated"  # uploaded (or found uploaded) and marked
ALREADY_RUNNING = "already-running"
WOULD_UPDATE = "would-update"  # --dry-run
CONFIRMED = "confirmed"
ALREADY_CONFIRMED = "already-confirmed"
NOT_RUNNING = "not-running-release"
FAILED = "failed"


@dataclass
class Outcome:
    target: Target
    result: str
    detail: str
    sent: int = 0  # bytes uploaded in this run
    error: HcdfTrustError | None = None

    def to_json(self) -> dict[str, Any]:
        return {
            "comp": self.target.comp,
            "component": self.target.component.name,
            "device": self.target.endpoint.uri if self.target.endpoint else None,
            "result": self.result,
            "detail": self.detail,
            "bytes_sent": self.sent,
        }


Progress = Callable[[Target, int, int], None]  # (target, offset, total)


async def _slots(session: Session) -> list[state.Slot]:
    from smp import image_management as img

    answer = await session.request(img.ImageStatesReadRequest(), img.ImageStatesReadResponse)
    try:
        return state.slots_from(list(answer.images))
    except state.BadAnswer as exc:
        raise DeviceMalformed(str(exc), file=session.endpoint.uri) from None


async def _initialize(session: Session) -> None:
    """Size upload chunks to the device's SMP buffer (MCUmgr parameters), when it says."""
    from smp import os_management as osm

    try:
        p = await session.request(osm.MCUMgrParametersReadRequest(), osm.MCUMgrParametersReadResponse)
    except DeviceRefused:
        return  # an older server: the transport's defaults
    if not 64 <= p.buf_size <= 0xFFFF:
        raise DeviceMalformed(f"MCUmgr buffer size {p.buf_size} out of range", file=session.endpoint.uri)
    session.transport.initialize(p.buf_size)


def _chunk_request(off: int, image: bytes, limit: int, first: bool) -> Any:
    """The largest upload request from ``off`` whose frame fits ``limit`` bytes."""
    from smp import image_management as img

    extra: dict[str, Any] = {}
    if first:
        extra = {"len": len(image), "sha": hashlib.sha256(image).digest(), "image": 0}
    size = min(len(image) - off, limit)
    while True:
        req = img.ImageUploadWriteRequest(off=off, data=image[off : off + size], **extra)
        over = len(req.BYTES) - limit
        if over <= 0:
            return req
        if size <= over:
            raise ValueError(f"an SMP buffer of {limit} bytes cannot carry an upload chunk")
        size -= over


async def upload(session: Session, image: bytes, *, progress: Progress | None, target: Target) -> int:
    """Upload ``image`` to image 0's secondary slot, resuming where the device says; the
    bytes sent in this run."""
    from smp import image_management as img

    uri = session.endpoint.uri
    limit = int(session.transport.max_unencoded_size)
    off, sent, stalls = 0, 0, 0
    first = True
    while True:
        try:
            req = _chunk_request(off, image, limit, first)
        except ValueError as exc:
            raise DeviceMalformed(str(exc), file=uri) from None
        answer = await session.request(req, img.ImageUploadWriteResponse)
        got = answer.off
        if not isinstance(got, int) or not 0 <= got <= len(image):
            raise DeviceMalformed(
                "upload answer without a valid offset", file=uri, expected=f"0..{len(image)}", actual=repr(got)
            )
        sent += len(req.data)
        if got <= off and not first:
            stalls += 1
            if stalls > MAX_STALLS:
                raise DeviceMalformed(f"upload does not move forward (offset {got})", file=uri)
        else:
            stalls = 0
        first = False
        off = got
        if progress is not None:
            progress(target, off, len(image))
        if off == len(image):
            if answer.match is False:
                raise FleetIntegrityError("the device says the uploaded image does not match its SHA-256", file=uri)
            return sent


async def update_one(
    target: Target,
    image: bytes,
    *,
    confirm: bool,
    dry_run: bool,
    timeout: float,
    progress: Progress | None = None,
) -> Outcome:
    """Upload, check and mark one device."""
    from smp import image_management as img

    want = target.component.mcuboot_hash
    assert want is not None
    if target.endpoint is None:
        err: HcdfTrustError = DeviceUnreachable(f"comp {target.comp!r}: no address", file=target.file)
        return Outcome(target, FAILED, err.message, error=err)
    try:
        session = await connect(target.endpoint, timeout)
    except DeviceError as exc:
        return Outcome(target, FAILED, exc.message, error=exc)
    uri = target.endpoint.uri
    sent = 0
    try:
        slots = await _slots(session)
        active = next((s for s in slots if s.image == 0 and s.active), None)
        if active is not None and active.hash == want:
            return Outcome(target, ALREADY_RUNNING, f"runs {target.component.version} already")
        staged = next((s for s in slots if s.image == 0 and s.slot == 1 and s.hash == want), None)
        mark = "permanent" if confirm else "test"
        if dry_run:
            what = "is in slot 1 already" if staged else f"would upload {len(image)} bytes to slot 1"
            return Outcome(target, WOULD_UPDATE, f"{target.component.version} {what}, then mark it {mark}")
        if staged is None:
            await _initialize(session)
            sent = await upload(session, image, progress=progress, target=target)
            slots = await _slots(session)
            staged = next((s for s in slots if s.image == 0 and s.slot == 1), None)
            if staged is None or staged.hash != want:
                raise FleetIntegrityError(
                    f"comp {target.comp!r}: after the upload slot 1 does not hold the release's image",
                    file=uri,
                    expected=want,
                    actual=staged.hash if staged else "no slot 1",
                )
        if state.version_tuple(staged.version) != state.version_tuple(target.component.version):
            raise FleetIntegrityError(
                f"comp {target.comp!r}: slot 1 reports another version",
                file=uri,
                expected=target.component.version,
                actual=staged.version,
            )
        answer = await session.request(
            img.ImageStatesWriteRequest(hash=bytes.fromhex(want), confirm=confirm), img.ImageStatesWriteResponse
        )
        marked = next((s for s in state.slots_from(list(answer.images)) if s.image == 0 and s.hash == want), None)
        if marked is None or not marked.pending or (confirm and not marked.permanent):
            raise FleetIntegrityError(
                f"comp {target.comp!r}: the device did not mark the image {mark}",
                file=uri,
                expected=f"pending{', permanent' if confirm else ''}",
                actual="absent" if marked is None else f"pending={marked.pending} permanent={marked.permanent}",
            )
        return Outcome(target, UPDATED, f"{target.component.version} in slot 1, marked {mark}", sent)
    except (DeviceError, FleetIntegrityError) as exc:
        return Outcome(target, FAILED, exc.message, sent, error=exc)
    except state.BadAnswer as exc:
        err = DeviceMalformed(str(exc), file=uri)
        return Outcome(target, FAILED, err.message, sent, error=err)
    finally:
        await session.close()


async def confirm_one(target: Target, *, timeout: float) -> Outcome:
    """Confirm the running image when it is the release's."""
    from smp import image_management as img

    want = target.component.mcuboot_hash
    if target.endpoint is None:
        err: HcdfTrustError = DeviceUnreachable(f"comp {target.comp!r}: no address", file=target.file)
        return Outcome(target, FAILED, err.message, error=err)
    try:
        session = await connect(target.endpoint, timeout)
    except DeviceError as exc:
        return Outcome(target, FAILED, exc.message, error=exc)
    uri = target.endpoint.uri
    try:
        slots = await _slots(session)
        active = next((s for s in slots if s.image == 0 and s.active), None)
        if active is None or active.hash != want:
            err = FleetIntegrityError(
                f"comp {target.comp!r} does not run the release: not confirmed",
                file=uri,
                expected=want,
                actual=active.hash if active else "no active image",
            )
            return Outcome(target, NOT_RUNNING, err.message, error=err)
        if active.confirmed:
            return Outcome(target, ALREADY_CONFIRMED, f"runs {target.component.version}, confirmed")
        answer = await session.request(
            img.ImageStatesWriteRequest(hash=bytes.fromhex(want), confirm=True), img.ImageStatesWriteResponse
        )
        now = next((s for s in state.slots_from(list(answer.images)) if s.image == 0 and s.active), None)
        if now is None or now.hash != want or not now.confirmed:
            raise FleetIntegrityError(f"comp {target.comp!r}: the device did not confirm the image", file=uri)
        return Outcome(target, CONFIRMED, f"runs {target.component.version}, now confirmed")
    except (DeviceError, FleetIntegrityError) as exc:
        return Outcome(target, FAILED, exc.message, error=exc)
    except state.BadAnswer as exc:
        err = DeviceMalformed(str(exc), file=uri)
        return Outcome(target, FAILED, err.message, error=err)
    finally:
        await session.close()


async def run_all(jobs: int, work: Sequence[Callable[[], Any]]) -> list[Outcome]:
    gate = asyncio.Semaphore(jobs)

    async def one(job: Callable[[], Any]) -> Outcome:
        async with gate:
            result: Outcome = await job()
            return result

    return list(await asyncio.gather(*(one(j) for j in work)))


def exit_code(outcomes: list[Outcome]) -> int:
    """1 when any device failed an integrity check or does not run the release (confirm),
    3 when any was unreachable or malformed, else 0."""
    errors = [o.error for o in outcomes if o.error is not None]
    if any(e.exit_code == 1 for e in errors):
        return 1
    return 3 if errors else 0
