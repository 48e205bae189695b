"""Resolve a document tree: walk includes, fetch each distinct file once, verify every pin.

The run has three steps:

1. Walk the include tree breadth first; each level's new includes are fetched in
   parallel, checked against their pins and parsed before the next level.
2. Fetch every other artifact (models, meshes, stream profiles, firmware
   manifests) in parallel, hashing while streaming.
3. Decide, in pure functions over digests, pins and the lock (:func:`check_artifact`,
   :func:`lockfile.compare`), which errors and warnings the tree has.

Trust on first use: the lock is the pin of every reference without a full pin. A
lock entry that disagrees with the content is an error (``changed since it was
locked``) unless that reference is being updated (``update_all``/``update``); a
full pin in the document that matches the content is authoritative, and the lock
follows it. New references are added to the lock, unreferenced ones dropped.

Nothing is written here except verified cache blobs; the lock file and the
flattened document are written by the caller, and only when the run is clean.
"""

from __future__ import annotations

import functools
import os
import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any
from urllib.parse import unquote, urlsplit

from ..digest import Hashed, Pin, hash_bytes, hash_chunks, include_mismatch_hint, parse_pin
from ..document import Document, Kind, Reference, foreign_major_notice
from ..errors import (
    DigestMismatchError,
    FetchError,
    HcdfTrustError,
    IncludeCycleError,
    IncludeDepthError,
    InputError,
    LockDriftError,
    LockFileError,
    NotFoundError,
    Notice,
    OfflineError,
    UnpinnedError,
    WeakPinError,
)
from ..localfile import ConfinedFolders, absolute, open_local, read_bounded
from ..store import ContentStore, default_cache_dir
from ..xml import MAX_DOCUMENT_BYTES
from . import lockfile
from .locate import Location, Locator, confinement_root, display_path, explain_missing, file_url

if TYPE_CHECKING:
    from ..bundle import BundleFiles
    from .fetch import HttpFetcher  # imported (with ssl, httpx) only when a URL is fetched

DEFAULT_MAX_DEPTH = 16
# The fetcher's defaults (fetch.py), repeated so that an offline run never imports it.
DEFAULT_MAX_BYTES = 4 << 30
DEFAULT_TIMEOUT = 30.0
DEFAULT_JOBS = 16
# Local files and cached blobs at least this large are hashed on a thread per core;
# smaller ones in the resolving thread (see _Run._plan).
PARALLEL_MIN_BYTES = 256 << 10
try:
    _CORES = max(1, len(os.sched_getaffinity(0)))
except AttributeError:  # not on Linux
    _CORES = os.cpu_count() or 1


@dataclass(frozen=True)
class ResolveOptions:
    """Everything a :func:`resolve` run may be told; each field is the ``hcdf-trust resolve``
    flag of the same name (docs/resolve.md). Pass fields by keyword; new ones may be added.

    Attributes:
        base: ``--base DIR|URL``: where relative references of published fragments resolve.
        mirrors: ``--mirror PREFIX=DIR|URL`` pairs, longest prefix wins.
        root: ``--root DIR``: local references must stay inside it.
        cache_dir: the content-addressed cache (default ``~/.cache/hcdf-trust``).
        lock_path: the lock file (default ``<DOC>.lock``).
        locked: fail on any difference from the lock instead of updating it.
        update_all, update: re-pin every lock entry, or those named (trust on first use).
        offline: never open a socket (local files, mirrors and the cache only).
        allow_http, strict, jobs, max_depth, max_bytes, timeout, ca_bundle: as the flags.
        write_cache: store fetched and local blobs in the cache (``verify`` does not).
        accept_mismatch: for ``pin``: keep walking past a pin mismatch (still an error).

    Example:
        >>> from hcdf_trust.include import ResolveOptions
        >>> ResolveOptions(offline=True, strict=True).locked
        False
    """

    base: str | None = None
    mirrors: tuple[tuple[str, str], ...] = ()
    root: str | None = None
    cache_dir: str | None = None
    lock_path: str | None = None
    locked: bool = False
    # Trust on first use: re-pin every lock entry (update_all) or those named here
    # (the uri as written, or the lock's url) to the content found now.
    update_all: bool = False
    update: tuple[str, ...] = ()
    offline: bool = False
    allow_http: bool = False
    strict: bool = False
    jobs: int = DEFAULT_JOBS
    max_depth: int = DEFAULT_MAX_DEPTH
    max_bytes: int = DEFAULT_MAX_BYTES
    timeout: float = DEFAULT_TIMEOUT
    ca_bundle: str | None = None
    write_cache: bool = True
    # For `pin`, which repairs mismatches: a pin mismatch no longer stops an include from
    # being parsed and walked (or a blob from being cached); it is still reported in errors.
    accept_mismatch: bool = False


@dataclass(frozen=True)
class TreeOptions:
    """Where a verb built on resolve (audit, sbom, macsec, ota build, validate) finds the tree:
    resolve's ``--base``, ``--mirror``, ``--root``, ``--cache-dir``, ``--lock``, ``--offline``
    and ``--ca-bundle``, with resolve's meaning. Such verbs read the tree offline unless told
    ``--online``."""

    base: str | None = None
    mirrors: tuple[tuple[str, str], ...] = ()
    root: str | None = None
    cache_dir: str | None = None
    lock_path: str | None = None
    offline: bool = True
    ca_bundle: str | None = None  # extra CAs for https, under --online (and the verb's other https)

    def resolve_options(self, **fixed: Any) -> ResolveOptions:
        """These options as a :class:`ResolveOptions`, with the verb's own ``fixed`` ones
        (``locked``, ``write_cache``...). The cache is written only online."""
        fixed.setdefault("write_cache", not self.offline)
        fixed.setdefault("ca_bundle", self.ca_bundle)
        return ResolveOptions(
            base=self.base,
            mirrors=self.mirrors,
            root=self.root,
            cache_dir=self.cache_dir,
            lock_path=self.lock_path,
            offline=self.offline,
            **fixed,
        )

    def finds_tree_by_default(self) -> bool:
        """True when the tree is read where resolve reads it by default, offline (the CAs
        trusted for https do not move it)."""
        return replace(self, ca_bundle=None) == TreeOptions()


@dataclass
class Use:
    """One place that references an artifact."""

    doc: str  # display name of the referencing document
    doc_url: str
    ref: Reference
    pin: Pin | None


@dataclass
class Artifact:
    """One distinct file (or firmware digest, or extension) the tree references, and what
    was found: every reference to the same URL shares one Artifact (:attr:`uses`).

    Attributes:
        kind: what references it (:class:`~hcdf_trust.document.Kind`: ``include``, ``model``,
            ``mesh``, ``stream-profile``, ``firmware``, ``firmware-manifest``, ``extension``).
        uri: the location as the first reference writes it.
        location: where it was looked for (:attr:`url` is its identity).
        uses: every referencing place (document, line, pin).
        sha256, size: of the bytes found; ``None`` when nothing was read.
        source: where the bytes came from: ``file``, ``mirror``, ``cache`` or ``network``.
        error: the error this file caused, if any (also in :attr:`Resolution.errors`).

    Example:
        >>> from hcdf_trust.include import verify
        >>> res = verify("examples/robot/robot.hcdf")
        >>> chassis = next(a for a in res.artifacts.values() if a.uri == "models/chassis.glb")
        >>> chassis.kind.value, chassis.size, chassis.pin_status, chassis.source
        ('model', 724, 'full', 'file')
    """

    kind: Kind
    uri: str  # as written in the first reference
    location: Location
    uses: list[Use] = field(default_factory=list)
    sha256: str | None = None
    size: int | None = None
    source: str | None = None  # file | mirror | cache | network
    error: HcdfTrustError | None = None
    inode: tuple[int, int] | None = None  # (st_dev, st_ino) of the local file hashed, when known
    lock_url: str | None = field(default=None, repr=False, compare=False)  # set by the run (Resolution.lock_url)

    @property
    def url(self) -> str:
        """The absolute URL that identifies this file: ``file:///…`` or the remote URL."""
        return self.location.url

    @property
    def pin_status(self) -> str:
        """``full`` (a reference pins all 64 hex digits), ``weak`` (a prefix) or ``unpinned``."""
        status = "unpinned"
        for use in self.uses:
            if use.pin is not None:
                if use.pin.is_full:
                    return "full"
                status = "weak"
        return status


@dataclass
class Resolution:
    """The result of :func:`resolve` or :func:`verify`: every document and file of the tree,
    what was found, and every error and warning. Nothing is written until you ask
    (:meth:`write_lock`); a run with errors should write nothing (``ok`` is False).

    Attributes:
        root: the root document, parsed (:class:`~hcdf_trust.document.Document`).
        root_location: where it was read.
        lock_path: the lock file this run compared against and :meth:`write_lock` writes.
        documents: every document of the include tree, keyed by its absolute URL.
        artifacts: every distinct referenced file, **keyed by its absolute URL**
            (``file:///abs/path`` for a local file, the URL as fetched otherwise; the lock
            file names it relative to the lock, :meth:`lock_url`). Iterate ``.values()`` for
            the files; look one up by ``res.artifacts[url]``.
        includes: per document URL, its ``<include>`` references and the URL each resolved to.
        others: references with nothing to fetch (``<software><hash>``, extensions).
        errors: every :class:`~hcdf_trust.errors.HcdfTrustError` found, with file and line.
        warnings: every :class:`~hcdf_trust.errors.Notice` (weak pins, lock-only pins, ...).

    Example:
        >>> from hcdf_trust.include import verify
        >>> res = verify("examples/robot/robot.hcdf")
        >>> res.ok, len(res.documents), len(res.artifacts)
        (True, 3, 9)
        >>> sorted(res.lock_url(url) for url in res.artifacts)[:2]
        ['assemblies/arm.hcdf', 'assemblies/sensor-head.hcdf']
        >>> [w.code for w in res.warnings]
        ['mesh-without-sha', 'lock-pins', 'weak-pin']
    """

    root: Document
    root_location: Location
    lock_path: Path
    documents: dict[str, Document] = field(default_factory=dict)
    artifacts: dict[str, Artifact] = field(default_factory=dict)
    includes: dict[str, list[tuple[Reference, str]]] = field(default_factory=dict)
    others: list[tuple[str, Reference]] = field(default_factory=list)  # firmware hashes, extensions
    errors: list[HcdfTrustError] = field(default_factory=list)
    warnings: list[Notice] = field(default_factory=list)
    locked: lockfile.Lock | None = field(default=None, repr=False)  # the lock file as read, if any
    # The URLs of the artifacts that ``--update`` names (every one under ``update_all``).
    updating: set[str] = field(default_factory=set, repr=False)
    # A tree read out of a ``.hcdfz``: its entries (``bundle.archive``: path, SHA-256 and size,
    # which ota build and the SBOM record), for a step after resolution that reads one again
    # (the registry's stream-profile check); None for a tree of files.
    bundle: BundleFiles | None = field(default=None, repr=False)

    @property
    def ok(self) -> bool:
        """True when the run found no error (warnings allowed)."""
        return not self.errors

    @functools.cached_property
    def _urls(self) -> LockUrls:
        return LockUrls(self.lock_path.parent)

    def lock_url(self, url: str) -> str:
        """``url`` as the lock file writes it (see :class:`LockUrls`)."""
        return self._urls.to_lock(url)

    def lock_entries(self, edited: dict[str, bytes] | None = None) -> list[lockfile.LockEntry]:
        """The lock file's entries for every artifact that was hashed.

        ``edited`` maps document URLs to new bytes (``pin --write``, ``ota build
        --update-hcdf``): their entries take the digest and size of those bytes, so the
        lock is what a plain ``resolve`` writes after the edits.
        """
        to_lock = self._urls.to_lock
        new_entry = lockfile.new_entry
        docs: dict[str, str] = {}  # a document's lock url, once per document
        entries = []
        for art in self.artifacts.values():
            if art.sha256 is None or art.size is None:
                continue
            uses = art.uses
            if len(uses) == 1:  # the common case, without a set
                ref = docs.get(uses[0].doc_url)
                if ref is None:
                    ref = docs[uses[0].doc_url] = to_lock(uses[0].doc_url)
                referenced_from: tuple[str, ...] = (ref,)
            else:
                refs = set()
                for use in uses:
                    ref = docs.get(use.doc_url)
                    if ref is None:
                        ref = docs[use.doc_url] = to_lock(use.doc_url)
                    refs.add(ref)
                referenced_from = tuple(refs) if len(refs) == 1 else tuple(sorted(refs))
            url = art.lock_url or to_lock(art.location.url)
            # kind._value_: Enum's .value is a Python-level descriptor, 10,000 calls here;
            # new_entry: LockEntry's own tuple constructor, without its Python __new__
            entries.append(new_entry((art.kind._value_, art.uri, url, art.sha256, art.size, referenced_from)))
        if edited:
            changed = {
                to_lock(url): hash_bytes(data) for url, data in edited.items() if data != self.documents[url].data
            }
            entries = [
                e._replace(sha256=changed[e.url].sha256, size=changed[e.url].size) if e.url in changed else e
                for e in entries
            ]
        return entries

    def pins_sha256(self, *, limit: int) -> str:
        """The SHA-256 of what pins this tree, which a release and an SBOM record: the lock
        file's bytes, or for a tree read from a ``.hcdfz`` the bundle's (it is its own lock).

        Raises:
            InputError: the lock file cannot be read (or is larger than ``limit``).
        """
        if self.bundle is not None:
            return self.bundle.archive.sha256
        import hashlib

        from ..localfile import read_input

        return hashlib.sha256(read_input(str(self.lock_path), limit=limit, what="lock file")).hexdigest()

    def render_lock(self, edited: dict[str, bytes] | None = None) -> bytes:
        """The lock file's bytes for this tree (what :meth:`write_lock` writes); ``edited``
        as for :meth:`lock_entries`. An unchanged lock is the bytes read (render's, by
        :func:`lockfile.render_unchanged`), not rendered again."""
        root = self.lock_url(self.root_location.url)
        return lockfile.render_unchanged(self.lock_entries(edited), root=root, before=self.locked)

    def write_lock(self) -> None:
        """Write the lock file alone, atomically, refusing a ``lock_path`` that is an input.
        A lock that already holds these bytes is left untouched. Call it only when :attr:`ok`.

        Example:
            >>> from hcdf_trust.include import resolve
            >>> res = resolve("examples/robot/robot.hcdf")
            >>> res.write_lock()  # the same bytes as the committed lock: nothing changes

        Raises:
            OutputError: it is an input of this tree, or cannot be written.
        """
        from ..outputs import OutputPlan, protect_inputs

        plan = OutputPlan()
        protect_inputs(plan, self)
        plan.add(self.lock_path, self.render_lock(), flag="lock file")
        plan.commit()


class LockUrls:
    """Local URLs relative to the lock file's folder; remote URLs as they are.

    ``os.path.relpath`` costs microseconds: it runs once per distinct folder, and
    each file's name is joined to its folder's answer (and remembered).
    """

    def __init__(self, base: Path) -> None:
        self.base = os.path.abspath(base)
        self._rel: dict[str, str] = {}
        self._memo: dict[str, str] = {}

    def to_lock(self, url: str) -> str:
        done = self._memo.get(url)
        if done is not None:
            return done
        if not url.startswith("file://"):
            return url
        folder, _, name = url.rpartition("/")
        rel = self._rel.get(folder)
        if rel is None:
            path = unquote(folder[len("file://") :]) or "/"
            rel = self._rel[folder] = Path(os.path.relpath(path, self.base)).as_posix()
        if "%" in name:
            name = unquote(name)
        done = self._memo[url] = name if rel == "." else f"{rel}/{name}"
        return done


def display_url(url: str) -> str:
    """How messages name a URL: local files by :func:`display_path`, others as they are."""
    return display_path(unquote(urlsplit(url).path)) if url.startswith("file://") else url


Reporter = Callable[[int, int], None]  # (files done, bytes done) increments


def resolve(
    doc_path: str | os.PathLike[str],
    options: ResolveOptions | None = None,
    *,
    on_start: Callable[[int], None] | None = None,
    on_progress: Reporter | None = None,
) -> Resolution:
    """Resolve ``doc_path`` and every file it references, as ``hcdf-trust resolve`` does:
    fetch each distinct file once, check it against its pin and the lock, cache it.

    Never raises for content errors: they are collected in :attr:`Resolution.errors`
    (check :attr:`Resolution.ok`). Nothing is written but verified cache blobs; write the
    lock with :meth:`Resolution.write_lock`.

    Args:
        doc_path: the root HCDF document.
        options: flags of the run (:class:`ResolveOptions`); defaults: online, not locked.
        on_start: called once with the number of files to obtain (a progress bar).
        on_progress: called with (files, bytes) increments as they are obtained.

    Returns:
        The :class:`Resolution`.

    Raises:
        InputError: the root document itself cannot be read.

    Example:
        >>> from hcdf_trust.include import resolve, ResolveOptions
        >>> res = resolve("examples/robot/robot.hcdf", ResolveOptions(offline=True))
        >>> res.ok, res.lock_path.name
        (True, 'robot.hcdf.lock')
    """
    run = _Run(options or ResolveOptions(), on_start=on_start, on_progress=on_progress)
    try:
        return run.run(Path(doc_path))
    finally:
        run.close()


def verify(
    doc_path: str | os.PathLike[str],
    options: ResolveOptions | None = None,
    *,
    on_start: Callable[[int], None] | None = None,
    on_progress: Reporter | None = None,
) -> Resolution:
    """Check ``doc_path``'s tree against its lock file, offline, writing nothing (not even
    the cache), as ``hcdf-trust verify`` does: :func:`resolve` with ``locked``, ``offline``
    and no cache writes, whatever ``options`` says about those three.

    Args, Returns and Raises: as :func:`resolve`.

    Example:
        >>> from hcdf_trust.include import verify
        >>> res = verify("examples/robot/robot.hcdf")
        >>> res.ok
        True
        >>> with open("examples/robot/models/chassis.glb", "ab") as glb:
        ...     _ = glb.write(b"tampered")
        >>> res = verify("examples/robot/robot.hcdf")
        >>> res.ok, res.errors[0].code, res.errors[0].exit_code
        (False, 'digest-mismatch', 1)
    """
    from dataclasses import replace

    fixed = replace(options or ResolveOptions(), locked=True, offline=True, write_cache=False)
    return resolve(doc_path, fixed, on_start=on_start, on_progress=on_progress)


class _Run:
    def __init__(
        self,
        options: ResolveOptions,
        *,
        on_start: Callable[[int], None] | None,
        on_progress: Reporter | None,
    ) -> None:
        self.o = options
        self.on_start = on_start
        self.on_progress = on_progress
        self.store = ContentStore(options.cache_dir or default_cache_dir())
        # Where local content is read: files (confined to their root), or a bundle's entries
        # (bundle.BundleFiles: the same interface, so the same walk and the same verdicts).
        self.folders: ConfinedFolders | BundleFiles = ConfinedFolders()
        self.bundle: BundleFiles | None = None
        self._pools: list[_Workers] = []  # every worker pool this run started
        self._fetcher: HttpFetcher | None = None
        self.lock: dict[str, lockfile.LockEntry] = {}  # by lock url (Resolution.lock_url)
        self._lock = threading.Lock()
        self._updating: set[str] = set()  # lock urls re-pinned by --update
        self._update_names = frozenset(options.update)
        self._named_files: dict[str, list[str]] = {}  # by artifact url: see _named_paths
        self._update_files: dict[tuple[int, int], list[str]] = {}  # --update names that are paths, by inode
        for name in options.update:
            try:
                st = os.stat(name)
            except (OSError, ValueError):
                continue  # not a path (a uri as written, a URL), or nothing there
            self._update_files.setdefault((st.st_dev, st.st_ino), []).append(name)
        if options.ca_bundle and not options.offline:
            # A bad --ca-bundle fails the run even when the tree needs no fetch: it is a
            # flag error, not something to find out on the first remote reference.
            self.fetcher()

    def fetcher(self) -> HttpFetcher:
        """The HTTPS fetcher, created (and fetch.py, ssl, httpx imported) at the first remote fetch."""
        with self._lock:
            if self._fetcher is None:
                from .fetch import HttpFetcher

                o = self.o
                self._fetcher = HttpFetcher(
                    ca_bundle=o.ca_bundle,
                    allow_http=o.allow_http,
                    timeout=o.timeout,
                    max_bytes=o.max_bytes,
                    max_connections=max(1, o.jobs),
                )
            return self._fetcher

    def close(self) -> None:
        self.store.abandon()  # downloads of workers still running when an interrupt stopped us
        # A worker still running (an interrupt stopped the join) may be about to open a file
        # relative to a folder descriptor: closing it could hand its number to another open,
        # and the worker would read from the wrong folder. The process exit closes them.
        if not any(pool.alive() for pool in self._pools):
            self.folders.close()
        if self._fetcher is not None:
            self._fetcher.close()

    # -- step 0: the root document and the lock --------------------------------------

    def run(self, doc_path: Path) -> Resolution:
        doc_path = Path(absolute(doc_path))
        from ..bundle import is_bundle

        if is_bundle(doc_path):
            data, doc_path = self._open_bundle(doc_path)
            root_dir = doc_path.parent
            lock_path = lockfile.default_path(doc_path)  # never read: the bundle's pins are its lock
        else:
            lock_path = Path(absolute(self.o.lock_path)) if self.o.lock_path else lockfile.default_path(doc_path)
            root_dir = self._confinement_root(doc_path)
            data = read_root(doc_path)
        locator = Locator.create(root=root_dir, base=self.o.base, mirrors=self.o.mirrors)
        root_loc = Location(url=file_url(doc_path), path=str(doc_path), root=doc_path.parent)
        stub = link_stub_target(doc_path, data) if self.bundle is None else None
        if stub is not None:
            doc_path, data = stub, read_root(stub)
            root_loc = Location(url=file_url(doc_path), path=str(doc_path), root=doc_path.parent)
        root = Document.from_bytes(data, source=display_url(root_loc.url))
        res = Resolution(root=root, root_location=root_loc, lock_path=lock_path)
        res.bundle = self.bundle
        res.documents[root_loc.url] = root
        self._to_lock = res._urls.to_lock
        try:
            self._load_lock(res)
            lock_error = None
        except HcdfTrustError as exc:
            # Reported after the walk, which writes nothing (the cache only takes content
            # that matches its pins): a "lock" that is really one of the tree's inputs
            # (`--lock robot.hcdf`) is then named as such, not just as malformed JSON.
            lock_error = exc
        self.res = res
        self.locator = locator
        self._walk_includes(root_loc)
        self._fetch(
            [a for a in res.artifacts.values() if a.kind is not Kind.INCLUDE and a.error is None and a.sha256 is None],
            keep=False,
        )
        self._find_cycles()
        self._check_all()
        if self.bundle is not None:
            from ..bundle import check_contents

            res.errors.extend(check_contents(res, self.bundle))
        if (notice := foreign_major_notice(res.documents.values())) is not None:
            res.warnings.append(notice)
        if lock_error is not None:
            # Without its lock, the run's drift findings say nothing: the lock error alone.
            others = [e for e in res.errors if not isinstance(e, LockDriftError | UnpinnedError)]
            res.errors = [self._lock_is_an_input() or lock_error, *others]
        return res

    def _open_bundle(self, path: Path) -> tuple[bytes, Path]:
        """Read a ``.hcdfz`` (structure checked, nothing extracted) and serve the run from it:
        the root document's bytes, and its path inside the bundle (``X.hcdfz/robot.hcdf``), the
        folder every reference of the bundle must resolve into."""
        from ..bundle import BundleFiles, read_archive

        o = self.o
        for flag, given in (("--base", o.base), ("--mirror", o.mirrors), ("--root", o.root), ("--lock", o.lock_path)):
            if given:
                raise InputError(
                    f"{flag} does not apply to a bundle: {display_path(path)} holds every file it references"
                    " and pins them itself",
                    file=display_path(path),
                )
        files = BundleFiles(read_archive(path), os.fspath(path))
        self.folders.close()
        self.folders = self.bundle = files
        root = files.root_path
        return files.read(root, limit=MAX_DOCUMENT_BYTES, source=display_path(root)), Path(root)

    def _lock_is_an_input(self) -> HcdfTrustError | None:
        """The error for a lock path that is one of the tree's inputs (``--lock robot.hcdf``)."""
        from ..outputs import OutputError, OutputPlan, protect_inputs

        plan = OutputPlan()
        protect_inputs(plan, self.res, options=self.o)
        what = plan.protected(self.res.lock_path)
        if what is None:
            return None
        shown = display_path(self.res.lock_path)
        return OutputError(
            f"--lock {shown} is {what}: refusing to overwrite an input (it is not a lock file)", file=shown
        )

    def _load_lock(self, res: Resolution) -> None:
        """Read the lock (every verb): a lock that exists but cannot be used stops the run,
        since under trust on first use it is the pin of every unpinned reference."""
        path = res.lock_path
        if self.bundle is not None:
            return  # every reference of a bundle is pinned in its document or by its entry's name
        if not self.o.locked and not os.path.lexists(path):
            return  # first use: nothing locked yet
        lock = lockfile.load(path)
        root = res.lock_url(res.root_location.url)
        if lock.root != root:
            raise LockFileError(
                f"lock file {display_path(path)} belongs to {lock.root}, not to {root}"
                " (each root document has its own lock: <DOC>.lock, or pass --lock)",
                file=display_path(path),
                expected=root,
                actual=lock.root,
            )
        self.lock = lock.entries
        res.locked = lock
        names = set(self.o.update)
        self._updating = {url for url, e in self.lock.items() if names & {e.uri, url}}

    def _entry(self, art: Artifact) -> lockfile.LockEntry | None:
        if not self.lock:
            return None
        key = art.lock_url
        if key is None:
            key = art.lock_url = self._to_lock(art.location.url)
        return self.lock.get(key)

    def _is_updating(self, art: Artifact) -> bool:
        """Does ``--update`` re-pin this artifact? (All, or named by one of :meth:`_names`.)"""
        if self.o.update_all:
            return True
        names = self._update_names
        if not names:
            return False
        lock_url = self.res.lock_url(art.url)
        return (
            lock_url in self._updating
            or lock_url in names
            or art.url in names
            or any(u.ref.uri in names for u in art.uses)
            or bool(self._named_paths(art))
        )

    def _names(self, art: Artifact) -> set[str]:
        """Every name ``--update`` may give this artifact (resolve and pin alike): a uri as
        written in a document, its lock url, its URL, or its path (a name that is the same
        file, compared by inode: what the shell names, through symlinks and ``..``)."""
        names = {self.res.lock_url(art.url), art.url, *self._named_paths(art)}
        return names | {u.ref.uri for u in art.uses if u.ref.uri}

    def _named_paths(self, art: Artifact) -> list[str]:
        """The ``--update`` names that are paths of this artifact's local file (by inode)."""
        if not self._update_files or art.location.path is None:
            return []
        hits = self._named_files.get(art.url)
        if hits is None:
            inode = art.inode
            if inode is None:
                try:
                    st = os.stat(art.location.path)
                    inode = (st.st_dev, st.st_ino)
                except OSError:
                    inode = None
            hits = self._named_files[art.url] = self._update_files.get(inode, []) if inode is not None else []
        return hits

    def _confinement_root(self, doc_path: Path) -> Path:
        return confinement_root(doc_path, root=self.o.root, base=self.o.base)

    # -- step 1: the include tree ----------------------------------------------------

    def _walk_includes(self, root_loc: Location) -> None:
        res = self.res
        parent: dict[str, str | None] = {root_loc.url: None}
        frontier = [root_loc]
        depth = 0
        while frontier:
            depth += 1
            pending: list[Artifact] = []
            for doc_loc in frontier:
                for art in self._collect(doc_loc):
                    if art.url in parent or art.error is not None:
                        continue
                    if depth > self.o.max_depth:
                        chain = " → ".join(display_url(u) for u in _chain(parent, doc_loc.url) + [art.url])
                        use = art.uses[-1]
                        res.errors.append(
                            IncludeDepthError(
                                f"includes nest deeper than {self.o.max_depth} levels: {chain}",
                                file=use.doc,
                                line=use.ref.line,
                            )
                        )
                        parent[art.url] = doc_loc.url
                        continue
                    parent[art.url] = doc_loc.url
                    pending.append(art)
            self._fetch(pending, keep=True)
            frontier = [a.location for a in pending if a.url in res.documents]

    def _collect(self, doc_loc: Location) -> list[Artifact]:
        """Record every reference of one document; return the include artifacts it names."""
        res = self.res
        doc = res.documents[doc_loc.url]
        includes: list[Artifact] = []
        edges = res.includes.setdefault(doc_loc.url, [])
        source, doc_url, artifacts, locate = doc.source, doc_loc.url, res.artifacts, self.locator.locate
        join = self.locator.plain_joiner(doc_loc)  # locate's fast path, without the call per reference
        for ref in doc.references():
            kind = ref.kind
            if kind in _NOT_FETCHED:
                res.others.append((source, ref))
                continue
            uri, sha, line = ref.uri, ref.sha, ref.line
            try:
                pin = parse_pin(sha, file=source, line=line, uri=uri)
                if not uri:
                    raise InputError(f"<{kind.value}> has no {ref.uri_attr or 'uri'}", file=source, line=line)
                loc = join(uri) or locate(uri, doc_loc, file=source, line=line)
                if self.bundle is not None:
                    pin = self._bundle_pin(pin, loc, uri, file=source, line=line)
            except HcdfTrustError as exc:
                res.errors.append(exc)
                continue
            url = loc.url
            art = artifacts.get(url)
            if art is None:
                art = artifacts[url] = Artifact(kind, uri, loc)
            art.uses.append(Use(source, doc_url, ref, pin))
            if kind is Kind.INCLUDE:
                edges.append((ref, url))
                includes.append(art)
        return includes

    def _bundle_pin(self, pin: Pin | None, loc: Location, uri: str, *, file: str, line: int | None) -> Pin | None:
        """A reference of a bundle: an entry of it (never a URL), pinned by the document or,
        where it has no ``sha`` site, by the full SHA-256 in the entry's name."""
        assert self.bundle is not None
        if loc.path is None:
            from ..bundle import BundleMissingError

            raise BundleMissingError(
                f"{uri} is not in the bundle {self.bundle.archive.path}: a bundle holds every file it references",
                file=file,
                line=line,
                expected=f"an entry of {self.bundle.archive.path}",
                actual=uri,
            )
        if pin is None and (named := self.bundle.name_pin(loc.path)) is not None:
            return parse_pin(named, file=file, line=line, uri=uri)
        return pin

    # -- step 2: fetching ------------------------------------------------------------

    def _fetch(self, artifacts: list[Artifact], *, keep: bool) -> None:
        if not artifacts:
            return
        if self.on_start:
            self.on_start(len(artifacts))
        inline, cpu, net = self._plan(artifacts)
        pools: list[_Workers] = []
        # Hashing threads drop the GIL for each 1 MiB read and update, then wait for it
        # while this thread runs Python for small files; at the default 5 ms switch
        # interval they idle most of that wait. 0.5 ms: 1.07 GB robot 0.59 s -> 0.53 s.
        switch = sys.getswitchinterval()
        sys.setswitchinterval(min(switch, 0.0005))
        try:
            for work, workers in ((net, self.o.jobs), (cpu, min(self.o.jobs, _CORES))):
                if work:
                    pools.append(_Workers(functools.partial(self._obtain_one, keep=keep), work, workers))
                    self._pools.append(pools[-1])
            if keep:
                for art in inline:
                    self._obtain_one(art, keep)
            else:
                self._hash_inline(inline)
        finally:
            for pool in pools:
                pool.join()
            sys.setswitchinterval(switch)
        for pool in pools:
            pool.reraise()

    def _hash_inline(self, artifacts: list[Artifact]) -> None:
        """:meth:`_obtain_one` for files that are not parsed, in this thread: a small local
        file of a checked folder by :meth:`ConfinedFolders.hash_entry` (the same checks,
        less Python per file); anything else, and every error, through :meth:`_obtain_one`."""
        hash_entry = self.folders.hash_entry
        progress = self.on_progress
        for art in artifacts:
            loc = art.location
            path = loc.path
            hashed = hash_entry(path, loc.root or os.path.dirname(path)) if path is not None else None
            if hashed is None:
                self._obtain_one(art, False)
                continue
            art.sha256, art.size, art.inode = hashed
            art.source = "file" if loc.url.startswith("file://") else "mirror"
            if progress:
                progress(1, art.size)

    def _plan(self, artifacts: list[Artifact]) -> tuple[list[Artifact], list[Artifact], list[Artifact]]:
        """Split work into (this thread, one thread per core, up to --jobs threads).

        Network fetches wait on latency: up to --jobs at once. Local files and cached
        blobs are CPU work: hashing a large one releases the GIL, so one thread per
        core hashes in parallel, but for a small one the per-file Python work costs
        more than the hash, and threads contending for the GIL make it several times
        slower than doing it here. The sizes are only a hint (the lock's, else a stat;
        no open): :meth:`_obtain` still makes every check.
        """
        if self.o.jobs <= 1:
            return artifacts, [], []
        inline: list[Artifact] = []
        sized: list[tuple[int, Artifact]] = []
        net: list[Artifact] = []
        for art in artifacts:
            entry = self._entry(art) if art.location.path is not None else None
            # A local file the lock knows: the size it had (a wrong hint costs speed, not safety).
            size = entry.size if entry is not None else self._stat_size(art)
            if size < 0:
                (inline if art.location.path is not None else net).append(art)
            elif size < PARALLEL_MIN_BYTES:
                inline.append(art)
            else:
                sized.append((size, art))
        sized.sort(key=lambda pair: -pair[0])  # largest first: the cores finish together
        return inline, [art for _, art in sized], net

    def _stat_size(self, art: Artifact) -> int:
        """The size of the local file, or of the cache blob of a remote one; -1 if none."""
        if self.bundle is not None:
            return self.bundle.size(art.location.path or "")
        try:
            path: str | Path | None = art.location.path
            if path is None:
                want = self._wanted_sha(art)
                path = self.store.path_for(want) if want else None
            return os.stat(path).st_size if path is not None else -1
        except (OSError, ValueError):
            return -1

    def _obtain_one(self, art: Artifact, keep: bool) -> None:
        use = art.uses[0]
        try:
            data = self._obtain(art, keep, file=use.doc, line=use.ref.line)
        except NotFoundError as exc:  # name the reference as written; hint at --base
            art.error = explain_missing(exc, uri=use.ref.uri, referrer_url=use.doc_url, base=self.o.base)
            data = None
        except HcdfTrustError as exc:
            art.error = exc
            data = None
        if keep and data is not None and self._acceptable(art):
            try:
                doc = Document.from_bytes(data, source=display_url(art.url))
            except HcdfTrustError as exc:
                art.error = exc
            else:
                with self._lock:
                    self.res.documents[art.url] = doc
        if self.on_progress:
            self.on_progress(1, art.size or 0)

    def _obtain(self, art: Artifact, keep: bool, *, file: str, line: int | None) -> bytes | None:
        loc = art.location
        data: bytes | None = None
        if loc.path is not None:
            root = loc.root or os.path.dirname(loc.path)
            if keep:  # an include: hash and parse the very same bytes
                if self.bundle is not None:
                    data = self.bundle.read(
                        loc.path, file=file, line=line, limit=MAX_DOCUMENT_BYTES, source=display_url(art.url)
                    )
                else:
                    with open_local(loc.path, root, file=file, line=line) as fd:
                        data = read_bounded(fd, MAX_DOCUMENT_BYTES, source=display_url(art.url))
                hashed = hash_bytes(data)
            else:
                hashed = self.folders.hash(loc.path, root, file=file, line=line)
            self._record(art, hashed, "file" if art.url.startswith("file://") else "mirror")
            return data
        assert loc.remote is not None
        want = self._wanted_sha(art)
        if want is not None:
            cached = self.store.verified_path(want, repair=self.o.write_cache)
            if cached is not None:
                data = _read_blob(cached, want, file=file, line=line, url=art.url) if keep else None
                try:
                    size = len(data) if data is not None else cached.stat().st_size
                except OSError as exc:  # removed by another process since it was verified
                    raise InputError(
                        f"cache blob {cached} vanished after it was verified: {exc.strerror}",
                        file=file,
                        line=line,
                        url=art.url,
                    ) from None
                self._record(art, Hashed(want, size), "cache")
                return data
        if self.o.offline:
            raise OfflineError(
                f"{art.url} is not in the cache or a mirror, and --offline forbids the network"
                + ("" if want else " (it has no full pin or lock entry to find it in the cache by)"),
                file=file,
                line=line,
                url=art.url,
            )
        if urlsplit(loc.remote).scheme == "http" and not (self.o.allow_http and want):
            raise FetchError(
                f"{loc.remote}: plain http is refused without --allow-http and a full SHA-256 pin",
                file=file,
                line=line,
                url=art.url,
            )
        limit = min(self.o.max_bytes, MAX_DOCUMENT_BYTES) if keep else self.o.max_bytes
        with self.fetcher().open(loc.remote, file=file, line=line) as chunks:
            if self.o.write_cache:
                try:
                    hashed, path = self.store.ingest(
                        chunks, accept=lambda h: self._acceptable(art, h), limit=limit, source=loc.remote
                    )
                except FetchError as exc:
                    exc.file, exc.line = file, line
                    raise
                if keep and path is not None:
                    data = _read_blob(path, hashed.sha256, file=file, line=line, url=art.url)
            else:
                sink = _Sink() if keep else None
                try:
                    hashed = hash_chunks(chunks, sink=sink, limit=limit)
                except ValueError as exc:
                    raise FetchError(f"{loc.remote}: body {exc}", file=file, line=line, url=art.url) from None
                data = sink.data() if sink is not None else None
        self._record(art, hashed, "network")
        return data

    def _record(self, art: Artifact, hashed: Hashed, source: str) -> None:
        art.sha256, art.size, art.source, art.inode = hashed.sha256, hashed.size, source, hashed.inode

    def _wanted_sha(self, art: Artifact) -> str | None:
        for use in art.uses:
            if use.pin is not None and use.pin.is_full:
                return use.pin.hex
        entry = self._entry(art)
        if entry is None or (self._is_updating(art) and not (self.o.locked or self.o.offline)):
            return None  # an update looks for the content as it is now, not in the cache
        if all(u.pin is None or u.pin.matches(entry.sha256) for u in art.uses):
            return entry.sha256
        return None

    def _acceptable(self, art: Artifact, hashed: Hashed | None = None) -> bool:
        """May this content be cached and (for includes) parsed? Its pins, and the lock
        where the lock is its pin (always under --locked; else unless a full pin in the
        document matches or the reference is being updated)."""
        sha = hashed.sha256 if hashed is not None else art.sha256
        size = hashed.size if hashed is not None else art.size
        if sha is None:
            return False
        mismatch = any(u.pin is not None and not u.pin.matches(sha) for u in art.uses)
        if mismatch and not self.o.accept_mismatch:
            return False
        entry = self._entry(art)
        if self.o.locked:
            return entry is not None and (entry.sha256, entry.size) == (sha, size)
        if entry is None or _full_pin_matches(art, sha) or self._is_updating(art):
            return True
        return (entry.sha256, entry.size) == (sha, size)

    # -- step 3: decisions -----------------------------------------------------------

    def _find_cycles(self) -> None:
        graph = self.res.includes
        documents = self.res.documents
        done: set[str] = set()
        reported: set[tuple[str, ...]] = set()
        root = self.res.root_location.url
        stack = [root]  # the include chain being walked, depth first (iterative: no recursion limit)
        on_stack = {root: 0}
        edges = [iter(graph.get(root, []))]
        while edges:
            url = stack[-1]
            for ref, child in edges[-1]:
                if child in on_stack:
                    cycle = stack[on_stack[child] :] + [child]
                    key = tuple(sorted(set(cycle)))
                    if key not in reported:
                        reported.add(key)
                        self.res.errors.append(
                            IncludeCycleError(
                                "include cycle: " + " → ".join(display_url(u) for u in cycle),
                                file=documents[url].source,
                                line=ref.line,
                            )
                        )
                elif child not in done and child in documents:
                    on_stack[child] = len(stack)
                    stack.append(child)
                    edges.append(iter(graph.get(child, [])))
                    break
            else:
                edges.pop()
                del on_stack[stack.pop()]
                done.add(url)

    def _check_all(self) -> None:
        res = self.res
        root = display_path(res.root.source)
        for art in res.artifacts.values():
            if art.error is not None:
                res.errors.append(art.error)
                continue
            sha = art.sha256
            if sha is None:
                continue  # never reached (an error elsewhere stopped the walk)
            uses = art.uses
            if len(uses) == 1 and (pin := uses[0].pin) is not None and pin.hex == sha:
                continue  # one full pin that matches: authoritative, no error, no warning, no drift
            entry = self._entry(art)
            # In a bundle every reference must be pinned: it has no lock to pin the others.
            must_pin = self.o.locked or self.bundle is not None
            errors, warnings = check_artifact(art, entry, strict=self.o.strict, locked=must_pin, root=root)
            res.errors.extend(errors)
            res.warnings.extend(warnings)
            if entry is not None and not self.o.locked and art.pin_status != "full" and not self._is_updating(art):
                assert art.size is not None
                use = art.uses[0]
                drift = lockfile.drift_error(
                    entry,
                    sha,
                    art.size,
                    uri=art.uri,
                    url=res.lock_url(art.url),
                    file=use.doc,
                    line=use.ref.line,
                    hint=f"; `resolve --update {art.uri}` accepts the new content",
                )
                if drift is not None:
                    res.errors.append(drift)
        for source, ref in res.others:
            if ref.kind is Kind.FIRMWARE and ref.sha:
                try:
                    parse_pin(ref.sha, file=source, line=ref.line, element="hash")
                except HcdfTrustError as exc:
                    res.warnings.append(
                        Notice("bad-digest", f"firmware {ref.name!r}: {exc.message}", file=source, line=ref.line)
                    )
        if self.o.locked and self.bundle is None:
            actual = {e.url: e for e in res.lock_entries()}
            failed = {res.lock_url(a.url) for a in res.artifacts.values() if a.sha256 is None}
            # An entry referenced from a document this run did not read (an include that failed its
            # pin is not walked) may well still be referenced: that document's error is the news.
            unread = {
                res.lock_url(a.url)
                for a in res.artifacts.values()
                if a.kind is Kind.INCLUDE and a.url not in res.documents
            }
            failed |= {url for url, e in self.lock.items() if unread.intersection(e.referenced_from)}
            locked = {url: e for url, e in self.lock.items() if url not in failed}
            where = {res.lock_url(a.url): (a.uses[0].doc, a.uses[0].ref.line) for a in res.artifacts.values()}
            res.errors.extend(lockfile.compare(locked, actual, lock_path=display_path(res.lock_path), where=where))
        self._check_update_names()

    def _check_update_names(self) -> None:
        """Every ``--update`` name must name a file of the tree or a lock entry (like ``cargo update -p``)."""
        res = self.res
        if self.o.update_all:
            res.updating = set(res.artifacts)
        if not self.o.update:
            return
        known = {e.uri for e in self.lock.values()} | {e.url for e in self.lock.values()}
        for art in res.artifacts.values():
            names = self._names(art)
            known |= names
            if self._is_updating(art):
                res.updating.add(art.url)
        for name in self.o.update:
            if name not in known:
                res.errors.append(
                    UnknownUpdateError(
                        f"--update {name} names no file of the tree and no lock entry (give the uri as written "
                        "in a document, a url of the lock file, the file's URL or its path)",
                        file=display_path(res.lock_path),
                        expected="a uri as written, a lock url, a URL or a path of the tree",
                        actual=name,
                    )
                )


class UnknownUpdateError(InputError):
    """An ``--update`` name matches no file of the tree and no lock entry."""

    code = "update-unknown"


def _full_pin_matches(art: Artifact, sha: str) -> bool:
    """A full pin in a document names this content: it is authoritative over the lock."""
    return any(u.pin is not None and u.pin.is_full and u.pin.matches(sha) for u in art.uses)


# A <mesh> reference: HCDF's schema gives the element no sha attribute, so only the lock pins it.
MESH_WITHOUT_SHA = "mesh-without-sha"


def check_artifact(
    art: Artifact, lock_entry: lockfile.LockEntry | None, *, strict: bool, locked: bool, root: str = "ROBOT.hcdf"
) -> tuple[list[HcdfTrustError], list[Notice]]:
    """Every pin of every use of one artifact against its actual digest (``root``: the tree's
    root document, as the fixes the messages name should be typed). Pure."""
    errors: list[HcdfTrustError] = []
    warnings: list[Notice] = []
    sha = art.sha256
    assert sha is not None
    for use in art.uses:
        pin = use.pin
        if pin is not None and pin.is_full and pin.hex == sha:
            continue  # the common case: a full pin that matches
        # The lock already held this content before the run: whatever it says about the pin,
        # the run that wrote that entry said it first (a person is not told again; --json lists it).
        covered = lock_entry is not None and lock_entry.sha256 == sha
        where = functools.partial(Notice, file=use.doc, line=use.ref.line, url=art.url, repeated=covered)
        if pin is None:
            if locked and lock_entry is None:
                errors.append(
                    UnpinnedError(
                        f"{use.ref.uri} has no sha and the lock file does not pin it",
                        file=use.doc,
                        line=use.ref.line,
                        url=art.url,
                        expected="a sha attribute or a lock entry",
                        actual=sha,
                    )
                )
            elif art.kind is Kind.MESH:  # the schema gives <mesh> no sha: the lock is its only pin
                pinned = "the lock file pins it" if lock_entry is not None else f"pinned by the lock as sha256 {sha}"
                warnings.append(where(MESH_WITHOUT_SHA, f"{use.ref.uri}: <mesh> has no sha in HCDF; {pinned}"))
            elif lock_entry is not None:
                warnings.append(where("lock-pins", f"{use.ref.uri} has no sha; the lock file pins it"))
            else:
                warnings.append(where("unpinned", f"{use.ref.uri} is unpinned (sha256 {sha})"))
            continue
        if not pin.matches(sha):
            hint = f": {include_mismatch_hint(use.ref.uri or '', root)}" if art.kind is Kind.INCLUDE else ""
            errors.append(
                DigestMismatchError(
                    f"{use.ref.uri}: digest mismatch{hint}",
                    file=use.doc,
                    line=use.ref.line,
                    url=art.url,
                    expected=pin.hex,
                    actual=sha,
                )
            )
        elif not pin.is_full:
            bits = len(pin.hex) * 4
            if strict:
                errors.append(
                    WeakPinError(
                        f"{use.ref.uri}: weak pin of {len(pin.hex)} hex digits ({bits} bits) refused by --strict; "
                        f"its full digest is sha256 {sha}: write it, or run `hcdf-trust pin --write {root}`",
                        file=use.doc,
                        line=use.ref.line,
                        url=art.url,
                        expected="a full 64-digit SHA-256",
                        actual=pin.hex,
                    )
                )
            else:
                warnings.append(where("weak-pin", f"{use.ref.uri} has a weak pin ({bits} bits): sha256 {sha}"))
    return errors, warnings


# Kind.fetchable is a Python-level property; `in` on a tuple compares by identity first.
_NOT_FETCHED = tuple(kind for kind in Kind if not kind.fetchable)


class _Workers:
    """Up to ``count`` threads that run ``fn`` over ``tasks``, each taking the next task.

    Plain threads, not concurrent.futures, which imports logging (~5 ms of start-up).
    An exception from ``fn`` stops its thread; :meth:`reraise` raises the first one.
    """

    def __init__(self, fn: Callable[[Artifact], None], tasks: list[Artifact], count: int) -> None:
        self._fn = fn
        self._tasks = iter(tasks)
        self._take = threading.Lock()
        self.errors: list[BaseException] = []
        self._threads = [threading.Thread(target=self._work, daemon=True) for _ in range(min(count, len(tasks)))]
        for thread in self._threads:
            thread.start()

    def _work(self) -> None:
        while True:
            with self._take:
                task = next(self._tasks, None)
            if task is None:
                return
            try:
                self._fn(task)
            except BaseException as exc:  # re-raised in the resolving thread
                self.errors.append(exc)
                return

    def alive(self) -> bool:
        return any(thread.is_alive() for thread in self._threads)

    def join(self) -> None:
        for thread in self._threads:
            thread.join()

    def reraise(self) -> None:
        if self.errors:
            raise self.errors[0]


class _Sink:
    def __init__(self) -> None:
        self.parts: list[bytes] = []

    def write(self, chunk: bytes) -> None:
        self.parts.append(bytes(chunk))

    def data(self) -> bytes:
        return b"".join(self.parts)


def _read_blob(path: Path, sha256: str, *, file: str, line: int | None, url: str) -> bytes:
    """A cache blob's bytes for parsing, hashed again: a blob swapped after it was
    verified (or replaced by a FIFO) must not be parsed under the verified digest."""
    with open_local(path, path.parent, file=file, line=line) as fd:
        data = read_bounded(fd, MAX_DOCUMENT_BYTES, source=url)
    if hash_bytes(data).sha256 != sha256:
        raise InputError(f"cache blob {path} changed after it was verified", file=file, line=line, url=url)
    return data


def read_root(path: Path) -> bytes:
    """The root document's bytes, read as every run reads them (confined to its folder, bounded)."""
    with open_local(path, path.parent, file=str(path)) as fd:
        return read_bounded(fd, MAX_DOCUMENT_BYTES, source=display_path(path))


def link_stub_target(path: Path, data: bytes) -> Path | None:
    """The sibling a ``{device}.hcdf`` pointer of hcdf_models names: a real symlink, or a
    symlink checked out as a plain file holding just the target's name (git with
    core.symlinks=false). Followed only to a sibling file, never across folders, so
    both checkouts name the same root document (and write the same lock)."""
    if path.is_symlink():
        name = os.readlink(path)
    elif len(data) > 255 or b"<" in data:
        return None
    else:
        name = data.strip().decode("utf-8", "replace")
    if not name or "/" in name or "\\" in name or name in (".", "..") or "\n" in name:
        return None
    target = path.parent / name
    return target if target.is_file() else None


def _chain(parent: dict[str, str | None], url: str) -> list[str]:
    out = []
    cur: str | None = url
    while cur is not None:
        out.append(cur)
        cur = parent.get(cur)
    return list(reversed(out))
