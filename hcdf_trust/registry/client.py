"""The registry client: ``tuf.ngclient`` over a published site, a URL or a local folder.

Trust starts from the root metadata bytes the user pins (``--trusted-root``); the client
walks newer root versions from there (key rotation), then timestamp, snapshot, targets
and, on demand, one domain's role. Every failure is matched on python-tuf's exception
classes (never on their wording) and named after the attack it reveals.

Fetchers: ``http(s)://`` goes through ngclient's default urllib3 fetcher (the one
python-tuf tests and ships; every download is capped at the signed length by
``FetcherInterface`` itself, so no second HTTP stack is needed for a signed
repository); a folder goes through :class:`DirectoryFetcher`, which reads through
:mod:`hcdf_trust.localfile` (confined to the site, regular files, never blocking).
"""

from __future__ import annotations

import contextlib
import hashlib
import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any
from urllib.parse import quote, unquote, urlsplit

from ..errors import HcdfTrustError, InputError, NotFoundError, redact
from ..localfile import JsonError, open_checked, parse_json, read_bounded, read_chunks, read_input
from .errors import AttackError, TransportError
from .source import domain_pattern, is_version

if TYPE_CHECKING:
    from tuf.api.metadata import TargetFile, Targets
    from tuf.ngclient import Updater

ROOT_LIMIT = 512_000
DEFAULT_TIMEOUT = 30.0  # seconds to connect or between bytes from an http(s) site (--timeout's default)


# The public API (docs/api.md); everything else here is internal.
__all__ = ["RegistryClient", "Report", "verify"]


def check_metadata(data: bytes, what: str) -> None:
    """Refuse metadata that parsers could read differently: python-tuf's ``json.loads`` keeps
    the last of two ``"signed"`` keys, another client the first (see :func:`.localfile.parse_json`).

    Raises:
        AttackError: duplicate keys, NaN, lone surrogates, too deep, not UTF-8 or not JSON.
    """
    try:
        parse_json(data, source=what, what=what, limit=max(len(data), 1))
    except JsonError as exc:
        raise AttackError(f"ambiguous or malformed metadata: {exc.message}", file=what, line=exc.line) from None


def _strict(base: type) -> type:
    """``base`` (a ``FetcherInterface``) whose metadata downloads pass :func:`check_metadata`.

    ngclient fetches metadata with ``download_bytes`` (capped at the role's maximum length)
    and targets with ``download_file``, so only metadata is parsed here.
    """

    class Strict(base):  # type: ignore[misc]
        def download_bytes(self, url: str, max_length: int) -> bytes:
            data: bytes = super().download_bytes(url, max_length)
            check_metadata(data, unquote(urlsplit(url).path.rsplit("/", 1)[-1]))
            return data

    return Strict


def _fetcher_base() -> type:
    from tuf.ngclient import FetcherInterface

    return _strict(FetcherInterface)


def _https_fetcher(timeout: float, ca_bundle: str | None) -> Any:
    """python-tuf's urllib3 fetcher (strict metadata), trusting ``ca_bundle``'s CAs too.

    ``Urllib3Fetcher`` takes no TLS argument; its pool manager (``_proxy_env``, a
    ``ProxyEnvironment`` handing its keyword arguments to every urllib3 ``PoolManager``) is
    replaced by one built with the same ``ssl.SSLContext`` every other https fetch here uses
    (:func:`hcdf_trust.include.fetch.load_ca_bundle`).
    """
    from tuf.ngclient import Urllib3Fetcher

    fetcher = _strict(Urllib3Fetcher)(socket_timeout=timeout)
    if ca_bundle:
        from tuf.ngclient._internal.proxy import ProxyEnvironment

        from ..include.fetch import load_ca_bundle

        fetcher._proxy_env = ProxyEnvironment(
            headers={"User-Agent": "hcdf-trust python-tuf"}, ssl_context=load_ca_bundle(ca_bundle)
        )
    return fetcher


def make_directory_fetcher(root: Path) -> Any:
    """A ``FetcherInterface`` serving ``file://`` URLs from the folder ``root``."""
    from tuf.api.exceptions import DownloadError, DownloadHTTPError

    class DirectoryFetcher(_fetcher_base()):  # type: ignore[misc]
        """Reads a site from a folder; a missing file is a 404, so root probing stops."""

        def _fetch(self, url: str) -> Iterator[bytes]:
            path = Path(unquote(urlsplit(url).path))
            try:
                fd, _ = open_checked(path, root)
            except NotFoundError:
                raise DownloadHTTPError(f"{path}: not found", 404) from None
            except InputError as exc:
                raise DownloadError(str(exc)) from None
            return _chunks(fd)

    return DirectoryFetcher()


def _chunks(fd: int) -> Iterator[bytes]:
    try:
        yield from read_chunks(fd)
    finally:
        os.close(fd)


def _attack(exc: Exception, what: str, site: str = "", flag: str = "--registry") -> HcdfTrustError:
    """The error (and attack name) for a python-tuf exception raised while loading ``what``."""
    from tuf.api import exceptions as tx

    target = what.startswith("target ")
    if isinstance(exc, tx.ExpiredMetadataError):
        return AttackError(f"freeze attack or stale mirror: {what}: expired metadata ({exc})")
    if isinstance(exc, tx.BadVersionNumberError):
        return AttackError(f"rollback attack: {what}: older than the version this client already trusts ({exc})")
    if isinstance(exc, tx.LengthOrHashMismatchError):
        if target:
            return AttackError(f"arbitrary content: {what} does not match its signed length and hash ({exc})")
        return AttackError(f"mix-and-match attack: {what} does not match the hash its parent metadata signed ({exc})")
    if isinstance(exc, tx.DownloadLengthMismatchError):
        if target:
            return AttackError(f"endless data: {what} is longer than its signed length ({exc})")
        return AttackError(f"endless data or mix-and-match attack: {what} is longer than its signed length ({exc})")
    if isinstance(exc, tx.UnsignedMetadataError):
        return AttackError(
            f"bad signature: {what} is not signed by a threshold of its keys, "
            f"e.g. a publisher without the owner's key ({exc})"
        )
    if isinstance(exc, tx.RepositoryError):
        return AttackError(f"the registry's metadata does not verify: {what}: {exc}")
    if isinstance(exc, tx.DownloadHTTPError):
        return TransportError(f"{what}: HTTP {exc.status_code} ({exc})")
    if isinstance(exc, tx.DownloadError):
        if "://" not in site:  # a folder copy of the site (DirectoryFetcher): its refusal as it is
            return TransportError(f"{what}: download failed: {exc.__cause__ or exc}")
        return TransportError(_unreachable(exc, what, site, flag))
    return InputError(f"{what}: {exc}")


def _unreachable(exc: Exception, what: str, site: str, flag: str) -> str:
    """A failed connection said as the user can act on it: the host, why in a few words, and the
    option that named the site (not urllib3's "HTTPSConnectionPool(...): Max retries exceeded")."""
    import re

    cause: BaseException = exc
    while cause.__cause__ is not None:
        cause = cause.__cause__
    reason = getattr(cause, "reason", None) or cause  # urllib3's MaxRetryError wraps the real one
    text = str(reason)
    errno = re.search(r"\[Errno -?\d+\] ([^'\")\]]+)", text)
    name = type(reason).__name__
    why = (
        errno.group(1).strip()
        if errno
        else "timed out"
        if "Timeout" in name or "timed out" in text
        else f"TLS failed: {text[:200]}"
        if "SSL" in name
        else text[:200]
    )
    parts = urlsplit(site)
    host = (f"{parts.hostname}:{parts.port}" if parts.port else parts.hostname) if parts.hostname else site
    return (
        f"cannot reach the registry at {host} ({why}) to fetch {what}; check {flag} {redact(site)} "
        "and the network, or give a folder holding a copy of the site"
    )


def _tuf_errors() -> tuple[type[Exception], ...]:
    from tuf.api import exceptions as tx

    return (tx.RepositoryError, tx.DownloadError)


@dataclass
class Finding:
    """A problem ``verify`` found that python-tuf's client silently ignores."""

    role: str
    path: str
    domain: bool = True  # False: the role is top-level targets or a shard, which should list no domain file


@dataclass
class Report:
    """What :func:`verify` checked: the root version trusted, the domain roles loaded, the
    files downloaded and verified, and ``stray`` paths that TUF clients silently ignore (listed
    outside their delegation: ``registry verify`` reports each as cross-domain signing).

    Example:
        >>> from pathlib import Path
        >>> from hcdf_trust.registry.client import RegistryClient
        >>> client = RegistryClient.open("site", "site/metadata/1.root.json", cache_dir=Path("client"))
        >>> from hcdf_trust.registry.client import verify
        >>> verify(client)
        Report(root_version=1, roles=2, targets=3, stray=[])
    """

    root_version: int = 0
    roles: int = 0
    targets: int = 0
    stray: list[Finding] = field(default_factory=list)


class RegistryClient:
    """A TUF client for one published registry (``site``: an http(s) URL or a folder).

    Construction loads the trusted root; nothing is fetched until :meth:`refresh`. Every
    answer is verified by python-tuf; a lying or stale site raises ``AttackError`` (exit 1).
    ``site`` here is a folder copy of a published site (``registry publish --out site``).

    Raises:
        InputError: the trusted root is unreadable or not TUF root metadata.

    Example:
        >>> from pathlib import Path
        >>> from hcdf_trust.registry.client import RegistryClient
        >>> client = RegistryClient.open("site", "site/metadata/1.root.json", cache_dir=Path("client"))
        >>> client.domains()
        ['org.gazebosim', 'org.ros2']
        >>> schema = client.download(client.versions("org.ros2")["1.0"])  # checked: length, SHA-256
        >>> schema.startswith(b"<?xml")
        True
        >>> sorted(client.artifacts("profile"))
        ['operational']
    """

    def __init__(
        self,
        site: str,
        *,
        trusted_root: bytes,
        cache_dir: Path | None = None,
        timeout: float = DEFAULT_TIMEOUT,
        ca_bundle: str | None = None,
        insecure_registries: tuple[str, ...] = (),
        flag: str = "--registry",
    ) -> None:

        try:
            parse_json(trusted_root, source="the trusted root", what="the trusted root", limit=ROOT_LIMIT)
        except JsonError as exc:
            raise InputError(f"the trusted root is not valid TUF root metadata: {exc.message}") from None
        self.site = site
        self.flag = flag  # how the user named the site, for messages (--registry, SITE)
        local = "://" not in site
        self.cache_dir = Path(cache_dir) if cache_dir else default_cache_dir(site, trusted_root)
        self.metadata_dir = self.cache_dir / "metadata"
        self.metadata_dir.mkdir(parents=True, exist_ok=True)
        (self.cache_dir / "targets").mkdir(exist_ok=True)
        self._previous = self._cached_roles()
        if site.startswith("oci://"):  # an OCI artifact (registry publish --oci): transport only
            from ..oci.site import BASE, oci_fetcher

            base, fetcher = (
                BASE.rstrip("/"),
                oci_fetcher(site, ca_bundle=ca_bundle, insecure_registries=insecure_registries),
            )
        elif local:
            folder = Path(site).resolve()
            if not folder.is_dir():
                raise NotFoundError(f"{site}: no such registry site folder", file=site)
            base, fetcher = folder.as_uri(), make_directory_fetcher(folder)
        else:
            scheme = urlsplit(site).scheme
            if scheme not in ("http", "https"):
                raise InputError(f"{site}: a registry is an http(s) URL or a folder", file=site)
            base, fetcher = site.rstrip("/"), _https_fetcher(timeout, ca_bundle)
        try:
            self.updater: Updater = _planned_updater()(
                str(self.metadata_dir),
                f"{base}/metadata/",
                str(self.cache_dir / "targets"),
                f"{base}/targets/",
                fetcher,
                bootstrap=trusted_root,
            )
        except (ValueError, TypeError, KeyError, *_tuf_errors()) as exc:  # type: ignore[misc]
            raise InputError(f"the trusted root is not valid TUF root metadata: {exc}") from None
        self._refreshed = False

    @classmethod
    def open(
        cls,
        site: str,
        trusted_root: str,
        *,
        cache_dir: Path | None = None,
        timeout: float = DEFAULT_TIMEOUT,
        ca_bundle: str | None = None,
        insecure_registries: tuple[str, ...] = (),
        flag: str = "--registry",
    ) -> RegistryClient:
        """A client whose trust anchor is the root metadata file ``trusted_root``
        (``ca_bundle``, ``insecure_registries``: as ``--ca-bundle``, ``--insecure-registry``)."""
        root = read_input(trusted_root, limit=ROOT_LIMIT, what="trusted root")
        return cls(
            site,
            trusted_root=root,
            cache_dir=cache_dir,
            timeout=timeout,
            ca_bundle=ca_bundle,
            insecure_registries=insecure_registries,
            flag=flag,
        )

    # -- loading ------------------------------------------------------------------------

    def _cached_roles(self) -> dict[str, bytes]:
        """The role files this client trusted before this run (to notice a replaced version)."""
        out = {}
        for path in self.metadata_dir.glob("*.json"):
            role = unquote(path.stem)
            if role in ("root", "timestamp", "snapshot") or not path.is_file():
                continue
            try:
                data = read_input(path, limit=8 << 20, what="cached metadata")
                check_metadata(data, path.name)
            except (InputError, AttackError):
                continue  # ngclient will not trust it either (see _planned_updater)
            out[role] = data
        return out

    def refresh(self) -> None:
        """Root (walking every newer version), timestamp, snapshot and top-level targets.

        Raises:
            AttackError: the repository is lying or stale (exit 1).
            TransportError: it could not be reached (exit 3).
        """
        if self._refreshed:
            return
        try:
            self.updater.refresh()
        except _tuf_errors() as exc:
            raise _attack(exc, "top-level metadata", self.site, self.flag) from None
        self._refreshed = True
        self._check_replaced("targets")

    def _trusted(self, role: str) -> Targets:
        # python-tuf keeps verified metadata in its trusted set; it has no public accessor.
        md: Targets = self.updater._trusted_set[role]  # type: ignore[assignment]
        return md

    @property
    def root_version(self) -> int:
        return int(self.updater._trusted_set.root.version)

    def domains(self) -> list[str]:
        """The registered extension domains: the ``extensions/<domain>/*`` patterns that
        top-level targets delegates (to shard roles, which delegate to the domains)."""
        self.refresh()
        delegations = self._trusted("targets").delegations
        out = set()
        for role in (delegations.roles or {}).values() if delegations else []:
            for pattern in role.paths or []:
                parts = pattern.split("/")
                if len(parts) == 3 and parts[0] == "extensions" and parts[2] == "*":
                    out.add(parts[1])
        return sorted(out)

    def role(self, domain: str) -> Targets:
        """A domain's verified role, loaded through the delegation."""
        self.refresh()
        if domain not in self.domains():
            raise NotFoundError(f"{domain} is not a registered domain", url=self.site)
        try:
            self.updater.get_targetinfo(f"extensions/{domain}/")
        except _tuf_errors() as exc:
            raise _attack(exc, f"{domain}.json", self.site, self.flag) from None
        self._check_replaced(domain)
        return self._trusted(domain)

    def versions(self, domain: str) -> dict[str, TargetFile]:
        """A domain's schema versions; paths outside its delegation are ignored, as TUF clients do."""
        role = self.role(domain)
        prefix = f"extensions/{domain}/"
        out = {}
        for path, info in role.targets.items():
            version = path.removeprefix(prefix).removesuffix(".xsd")
            if path.startswith(prefix) and path.count("/") == 2 and is_version(version):
                out[version] = info
        return out

    def stray(self, domain: str) -> list[Finding]:
        """Paths a domain's role lists outside its delegation (clients ignore them)."""
        from tuf.api.metadata import DelegatedRole

        pattern = DelegatedRole(domain, [], 1, True, paths=[domain_pattern(domain)])
        return [Finding(domain, p) for p in self.role(domain).targets if not pattern.is_delegated_path(p)]

    def artifacts(self, kind: str) -> dict[str, dict[str, TargetFile]]:
        """Stream profiles (``kind="profile"``) or core schemas: name -> version -> target."""
        self.refresh()
        top, suffix = ("profiles/", ".streams.xml") if kind == "profile" else ("schemas/", ".xsd")
        out: dict[str, dict[str, TargetFile]] = {}
        for path, info in self._trusted("targets").targets.items():
            parts = path.split("/")
            if path.startswith(top) and len(parts) == 3 and parts[2].endswith(suffix):
                out.setdefault(parts[1], {})[parts[2].removesuffix(suffix)] = info
        return out

    def download(self, info: TargetFile) -> bytes:
        """A target's bytes, verified against its signed length and hash.

        Raises:
            AttackError: arbitrary content or endless data (exit 1).
            TransportError: the file could not be fetched (exit 3).
        """
        # Into memory (python-tuf writes to a path: this one names the memfd), so a killed
        # run leaves no partial download in the cache.
        fd = os.memfd_create("registry-target", os.MFD_CLOEXEC)
        try:
            self.updater.download_target(info, filepath=f"/proc/self/fd/{fd}")
            return read_bounded(fd, info.length, source=info.path, what="downloaded target")
        except _tuf_errors() as exc:
            raise _attack(exc, f"target {info.path}", self.site, self.flag) from None
        finally:
            os.close(fd)

    def _check_replaced(self, role: str) -> None:
        """A version this client saw before must keep its content.

        Raises:
            AttackError: a replaced published version; the previously trusted role is restored.
        """
        from tuf.api.metadata import Metadata

        before = self._previous.get(role)
        if before is None:
            return
        with contextlib.suppress(OSError):
            if (self.metadata_dir / f"{quote(role, '')}.json").read_bytes() == before:
                return  # the same signed file as last time (the usual warm refresh)
        try:
            old = Metadata.from_bytes(before).signed.targets  # type: ignore[attr-defined]
        except Exception:  # a cache file we cannot parse proves nothing
            return
        new = self._trusted(role).targets
        for path, was in old.items():
            now = new.get(path)
            if now is not None and (now.length, now.hashes) != (was.length, was.hashes):
                from ..outputs import OutputPlan

                restore = OutputPlan()  # put back what this client trusted, all or nothing
                restore.add(self.metadata_dir / f"{quote(role, '')}.json", before, flag="the registry cache")
                restore.commit()
                raise AttackError(
                    f"replaced published version: {path} ({role}) changed content since this client last saw it",
                    expected=f"sha256:{was.hashes.get('sha256')} ({was.length} bytes)",
                    actual=f"sha256:{now.hashes.get('sha256')} ({now.length} bytes)",
                    url=self.site,
                )


def _planned_updater() -> type[Updater]:
    """python-tuf's Updater with its metadata written through OutputPlan: staged beside the
    file, renamed, and a killed refresh's temporary file removed by the next one (python-tuf's
    own ``tmpXXXX`` files would stay in the client cache for ever). Its one writer,
    ``_persist_file``, is overridden; the test of a killed refresh notices if it is renamed.

    Its cached metadata is read through :func:`check_metadata`: a cached file that fails it
    counts as absent, as ngclient treats any invalid cache file (``_load_local_metadata``,
    its one reader, is overridden; test_attack_ota's cached-file test notices if it is renamed)."""
    from tuf.api.exceptions import RepositoryError
    from tuf.ngclient import Updater

    class PlannedUpdater(Updater):
        def _persist_file(self, filename: str, data: bytes) -> None:
            from ..outputs import OutputPlan

            plan = OutputPlan()
            plan.add(filename, data, flag="the registry client cache")
            plan.commit()

        def _load_local_metadata(self, rolename: str) -> bytes:
            data: bytes = super()._load_local_metadata(rolename)
            try:
                check_metadata(data, f"cached {rolename}.json")
            except AttackError as exc:
                raise RepositoryError(exc.message) from None
            return data

    return PlannedUpdater


def default_cache_dir(site: str, trusted_root: bytes) -> Path:
    """Where a client of ``site`` trusting ``trusted_root`` keeps its metadata by default:
    one folder per site and root, under ``$XDG_CACHE_HOME/hcdf-trust/registry``."""
    local = "://" not in site
    key = hashlib.sha256(f"{os.path.realpath(site) if local else site}\0".encode() + trusted_root).hexdigest()
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "hcdf-trust" / "registry" / key[:24]


def latest(versions: dict[str, Any]) -> str:
    """The highest version (numeric order)."""
    return max(versions, key=lambda v: tuple(int(p) for p in v.split(".")))


def verify(client: RegistryClient) -> Report:
    """Refresh, load every domain's role and download every target, checking each one
    (``hcdf-trust registry verify``).

    Raises:
        AttackError, TransportError: the first check that fails.

    Example:
        >>> from pathlib import Path
        >>> from hcdf_trust.registry.client import RegistryClient
        >>> client = RegistryClient.open("site", "site/metadata/1.root.json", cache_dir=Path("client"))
        >>> from hcdf_trust.registry.client import verify
        >>> report = verify(client)
        >>> report.roles, report.targets, report.stray
        (2, 3, [])
    """
    client.refresh()
    report = Report(root_version=client.root_version)
    infos: list[TargetFile] = []
    for domain in client.domains():
        infos += client.versions(domain).values()
        report.stray += client.stray(domain)
        report.roles += 1
    for kind in ("profile", "schema"):
        for versions in client.artifacts(kind).values():
            infos += versions.values()
    # Targets listed above the domain roles would shadow them (a client takes the first match).
    top = client._trusted("targets").targets
    report.stray += [Finding("targets", p, domain=False) for p in top if p.startswith("extensions/")]
    delegations = client._trusted("targets").delegations
    for shard in sorted(delegations.roles or {}) if delegations else []:
        if client.updater._trusted_set.contains(shard, "targets"):  # loaded by the lookups above
            report.stray += [Finding(shard, p, domain=False) for p in client._trusted(shard).targets]
    for info in infos:
        client.download(info)
        report.targets += 1
    return report
