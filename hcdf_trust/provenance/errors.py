"""Errors of provenance checks: integrity (exit 1) and malformed input (exit 3)."""

from __future__ import annotations

from ..ota.errors import MalformedReleaseError, ReleaseIntegrityError


class ProvenanceError(ReleaseIntegrityError):
    """The provenance does not verify: signature, type, subject, dependency or parameter."""

    code = "provenance"


class MalformedProvenanceError(MalformedReleaseError):
    """``provenance.intoto.json`` is not a DSSE envelope over a JSON in-toto Statement."""

    code = "malformed-provenance"
