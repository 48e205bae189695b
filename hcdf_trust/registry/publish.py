"""``registry publish``: the source, its content and its keys become a static TUF repository.

Site layout (consistent snapshots, ready for any static web server)::

    metadata/N.root.json, root.json     root, every version kept (clients walk the chain)
    metadata/timestamp.json             the only unversioned role, re-signed by every publish
    metadata/N.snapshot.json            lists every targets role's version
    metadata/N.targets.json             stream profiles and core schemas; one delegated role
                                        per domain, restricted to ``extensions/<domain>/*``
    metadata/N.<domain>.json            a domain's schemas, signed by its owner's keys
    targets/<dir>/<sha256>.<name>       the content files, named by their digest

Publishing is incremental: the previous site in ``--out`` is read back, a role whose
content and keys are unchanged keeps its signed file (so a publisher needs an owner's
key only when that owner's domain changes), a changed role gets the next version, and a
published version whose content differs is refused. Before anything is signed, every
domain version must carry its owner's signatures (:func:`check_source`) and every path
must lie inside its role's delegation (TUF clients silently ignore one that does not).
"""

from __future__ import annotations

import datetime as dt
import hashlib
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..errors import DigestMismatchError, InputError, counted
from ..localfile import open_checked, read_bounded, read_input
from ..outputs import OutputPlan
from . import keys as keymod
from .errors import RefusedError
from .source import TOP_ROLES, Artifact, Domain, PublicKey, Release, Source, domain_pattern

if TYPE_CHECKING:
    from tuf.api.metadata import Metadata, Root, Snapshot, Targets

SHARD_SIZE = 64  # domains per shard role
LONG_LIFETIME = dt.timedelta(days=365)  # root, targets and domain roles (re-signed when the timestamp outlives them)
DEFAULT_TIMESTAMP_LIFETIME = dt.timedelta(days=7)
METADATA_LIMIT = 8 << 20


@dataclass
class Published:
    """What a publish run did: role versions, which roles were re-signed, files written."""

    site: Path
    versions: dict[str, int] = field(default_factory=dict)
    signed: list[str] = field(default_factory=list)
    written: list[Path] = field(default_factory=list)


# -- checks on the source (pure) ------------------------------------------------------------


def check_source(source: Source, *, sigstore_root: str | None = None) -> None:
    """Every domain version is approved by its owner (a threshold of its keys, or a sigstore
    bundle by its sigstore identity, checked offline against ``sigstore_root``) and lies
    inside the domain's delegation; profiles and schemas stay out of every domain's paths.

    Raises:
        RefusedError: the first rule broken, naming the entry.
    """
    for domain in source.domains.values():
        for release in domain.versions.values():
            check_path(domain.domain, release.path, source=domain.source)
            if release.sigstore:
                _check_bundle(source, domain, release, sigstore_root)
                continue
            good = [
                k
                for k, sig in release.signatures.items()
                if k in domain.keys and keymod.verify(domain.keys[k], sig, domain.statement(release))
            ]
            if len(good) < domain.threshold:
                raise RefusedError(
                    f"{domain.domain} {release.version} is not signed by the domain's owner "
                    f"({len(good)} of {counted(domain.threshold, 'required owner signature')} verify)",
                    file=domain.source,
                    expected=f"{counted(domain.threshold, 'signature')} by {domain.owner}",
                    actual=f"{len(good)}",
                )
    for art in [*source.profiles.values(), *source.schemas.values()]:
        top = "profiles/" if art.kind == "profile" else "schemas/"
        for release in art.versions.values():
            if not release.path.startswith(top):
                raise RefusedError(
                    f"{art.kind} {art.name} {release.version}: path {release.path} is not under {top}",
                    file=art.source,
                    expected=f"{top}...",
                    actual=release.path,
                )


def _check_bundle(source: Source, domain: Domain, release: Release, sigstore_root: str | None) -> None:
    from .sigstore_bundle import bundle_path, read_bundle, verify_bundle

    what = f"{domain.domain} {release.version}"
    if domain.sigstore is None:
        raise RefusedError(
            f"{what} says it is approved by a sigstore bundle, but the owner has no [owner.sigstore] identity",
            file=domain.source,
        )
    if sigstore_root is None:
        raise RefusedError(
            f"{what} is approved by a sigstore bundle: give --sigstore-trusted-root to verify it", file=domain.source
        )
    verify_bundle(
        read_bundle(bundle_path(source.dir, domain.domain, release.version)),
        domain.statement(release),
        identity=domain.sigstore[0],
        issuer=domain.sigstore[1],
        trusted_root=sigstore_root,
        what=what,
        source=domain.source,
    )


def check_path(domain: str, path: str, *, source: str | None = None) -> None:
    """Refuse a path outside ``domain``'s delegation (a cross-domain hijack attempt).

    Raises:
        RefusedError: ``path`` does not match ``extensions/<domain>/*``.
    """
    from tuf.api.metadata import DelegatedRole

    role = DelegatedRole(domain, [], 1, True, paths=[domain_pattern(domain)])
    if not role.is_delegated_path(path):
        raise RefusedError(
            f"cross-domain signing refused: {domain} lists {path}, outside its delegation {domain_pattern(domain)}",
            file=source,
            expected=domain_pattern(domain),
            actual=path,
        )


def shard_count(n_domains: int) -> int:
    """How many shard roles hold ``n_domains`` delegations (about :data:`SHARD_SIZE` each)."""
    return max(1, -(-n_domains // SHARD_SIZE))


def shard_of(domain: str, n_shards: int) -> str:
    """The shard role delegating ``domain``: stable while the shard count stays the same.

    Shard names have no dot, so they never collide with a (reverse-DNS) domain role.
    """
    return f"extensions-{int(hashlib.sha256(domain.encode()).hexdigest()[:8], 16) % n_shards:03d}"


# -- the previous site ------------------------------------------------------------------------


@dataclass
class _Previous:
    root: Metadata[Root] | None = None
    timestamp_version: int = 0
    snapshot: Metadata[Snapshot] | None = None
    snapshot_bytes: bytes = b""
    roles: dict[str, Metadata[Targets]] = field(default_factory=dict)  # "targets" and every domain


def _load_md(path: Path) -> Any:
    from tuf.api.metadata import Metadata

    data = read_input(path, limit=METADATA_LIMIT, what="site metadata")
    try:
        return Metadata.from_bytes(data)
    except Exception as exc:  # tuf raises DeserializationError, ValueError, KeyError, TypeError
        raise InputError(f"{path}: not TUF metadata: {exc}", file=str(path)) from None


def load_previous(site: Path) -> _Previous:
    """The metadata of the last publication in ``site`` (nothing when it is a new site)."""
    meta = site / "metadata"
    prev = _Previous()
    roots = sorted(int(p.name.split(".", 1)[0]) for p in meta.glob("*.root.json") if p.name.split(".")[0].isdigit())
    if roots:
        prev.root = _load_md(meta / f"{roots[-1]}.root.json")
    if not (meta / "timestamp.json").exists():
        return prev
    ts = _load_md(meta / "timestamp.json")
    prev.timestamp_version = ts.signed.version
    snap_path = meta / f"{ts.signed.snapshot_meta.version}.snapshot.json"
    prev.snapshot_bytes = read_input(snap_path, limit=METADATA_LIMIT, what="site metadata")
    prev.snapshot = _load_md(snap_path)
    for name, mf in prev.snapshot.signed.meta.items():
        role = name.removesuffix(".json")
        prev.roles[role] = _load_md(meta / f"{mf.version}.{name}")
    return prev


# -- building -----------------------------------------------------------------------------------


def _sslib(key: PublicKey) -> Any:
    from securesystemslib.signer import SSlibKey

    return SSlibKey.from_dict(key.keyid, key.to_dict())


def _public(key: Any) -> PublicKey:
    return PublicKey(key.keyid, key.keytype, key.scheme, key.keyval["public"])


def _now() -> dt.datetime:
    return dt.datetime.now(dt.UTC).replace(microsecond=0)


def _comparable(obj: Any) -> dict[str, Any]:
    """``obj.to_dict()`` without version and expiry: what a re-publication must keep equal to reuse it."""
    d: dict[str, Any] = obj.to_dict()
    for k in ("version", "expires"):
        d.pop(k, None)
    return d


def _targets_for(releases: list[Release]) -> dict[str, Any]:
    from tuf.api.metadata import TargetFile

    return {r.path: TargetFile(r.length, {"sha256": r.sha256}, r.path) for r in releases}


def read_content(source: Source, content_dir: Path) -> dict[str, bytes]:
    """Every release's content file, checked against its entry's length and SHA-256.

    Raises:
        DigestMismatchError: a file differs from its registry entry.
        NotFoundError, InputError: a file is missing, not regular, or outside ``content_dir``.
    """
    out: dict[str, bytes] = {}
    owners: list[Domain | Artifact] = [*source.domains.values(), *source.profiles.values(), *source.schemas.values()]
    entries = [(e, r) for e in owners for r in e.versions.values()]
    for entry, release in entries:
        path = content_dir / release.file
        fd, _ = open_checked(path, content_dir, file=entry.source)
        try:
            data = read_bounded(fd, max(release.length, 0), source=str(path), what="content file")
        except InputError:
            raise DigestMismatchError(
                f"{path} is larger than the {release.length} bytes its registry entry records",
                file=entry.source,
                expected=f"{release.length} bytes",
                actual="more",
            ) from None
        finally:
            os.close(fd)
        digest = hashlib.sha256(data).hexdigest()
        if digest != release.sha256 or len(data) != release.length:
            raise DigestMismatchError(
                f"{path} does not match its registry entry ({release.version})",
                file=entry.source,
                expected=f"sha256:{release.sha256} ({release.length} bytes)",
                actual=f"sha256:{digest} ({len(data)} bytes)",
            )
        out[release.path] = data
    return out


def publish(
    source: Source,
    ring: keymod.KeyRing,
    content_dir: Path,
    site: Path,
    *,
    plan: OutputPlan,
    timestamp_lifetime: dt.timedelta = DEFAULT_TIMESTAMP_LIFETIME,
    now: dt.datetime | None = None,
    sigstore_root: str | None = None,
) -> Published:
    """Plan the files of a new publication of ``source`` into ``site`` (the caller commits ``plan``).

    Raises:
        RefusedError: an unsigned version, a hijacked path, a replaced published version,
            or a role that must be re-signed whose keys ``ring`` does not hold.
        DigestMismatchError: a content file differs from its entry.
        KeyFileError: a key file is unreadable or its passphrase is wrong.
    """
    from tuf.api.metadata import (
        DelegatedRole,
        Delegations,
        Metadata,
        MetaFile,
        Root,
        Snapshot,
        Targets,
        Timestamp,
    )

    # (1) The source obeys the registry's rules, and the content is what it records.
    check_source(source, sigstore_root=sigstore_root)
    content = read_content(source, content_dir)
    prev = load_previous(site)
    now = now or _now()
    ts_expires = now + timestamp_lifetime
    long_expires = now + max(LONG_LIFETIME, timestamp_lifetime + dt.timedelta(days=1))
    result = Published(site)
    files: dict[str, bytes] = {}  # name in metadata/ -> bytes

    def reusable(old: Metadata[Any] | None, new_signed: Any) -> bool:
        return (
            old is not None and _comparable(old.signed) == _comparable(new_signed) and old.signed.expires >= ts_expires
        )

    # (2) Root: from root.toml; a change is signed by the old root's keys and the new ones.
    root = Root(expires=long_expires, consistent_snapshot=True)
    for role in TOP_ROLES:
        want = source.root.roles[role]
        for keyid in want.keyids:
            root.add_key(_sslib(source.root.keys[keyid]), role)
        root.roles[role].threshold = want.threshold
    if prev.root is not None and reusable(prev.root, root):
        root_md = prev.root
    else:
        root.version = prev.root.signed.version + 1 if prev.root else 1
        root_md = Metadata(root)
        payload = root_md.signed_bytes
        signers = _role_keys(root, "root")
        sigs = ring.sign_threshold(signers, root.roles["root"].threshold, payload, what="root (new keys)")
        if prev.root is not None and _comparable(prev.root.signed.roles["root"]) != _comparable(root.roles["root"]):
            old_root = prev.root.signed
            sigs += ring.sign_threshold(
                _role_keys(old_root, "root"),
                old_root.roles["root"].threshold,
                payload,
                what="root rotation (the previous root's keys)",
            )
        for sig in sigs:
            root_md.signatures[sig.keyid] = sig
        files[f"{root.version}.root.json"] = root_md.to_bytes()
        files["root.json"] = files[f"{root.version}.root.json"]
        result.signed.append("root")
    result.versions["root"] = root_md.signed.version

    # (3) Shards: top-level targets delegates each domain's pattern to one shard role
    # (signed by the targets keys), which delegates it to the domain's role (signed by
    # the owner's keys). Refresh then reads a small targets.json; a lookup loads one shard.
    targets_keys = _role_keys(root_md.signed, "targets")
    n_shards = shard_count(len(source.domains))
    shards: dict[str, list[str]] = {}
    for name in sorted(source.domains):
        shards.setdefault(shard_of(name, n_shards), []).append(name)
    top_roles = {
        shard: DelegatedRole(
            shard,
            sorted(targets_keys),
            root_md.signed.roles["targets"].threshold,
            True,
            paths=[domain_pattern(d) for d in names],
        )
        for shard, names in sorted(shards.items())
    }
    top = Targets(
        expires=long_expires,
        targets={},
        delegations=Delegations(keys={k: _sslib(v) for k, v in targets_keys.items()}, roles=top_roles),
    )
    for art in [*source.profiles.values(), *source.schemas.values()]:
        top.targets.update(_targets_for(list(art.versions.values())))

    # (4) Top-level targets: stream profiles, core schemas and the shards.
    old_top = prev.roles.get("targets")
    _check_immutable("targets", old_top, top, source=source.root.source)
    top_md = _resign(top, old_top, "targets", reusable, ring, root_md.signed, files, result)
    role_mds: dict[str, Metadata[Targets]] = {}
    for shard, names in sorted(shards.items()):
        roles: dict[str, DelegatedRole] = {}
        keys: dict[str, Any] = {}
        for name in names:
            domain = source.domains[name]
            roles[name] = DelegatedRole(name, sorted(domain.keys), domain.threshold, True, paths=[domain_pattern(name)])
            keys.update({k: _sslib(v) for k, v in domain.keys.items()})
        signed_shard = Targets(expires=long_expires, targets={}, delegations=Delegations(keys=keys, roles=roles))
        shard_md = _resign(
            signed_shard, prev.roles.get(shard), shard, reusable, ring, root_md.signed, files, result,
            delegator=top, key_role="targets",
        )  # fmt: skip
        role_mds[shard] = shard_md

        # (5) One delegated role per domain, signed by its owner's keys.
        for name in names:
            domain = source.domains[name]
            signed = Targets(expires=long_expires, targets=_targets_for(list(domain.versions.values())))
            old = prev.roles.get(name)
            _check_immutable(name, old, signed, source=domain.source)
            if old is not None and reusable(old, signed) and _signed_by(signed_shard, name, old):
                role_mds[name] = old
                continue
            signed.version = old.signed.version + 1 if old is not None else 1
            md = Metadata(signed)
            for sig in ring.sign_threshold(
                domain.keys, domain.threshold, md.signed_bytes, what=f"domain {name} (owner: {domain.owner})"
            ):
                md.signatures[sig.keyid] = sig
            role_mds[name] = md
            files[f"{signed.version}.{name}.json"] = md.to_bytes()
            result.signed.append(name)

    # (6) Snapshot: every targets role's version; (7) timestamp: the snapshot's hash and length.
    snap = Snapshot(expires=ts_expires, meta={"targets.json": MetaFile(top_md.signed.version)})
    for name, md in role_mds.items():
        snap.meta[f"{name}.json"] = MetaFile(md.signed.version)
    snap_md = _resign(snap, prev.snapshot, "snapshot", reusable, ring, root_md.signed, files, result)
    snap_bytes = files.get(f"{snap_md.signed.version}.snapshot.json", prev.snapshot_bytes)
    ts = Timestamp(
        version=prev.timestamp_version + 1,
        expires=ts_expires,
        snapshot_meta=MetaFile.from_data(snap_md.signed.version, snap_bytes, ["sha256"]),
    )
    ts_md = Metadata(ts)
    _sign_top(ts_md, "timestamp", ring, root_md.signed)
    files["timestamp.json"] = ts_md.to_bytes()
    result.signed.append("timestamp")
    result.versions.update(targets=top_md.signed.version, snapshot=snap_md.signed.version, timestamp=ts.version)

    # (8) Plan the writes: new metadata, and content files not yet on the site.
    for fname, data in files.items():
        path = site / "metadata" / fname
        if fname not in ("root.json", "timestamp.json") and path.exists():
            raise RefusedError(f"{path} already exists: the site was changed outside publish", file=str(path))
        plan.add(path, data, flag="--out", under=site)
    for tpath, data in content.items():
        folder, _, base = tpath.rpartition("/")
        dest = site / "targets" / folder / f"{hashlib.sha256(data).hexdigest()}.{base}"
        if not dest.exists():
            plan.add(dest, data, flag="--out", under=site)
    result.written = plan.paths
    return result


def _role_keys(signed: Root, role: str) -> dict[str, PublicKey]:
    return {k: _public(signed.keys[k]) for k in signed.roles[role].keyids}


def _sign_top(md: Metadata[Any], role: str, ring: keymod.KeyRing, root: Root) -> None:
    for sig in ring.sign_threshold(_role_keys(root, role), root.roles[role].threshold, md.signed_bytes, what=role):
        md.signatures[sig.keyid] = sig


def _signed_by(delegator: Any, role: str, md: Metadata[Any]) -> bool:
    from tuf.api.exceptions import UnsignedMetadataError

    try:
        delegator.verify_delegate(role, md.signed_bytes, md.signatures)
    except UnsignedMetadataError:
        return False
    return True


def _resign(
    signed: Any,
    old: Metadata[Any] | None,
    role: str,
    reusable: Any,
    ring: keymod.KeyRing,
    root: Root,
    files: dict[str, bytes],
    result: Published,
    *,
    delegator: Any = None,
    key_role: str | None = None,
) -> Metadata[Any]:
    """Keep ``old`` when unchanged and still signed under its delegator (default: ``root``),
    else sign the next version with the keys of ``key_role`` (default: ``role``)."""
    from tuf.api.metadata import Metadata

    if old is not None and reusable(old, signed) and _signed_by(delegator or root, role, old):
        return old
    signed.version = old.signed.version + 1 if old is not None else 1
    md = Metadata(signed)
    _sign_top(md, key_role or role, ring, root)
    files[f"{signed.version}.{role}.json"] = md.to_bytes()
    result.signed.append(role)
    return md


def _check_immutable(role: str, old: Metadata[Any] | None, new: Targets, *, source: str) -> None:
    """A path published before keeps its length and hashes forever.

    Raises:
        RefusedError: a published version would be replaced by different content.
    """
    if old is None:
        return
    for path, was in old.signed.targets.items():
        now = new.targets.get(path)
        if now is not None and (now.length != was.length or now.hashes != was.hashes):
            raise RefusedError(
                f"replaced published version refused: {path} ({role}) was published with other content",
                file=source,
                expected=f"sha256:{was.hashes.get('sha256')} ({was.length} bytes)",
                actual=f"sha256:{now.hashes.get('sha256')} ({now.length} bytes)",
            )
