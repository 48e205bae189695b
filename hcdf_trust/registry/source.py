"""The registry's source: the reviewed TOML entries under ``registry/``.

Layout (one file per entry, named after it)::

    root.toml                    the root of trust: public keys and thresholds of the
                                 four top-level TUF roles (root, targets, snapshot, timestamp)
    domains/<domain>.toml        an extension domain: description, owner (name, public keys,
                                 threshold) and per version the schema's path, SHA-256 and
                                 length, signed by the owner
    profiles/<name>.toml         a TSN stream profile: per version its path, SHA-256, length
    schemas/<name>.toml          a core schema (``hcdf``, ``hcdf-stream-profile``): per version

Every file is read through :func:`hcdf_trust.localfile.read_input` and validated
strictly: an unknown key, a wrong type or a malformed value is a :class:`SourceError`
naming the file and the key. The content files themselves are not here: ``file`` is
their path inside the content folder given to ``publish``.
"""

from __future__ import annotations

import os
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import tomli_w

from ..localfile import read_toml
from .errors import SourceError

ENTRY_LIMIT = 1 << 20  # bytes per TOML entry
TOP_ROLES = ("root", "targets", "snapshot", "timestamp")
KEY_SCHEMES = {"ed25519": "ed25519", "ecdsa": "ecdsa-sha2-nistp256"}

_LABEL = r"[a-z0-9](?:[a-z0-9-]{0,61}[a-z0-9])?"
_DOMAIN = re.compile(rf"[a-z]{{2,63}}(?:\.{_LABEL})+")
_VERSION = re.compile(r"[0-9]{1,9}(?:\.[0-9]{1,9}){0,3}")
_NAME = re.compile(r"[a-z0-9][a-z0-9._-]{0,63}")
_SEGMENT = re.compile(r"[A-Za-z0-9_][A-Za-z0-9._-]{0,127}")
_HEX64 = re.compile(r"[0-9a-f]{64}")
_HEX = re.compile(r"(?:[0-9a-f]{2})+")


def is_reverse_dns(domain: str) -> bool:
    """``org.ros2``, ``org.ieee.1722``: lower-case labels, at least two, the first alphabetic."""
    return len(domain) <= 253 and _DOMAIN.fullmatch(domain) is not None


def is_version(version: str) -> bool:
    return _VERSION.fullmatch(version) is not None


def is_target_path(path: str) -> bool:
    """A relative path of plain segments: no ``..``, no glob characters, no empty segment."""
    return len(path) <= 512 and all(_SEGMENT.fullmatch(s) for s in path.split("/"))


@dataclass(frozen=True)
class PublicKey:
    """A public key as TUF metadata lists it; ``keyid`` is securesystemslib's default key id."""

    keyid: str
    keytype: str
    scheme: str
    public: str

    def to_dict(self) -> dict[str, Any]:
        return {"keytype": self.keytype, "scheme": self.scheme, "keyval": {"public": self.public}}

    def to_toml(self) -> dict[str, str]:
        return {"keytype": self.keytype, "scheme": self.scheme, "public": self.public}


@dataclass(frozen=True)
class Threshold:
    """``threshold`` of the keys ``keyids`` must sign."""

    threshold: int
    keyids: tuple[str, ...]


@dataclass(frozen=True)
class RootOfTrust:
    keys: dict[str, PublicKey]
    roles: dict[str, Threshold]
    source: str = "root.toml"

    def to_toml(self) -> dict[str, Any]:
        return {
            "roles": {r: {"threshold": t.threshold, "keys": list(t.keyids)} for r, t in self.roles.items()},
            "keys": {k: v.to_toml() for k, v in sorted(self.keys.items())},
        }


@dataclass(frozen=True)
class Release:
    """One version of a domain's schema, a stream profile or a core schema."""

    version: str
    path: str  # the TUF target path
    file: str  # inside the content folder
    sha256: str
    length: int
    signatures: dict[str, str] = field(default_factory=dict)  # keyid -> hex (domains only)
    sigstore: bool = False  # approved by a sigstore bundle in bundles/<domain>/<version>.sigstore.json

    def to_toml(self) -> dict[str, Any]:
        out: dict[str, Any] = {"path": self.path, "file": self.file, "sha256": self.sha256, "length": self.length}
        if self.sigstore:
            out["sigstore"] = True
        if self.signatures:
            out["signatures"] = dict(sorted(self.signatures.items()))
        return out


@dataclass(frozen=True)
class Domain:
    """An extension domain: only its owner's keys may sign its versions."""

    domain: str
    description: str
    owner: str
    threshold: int
    keys: dict[str, PublicKey]
    versions: dict[str, Release]
    source: str = ""
    sigstore: tuple[str, str] | None = None  # (identity, OIDC issuer) whose bundles approve versions

    def statement(self, release: Release) -> bytes:
        """The canonical bytes an owner signs for ``release`` (see :mod:`.keys`)."""
        return canonical(
            {
                "type": "hcdf-registry-release",
                "domain": self.domain,
                "version": release.version,
                "path": release.path,
                "sha256": release.sha256,
                "length": release.length,
            }
        )

    def to_toml(self) -> dict[str, Any]:
        return {
            "domain": self.domain,
            "description": self.description,
            "owner": {
                "name": self.owner,
                "threshold": self.threshold,
                "keys": {k: v.to_toml() for k, v in sorted(self.keys.items())},
                **({"sigstore": {"identity": self.sigstore[0], "issuer": self.sigstore[1]}} if self.sigstore else {}),
            },
            "versions": {v: r.to_toml() for v, r in sorted(self.versions.items(), key=lambda i: _vkey(i[0]))},
        }


@dataclass(frozen=True)
class Artifact:
    """A stream profile (``kind="profile"``) or a core schema (``kind="schema"``), signed by targets."""

    kind: str
    name: str
    description: str
    versions: dict[str, Release]
    source: str = ""

    def to_toml(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "description": self.description,
            "versions": {v: r.to_toml() for v, r in sorted(self.versions.items(), key=lambda i: _vkey(i[0]))},
        }


@dataclass(frozen=True)
class Source:
    """The whole registry source, as read from its folder."""

    dir: Path
    root: RootOfTrust
    domains: dict[str, Domain]
    profiles: dict[str, Artifact]
    schemas: dict[str, Artifact]

    def entry_path(self, kind: str, name: str) -> Path:
        folder = {"domain": "domains", "profile": "profiles", "schema": "schemas"}[kind]
        return self.dir / folder / f"{name}.toml"


def canonical(obj: Any) -> bytes:
    """Canonical JSON (securesystemslib's), the bytes that are signed."""
    from securesystemslib.formats import encode_canonical

    text = encode_canonical(obj)
    assert isinstance(text, str)
    return text.encode()


def _vkey(version: str) -> tuple[int, ...]:
    return tuple(int(p) for p in version.split(".")) if is_version(version) else (1 << 31,)


def domain_path(domain: str, version: str) -> str:
    """Where a domain's schema is published: one segment under its role's pattern."""
    return f"extensions/{domain}/{version}.xsd"


def domain_pattern(domain: str) -> str:
    """The delegation pattern of a domain role (``*`` is one path segment)."""
    return f"extensions/{domain}/*"


def artifact_path(kind: str, name: str, version: str) -> str:
    return f"profiles/{name}/{version}.streams.xml" if kind == "profile" else f"schemas/{name}/{version}.xsd"


def compute_keyid(keytype: str, scheme: str, public: str) -> str:
    from securesystemslib.signer._utils import compute_default_keyid

    return compute_default_keyid(keytype, scheme, {"public": public})


# -- reading ------------------------------------------------------------------------------


class _Reader:
    """Strict access to one parsed TOML entry; every error names the file and the key."""

    def __init__(self, data: Mapping[str, Any], file: str, prefix: str = "") -> None:
        self.data = data
        self.file = file
        self.prefix = prefix
        self.seen: set[str] = set()

    def fail(self, key: str, message: str, *, expected: str | None = None, actual: Any = None) -> SourceError:
        return SourceError(
            f"key `{self.prefix}{key}`: {message}",
            file=self.file,
            expected=expected if expected is not None or actual is None else message,
            actual=None if actual is None else repr(actual),
        )

    def get(self, key: str, kind: type, *, default: Any = ...) -> Any:
        self.seen.add(key)
        if key not in self.data:
            if default is not ...:
                return default
            raise self.fail(key, "missing", expected=f"a {kind.__name__}", actual="nothing")
        value = self.data[key]
        if kind is int and isinstance(value, bool) or not isinstance(value, kind):
            raise self.fail(key, f"must be a {kind.__name__}", expected=kind.__name__, actual=value)
        return value

    def table(self, key: str, *, default: Any = ...) -> _Reader:
        value = self.get(key, dict, default=default)
        return _Reader(value, self.file, f"{self.prefix}{key}.")

    def items(self) -> list[tuple[str, _Reader]]:
        out = []
        for key, value in self.data.items():
            self.seen.add(key)
            if not isinstance(value, dict):
                raise self.fail(key, "must be a table", expected="table", actual=value)
            out.append((key, _Reader(value, self.file, f"{self.prefix}{key}.")))
        return out

    def done(self) -> None:
        extra = sorted(set(self.data) - self.seen)
        if extra:
            raise self.fail(extra[0], "unknown key", expected="one of " + ", ".join(sorted(self.seen)), actual=extra[0])


def _parse(path: Path, shown: str) -> dict[str, Any]:
    return read_toml(path, limit=ENTRY_LIMIT, what="registry entry", source=shown, error=SourceError)


def _key(r: _Reader, keyid: str) -> PublicKey:
    keytype = r.get("keytype", str)
    scheme = r.get("scheme", str)
    public = r.get("public", str)
    r.done()
    if KEY_SCHEMES.get(keytype) != scheme:
        raise r.fail("scheme", "unsupported key type or scheme", expected=str(KEY_SCHEMES), actual=(keytype, scheme))
    if not _HEX.fullmatch(public) or (keytype == "ed25519" and len(public) != 64):
        raise r.fail("public", "must be the key in lower-case hex (ed25519: 64 digits)", actual=public)
    real = compute_keyid(keytype, scheme, public)
    if keyid != real:
        raise SourceError(
            f"key `{r.prefix.rstrip('.')}`: key id does not match the key", file=r.file, expected=real, actual=keyid
        )
    return PublicKey(keyid, keytype, scheme, public)


def _keys(r: _Reader) -> dict[str, PublicKey]:
    return {keyid: _key(sub, keyid) for keyid, sub in r.items()}


def _threshold(r: _Reader, key: str, n_keys: int) -> int:
    value: int = r.get(key, int, default=1)
    if not 1 <= value <= max(n_keys, 1):
        raise r.fail(key, f"must be between 1 and the number of keys ({n_keys})", actual=value)
    return value


def _release(r: _Reader, version: str, *, signed: bool) -> Release:
    if not is_version(version):
        raise SourceError(f"key `{r.prefix.rstrip('.')}`: not a version (digits and dots)", file=r.file)
    path = r.get("path", str)
    file = r.get("file", str)
    sha = r.get("sha256", str)
    length = r.get("length", int)
    sigs: dict[str, str] = {}
    by_sigstore: bool = r.get("sigstore", bool, default=False) if signed else False
    if signed:
        sr = r.table("signatures", default={})
        for keyid in list(sr.data):
            value = sr.get(keyid, str)
            if not _HEX.fullmatch(value):
                raise sr.fail(keyid, "must be a hex signature", actual=value)
            sigs[keyid] = value
    r.done()
    if not is_target_path(path):
        raise r.fail("path", "must be a relative path of plain segments", actual=path)
    if not is_target_path(file):
        raise r.fail("file", "must be a relative path inside the content folder", actual=file)
    if not _HEX64.fullmatch(sha):
        raise r.fail("sha256", "must be 64 lower-case hex digits", actual=sha)
    if length < 0:
        raise r.fail("length", "must be >= 0", actual=length)
    return Release(version, path, file, sha, length, sigs, by_sigstore)


def load_root(path: Path, shown: str) -> RootOfTrust:
    r = _Reader(_parse(path, shown), shown)
    keys = _keys(r.table("keys"))
    roles_r = r.table("roles")
    roles: dict[str, Threshold] = {}
    for role in TOP_ROLES:
        rr = roles_r.table(role)
        ids = rr.get("keys", list)
        for keyid in ids:
            if not isinstance(keyid, str) or keyid not in keys:
                raise rr.fail("keys", "lists a key that is not in [keys]", actual=keyid)
        if len(set(ids)) != len(ids):
            raise rr.fail("keys", "lists a key twice", actual=ids)
        roles[role] = Threshold(_threshold(rr, "threshold", len(ids)), tuple(ids))
        rr.done()
    roles_r.done()
    r.done()
    return RootOfTrust(keys, roles, shown)


def load_domain(path: Path, shown: str) -> Domain:
    r = _Reader(_parse(path, shown), shown)
    domain = r.get("domain", str)
    if not is_reverse_dns(domain):
        raise r.fail("domain", "not a reverse-DNS domain (e.g. org.ros2)", actual=domain)
    if path.stem != domain:
        raise r.fail("domain", "must match the file name", expected=path.stem, actual=domain)
    description = r.get("description", str, default="")
    owner = r.table("owner")
    name = owner.get("name", str)
    keys = _keys(owner.table("keys"))
    if not keys:
        raise owner.fail("keys", "an owner needs at least one public key")
    threshold = _threshold(owner, "threshold", len(keys))
    sigstore = None
    if "sigstore" in owner.data:
        sr = owner.table("sigstore")
        sigstore = (sr.get("identity", str), sr.get("issuer", str))
        sr.done()
    owner.done()
    versions = {v: _release(vr, v, signed=True) for v, vr in r.table("versions", default={}).items()}
    r.done()
    return Domain(domain, description, name, threshold, keys, versions, shown, sigstore)


def load_artifact(kind: str, path: Path, shown: str) -> Artifact:
    r = _Reader(_parse(path, shown), shown)
    name = r.get("name", str)
    if not _NAME.fullmatch(name):
        raise r.fail("name", "must be lower-case letters, digits, '.', '_' or '-'", actual=name)
    if path.stem != name:
        raise r.fail("name", "must match the file name", expected=path.stem, actual=name)
    description = r.get("description", str, default="")
    versions = {v: _release(vr, v, signed=False) for v, vr in r.table("versions", default={}).items()}
    r.done()
    return Artifact(kind, name, description, versions, shown)


def load_source(folder: str | os.PathLike[str]) -> Source:
    """Read and validate a registry source folder.

    Raises:
        SourceError: an entry is malformed (file and key named), or ``root.toml`` is missing.
        InputError: an entry is not a regular file, or is over the size limit.
    """
    base = Path(folder)
    if not (base / "root.toml").is_file():
        raise SourceError(f"{folder} is not a registry source: no root.toml", file=os.fspath(folder))
    root = load_root(base / "root.toml", os.fspath(base / "root.toml"))
    domains = {d.domain: d for d in (load_domain(p, s) for p, s in _entries(base, "domains"))}
    profiles = {a.name: a for a in (load_artifact("profile", p, s) for p, s in _entries(base, "profiles"))}
    schemas = {a.name: a for a in (load_artifact("schema", p, s) for p, s in _entries(base, "schemas"))}
    return Source(base, root, domains, profiles, schemas)


def _entries(base: Path, folder: str) -> list[tuple[Path, str]]:
    d = base / folder
    if not d.is_dir():
        return []
    return [(p, os.fspath(p)) for p in sorted(d.iterdir()) if p.suffix == ".toml"]


def dump(entry: Domain | Artifact | RootOfTrust) -> bytes:
    """An entry as the TOML text ``registry add`` writes."""
    head = {
        Domain: "# An HCDF extension domain: only its owner's keys may sign new versions.\n",
        Artifact: "# Signed by the registry's targets key; published versions never change.\n",
        RootOfTrust: "# The registry's root of trust: the public keys of the four top-level TUF roles.\n",
    }[type(entry)]
    return (head + tomli_w.dumps(entry.to_toml())).encode()


__all__ = [
    "Artifact",
    "Domain",
    "PublicKey",
    "Release",
    "RootOfTrust",
    "Source",
    "Threshold",
    "canonical",
    "domain_path",
    "domain_pattern",
    "dump",
    "is_reverse_dns",
    "load_source",
]
