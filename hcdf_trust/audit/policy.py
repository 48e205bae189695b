"""The audit policy: which checks run, how severe each finding is, and what fails the run.

A policy file is TOML (every key optional; anything not written keeps the built-in default)::

    threshold = "error"              # a finding at or above this severity fails the run (exit 1)

    [macsec]
    minimum-cipher = "gcm-aes-128"   # weaker associations are reported (macsec-weak-cipher)

    [checks.weak-pin]                # one table per check, named as in CHECKS
    enabled = true
    severity = "error"               # info | warning | error

Unknown keys, wrong types and unknown values are refused (:class:`PolicyError`, exit 3),
naming the file and the key.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Literal, cast

from ..errors import InputError, display_path
from ..localfile import read_toml
from ..macsec.plan import CIPHERS

Severity = Literal["info", "warning", "error"]
SEVERITIES: tuple[Severity, ...] = ("info", "warning", "error")
MAX_POLICY_BYTES = 1 << 20

# Cipher strength, weakest first: key length first, then XPN (64-bit packet numbers) over 32-bit.
CIPHER_ORDER = ("gcm-aes-128", "gcm-aes-xpn-128", "gcm-aes-256", "gcm-aes-xpn-256")
assert sorted(CIPHER_ORDER) == sorted(CIPHERS)


@dataclass(frozen=True)
class Check:
    area: str
    severity: Severity
    summary: str


# Every switchable check: name (also the finding's code) -> area, default severity, what it reports.
CHECKS: dict[str, Check] = {
    "unpinned": Check("references", "error", "a reference with no sha that no lock entry pins"),
    "weak-pin": Check("references", "warning", "a sha that is a short prefix, not a full SHA-256"),
    "plain-http": Check("references", "error", "a reference fetched over plain http"),
    "not-locked": Check("references", "warning", "no lock file, or a reference the lock file does not hold"),
    "lock-drift": Check("references", "error", "content that differs from its lock entry, or a stale entry"),
    "foreign-major-version": Check(
        "references", "warning", 'a document whose version is not 1.x ("2.0"): upstream\'s reader refuses it'
    ),
    "stream-profile-selection": Check(
        "stream-profiles", "error", "more than one stream profile selected, or a selection that reads two ways"
    ),
    "firmware-no-hash": Check("firmware", "error", "a <software> without a <hash>"),
    "firmware-hash": Check("firmware", "error", "a <hash> that is not a full SHA-256"),
    "firmware-version": Check("firmware", "warning", "a <version> that is not semantic (SemVer 2.0.0)"),
    "firmware-unreleased": Check("firmware", "error", "firmware the signed release manifest (--release) lacks"),
    "release-no-provenance": Check(
        "release", "warning", "a release (--release) without provenance.intoto.json: nothing says how it was built"
    ),
    "macsec-control-traffic": Check(
        "macsec", "error", "a link or chain of a network carrying control traffic that is not must-secure"
    ),
    "macsec-file-key-store": Check("macsec", "warning", '<key-store type="file"> (development only)'),
    "macsec-weak-cipher": Check("macsec", "error", "an association whose cipher is weaker than the minimum"),
    "macsec-rekey-due": Check("macsec", "error", "a key older than its rekey interval (--store)"),
    "macsec-capability": Check("macsec", "warning", "an endpoint port that does not declare the cipher"),
    "extension-unregistered": Check("extensions", "warning", "an extension domain or version not in --registry"),
    "extension-content": Check("extensions", "error", "extension content that fails its registered schema"),
    "fleet-device": Check(
        "fleet", "error", "a comp the signed fleet report (--fleet-report) shows not running the release, or lacks"
    ),
    "fleet-report-stale": Check("fleet", "error", "a fleet report about another description or release"),
}


class PolicyError(InputError):
    """The policy file cannot be read, is not TOML, or holds an unknown key or value."""

    code = "audit-policy"


@dataclass(frozen=True)
class Rule:
    enabled: bool
    severity: Severity


@dataclass(frozen=True)
class Policy:
    threshold: Severity = "error"
    minimum_cipher: str = "gcm-aes-128"
    rules: dict[str, Rule] = field(default_factory=lambda: {n: Rule(True, c.severity) for n, c in CHECKS.items()})
    source: str = "built-in"

    def enabled(self, check: str) -> bool:
        return self.rules[check].enabled

    def severity(self, check: str) -> Severity:
        return self.rules[check].severity

    def fails(self, severity: Severity) -> bool:
        """Is a finding of ``severity`` at or above the threshold?"""
        return rank(severity) >= rank(self.threshold)

    def to_dict(self) -> dict[str, Any]:
        return {
            "source": self.source,
            "threshold": self.threshold,
            "minimum_cipher": self.minimum_cipher,
            "checks": {n: {"enabled": r.enabled, "severity": r.severity} for n, r in self.rules.items()},
        }


DEFAULT = Policy()


def rank(severity: Severity) -> int:
    return SEVERITIES.index(severity)


def cipher_rank(cipher: str) -> int:
    return CIPHER_ORDER.index(cipher)


def load(path: str) -> Policy:
    """Read and strictly check a policy file (bounded, regular files only).

    Raises:
        NotFoundError / InputError: the file cannot be read (missing, a FIFO, too large).
        PolicyError: not UTF-8 TOML, or an unknown key, a wrong type, an unknown value.
    """
    shown = display_path(path)
    raw = read_toml(path, limit=MAX_POLICY_BYTES, what="audit policy", source=shown, error=PolicyError)
    return _policy(raw, shown)


def _policy(raw: dict[str, Any], source: str) -> Policy:
    def bad(key: str, message: str, *, expected: str, actual: object) -> PolicyError:
        return PolicyError(f"{key}: {message}", file=source, expected=expected, actual=repr(actual))

    _only(raw, {"threshold", "macsec", "checks"}, "", source)
    policy = replace(DEFAULT, source=source)
    if "threshold" in raw:
        policy = replace(policy, threshold=_severity(raw["threshold"], "threshold", source))
    macsec = _table(raw.get("macsec", {}), "macsec", source)
    _only(macsec, {"minimum-cipher"}, "macsec.", source)
    if "minimum-cipher" in macsec:
        cipher = macsec["minimum-cipher"]
        if cipher not in CIPHER_ORDER:
            raise bad("macsec.minimum-cipher", "not a MACsec cipher", expected=" | ".join(CIPHER_ORDER), actual=cipher)
        policy = replace(policy, minimum_cipher=cipher)
    checks = _table(raw.get("checks", {}), "checks", source)
    rules = dict(policy.rules)
    for name, value in checks.items():
        if name not in CHECKS:
            raise bad(f"checks.{name}", "not a known check", expected=" | ".join(CHECKS), actual=name)
        table = _table(value, f"checks.{name}", source)
        _only(table, {"enabled", "severity"}, f"checks.{name}.", source)
        rule = rules[name]
        if "enabled" in table:
            if not isinstance(table["enabled"], bool):
                raise bad(f"checks.{name}.enabled", "not a boolean", expected="true | false", actual=table["enabled"])
            rule = replace(rule, enabled=table["enabled"])
        if "severity" in table:
            rule = replace(rule, severity=_severity(table["severity"], f"checks.{name}.severity", source))
        rules[name] = rule
    return replace(policy, rules=rules)


def _only(table: dict[str, Any], allowed: set[str], prefix: str, source: str) -> None:
    for key in table:
        if key not in allowed:
            raise PolicyError(
                f"{prefix}{key}: unknown key",
                file=source,
                expected=" | ".join(f"{prefix}{k}" for k in sorted(allowed)),
                actual=f"{prefix}{key}",
            )


def _table(value: object, key: str, source: str) -> dict[str, Any]:
    if not isinstance(value, dict):
        raise PolicyError(f"{key}: not a table", file=source, expected=f"[{key}]", actual=repr(value))
    return cast("dict[str, Any]", value)


def _severity(value: object, key: str, source: str) -> Severity:
    for severity in SEVERITIES:
        if value == severity:
            return severity
    raise PolicyError(f"{key}: not a severity", file=source, expected=" | ".join(SEVERITIES), actual=repr(value))
