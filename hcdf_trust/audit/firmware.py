"""Firmware: every ``<software>`` has a full SHA-256 ``<hash>`` and a semantic version, and,
given a release, the latest signed manifest lists it with that hash.

The ``<hash>`` values are the walker's (``Resolution.others``, :class:`~hcdf_trust.document.Kind`
``FIRMWARE``); the release is read and verified by :mod:`hcdf_trust.ota` first.
"""

from __future__ import annotations

import os
import re
from typing import TYPE_CHECKING, Any

from ..digest import is_full_sha256
from ..document import Kind, single, single_text, software_elements
from ..errors import HcdfTrustError
from ..include.resolver import Resolution
from ..xml import sourceline
from .report import Report

if TYPE_CHECKING:
    from ..ota import suit

# The grammar of https://semver.org/spec/v2.0.0.html (its suggested regular expression).
SEMVER = re.compile(
    r"(0|[1-9]\d*)\.(0|[1-9]\d*)\.(0|[1-9]\d*)"
    r"(?:-((?:0|[1-9]\d*|\d*[a-zA-Z-][0-9a-zA-Z-]*)(?:\.(?:0|[1-9]\d*|\d*[a-zA-Z-][0-9a-zA-Z-]*))*))?"
    r"(?:\+([0-9a-zA-Z-]+(?:\.[0-9a-zA-Z-]+)*))?"
)


def read_release(folder: str, key: str) -> tuple[suit.Release | None, list[HcdfTrustError]]:
    """The release in ``folder``, verified as ``ota verify`` does: (release, errors).

    A release whose manifest does not verify is returned as None with its error.

    Raises:
        InputError: the key cannot be read.
    """
    from ..ota.keys import load_public
    from ..ota.release import read_release as read
    from ..ota.verify import check_release

    public = load_public(key)
    try:
        release, files = read(folder, public)
        errors = check_release(release, files, public)
    except HcdfTrustError as exc:
        return None, [_in_folder(exc, folder)]
    return release, [_in_folder(e, folder) for e in errors]


def check_provenance(report: Report, folder: str, release: suit.Release, key: str) -> None:
    """``release-no-provenance``: the release folder has no ``provenance.intoto.json``.
    One that is there is verified with the release key as ``ota verify --provenance``
    verifies it: what does not verify is an integrity finding (a forged statement is no
    better than none)."""
    from ..ota.keys import load_public
    from ..provenance import FILE_NAME
    from ..provenance.verify import read_envelope, verify_provenance

    try:
        data = read_envelope(folder)
        if data is None:
            report.add(
                "release-no-provenance",
                f"release {release.sequence_number} has no {FILE_NAME}: nothing signed says how it was built "
                "or from what (ota build --provenance)",
                file=os.path.join(folder, FILE_NAME),
                line=None,
            )
            return
        errors = verify_provenance(folder, release, [load_public(key)], data=data)
    except HcdfTrustError as exc:
        errors = [exc]
    for error in errors:
        report.add_error(_in_folder(error, folder))


def _in_folder(error: HcdfTrustError, folder: str) -> HcdfTrustError:
    """ota names a release's files relative to its folder; the audit report names the folder too."""
    if error.file and not os.path.isabs(error.file) and not error.file.startswith(folder):
        error.file = os.path.join(folder, error.file)
    return error


def check(report: Report, res: Resolution, release: suit.Release | None) -> None:
    hashes = {ref.element: ref for _, ref in res.others if ref.kind is Kind.FIRMWARE and ref.element is not None}
    for doc in res.documents.values():
        for sw in software_elements(doc):
            _software(report, doc.source, sw, hashes, release)


def _software(report: Report, source: str, sw: Any, hashes: dict[Any, Any], release: suit.Release | None) -> None:
    line = sourceline(sw)
    name = (sw.get("name") or "").strip() or "?"
    comp = sw.getparent()
    comp_name = comp.get("name") if comp is not None and comp.tag == "comp" else None
    what = f"comp {comp_name!r}: <software name={name!r}>" if comp_name else f"<software name={name!r}>"
    hash_el = single(sw, "hash", source=source)
    ref = hashes.get(hash_el) if hash_el is not None else None
    sha = ref.sha if ref is not None else None
    if sha is None:
        report.add("firmware-no-hash", f"{what} has no <hash>: nothing binds it to an image", file=source, line=line)
    elif not is_full_sha256(sha.lower()):
        report.add(
            "firmware-hash",
            f"{what}: <hash> {sha!r} is not a full SHA-256 (64 hex digits)",
            file=source,
            line=ref.line if ref is not None else line,
        )
    version_el = single(sw, "version", source=source)
    version = single_text(sw, "version", source=source) or ""
    if not SEMVER.fullmatch(version):
        shown = repr(version) if version else "missing"
        report.add(
            "firmware-version",
            f"{what}: version {shown} is not semantic (MAJOR.MINOR.PATCH, SemVer 2.0.0)",
            file=source,
            line=sourceline(version_el) if version_el is not None else line,
        )
    if release is None or comp_name is None:
        return
    board = single_text(comp, "board", source=source) or comp_name
    component = release.component(board, name)
    if component is None:
        report.add(
            "firmware-unreleased",
            f"{what}: {board}/{name} is not in release {release.sequence_number}",
            file=source,
            line=line,
        )
        return
    # What <hash> must be (docs/ota.md): MCUboot's image hash, or a raw image's file SHA-256.
    signed = component.mcuboot_hash if component.type == "mcuboot" else component.sha256
    if sha is not None and sha.lower() != signed:
        report.add(
            "firmware-unreleased",
            f"{what}: <hash> is not the image of release {release.sequence_number} "
            f"({board}/{name} {component.version} has {signed})",
            file=source,
            line=ref.line if ref is not None else line,
        )
