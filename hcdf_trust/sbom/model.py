"""The facts of one robot's bill of materials, collected once from a verified tree.

:func:`collect` reads a clean :class:`~hcdf_trust.include.resolver.Resolution` (its parsed
documents and include edges, never a second parser) and, optionally, a verified OTA
release. The writers (:mod:`.cyclonedx`, :mod:`.spdx`) only render these facts.

Shape of the tree:

- the robot is the root document; every ``<include>`` is one sub-assembly *instance*
  (a file included twice is two physical sub-assemblies, with one file digest);
- a ``<comp>`` of a document is a device in every instance of that document, named as
  the flattened document names it (include names joined with ``_``: ``left_arm_shoulder``);
- a ``<software>`` is firmware, one entry per (board, name, version, hash) however many
  comps run it (board: the comp's ``<board>``, else its name, as ``ota build`` keys images);
- a ``<driver name>`` (sensor drivers) is a device driver, one entry per name;
- every model, mesh, stream profile and firmware manifest file is one file with its
  SHA-256, owned by its comp (or firmware, or the document when outside any comp).

Identifiers (``ref``) are stable strings: the same tree gives the same refs.
"""

from __future__ import annotations

import hashlib
import os
import uuid
from collections import Counter
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field, replace
from datetime import datetime
from typing import TYPE_CHECKING, Any
from urllib.parse import quote

from lxml import etree

from ..document import Document, Kind, single, single_text, software_elements, stream_profile_selection
from ..errors import InputError, Notice, StreamSelectionError
from ..xml import sourceline

if TYPE_CHECKING:
    from ..include.resolver import Resolution

SEPARATOR = "_"  # == include.flatten.SEPARATOR: how an include name prefixes a comp name
MAX_COMPONENTS = 100_000  # an include tree that multiplies past this is refused, not expanded
MAX_LOCK_BYTES = 64 << 20
# Files that are content of the tree; includes are the sub-assemblies themselves.
FILE_KINDS = (Kind.MODEL, Kind.MESH, Kind.STREAM_PROFILE, Kind.FIRMWARE_MANIFEST)
# The BOM identity's namespace: serial numbers are uuid5(NAMESPACE, digest of the inputs).
NAMESPACE = uuid.uuid5(uuid.NAMESPACE_URL, "https://github.com/hcdf-trust/sbom")


@dataclass(frozen=True)
class FileFact:
    ref: str
    kind: str  # model | mesh | stream-profile | firmware-manifest
    name: str  # the lock file's url (relative to the lock's folder, or the URL)
    sha256: str
    size: int
    selected: bool | None = None  # a stream profile: the one its document selects (None: not a profile)


@dataclass(frozen=True)
class Signature:
    """A firmware image in a verified release: who signed it and what was signed."""

    key_sha256: str  # SHA-256 of the signing key's SubjectPublicKeyInfo (the COSE kid, MCUboot KEYHASH)
    key_type: str  # ecdsa-p256 | ed25519 | rsa-2048 | rsa-3072
    alg: str  # the COSE algorithm of the release manifest's signature
    sequence_number: int  # the release manifest's
    file_sha256: str  # the file a device downloads
    size: int
    uri: str
    security_counter: int | None


@dataclass(frozen=True)
class FirmwareFact:
    ref: str
    name: str
    version: str | None
    board: str  # the comp's <board>, else the comp's name (the release's key)
    mcuboot_hash: str | None  # <software><hash> (the MCUboot image hash), else the release's
    file: str  # where the first <software> is written
    line: int | None
    manifest: str | None = None  # ref of its firmware-manifest file
    signature: Signature | None = None


@dataclass(frozen=True)
class DriverFact:
    ref: str
    name: str


@dataclass(frozen=True)
class CompFact:
    ref: str
    name: str  # prefixed, as in the flattened document
    local_name: str  # as written in its document
    instance: str  # the sub-assembly instance path ("" for the robot's own comps)
    board: str | None
    role: str | None
    description: str | None
    file: str
    line: int | None
    depends_on: tuple[str, ...]  # firmware, drivers, files


@dataclass(frozen=True)
class AssemblyFact:
    ref: str
    name: str  # the document's <hcdf name>, else its file name
    instance: str  # include names from the robot, "/"-joined ("" for the robot)
    file: str  # its lock url (the root: relative to the lock's folder too)
    sha256: str
    size: int
    author: str | None
    license: str | None
    description: str | None
    line: int | None  # of the <include> that makes this instance
    depends_on: tuple[str, ...]  # sub-assemblies, comps, files outside comps


@dataclass(frozen=True)
class ProvenanceRef:
    """A release's signed build provenance (``provenance.intoto.json``), verified: where it
    is published and its file SHA-256. Both writers list it as an external reference."""

    url: str  # the release's base URL + the file name, else the file name (relative to the release)
    sha256: str


PROVENANCE_COMMENT = "build provenance: in-toto Statement v1, SLSA Provenance v1 predicate, DSSE envelope"


@dataclass(frozen=True)
class Facts:
    robot: AssemblyFact
    assemblies: tuple[AssemblyFact, ...]  # sub-assembly instances, by ref
    comps: tuple[CompFact, ...]
    firmware: tuple[FirmwareFact, ...]
    drivers: tuple[DriverFact, ...]
    files: tuple[FileFact, ...]
    lock_sha256: str
    identity: str  # hex SHA-256 over the inputs: the serial number / document namespace
    created: datetime
    release_sequence: int | None = None
    release_key_sha256: str | None = None
    provenance: ProvenanceRef | None = None
    notices: tuple[Notice, ...] = ()
    bundle_sha256: str | None = None  # the .hcdfz the tree was read from (then also lock_sha256)

    @property
    def serial(self) -> uuid.UUID:
        return uuid.uuid5(NAMESPACE, self.identity)

    def all_refs(self) -> dict[str, tuple[str, ...]]:
        """Every element's ref and what it depends on (the dependency graph)."""
        graph: dict[str, tuple[str, ...]] = {self.robot.ref: self.robot.depends_on}
        for a in self.assemblies:
            graph[a.ref] = a.depends_on
        for c in self.comps:
            graph[c.ref] = c.depends_on
        for f in self.firmware:
            graph[f.ref] = (f.manifest,) if f.manifest else ()
        for d in self.drivers:
            graph[d.ref] = ()
        for fl in self.files:
            graph[fl.ref] = ()
        return graph


@dataclass(frozen=True)
class ReleaseFacts:
    """A verified release (see :func:`read_release`), keyed by (board, app)."""

    sequence_number: int
    lock_sha256: str
    root_sha256: str
    key_sha256: str
    key_type: str
    alg: str
    manifest_sha256: str
    components: dict[tuple[str, str], Any] = field(default_factory=dict)  # suit.Component
    source: str = ""
    provenance: ProvenanceRef | None = None


def read_release(folder: str, public_key_path: str) -> ReleaseFacts:
    """The release in ``folder``, verified as ``ota verify`` verifies it (signature with the
    key, every image and ``latest.json``), and its ``provenance.intoto.json`` when there is
    one, as ``ota verify --provenance`` does (with the key, threshold 1).

    Raises:
        HcdfTrustError / ErrorGroup: the release does not verify (exit 1) or cannot be read (exit 3).
    """
    from ..errors import ErrorGroup
    from ..ota import release as ota_release
    from ..ota import suit
    from ..ota.keys import key_type, load_public
    from ..ota.signer import ALG_NAMES, key_id
    from ..ota.verify import check_release

    public = load_public(public_key_path)
    release, files = ota_release.read_release(folder, public)
    errors = check_release(release, files, public)
    provenance = None
    if not errors:
        provenance, errors = _provenance(folder, release, public)
    if errors:
        raise ErrorGroup(errors)
    env = suit.parse_envelope(files.manifest, source=files.manifest_source)
    alg = env.protected_map.get(1)
    return ReleaseFacts(
        sequence_number=release.sequence_number,
        lock_sha256=release.lock_sha256,
        root_sha256=release.root_sha256,
        key_sha256=key_id(public).hex(),
        key_type=key_type(public),
        alg=ALG_NAMES.get(alg, str(alg)) if isinstance(alg, int) else str(alg),
        manifest_sha256=hashlib.sha256(files.manifest).hexdigest(),
        components={(c.board, c.app): c for c in release.components},
        source=files.manifest_source,
        provenance=provenance,
    )


def _provenance(folder: str, release: Any, public: Any) -> tuple[ProvenanceRef | None, list[Any]]:
    """The release's provenance, verified, and where it is published (its statement's
    ``baseUrl``, the one the images' URLs start with); (None, []) when there is none."""
    from ..provenance import FILE_NAME, dsse
    from ..provenance.verify import read_envelope, verify_provenance

    data = read_envelope(folder)
    if data is None:
        return None, []
    errors = verify_provenance(folder, release, [public], data=data)
    if errors:
        return None, errors
    stmt = dsse.strict_json(dsse.parse(data, source=FILE_NAME).payload, source=FILE_NAME, what="statement")
    base = stmt["predicate"]["buildDefinition"]["externalParameters"].get("baseUrl")  # verified: a dict
    url = base.rstrip("/") + "/" + FILE_NAME if isinstance(base, str) and base else FILE_NAME
    return ProvenanceRef(url=url, sha256=hashlib.sha256(data).hexdigest()), []


def created_time() -> datetime:
    """``SOURCE_DATE_EPOCH`` when set (reproducible builds), else the Unix epoch: never the clock.

    Raises:
        InputError: ``SOURCE_DATE_EPOCH`` is refused by :func:`hcdf_trust.clock.parse_epoch`
            (the CLI refuses it first, as a usage error).
    """
    from ..clock import EARLIEST, source_date_epoch

    try:
        return source_date_epoch() or EARLIEST
    except ValueError as exc:
        raise InputError(f"SOURCE_DATE_EPOCH: {exc}", file="SOURCE_DATE_EPOCH") from None


def collect(
    res: Resolution, *, release: ReleaseFacts | None = None, fmt: str = "", created: datetime | None = None
) -> Facts:
    """The facts of ``res`` (which must be clean: ``res.ok``), with ``release``'s signatures.

    Raises:
        ReleaseIntegrityError: ``release`` was built from another tree (lock or root digest).
        InputError: the lock cannot be read, a ``<software>`` has no name, or the tree
            multiplies past :data:`MAX_COMPONENTS`.
    """
    return _Collector(res, release).run(fmt, created)


class _Collector:
    def __init__(self, res: Resolution, release: ReleaseFacts | None) -> None:
        self.res = res
        self.release = release
        self.notices: list[Notice] = []
        # (document url, reference element) -> the artifact it resolved to
        self.artifact_of: dict[tuple[str, Any], Any] = {}
        for art in res.artifacts.values():
            for use in art.uses:
                self.artifact_of[(use.doc_url, use.ref.element)] = art
        self.hash_of: dict[Any, Any] = {}  # <hash> element -> its FIRMWARE reference
        for _src, ref in res.others:
            if ref.kind is Kind.FIRMWARE and ref.element is not None:
                self.hash_of[ref.element] = ref
        self.files: dict[str, FileFact] = {}
        self.firmware: dict[tuple[str, str, str | None, str | None], FirmwareFact] = {}
        self.drivers: dict[str, DriverFact] = {}
        self.comps: list[CompFact] = []
        self.assemblies: list[AssemblyFact] = []
        self._doc_parts: dict[str, tuple[list[tuple[Any, list[str]]], list[str]]] = {}

    def run(self, fmt: str, created: datetime | None = None) -> Facts:
        res = self.res
        lock_sha = res.pins_sha256(limit=MAX_LOCK_BYTES)  # a bundle's digest, for a tree read from one
        root_sha = hashlib.sha256(res.root.data).hexdigest()
        if self.release is not None:
            self._check_binding(lock_sha, root_sha)
        root_url = res.root_location.url
        robot = self._assembly(root_url, res.root, _Instance(), "robot", None, root_sha, len(res.root.data))
        seed = hashlib.sha256()
        provenance = self.release.provenance if self.release else None
        for part in (
            fmt,
            lock_sha,
            root_sha,
            self.release.manifest_sha256 if self.release else "",
            *((provenance.sha256,) if provenance else ()),
        ):
            seed.update(part.encode() + b"\0")
        return Facts(
            robot=robot,
            assemblies=tuple(sorted(self.assemblies, key=lambda a: a.ref)),
            comps=tuple(sorted(self.comps, key=lambda c: c.ref)),
            firmware=tuple(sorted(self.firmware.values(), key=lambda f: f.ref)),
            drivers=tuple(sorted(self.drivers.values(), key=lambda d: d.ref)),
            files=tuple(sorted(self.files.values(), key=lambda f: f.ref)),
            lock_sha256=lock_sha,
            bundle_sha256=res.bundle.archive.sha256 if res.bundle is not None else None,
            identity=seed.hexdigest(),
            created=created or created_time(),
            release_sequence=self.release.sequence_number if self.release else None,
            release_key_sha256=self.release.key_sha256 if self.release else None,
            provenance=provenance,
            notices=tuple(self.notices),
        )

    def _check_binding(self, lock_sha: str, root_sha: str) -> None:
        from ..ota.errors import ReleaseIntegrityError

        rel = self.release
        assert rel is not None
        for what, theirs, ours in (
            ("lock file", rel.lock_sha256, lock_sha),
            ("root document", rel.root_sha256, root_sha),
        ):
            if theirs != ours:
                raise ReleaseIntegrityError(
                    f"the release was built from another {what} than this tree's: its firmware is not this robot's",
                    file=rel.source,
                    expected=ours,
                    actual=theirs,
                )

    # -- the include tree ----------------------------------------------------------

    def _assembly(
        self,
        url: str,
        doc: Document,
        at: _Instance,
        ref: str,
        line: int | None,
        sha256: str,
        size: int,
    ) -> AssemblyFact:
        root = doc.root
        depends: list[str] = []
        comps, loose = self._parts(url, doc)
        depends += loose
        for (seg, shown), (comp, comp_deps) in _unique([c.get("name") for c, _ in comps], comps, "comp"):
            cref = "comp/" + "/".join((*at.path, seg))
            local = comp.get("name") or shown
            self._count()
            self.comps.append(
                CompFact(
                    ref=cref,
                    name=SEPARATOR.join((*at.prefix, local)),
                    local_name=local,
                    instance=at.shown,
                    board=single_text(comp, "board", source=doc.source),
                    role=comp.get("role"),
                    description=_text(comp, "description", doc.source),
                    file=self.res.lock_url(url),
                    line=sourceline(comp),
                    depends_on=tuple(sorted(set(comp_deps))),
                )
            )
            depends.append(cref)
        for sub, (inc_ref, child_url) in _instances(at, self.res.includes.get(url, [])):
            child = self.res.documents.get(child_url)
            art = self.res.artifacts.get(child_url)
            if child is None or art is None or art.sha256 is None or art.size is None:
                continue  # not parsed: the resolver reported it (and the caller refused the run)
            self._count()
            fact = self._assembly(
                child_url, child, sub, "assembly/" + "/".join(sub.path), inc_ref.line, art.sha256, art.size
            )
            self.assemblies.append(fact)
            depends.append(fact.ref)
        return AssemblyFact(
            ref=ref,
            name=root.get("name") or os.path.basename(self.res.lock_url(url)),
            instance=at.shown,
            file=self.res.lock_url(url),
            sha256=sha256,
            size=size,
            author=_text(root, "author", doc.source),
            license=_text(root, "license", doc.source),
            description=_text(root, "description", doc.source),
            line=line,
            depends_on=tuple(sorted(set(depends))),
        )

    def _count(self) -> None:
        if len(self.comps) + len(self.assemblies) >= MAX_COMPONENTS:
            raise InputError(
                f"the include tree expands to more than {MAX_COMPONENTS} comps and sub-assemblies",
                file=self.res.root.source,
                expected=f"at most {MAX_COMPONENTS}",
                actual="more",
            )

    def _parts(self, url: str, doc: Document) -> tuple[list[tuple[Any, list[str]]], list[str]]:
        """A document's comps (each with what it depends on) and the files outside any comp;
        the same for every instance of the document, so computed once."""
        done = self._doc_parts.get(url)
        if done is not None:
            return done
        comps = [c for c in doc.root if c.tag == "comp"]
        deps: dict[Any, list[str]] = {c: [] for c in comps}
        loose: list[str] = []
        software: dict[Any, FirmwareFact] = {}
        for sw in software_elements(doc):
            comp = sw.getparent()
            if comp is None or comp not in deps:
                self.notices.append(
                    Notice(
                        "sbom-software", "<software> outside a <comp>: not listed", file=doc.source, line=sourceline(sw)
                    )
                )
                continue
            fw = self._firmware(sw, comp, doc)
            software[sw] = fw
            deps[comp].append(fw.ref)
        for comp in comps:
            for drv in comp.iter("driver"):
                name = (drv.get("name") or "").strip()
                if not name or any(True for _ in drv.iterancestors("extension")):
                    continue
                d = self.drivers.setdefault(name, DriverFact(ref=f"driver/{_q(name)}", name=name))
                deps[comp].append(d.ref)
        streams = stream_profile_selection(doc)
        if streams.problems:
            text, line = streams.problems[0]
            raise StreamSelectionError(text, file=doc.source, line=line)
        chosen = {id(r) for r in streams.selected}
        for ref in doc.references():
            if ref.kind not in FILE_KINDS:
                continue
            art = self.artifact_of.get((url, ref.element))
            if art is None or art.sha256 is None or art.size is None:
                continue
            name = self.res.lock_url(art.url)
            selected = (id(ref) in chosen) if ref.kind is Kind.STREAM_PROFILE else None
            f = self.files.setdefault(
                name,
                FileFact(
                    ref=f"file/{quote(name)}",
                    kind=art.kind.value,
                    name=name,
                    sha256=art.sha256,
                    size=art.size,
                    selected=selected,
                ),
            )
            if selected and not f.selected:  # one document selects what another only lists
                f = self.files[name] = replace(f, selected=True)
            owner = _owner(ref.element, deps)
            holder = ref.element.getparent() if ref.kind is Kind.FIRMWARE_MANIFEST else None
            if holder is not None and holder in software:
                self._set_manifest(software[holder], f.ref)
            elif owner is not None:
                deps[owner].append(f.ref)
            else:
                loose.append(f.ref)
        done = ([(c, deps[c]) for c in comps], loose)
        self._doc_parts[url] = done
        return done

    def _firmware(self, sw: Any, comp: Any, doc: Document) -> FirmwareFact:
        line = sourceline(sw)
        name = (sw.get("name") or "").strip()
        if not name:
            raise InputError(
                f"comp {comp.get('name')!r}: <software> has no name (an SBOM entry needs one)",
                file=doc.source,
                line=line,
                expected='<software name="...">',
                actual="no name",
            )
        ref = self.hash_of.get(single(sw, "hash", source=doc.source))
        digest = ref.sha.lower() if ref is not None and ref.sha else None
        version = single_text(sw, "version", source=doc.source)
        board = single_text(comp, "board", source=doc.source) or (comp.get("name") or "")
        signature = None
        if self.release is not None:
            c = self.release.components.get((board, name))
            if c is None:
                self.notices.append(
                    Notice(
                        "sbom-unsigned",
                        f"{board}/{name} is not in the release: listed without a signer",
                        file=doc.source,
                        line=line,
                    )
                )
            else:
                signature = Signature(
                    key_sha256=self.release.key_sha256,
                    key_type=self.release.key_type,
                    alg=self.release.alg,
                    sequence_number=self.release.sequence_number,
                    file_sha256=c.sha256,
                    size=c.size,
                    uri=c.uri,
                    security_counter=c.security_counter,
                )
                digest = digest or c.mcuboot_hash
        key = (board, name, version, digest)
        fact = self.firmware.get(key)
        if fact is None:
            base = f"firmware/{_q(board)}/{_q(name)}" + (f"@{_q(version)}" if version else "")
            taken = {f.ref for f in self.firmware.values()}
            fref = base if base not in taken else f"{base}~{digest or 'none'}"  # same name, another hash
            fact = self.firmware[key] = FirmwareFact(
                ref=fref,
                name=name,
                version=version,
                board=board,
                mcuboot_hash=digest,
                file=doc.source,
                line=line,
                signature=signature,
            )
        return fact

    def _set_manifest(self, fw: FirmwareFact, file_ref: str) -> None:
        for key, f in self.firmware.items():
            if f is fw:
                self.firmware[key] = _replace(f, manifest=file_ref)
                return


def _replace(fw: FirmwareFact, **kw: Any) -> FirmwareFact:
    return replace(fw, **kw)


@dataclass(frozen=True)
class _Instance:
    """Where a sub-assembly instance sits: its ref path, display path and comp-name prefix."""

    path: tuple[str, ...] = ()  # ref segments (percent-encoded, so never ambiguous)
    shown: str = ""  # include names (else include@K) joined with "/"
    prefix: tuple[str, ...] = ()  # include names only: an unnamed include adds no prefix (flatten's rule)


def _instances(at: _Instance, includes: list[tuple[Any, str]]) -> Iterator[tuple[_Instance, tuple[Any, str]]]:
    """Each include's instance, named by its ``name``; an unnamed include, or a name several
    includes of one document share, by its position K (1-based) among them: ``name@K``."""
    for (seg, shown), (ref, url) in _unique([r.name for r, _ in includes], includes, "include"):
        prefix = (*at.prefix, ref.name) if ref.name else at.prefix
        yield _Instance((*at.path, seg), f"{at.shown}/{shown}" if at.shown else shown, prefix), (ref, url)


def _unique(names: list[str | None], items: list[Any], what: str) -> Iterator[tuple[tuple[str, str], Any]]:
    """((ref segment, shown name), item): the name when written once, else ``name@K`` (``what@K``
    when unnamed), K the item's position (1-based): never two items with one ref."""
    counts = Counter(names)
    for k, (name, item) in enumerate(zip(names, items, strict=True), start=1):
        if name and counts[name] == 1:
            yield (_q(name), name), item
        else:
            yield (f"{_q(name) if name else ''}@{k}", f"{name or what}@{k}"), item


def _q(text: str) -> str:
    """One ref segment: percent-encoded (also '/', '@', '~'), so refs are unique and valid IRI paths."""
    return quote(text, safe="").replace("~", "%7E")


def _owner(el: Any, comps: dict[Any, list[str]]) -> Any:
    for anc in el.iterancestors("comp"):
        if anc in comps:
            return anc
    return None


def _text(el: etree._Element, tag: str, source: str) -> str | None:
    """Free text of the one ``<tag>`` child (author, license, description), whitespace collapsed."""
    child = single(el, tag, source=source)
    if child is None:
        return None
    text = " ".join("".join(str(t) for t in child.itertext()).split())
    return text or None


# -- HCDF facts without a field in either format: hcdf:* properties (both writers) --


def properties(pairs: Iterable[tuple[str, str | int | None]]) -> list[tuple[str, str]]:
    """``(name, value)`` pairs with a value, values as strings (shared with the SPDX writer)."""
    return [(name, str(value)) for name, value in pairs if value is not None and value != ""]


def assembly_properties(a: AssemblyFact) -> list[tuple[str, str]]:
    return properties([("hcdf:file", a.file), ("hcdf:instance", a.instance), ("hcdf:include-line", a.line)])


def comp_properties(c: CompFact) -> list[tuple[str, str]]:
    return properties(
        [
            ("hcdf:board", c.board),
            ("hcdf:role", c.role),
            ("hcdf:comp", c.local_name),
            ("hcdf:instance", c.instance),
            ("hcdf:file", f"{c.file}:{c.line}" if c.line else c.file),
        ]
    )


def file_properties(f: FileFact) -> list[tuple[str, str]]:
    selected = None if f.selected is None else str(f.selected).lower()
    return properties([("hcdf:kind", f.kind), ("hcdf:size", f.size), ("hcdf:stream-profile-selected", selected)])


def firmware_properties(f: FirmwareFact) -> list[tuple[str, str]]:
    s = f.signature
    return properties(
        [
            ("hcdf:board", f.board),
            ("hcdf:mcuboot-hash", f.mcuboot_hash),
            ("hcdf:signature:key-sha256", s.key_sha256 if s else None),
            ("hcdf:signature:key-type", s.key_type if s else None),
            ("hcdf:signature:alg", s.alg if s else None),
            ("hcdf:release:sequence-number", s.sequence_number if s else None),
            ("hcdf:release:uri", s.uri if s else None),
            ("hcdf:security-counter", s.security_counter if s else None),
        ]
    )
