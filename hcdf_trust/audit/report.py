"""What ``audit`` reports: findings with severity, code, file and line, in one report."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from ..errors import HcdfTrustError, Notice, display_place
from .policy import Policy, Severity, rank

# Findings that are not switchable: the tree, the release or the key store could not be checked
# (a digest mismatch, a missing file, a bad signature). Always errors.
ALWAYS = "integrity"


@dataclass(frozen=True)
class Finding:
    """One problem. ``check`` is the policy check that found it (or ``integrity``); ``code``
    is stable (the check's name, or the error's code for an integrity finding)."""

    check: str
    code: str
    severity: Severity
    message: str
    file: str | None = None
    line: int | None = None

    def to_dict(self) -> dict[str, Any]:
        return {
            "check": self.check,
            "code": self.code,
            "severity": self.severity,
            "message": self.message,
            "file": display_place(self.file) if self.file else None,
            "line": self.line,
        }

    def __str__(self) -> str:
        file = display_place(self.file) if self.file else None
        where = f"{file}:{self.line}: " if file and self.line else f"{file}: " if file else ""
        return f"{where}{self.severity}[{self.code}]: {self.message}"


@dataclass
class Report:
    """Every finding of one run, and which areas were checked."""

    document: str
    policy: Policy
    checked: list[str] = field(default_factory=list)
    findings: list[Finding] = field(default_factory=list)

    def add(self, check: str, message: str, *, file: str | None, line: int | None) -> None:
        """Record a finding of ``check`` with the policy's severity (nothing when it is disabled)."""
        if self.policy.enabled(check):
            self.findings.append(Finding(check, check, self.policy.severity(check), message, file=file, line=line))

    def add_error(self, error: HcdfTrustError) -> None:
        """Record an error that stopped a check (always an error-severity finding)."""
        errors = getattr(error, "errors", None) or [error]  # an ErrorGroup: each of its errors
        for e in errors:
            text = e.message
            if e.expected is not None:
                text += f" (expected {e.expected}, actual {e.actual})"
            self.findings.append(Finding(ALWAYS, e.code, "error", text, file=e.file, line=e.line))

    def add_notice(self, check: str, notice: Notice) -> None:
        self.add(check, notice.message, file=notice.file, line=notice.line)

    @property
    def failing(self) -> list[Finding]:
        return [f for f in self.findings if self.policy.fails(f.severity)]

    @property
    def ok(self) -> bool:
        return not self.failing

    def sorted(self) -> list[Finding]:
        return sorted(
            self.findings, key=lambda f: (f.file != self.document, f.file or "", f.line or 0, -rank(f.severity), f.code)
        )

    def to_dict(self) -> dict[str, Any]:
        counts = {s: sum(1 for f in self.findings if f.severity == s) for s in ("error", "warning", "info")}
        return {
            "ok": self.ok,
            "document": display_place(self.document),
            "threshold": self.policy.threshold,
            "policy": self.policy.source,
            "checked": list(self.checked),
            "counts": counts,
            "findings": [f.to_dict() for f in self.sorted()],
            "errors": [f.to_dict() for f in self.sorted() if self.policy.fails(f.severity)],
        }
