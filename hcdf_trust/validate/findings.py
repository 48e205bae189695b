"""What ``validate`` reports: findings (error or warning) collected into one report."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

Severity = Literal["error", "warning"]


@dataclass(frozen=True)
class Finding:
    """One problem found in a document, with where it was written.

    ``code`` is stable and machine-readable (``xsd``, ``unresolved-port``, ...);
    ``path`` is the XPath of the offending element when the validator gave one.
    """

    code: str
    severity: Severity
    message: str
    file: str | None = None
    line: int | None = None
    path: str | None = None

    @property
    def is_error(self) -> bool:
        return self.severity == "error"

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "code": self.code,
            "severity": self.severity,
            "message": self.message,
            "file": self.file,
            "line": self.line,
        }
        if self.path is not None:
            out["path"] = self.path
        return out

    def __str__(self) -> str:
        where = ""
        if self.file:
            where = f"{self.file}:{self.line}: " if self.line else f"{self.file}: "
        return f"{where}{self.severity}[{self.code}]: {self.message}"


@dataclass
class ValidationReport:
    """Everything one ``validate`` run found.

    ``checked`` names what ran (``"xsd"``, ``"semantic"``); ``schema`` names the
    XSD used and ``schema_sha256`` its digest, both None when no schema was checked. ``notes`` are facts worth
    telling the user that are not problems (e.g. which port-reference form the
    document uses).
    """

    source: str
    schema: str | None = None
    schema_sha256: str | None = None  # of the XSD's bytes: which schema, as upstream's versions/HASHES names it
    checked: list[str] = field(default_factory=list)
    findings: list[Finding] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        """True when no finding is an error (warnings do not fail a run)."""
        return not any(f.is_error for f in self.findings)

    @property
    def errors(self) -> list[Finding]:
        return [f for f in self.findings if f.is_error]

    @property
    def warnings(self) -> list[Finding]:
        return [f for f in self.findings if not f.is_error]

    def to_dict(self) -> dict[str, Any]:
        return {
            "ok": self.ok,
            "source": self.source,
            "schema": self.schema,
            "schema_sha256": self.schema_sha256,
            "checked": list(self.checked),
            "findings": [f.to_dict() for f in self.findings],
            "errors": [f.to_dict() for f in self.errors],
            "notes": list(self.notes),
        }
