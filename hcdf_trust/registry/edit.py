"""Changes to a registry source: ``init``, ``keygen``, ``add`` and ``rotate``.

Each function plans its writes in an :class:`~hcdf_trust.outputs.OutputPlan` (the caller
commits it) and never writes a private key inside the source folder, which is meant to
be committed. The rules: a new domain must be reverse-DNS and name its owner's public
keys; every version of a domain is signed by a threshold of its owner's keys; a version
once recorded is never replaced by different content.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import replace
from pathlib import Path

from ..errors import InputError
from ..localfile import open_checked, read_bounded, read_input
from ..outputs import NEW_ONLY, ORDINARY, PUBLIC_KEY, REGISTRY_SOURCE, OutputPlan
from . import keys as keymod
from .errors import RefusedError, SourceError
from .source import (
    _NAME,
    TOP_ROLES,
    Artifact,
    Domain,
    PublicKey,
    Release,
    RootOfTrust,
    Source,
    Threshold,
    _key,
    _parse,
    _Reader,
    artifact_path,
    domain_path,
    dump,
    is_reverse_dns,
    is_version,
)

CONTENT_LIMIT = 16 << 20
_SOURCE = (ORDINARY, REGISTRY_SOURCE)  # what an edit of the source may replace


def _outside(keydir: Path, source_dir: Path) -> None:
    real_keys, real_src = os.path.realpath(keydir), os.path.realpath(source_dir)
    if real_keys == real_src or real_keys.startswith(real_src.rstrip("/") + "/"):
        raise InputError(
            f"--keys {keydir} is inside the registry source {source_dir}: private keys must not be committed",
            file=str(keydir),
        )


def init(source_dir: Path, keydir: Path, passphrase: bytes, *, plan: OutputPlan) -> RootOfTrust:
    """A new source: ``root.toml`` with a fresh key for each top-level role, private keys in ``keydir``.

    Raises:
        InputError: ``source_dir`` already holds a registry, or ``keydir`` lies inside it.
    """
    if (source_dir / "root.toml").exists():
        raise InputError(f"{source_dir} already holds a registry (root.toml)", file=str(source_dir / "root.toml"))
    _outside(keydir, source_dir)
    keys: dict[str, PublicKey] = {}
    roles: dict[str, Threshold] = {}
    for role in TOP_ROLES:
        key = keymod.plan_private(plan, keydir, keymod.generate(), passphrase)
        keys[key.keyid] = key
        roles[role] = Threshold(1, (key.keyid,))
    root = RootOfTrust(keys, roles)
    plan.add(source_dir / "root.toml", dump(root), flag="DIR", replaces=_SOURCE)
    return root


def keygen(keydir: Path, public_out: Path, passphrase: bytes, *, plan: OutputPlan, force: bool = False) -> PublicKey:
    """A new owner key: the private half in ``keydir``, the public half (TOML) in ``public_out``.

    An existing ``public_out`` is replaced only with ``force``, and only when it is a public key.
    """
    replaces = (PUBLIC_KEY,) if force else NEW_ONLY
    plan.check(public_out, flag="--out", replaces=replaces)  # before the passphrase is spent on a key
    key = keymod.plan_private(plan, keydir, keymod.generate(), passphrase)
    text = f'# hcdf-trust registry owner public key\nkeyid = "{key.keyid}"\n'
    text += "".join(f'{k} = "{v}"\n' for k, v in key.to_toml().items())
    plan.add(public_out, text.encode(), flag="--out", replaces=replaces)
    return key


def read_public_key(path: str) -> PublicKey:
    """A public key file written by :func:`keygen`.

    Raises:
        SourceError: malformed, or its key id does not match the key.
    """
    data = _parse(Path(path), path)
    keyid = data.pop("keyid", None)
    if not isinstance(keyid, str):
        raise SourceError("key `keyid`: missing", file=path)
    return _key(_Reader(data, path), keyid)


def _release(content_dir: Path, file: str | os.PathLike[str], version: str, path: str) -> Release:
    """A release of ``file``, which must lie inside ``content_dir`` (its recorded name is relative)."""
    fd, _ = open_checked(os.fspath(file), content_dir)
    try:
        data = read_bounded(fd, CONTENT_LIMIT, source=os.fspath(file), what="content file")
    finally:
        os.close(fd)
    rel = Path(os.path.relpath(os.path.realpath(file), os.path.realpath(content_dir))).as_posix()
    return Release(version, path, rel, hashlib.sha256(data).hexdigest(), len(data))


def statement(domain: str, version: str, schema: str | os.PathLike[str], *, content_dir: Path) -> bytes:
    """The bytes an owner signs to approve ``version`` of ``domain`` (e.g. with ``sigstore sign``)."""
    if not is_reverse_dns(domain) or not is_version(version):
        raise SourceError(f"{domain!r} {version!r}: not a reverse-DNS domain and a version")
    release = _release(content_dir, schema, version, domain_path(domain, version))
    return Domain(domain, "", "", 1, {}, {}).statement(release)


def _merge(versions: dict[str, Release], new: Release, *, what: str, file: str) -> dict[str, Release] | None:
    """``versions`` plus ``new``; None when it is already there with the same content.

    Raises:
        RefusedError: the version exists with other content.
    """
    old = versions.get(new.version)
    if old is None:
        return {**versions, new.version: new}
    if (old.sha256, old.length, old.path) == (new.sha256, new.length, new.path):
        return None
    raise RefusedError(
        f"replaced published version refused: {what} {new.version} is already registered with other content",
        file=file,
        expected=f"sha256:{old.sha256} ({old.length} bytes)",
        actual=f"sha256:{new.sha256} ({new.length} bytes)",
    )


def add_domain(
    source: Source,
    domain: str,
    version: str | None,
    schema: str | os.PathLike[str] | None,
    *,
    content_dir: Path,
    ring: keymod.KeyRing,
    plan: OutputPlan,
    owner: str | None = None,
    owner_keys: list[PublicKey] | None = None,
    threshold: int = 1,
    description: str = "",
    sigstore: tuple[str, str] | None = None,
    bundle: str | None = None,
    sigstore_root: str | None = None,
) -> Domain | None:
    """Record ``version`` of ``domain`` (its schema file, SHA-256, length), signed by its owner.

    A new domain needs ``owner`` and ``owner_keys``; an existing one refuses them (key
    changes go through :func:`rotate_owner`). Without ``version`` and ``schema`` a new
    domain is registered with no version yet. With ``bundle`` (a sigstore bundle over the
    version's statement, see :mod:`.sigstore_bundle`) the owner's sigstore identity approves
    the version instead of its keys; it is verified offline against ``sigstore_root``.
    Returns None when already recorded.

    Raises:
        SourceError: not reverse-DNS, not a version, missing or unexpected owner data.
        RefusedError: the keys folder lacks the owner's keys, or the version exists with other content.
    """
    entry_file = source.entry_path("domain", domain)
    if not is_reverse_dns(domain):
        raise SourceError(f"--domain {domain!r} is not a reverse-DNS domain (e.g. org.ros2)", file=str(entry_file))
    if (version is None) != (schema is None):
        raise SourceError("--version and --schema go together")
    if version is not None and not is_version(version):
        raise SourceError(f"--version {version!r} is not a version (digits and dots, e.g. 1.0)")
    current = source.domains.get(domain)
    if current is None:
        if not owner_keys or not owner:
            raise SourceError(f"{domain} is a new domain: give --owner NAME and --owner-key PUB")
        keys = {k.keyid: k for k in owner_keys}
        if not 1 <= threshold <= len(keys):
            raise SourceError(f"--threshold {threshold} must be between 1 and {len(keys)}")
        current = Domain(domain, description, owner, threshold, keys, {}, str(entry_file), sigstore)
    elif owner_keys or sigstore:
        raise RefusedError(
            f"{domain} exists: its owner keys change only through `registry rotate --domain {domain}`",
            file=str(entry_file),
        )
    if version is None or schema is None:
        if current.versions or domain in source.domains:
            return None
        plan.add(entry_file, dump(current), flag="DIR", replaces=_SOURCE)
        return current
    release = _release(content_dir, schema, version, domain_path(domain, version))
    versions = _merge(current.versions, release, what=domain, file=str(entry_file))
    if versions is None:
        return None
    if bundle is not None:
        from .sigstore_bundle import bundle_path, read_bundle, verify_bundle

        if current.sigstore is None:
            raise SourceError(f"{domain} has no sigstore identity: a new domain takes --sigstore-identity/-issuer")
        if sigstore_root is None:
            raise SourceError("--sigstore-bundle needs --sigstore-trusted-root")
        data = read_bundle(Path(bundle))
        verify_bundle(
            data,
            current.statement(release),
            identity=current.sigstore[0],
            issuer=current.sigstore[1],
            trusted_root=sigstore_root,
            what=f"{domain} {version}",
            source=bundle,
        )
        plan.add(bundle_path(source.dir, domain, version), data, flag="DIR", replaces=_SOURCE)
        release = replace(release, sigstore=True)
    else:
        sigs = ring.sign_threshold(
            current.keys, current.threshold, current.statement(release), what=f"{domain} {version}"
        )
        release = replace(release, signatures={s.keyid: s.signature for s in sigs})
    updated = replace(current, versions={**versions, version: release})
    plan.add(entry_file, dump(updated), flag="DIR", replaces=_SOURCE)
    return updated


def add_artifact(
    source: Source,
    kind: str,
    name: str,
    version: str,
    file: str | os.PathLike[str],
    *,
    content_dir: Path,
    plan: OutputPlan,
    description: str = "",
) -> Artifact | None:
    """Record a stream profile or a core schema version. Returns None when already recorded.

    Raises:
        SourceError: a malformed name or version.
        RefusedError: the version exists with other content.
    """
    entry_file = source.entry_path(kind, name)
    if not _NAME.fullmatch(name):
        raise SourceError(f"{kind} name {name!r} must be lower-case letters, digits, '.', '_' or '-'")
    if not is_version(version):
        raise SourceError(f"{kind} {name}: version {version!r} is not digits and dots", file=os.fspath(file))
    table = source.profiles if kind == "profile" else source.schemas
    current = table.get(name) or Artifact(kind, name, description, {}, str(entry_file))
    release = _release(content_dir, file, version, artifact_path(kind, name, version))
    versions = _merge(current.versions, release, what=f"{kind} {name}", file=str(entry_file))
    if versions is None:
        return None
    updated = replace(current, versions=versions)
    plan.add(entry_file, dump(updated), flag="DIR", replaces=_SOURCE)
    return updated


def profile_identity(file: str) -> tuple[str, str]:
    """The ``name`` and ``version`` attributes of a ``<stream-profile>`` file.

    Raises:
        SourceError: not a stream profile, or either attribute is missing.
    """
    from ..xml import parse_bytes

    tree = parse_bytes(read_input(file, limit=CONTENT_LIMIT, what="stream profile"), source=file)
    root = tree.getroot()
    if root.tag != "stream-profile":
        raise SourceError(f"not a stream profile: the root element is <{root.tag}>", file=file)
    name, version = root.get("name"), root.get("version")
    if not name or not version:
        raise SourceError("<stream-profile> needs name and version attributes", file=file)
    return name, version


def rotate_role(source: Source, role: str, keydir: Path, passphrase: bytes, *, plan: OutputPlan) -> PublicKey:
    """Replace a top-level role's keys with one fresh key. The old private keys stay in
    ``keydir``: ``publish`` needs the old root keys to sign the new root version."""
    _outside(keydir, source.dir)
    key = keymod.plan_private(plan, keydir, keymod.generate(), passphrase)
    roles = dict(source.root.roles)
    roles[role] = Threshold(1, (key.keyid,))
    used = {k for t in roles.values() for k in t.keyids}
    keys = {k: v for k, v in {**source.root.keys, key.keyid: key}.items() if k in used}
    plan.add(source.dir / "root.toml", dump(RootOfTrust(keys, roles)), flag="DIR", replaces=_SOURCE)
    return key


def rotate_owner(
    source: Source, domain: str, keydir: Path, ring: keymod.KeyRing, passphrase: bytes, *, plan: OutputPlan
) -> PublicKey:
    """Give ``domain`` a fresh owner key, authorised by a threshold of its current keys;
    every version is re-signed with the new key.

    Raises:
        SourceError: no such domain.
        RefusedError: the keys folder lacks the current owner's keys.
    """
    current = source.domains.get(domain)
    if current is None:
        raise SourceError(f"no domain {domain} in {source.dir}")
    _outside(keydir, source.dir)
    statement = f"hcdf-registry-rotate:{domain}".encode()
    ring.sign_threshold(current.keys, current.threshold, statement, what=f"rotating {domain}'s owner key")
    private = keymod.generate()
    key = keymod.plan_private(plan, keydir, private, passphrase)
    from securesystemslib.signer import CryptoSigner

    signer = CryptoSigner(private)
    updated = replace(current, keys={key.keyid: key}, threshold=1)
    versions = {
        v: replace(r, signatures={key.keyid: signer.sign(updated.statement(r)).signature})
        for v, r in current.versions.items()
    }
    updated = replace(updated, versions=versions)
    plan.add(source.entry_path("domain", domain), dump(updated), flag="DIR", replaces=_SOURCE)
    return key
