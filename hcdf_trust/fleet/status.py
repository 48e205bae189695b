"""``fleet status``: for each comp with ``<software>``, ask its MCU over SMP what it runs
and judge that against the verified release (:mod:`.state`).

Steps: the description tree resolves under its lock (as ``ota build`` reads it); the
release verifies exactly as ``ota verify`` (and each ``--previous`` release's manifest with
the same key); then the devices are asked in parallel, at most ``jobs`` at once, each
request with a timeout. A device that cannot be reached or says something that cannot be
interpreted gets a verdict (``unreachable``, ``malformed-answer``), never a guess.
"""

from __future__ import annotations

import asyncio
from dataclasses import dataclass, field
from typing import Any

from ..errors import HcdfTrustError, IntegrityError, Notice
from ..ota import suit
from . import state
from .smp import DeviceError, DeviceMalformed, DeviceRefused, DeviceUnreachable, Endpoint, parse_endpoint

DEFAULT_JOBS = 16
DEFAULT_TIMEOUT = 5.0


class FleetIntegrityError(IntegrityError):
    code = "fleet"


@dataclass(frozen=True)
class Target:
    """One comp whose MCU is asked: where it is described, what the release says it runs."""

    comp: str
    file: str
    line: int | None
    component: suit.Component
    endpoint: Endpoint | None
    description_sha: str | None  # SHA-256 of the document that describes this comp (None: not checked)


@dataclass
class DeviceStatus:
    target: Target
    verdict: str
    reason: str
    slots: list[state.Slot] = field(default_factory=list)
    description: state.Description | None = None
    expected: str | None = None
    actual: str | None = None

    def error(self) -> HcdfTrustError | None:
        """The verdict as an error for ``errors`` (None for ``current``)."""
        if self.verdict == state.CURRENT:
            return None
        where = self.target.endpoint.uri if self.target.endpoint else self.target.file
        msg = f"comp {self.target.comp!r} ({self.target.component.name}): {self.verdict}: {self.reason}"
        cls: type[HcdfTrustError] = FleetIntegrityError
        if self.verdict == state.UNREACHABLE:
            cls = DeviceUnreachable
        elif self.verdict == state.MALFORMED:
            cls = DeviceMalformed
        err = cls(msg, file=where, expected=self.expected, actual=self.actual)
        err.code = self.verdict
        return err

    def to_json(self) -> dict[str, Any]:
        c = self.target.component
        return {
            "comp": self.target.comp,
            "component": c.name,
            "device": self.target.endpoint.uri if self.target.endpoint else None,
            "verdict": self.verdict,
            "reason": self.reason,
            "expected": {"version": c.version, "mcuboot_hash": c.mcuboot_hash},
            "slots": [s.to_json() for s in self.slots],
            "description": (
                {"url": self.description.url, "sha256": self.description.sha} if self.description else None
            ),
            "description_expected": self.target.description_sha,
        }


@dataclass
class StatusReport:
    release: suit.Release
    devices: list[DeviceStatus]
    notices: list[Notice]
    resolution: Any = None  # the description tree as resolved (what was read, for outputs to protect)

    @property
    def exit_code(self) -> int:
        """0 only when every comp is current; 1 for an unknown image (or any other verdict
        but the unreadable ones); 3 when a device was unreachable or malformed and nothing
        worse was seen."""
        verdicts = {d.verdict for d in self.devices}
        if verdicts & state.INTEGRITY:
            return 1
        if verdicts & state.UNREADABLE:
            return 3
        return 0 if verdicts <= {state.CURRENT} else 1


def resolve_tree(doc_path: str, tree: Any) -> Any:
    """DOC's tree under its lock, as ``ota build`` reads it (raises ErrorGroup when it does not verify)."""
    from ..errors import ErrorGroup
    from ..include.resolver import resolve

    res = resolve(doc_path, tree.resolve_options(locked=True))
    if not res.ok:
        raise ErrorGroup(res.errors)
    return res


def root_sha256(res: Any) -> str:
    sha = _document_sha(res, res.root_location.url)
    assert sha is not None
    return sha


def targets(
    res: Any, release: suit.Release, devices: dict[str, str], *, check_description: bool
) -> tuple[list[Target], list[Notice]]:
    """The comps to ask, from the verified tree ``res``."""
    from ..document import single, single_text, software_elements
    from ..xml import sourceline

    by_comp: dict[str, suit.Component] = {}
    for c in release.components:
        for name in c.comps:
            by_comp.setdefault(name, c)
    out: list[Target] = []
    notices: list[Notice] = []
    seen: set[str] = set()
    for doc_url, doc in res.documents.items():
        doc_sha = _document_sha(res, doc_url) if check_description else None
        for sw in software_elements(doc):
            comp_el = sw.getparent()
            if comp_el is None or comp_el.tag != "comp":
                continue
            name = comp_el.get("name") or "?"
            line = sourceline(sw)
            component = by_comp.get(name)
            if component is None or component.type != "mcuboot":
                why = "is not in the release" if component is None else "is a raw image (no MCUboot slots to ask)"
                notices.append(Notice("not-asked", f"comp {name!r} {why}", file=doc.source, line=line))
                continue
            seen.add(name)
            uri = devices.get(name)
            if uri is None:
                disc = single(comp_el, "discovered", source=doc.source)
                ip = single_text(disc, "ip", source=doc.source) if disc is not None else None
                port = single_text(disc, "port", source=doc.source) if disc is not None else None
                if ip:
                    host = f"[{ip}]" if ":" in ip else ip
                    uri = f"udp://{host}:{port}" if port else f"udp://{host}"
            ep = parse_endpoint(uri) if uri else None
            out.append(Target(name, doc.source, line, component, ep, doc_sha))
    unknown = sorted(set(devices) - seen)
    if unknown:
        from ..errors import InputError

        raise InputError(f"--device names comps that have no released MCUboot image here: {', '.join(unknown)}")
    return out, notices


def _document_sha(res: Any, doc_url: str) -> str | None:
    artifact = res.artifacts.get(doc_url)
    if artifact is not None and artifact.sha256:
        return str(artifact.sha256)
    if doc_url == res.root_location.url:
        import hashlib

        from ..localfile import read_input

        return hashlib.sha256(read_input(res.root.source, limit=64 << 20, what="description")).hexdigest()
    return None


def earlier_components(previous: list[suit.Release]) -> dict[tuple[str, str], list[tuple[int, suit.Component]]]:
    out: dict[tuple[str, str], list[tuple[int, suit.Component]]] = {}
    for rel in previous:
        for c in rel.components:
            out.setdefault((c.board, c.app), []).append((rel.sequence_number, c))
    return out


async def ask(target: Target, earlier: list[tuple[int, suit.Component]], timeout: float) -> DeviceStatus:
    """Read one device's image state (and HCDF group) and judge it."""
    from smp import image_management as img

    from .smp import MGMT_ERR_ENOTSUP, connect, hcdf_models

    if target.endpoint is None:
        return DeviceStatus(target, state.UNREACHABLE, "no address: give --device COMP=URI or <discovered><ip>")
    try:
        session = await connect(target.endpoint, timeout)
    except DeviceError as exc:
        return DeviceStatus(target, state.UNREACHABLE, exc.message)
    slots: list[state.Slot] = []
    description = None
    try:
        answer = await session.request(img.ImageStatesReadRequest(), img.ImageStatesReadResponse)
        slots = state.slots_from(list(answer.images))
        if target.description_sha is not None:
            request, response = hcdf_models()
            try:
                d = await session.request(request(), response)
                description = state.description_from(d.url, d.sha)
            except DeviceRefused as exc:
                if exc.rc != MGMT_ERR_ENOTSUP:
                    raise
    except DeviceUnreachable as exc:
        return DeviceStatus(target, state.UNREACHABLE, exc.message, slots)
    except DeviceError as exc:
        return DeviceStatus(target, state.MALFORMED, exc.message, slots, expected=exc.expected, actual=exc.actual)
    except state.BadAnswer as exc:
        return DeviceStatus(target, state.MALFORMED, str(exc), slots)
    finally:
        await session.close()
    v = state.judge(slots, target.component, earlier, description, target.description_sha)
    return DeviceStatus(target, v.verdict, v.reason, slots, description, v.expected, v.actual)


async def ask_all(
    todo: list[Target],
    earlier: dict[tuple[str, str], list[tuple[int, suit.Component]]],
    *,
    jobs: int,
    timeout: float,
) -> list[DeviceStatus]:
    """Every target, at most ``jobs`` at once; results in the order of ``todo``."""
    gate = asyncio.Semaphore(jobs)

    async def one(t: Target) -> DeviceStatus:
        async with gate:
            return await ask(t, earlier.get((t.component.board, t.component.app), []), timeout)

    return list(await asyncio.gather(*(one(t) for t in todo)))


def run_status(
    doc_path: str,
    tree: Any,
    release: suit.Release,
    previous: list[suit.Release],
    devices: dict[str, str],
    *,
    jobs: int = DEFAULT_JOBS,
    timeout: float = DEFAULT_TIMEOUT,
    check_description: bool = True,
) -> StatusReport:
    res = resolve_tree(doc_path, tree)
    todo, notices = targets(res, release, devices, check_description=check_description)
    results = asyncio.run(ask_all(todo, earlier_components(previous), jobs=jobs, timeout=timeout))
    return StatusReport(release, results, notices, res)
