"""``resolve --registry`` / ``verify --registry``: a resolved tree checked against the registry.

A step after resolution, over what the resolver found (it is not part of the resolver):

1. every document of the tree (:attr:`Resolution.documents`) goes through
   :func:`.validation.check_document`: each ``<extension domain version>`` must be
   registered (a warning, an error under ``strict``) and its content must be valid
   against the registered schema;
2. every stream-profile artifact is read again (the local file or mirror copy, else the
   cache blob), checked against the digest the resolution verified, and its root's
   ``name`` and ``version`` looked up: a registered profile must have the registered
   SHA-256 and length (a digest mismatch, exit 1).

``verify`` writes nothing, so its TUF client works in a temporary copy of the metadata
cache (``persist=False``): the rollback protection of what was trusted before is kept,
and the cache is left as it was.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from ..digest import hash_bytes
from ..document import Kind
from ..errors import DigestMismatchError, HcdfTrustError, InputError, IntegrityError, NotFoundError, Notice
from ..localfile import open_local, read_bounded, read_input
from ..store import ContentStore, default_cache_dir
from ..xml import parse_bytes
from .client import DEFAULT_TIMEOUT, ROOT_LIMIT, RegistryClient
from .client import default_cache_dir as client_cache_dir
from .validation import PROFILE_LIMIT, RegistrySchemaSource, check_document

if TYPE_CHECKING:
    from ..bundle import BundleFiles
    from ..include.resolver import Artifact, Resolution
    from ..outputs import OutputPlan

METADATA_LIMIT = 8 << 20


class RegistryCheckError(IntegrityError):
    """A document breaks the registry's rules: an unregistered extension (under ``strict``)
    or extension content that is not valid against its registered schema. ``code`` is the
    finding's (``extension-unregistered``, ``extension-content``)."""

    code = "registry-check"

    def __init__(self, code: str, message: str, *, file: str | None = None, line: int | None = None) -> None:
        super().__init__(message, file=file, line=line)
        self.code = code


class ProfileDigestError(DigestMismatchError):
    """A stream profile whose name and version are registered, with other content."""

    code = "stream-profile-digest"


@dataclass(frozen=True, kw_only=True)
class RegistryCheck:
    """The registry a resolve run is checked against (``site``: an http(s) URL or a folder).

    ``trusted_root`` is the root metadata file's path, ``root`` its bytes; ``persist``
    False (``verify``) keeps the TUF client's metadata in a temporary copy.
    """

    site: str
    trusted_root: str
    root: bytes
    strict: bool = False
    persist: bool = True
    ca_bundle: str | None = None  # --ca-bundle, for an https site
    timeout: float = DEFAULT_TIMEOUT  # resolve's --timeout: seconds without data from an https site

    @classmethod
    def open(
        cls,
        site: str,
        trusted_root: str,
        *,
        strict: bool = False,
        persist: bool = True,
        ca_bundle: str | None = None,
        timeout: float = DEFAULT_TIMEOUT,
    ) -> RegistryCheck:
        """Read the trusted root, and check that a folder site exists, before anything is resolved.

        Raises:
            InputError: the trusted root is unreadable, or the site is neither a folder nor an http(s) URL.
        """
        if "://" in site:
            if site.partition("://")[0].lower() not in ("http", "https"):
                raise InputError(f"{site}: a registry is an http(s) URL or a folder", file=site)
        elif not os.path.isdir(site):
            raise NotFoundError(f"{site}: no such registry site folder", file=site)
        root = read_input(trusted_root, limit=ROOT_LIMIT, what="trusted root")
        return cls(
            site=site,
            trusted_root=trusted_root,
            root=root,
            strict=strict,
            persist=persist,
            ca_bundle=ca_bundle,
            timeout=timeout,
        )

    def protect(self, plan: OutputPlan) -> None:
        """No output of the run may replace the trusted root or a file of a local site."""
        plan.protect(self.trusted_root, what="the registry's trusted root")
        if "://" not in self.site:
            plan.protect_tree(self.site, what="the registry site")

    def check(self, res: Resolution, *, cache_dir: str | None = None) -> tuple[list[HcdfTrustError], list[Notice]]:
        """The registry's errors and warnings for a resolved tree (``cache_dir``: the resolve cache).

        Raises:
            AttackError: the registry does not verify (exit 1).
            TransportError: it cannot be reached (exit 3).
        """
        with self._client() as client:
            return check_resolution(res, client, strict=self.strict, cache_dir=cache_dir)

    @contextlib.contextmanager
    def _client(self) -> Iterator[RegistryClient]:
        if self.persist:
            yield RegistryClient(self.site, trusted_root=self.root, ca_bundle=self.ca_bundle, timeout=self.timeout)
            return
        with tempfile.TemporaryDirectory(prefix="hcdf-trust-registry-") as tmp:
            _seed(client_cache_dir(self.site, self.root) / "metadata", Path(tmp) / "metadata")
            yield RegistryClient(
                self.site, trusted_root=self.root, cache_dir=Path(tmp), ca_bundle=self.ca_bundle, timeout=self.timeout
            )


def _seed(cached: Path, dest: Path) -> None:
    """Copy the metadata a client trusted before (regular files only, bounded) into ``dest``."""
    from ..outputs import OutputPlan

    dest.mkdir(parents=True)
    try:
        entries = list(os.scandir(cached))
    except OSError:
        return  # no client state yet: trust starts from the root
    plan = OutputPlan()
    for entry in entries:
        if not entry.name.endswith(".json") or not entry.is_file(follow_symlinks=False):
            continue
        with contextlib.suppress(InputError):  # state we cannot read proves nothing
            data = read_input(entry.path, limit=METADATA_LIMIT, what="cached metadata")
            plan.add(dest / entry.name, data, flag="registry state", under=dest)
    plan.commit()


def check_resolution(
    res: Resolution, client: RegistryClient, *, strict: bool = False, cache_dir: str | None = None
) -> tuple[list[HcdfTrustError], list[Notice]]:
    """Extensions of every document, and the digest of every registered stream profile.

    Returns:
        The errors (exit 1, or 3 for a profile that cannot be read again) and the warnings.

    Raises:
        AttackError, TransportError: the registry does not verify or cannot be reached.
    """
    errors: list[HcdfTrustError] = []
    warnings: list[Notice] = []
    schemas = RegistrySchemaSource(client)
    for doc in res.documents.values():
        for f in check_document(doc.tree, source=doc.source, path=None, schemas=schemas, strict=strict):
            if f.is_error:
                errors.append(RegistryCheckError(f.code, f.message, file=f.file, line=f.line))
            else:
                warnings.append(Notice(f.code, f.message, file=f.file, line=f.line))
    profiles = [a for a in res.artifacts.values() if a.kind is Kind.STREAM_PROFILE and a.sha256 is not None]
    if profiles:
        registered = client.artifacts("profile")
        store = ContentStore(cache_dir or default_cache_dir())
        for art in sorted(profiles, key=lambda a: a.url):
            try:
                name, version = _profile_identity(art, store, res.bundle)
            except HcdfTrustError as exc:
                errors.append(exc)
                continue
            info = registered.get(name or "", {}).get(version or "")
            if info is None:
                continue
            want = f"sha256:{info.hashes.get('sha256')} ({info.length} bytes)"
            have = f"sha256:{art.sha256} ({art.size} bytes)"
            if (info.hashes.get("sha256"), info.length) == (art.sha256, art.size):
                continue
            for use in art.uses:
                errors.append(
                    ProfileDigestError(
                        f"stream profile {use.ref.uri} ({name} {version}) differs from the one "
                        f"registered in {client.site}",
                        file=use.doc,
                        line=use.ref.line,
                        expected=want,
                        actual=have,
                        url=art.url,
                    )
                )
    return errors, warnings


def _profile_identity(art: Artifact, store: ContentStore, bundle: BundleFiles | None) -> tuple[str | None, str | None]:
    """The ``name`` and ``version`` on the root of the profile the resolution verified (an entry
    of ``bundle`` when the tree was read from one).

    Raises:
        InputError: the bytes are gone, changed since they were verified, or are not XML.
    """
    use = art.uses[0]
    file, line = use.doc, use.ref.line
    assert art.sha256 is not None
    path = art.location.path
    if path is None:  # remote: the verified blob in the cache
        path = str(store.path_for(art.sha256))
        root = os.path.dirname(path)
    else:
        root = str(art.location.root or os.path.dirname(path))
    try:
        if bundle is not None:
            data = bundle.read(path, file=file, line=line, limit=PROFILE_LIMIT, source=art.url)
        else:
            with open_local(path, root, file=file, line=line) as fd:
                data = read_bounded(fd, PROFILE_LIMIT, source=art.url, what="stream profile")
    except NotFoundError:
        raise InputError(
            f"stream profile {use.ref.uri}: its verified content is no longer available to check against the registry",
            file=file,
            line=line,
            url=art.url,
        ) from None
    if hash_bytes(data).sha256 != art.sha256:
        raise InputError(
            f"stream profile {use.ref.uri} changed after it was verified", file=file, line=line, url=art.url
        )
    element = parse_bytes(data, source=art.url).getroot()
    return element.get("name"), element.get("version")
