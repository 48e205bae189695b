"""Sigstore bundles as an owner's approval of a domain version (the optional ``[sigstore]`` extra).

An owner whose entry names a sigstore identity (``[owner.sigstore] identity, issuer``) may
approve a version with a sigstore bundle over the version's statement (the same canonical
bytes an ed25519 owner key signs, written by ``registry statement``) instead of a key
signature. The bundle is kept in the source (``bundles/<domain>/<version>.sigstore.json``)
and verified fully offline, against a pinned sigstore trusted-root file, by ``add`` and
again by ``publish``: no network is ever used. Signing happens elsewhere (CI with an
ambient OIDC identity: ``sigstore sign``), because sigstore cannot sign offline.
The domain's TUF role is still signed by the owner's TUF keys.
"""

from __future__ import annotations

from pathlib import Path

from ..errors import InputError
from ..localfile import JsonError, parse_json, read_input
from .errors import RefusedError

BUNDLE_LIMIT = 1 << 20
TRUSTED_ROOT_LIMIT = 4 << 20


def bundle_path(source_dir: Path, domain: str, version: str) -> Path:
    """Where a version's bundle lives in the source."""
    return source_dir / "bundles" / domain / f"{version}.sigstore.json"


def verify_bundle(
    bundle: bytes, statement: bytes, *, identity: str, issuer: str, trusted_root: str, what: str, source: str
) -> None:
    """Check ``bundle`` signs ``statement`` as ``identity`` (from ``issuer``), offline.

    Raises:
        InputError: sigstore is not installed, or the trusted root is unreadable or malformed.
        RefusedError: the bundle is malformed or does not verify (wrong identity, other content, ...).
    """
    try:
        from sigstore.errors import Error as SigstoreError
        from sigstore.models import Bundle, TrustedRoot
        from sigstore.verify import Verifier, policy
        from sigstore_models.trustroot import v1 as trustroot_v1
    except ImportError:
        raise InputError("sigstore bundles need the optional extra: pip install 'hcdf-trust[sigstore]'") from None
    raw_root = read_input(trusted_root, limit=TRUSTED_ROOT_LIMIT, what="sigstore trusted root")
    parse_json(raw_root, source=trusted_root, what="sigstore trusted root", limit=TRUSTED_ROOT_LIMIT)
    try:
        parse_json(bundle, source=source, what=f"{what}: sigstore bundle", limit=BUNDLE_LIMIT)
    except JsonError as exc:  # pydantic keeps the last of two equal keys: refused like any ambiguous JSON
        raise RefusedError(exc.message, file=source, line=exc.line) from None
    try:
        root = TrustedRoot(trustroot_v1.TrustedRoot.from_json(raw_root))
    except Exception as exc:  # pydantic ValidationError, sigstore Error, ValueError
        raise InputError(f"not a sigstore trusted root: {exc}", file=trusted_root) from None
    try:
        Verifier(trusted_root=root).verify_artifact(
            statement, Bundle.from_json(bundle), policy.Identity(identity=identity, issuer=issuer)
        )
    except (SigstoreError, ValueError) as exc:  # ValueError: a bundle that is not JSON of the right shape
        raise RefusedError(
            f"{what}: the sigstore bundle does not verify as {identity} ({issuer}): {exc}",
            file=source,
            expected=f"a bundle by {identity} over this version's statement",
            actual=str(exc).splitlines()[0] if str(exc) else type(exc).__name__,
        ) from None


def read_bundle(path: Path) -> bytes:
    return read_input(path, limit=BUNDLE_LIMIT, what="sigstore bundle")
