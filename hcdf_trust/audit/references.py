"""References: unpinned, weak pins, plain http, the lock file (missing entries, drift).

Everything is read from the :class:`~hcdf_trust.include.resolver.Resolution` of the tree
(its ``unpinned``/``weak-pin`` notices, its artifacts) and compared with the lock by
:func:`hcdf_trust.include.lockfile.compare`; nothing is parsed here.
"""

from __future__ import annotations

from urllib.parse import urlsplit

from ..document import FOREIGN_MAJOR
from ..errors import LockDriftError, UnpinnedError
from ..include import lockfile
from ..include.locate import display_path
from ..include.resolver import MESH_WITHOUT_SHA, Resolution
from .report import Report

# resolver notice code -> check
_NOTICES = {"unpinned": "unpinned", "weak-pin": "weak-pin", FOREIGN_MAJOR: "foreign-major-version"}


def check(report: Report, res: Resolution, lock: lockfile.Lock | None) -> None:
    """Add the reference findings of ``res``; ``lock`` is the tree's lock file, if it has one."""
    for notice in res.warnings:
        name = _NOTICES.get(notice.code)
        if notice.code == MESH_WITHOUT_SHA and notice.url is not None:  # a mesh no lock entry pins yet
            name = "unpinned" if lock is None or res.lock_url(notice.url) not in lock.entries else None
        if name is not None:
            report.add_notice(name, notice)
    for art in res.artifacts.values():
        remote = art.location.remote or art.url
        if urlsplit(remote).scheme == "http":
            for use in art.uses:
                report.add(
                    "plain-http",
                    f"{use.ref.uri} is fetched over plain http (no transport security)",
                    file=use.doc,
                    line=use.ref.line,
                )
    if res.bundle is not None:  # a bundle is its own lock: every pin in it is full, or an error
        for error in res.errors:
            report.add_error(error)
        return
    _lock(report, res, lock)
    for error in res.errors:
        if not isinstance(error, LockDriftError | UnpinnedError):  # the lock is compared below, once
            report.add_error(error)


def _lock(report: Report, res: Resolution, lock: lockfile.Lock | None) -> None:
    if lock is None:
        report.add(
            "not-locked",
            f"no lock file ({display_path(res.lock_path)}): nothing pins the unpinned references",
            file=res.root.source,
            line=None,
        )
        return
    actual = {e.url: e for e in res.lock_entries()}
    failed = {res.lock_url(a.url) for a in res.artifacts.values() if a.sha256 is None}  # not checked: errors
    locked = {url: e for url, e in lock.entries.items() if url not in failed}
    where = {res.lock_url(a.url): (a.uses[0].doc, a.uses[0].ref.line) for a in res.artifacts.values()}
    for drift in lockfile.compare(locked, actual, lock_path=display_path(res.lock_path), where=where):
        name = "not-locked" if drift.url not in locked else "lock-drift"
        text = drift.message
        if drift.expected is not None:
            text += f" (locked {drift.expected}, now {drift.actual})"
        report.add(name, text, file=drift.file, line=drift.line)
