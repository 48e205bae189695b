"""``hcdf-trust audit``: is this robot's supply chain sound? One report over the whole tree.

>>> from hcdf_trust.audit import AuditOptions, audit       # doctest: +SKIP
>>> report = audit("robot.hcdf", AuditOptions())           # doctest: +SKIP
>>> report.ok, [str(f) for f in report.findings]           # doctest: +SKIP

The steps, each built on the verb that owns the subject (nothing is parsed twice):

1. Resolve the tree (:func:`hcdf_trust.include.resolve`: offline unless asked, no cache or
   lock written); read its lock with :func:`hcdf_trust.include.lockfile.load`.
2. References (:mod:`.references`), firmware (:mod:`.firmware`, with ``--release`` verified
   by :mod:`hcdf_trust.ota` first, and its provenance by :mod:`hcdf_trust.provenance`), the
   fleet (:mod:`.fleet`, a signed ``fleet status`` report), MACsec (:mod:`.macsec`, on the
   macsec plan and, with a key store, its status), extensions (:mod:`.extensions`, with a registry).
3. Every finding gets its severity from the :class:`~.policy.Policy`; the run fails when
   one is at or above the threshold. An error that stops a check (a digest mismatch, a file
   that cannot be read, a release that does not verify) is an ``integrity`` finding, always
   an error.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from ..document import STREAM_SELECTION, stream_profile_selection
from ..errors import AmbiguousError, InputError, LockFileError
from ..include import lockfile
from ..include.resolver import TreeOptions, resolve
from . import extensions, firmware, macsec, references
from .policy import CHECKS, DEFAULT, Policy, PolicyError
from .report import Finding, Report

__all__ = ["CHECKS", "AuditOptions", "Finding", "Policy", "PolicyError", "Report", "audit"]


@dataclass(frozen=True)
class AuditOptions:
    """What to audit against. Keyword-only by convention."""

    policy: Policy = DEFAULT
    tree: TreeOptions = TreeOptions()  # resolve's --base, --mirror, --root, --cache-dir, --lock, --offline
    release_dir: str | None = None
    release_key: str | None = None
    store_dir: str | None = None
    store_wrapper: Any = None  # a hcdf_trust.macsec.backends wrapper, with store_dir
    now: datetime | None = None
    registry: Any = None  # a RegistrySchemaSource
    fleet_report: str | None = None  # `fleet status --out` (a signed, host-attested version report)
    fleet_key: str | None = None  # the host's public key that signed it


def audit(doc: str | os.PathLike[str], options: AuditOptions | None = None) -> Report:
    """Audit ``doc`` and everything it includes.

    Raises:
        InputError: the root document, the lock file, the release key or the key store
            cannot be read (a wrong passphrase included); the registry cannot be reached.
    """
    o = options or AuditOptions()
    lock_path = o.tree.lock_path
    if lock_path is not None and not os.path.lexists(lock_path):
        raise LockFileError(f"lock file {lock_path} does not exist", file=lock_path)
    res = resolve(doc, o.tree.resolve_options(write_cache=False))
    for error in res.errors:
        # A lock that cannot be read, or a document that reads two ways: nothing about the tree
        # can be trusted to it (exit 3, as every other verb refuses it).
        if isinstance(error, LockFileError | AmbiguousError):
            raise error
    lock = lockfile.load(res.lock_path) if os.path.lexists(res.lock_path) else None
    report = Report(document=res.root.source, policy=o.policy)
    report.checked.append("references")
    references.check(report, res, lock)

    release = None
    if o.release_dir is not None:
        if o.release_key is None:
            raise InputError("a release is verified with its public key: release_key is missing", file=o.release_dir)
        release, errors = firmware.read_release(o.release_dir, o.release_key)
        for error in errors:
            report.add_error(error)
        report.checked.append("release")
        if release is not None:
            firmware.check_provenance(report, o.release_dir, release, o.release_key)
            report.checked.append("provenance")
    report.checked.append("stream-profiles")
    for part in res.documents.values():
        for text, line in stream_profile_selection(part).problems:
            report.add(STREAM_SELECTION, text, file=part.source, line=line)
    report.checked.append("firmware")
    firmware.check(report, res, release)
    if o.fleet_report is not None:
        if o.fleet_key is None:
            raise InputError("a fleet report is verified with the host's public key: fleet_key is missing")
        from . import fleet

        fleet.check(report, res, release, o.fleet_report, o.fleet_key)
        report.checked.append("fleet")

    plan = macsec.plan_of(report, res)
    if plan is not None:
        report.checked.append("macsec")
        macsec.check(report, res, plan)
        if o.store_dir is not None:
            from ..macsec.store import now_utc

            macsec.check_store(report, plan, o.store_dir, o.store_wrapper, now=o.now or now_utc())
            report.checked.append("key-store")
    if o.registry is not None:
        extensions.check(report, res, o.registry)
        report.checked.append("extensions")
    return report
