"""The fleet: a signed ``fleet status`` report (host-attested, see :mod:`hcdf_trust.fleet.report`)
says each comp's device runs the release; every comp it shows otherwise, or leaves out, is
a finding. The report is verified with the host's public key first (a bad signature is an
integrity finding) and must be about this description and, given ``--release``, this release.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from ..errors import HcdfTrustError
from .report import Report

if TYPE_CHECKING:
    from ..ota import suit


def check(report: Report, res: Any, release: suit.Release | None, path: str, key: str) -> None:
    from ..fleet import report as fleet_report
    from ..fleet.status import root_sha256
    from ..ota.keys import load_public

    try:
        statement = fleet_report.read(path, load_public(key))
    except HcdfTrustError as exc:
        if exc.exit_code == 1:
            report.add_error(exc)
            return
        raise
    about = statement.get("description", {}).get("sha256") if isinstance(statement.get("description"), dict) else None
    doc_sha = root_sha256(res)
    if about != doc_sha:
        report.add(
            "fleet-report-stale",
            f"the fleet report is about another description (sha256 {str(about)[:16]}…, this one {doc_sha[:16]}…)",
            file=path,
            line=None,
        )
    rel: dict[str, Any] = statement["release"] if isinstance(statement.get("release"), dict) else {}
    if release is not None and (rel.get("sequence_number"), rel.get("lock_sha256")) != (
        release.sequence_number,
        release.lock_sha256,
    ):
        report.add(
            "fleet-report-stale",
            f"the fleet report checked release {rel.get('sequence_number')}, not release {release.sequence_number}",
            file=path,
            line=None,
        )
    seen: set[str] = set()
    for d in statement["devices"]:
        comp, verdict = d["comp"], d["verdict"]
        seen.add(comp)
        if verdict != "current":
            reason = d.get("reason") if isinstance(d.get("reason"), str) else ""
            report.add(
                "fleet-device",
                f"comp {comp!r} ({d.get('device')}): {verdict}: {reason} (as reported by the device, unauthenticated)",
                file=path,
                line=None,
            )
    if release is not None:
        wanted = {name for c in release.components if c.type == "mcuboot" for name in c.comps}
        for comp in sorted(wanted - seen):
            report.add("fleet-device", f"comp {comp!r}: not in the fleet report", file=path, line=None)
