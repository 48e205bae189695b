"""``ota build``: a release from a verified HCDF tree, written all or nothing.

The steps, in order (any error stops the build before anything is written):

1. Resolve the document tree under its lock, offline; refuse on any error.
2. Plan one image per (board, app) from the ``<comp>``/``<software>`` entries and ``ota.toml``.
3. Read the previous release (its manifest verified with our key) for history,
   sequence number and security counters.
4. Sign every image in parallel through imgtool; compare each image hash with the
   HCDF's ``<software><hash>``.
5. Render ``{board}/{app}/{version}.bin``, ``latest.json``, ``release.suit`` and
   ``release.suit.json``; commit them through one :class:`~hcdf_trust.outputs.OutputPlan`.
"""

from __future__ import annotations

import hashlib
import os
import re
import stat
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import unquote, urlsplit

from ..digest import parse_pin
from ..document import Kind, single, single_text, software_elements
from ..errors import ErrorGroup, HcdfTrustError, InputError, NotFoundError, Notice
from ..include.resolver import TreeOptions
from ..localfile import open_checked, read_bounded, read_input
from ..outputs import DOCUMENT, ORDINARY, OutputPlan
from ..xml import sourceline
from . import latest as latest_json
from . import suit
from .config import ImageSettings, OtaConfig, load_config
from .errors import FirmwareError, FirmwareHashError, RollbackError
from .hcdf_edit import HashEdit, check_unchanged, update_tree
from .images import SignedImage, quiet, sign_image
from .signer import ALG_NAMES, COSE_ALGS, Signer, key_id
from .version import McubootVersion, parse_version

MAX_FIRMWARE_BYTES = 256 << 20
MAX_LATEST_BYTES = 4 << 20
MANIFEST_NAME = "release.suit"
MANIFEST_JSON_NAME = "release.suit.json"
_SAFE = re.compile(r"[A-Za-z0-9][A-Za-z0-9._+-]*")


@dataclass(frozen=True)
class BuildOptions:
    firmware_dir: str
    out_dir: str
    signer: Signer
    inputs: tuple[tuple[str, str], ...] = ()  # (path, what): keys, passphrase/PIN files
    base_url: str | None = None
    previous: str | None = None
    config: str | None = None
    changelog: str | None = None
    update_hcdf: bool = False
    date: str | None = None
    jobs: int = 0  # 0: one per core
    ca_bundle: str | None = None  # for https: --previous, and the tree under --online
    provenance: bool = False  # also write provenance.intoto.json, signed with the release key
    builder_id: str | None = None  # its runDetails.builder.id
    # resolve's --base, --mirror, --root, --cache-dir, --lock, --offline (the default) / --online
    tree: TreeOptions = field(default_factory=TreeOptions)


@dataclass
class Use:
    comp: str
    file: str
    line: int | None
    hash_text: str | None
    hash_line: int | None
    doc_url: str = ""
    hash_element: Any = None


@dataclass
class Planned:
    board: str
    app: str
    version_text: str | None
    settings: ImageSettings
    uses: list[Use] = field(default_factory=list)

    @property
    def first(self) -> Use:
        return self.uses[0]


@dataclass
class BuildReport:
    release: suit.Release
    notices: list[Notice]
    wrote: list[str]
    excluded: list[str]
    hcdf_changes: list[dict[str, Any]] = field(default_factory=list)


@dataclass(frozen=True)
class PreviousRelease:
    release: suit.Release | None
    latest: dict[tuple[str, str], latest_json.Latest]
    source: str


def build_release(doc_path: str, options: BuildOptions) -> BuildReport:
    """Build and write a release; raise on any error with nothing written.

    Raises:
        ErrorGroup / HcdfTrustError: the tree does not verify, an input is missing or
            malformed, a hash or counter check fails, or an output cannot be written.
    """
    from ..include.resolver import resolve

    # 1. a verified description: the tree under its lock (offline unless --online)
    res = resolve(doc_path, options.tree.resolve_options(locked=True, ca_bundle=options.ca_bundle))
    if not res.ok:
        raise ErrorGroup(res.errors)
    lock_data = read_input(str(res.lock_path), limit=64 << 20, what="lock file")
    lock_sha = hashlib.sha256(lock_data).hexdigest()
    config_path = options.config
    if config_path is None:
        default = Path(doc_path).parent / "ota.toml"
        config_path = str(default) if default.exists() else None
    config = load_config(config_path)

    # 2. the plan
    notices: list[Notice] = []
    plans = _plan(res, config, notices)
    excluded = [f"{p.board}/{p.app}" for p in plans if p.settings.exclude]
    for p in plans:
        if p.settings.exclude:
            notices.append(
                Notice("excluded", f"{p.board}/{p.app} is excluded by ota.toml", file=p.first.file, line=p.first.line)
            )
    todo = [p for p in plans if not p.settings.exclude]
    if not todo:
        raise FirmwareError("no <software> entry to build", file=res.root.source)

    # 3. the previous release: --previous, else what --out already holds (history is never lost)
    source = options.previous
    if source is None and _holds_release(options.out_dir, todo):
        source = options.out_dir
        notices.append(
            Notice(
                "previous", f"{options.out_dir} already holds a release: using it as --previous", file=options.out_dir
            )
        )
    previous = load_previous(source, options.signer, [(p.board, p.app) for p in todo], ca_bundle=options.ca_bundle)

    # 4. the images
    built = _build_images(todo, options, config)
    errors: list[HcdfTrustError] = []
    base_url = options.base_url if options.base_url is not None else config.base_url
    date = options.date or _now()
    outputs: list[tuple[Path, bytes]] = []
    hash_edits: list[HashEdit] = []
    changes: list[dict[str, Any]] = []
    components: list[suit.Component] = []
    for p, (image, version_name) in zip(todo, built, strict=True):
        is_raw = p.settings.type == "raw"
        computed = image.image_hash  # for a raw image: its file's SHA-256
        for use in p.uses:
            pin = parse_pin(use.hash_text, file=use.file, line=use.hash_line) if use.hash_text else None
            if pin is not None and not pin.matches(computed) and options.update_hcdf:
                hash_edits.append(HashEdit(use.doc_url, use.hash_element, use.hash_text or "", computed))
                changes.append(
                    {"file": use.file, "line": use.hash_line, "comp": use.comp, "old": use.hash_text, "new": computed}
                )
            elif pin is not None and not pin.matches(computed):
                errors.append(
                    FirmwareHashError(
                        f"comp {use.comp!r}: <software name={p.app!r}><hash> is not the "
                        + ("SHA-256 of the raw image" if is_raw else "MCUboot image hash")
                        + " built from it",
                        file=use.file,
                        line=use.hash_line,
                        expected=use.hash_text,
                        actual=computed,
                    )
                )
        prev_comp = previous.release.component(p.board, p.app) if previous.release else None
        if (
            prev_comp is not None
            and prev_comp.security_counter is not None
            and (image.security_counter or 0) < prev_comp.security_counter
        ):
            errors.append(
                RollbackError(
                    f"{p.board}/{p.app}: security counter went down since the previous release",
                    file=p.first.file,
                    line=p.first.line,
                    expected=f"≥ {prev_comp.security_counter}",
                    actual=str(image.security_counter),
                )
            )
        rel = f"{p.board}/{p.app}/{version_name}.bin"
        url = _join(base_url, rel)
        changelog = p.settings.changelog or options.changelog or config.changelog
        outputs.append((Path(options.out_dir, rel), image.data))
        components.append(
            suit.Component(
                board=p.board,
                app=p.app,
                type=p.settings.type,
                version=version_name,
                uri=url,
                size=image.size,
                sha256=image.sha256,
                mcuboot_hash=None if is_raw else image.image_hash,
                security_counter=None if is_raw else image.security_counter,
                comps=tuple(u.comp for u in p.uses),
                changelog=changelog,
            )
        )
        if not is_raw:
            entry = latest_json.Entry(
                version=version_name,
                date=date,
                mcuboot_hash=image.image_hash,
                size=image.size,
                url=url,
                changelog=changelog,
            )
            try:
                doc = latest_json.advance(
                    previous.latest.get((p.board, p.app)), board=p.board, app=p.app, new=entry, source=previous.source
                )
            except HcdfTrustError as exc:
                errors.append(exc)
                continue
            outputs.append((Path(options.out_dir, p.board, p.app, "latest.json"), latest_json.render(doc)))
    sequence = _sequence(config, previous, errors)
    edited: dict[str, bytes] = {}
    root_data = res.root.data
    if hash_edits and not errors:
        result = update_tree(res, hash_edits)
        errors += check_unchanged(res, list(result.documents))
        edited = result.documents
        lock_data = result.lock
        lock_sha = hashlib.sha256(lock_data).hexdigest()
        root_data = edited.get(res.root_location.url, root_data)
    if errors:
        raise ErrorGroup(errors)
    plan = OutputPlan()
    _protect(plan, res, options, config_path, edited=set(edited))
    for path, data in outputs:
        plan.add(path, data, flag="--out", under=options.out_dir)
    for url, data in edited.items():
        local = unquote(urlsplit(url).path)
        plan.add(
            local, data, flag="--update-hcdf", mode=stat.S_IMODE(os.stat(local).st_mode), replaces=(ORDINARY, DOCUMENT)
        )
    if edited:
        plan.add(res.lock_path, lock_data, flag="--update-hcdf", mode=stat.S_IMODE(os.stat(res.lock_path).st_mode))

    # 5. the manifest, then everything at once
    release = suit.Release(
        sequence_number=sequence,
        lock_sha256=lock_sha,
        root=os.path.basename(res.root.source),
        root_sha256=hashlib.sha256(root_data).hexdigest(),
        components=tuple(components),
        date=date,
    )
    env, alg, kid = sign_release(release, options.signer)
    plan.add(Path(options.out_dir, MANIFEST_NAME), env, flag="--out", under=options.out_dir)
    rendering = suit.render_json(release, alg=ALG_NAMES[alg], kid=kid.hex())
    plan.add(Path(options.out_dir, MANIFEST_JSON_NAME), rendering, flag="--out", under=options.out_dir)
    if options.provenance:
        from ..provenance import FILE_NAME
        from ..provenance.build import release_provenance

        signed = release_provenance(  # the last output: its subjects are every other one
            out_dir=options.out_dir,
            new_files=plan.planned(options.out_dir),
            release=release,
            lock_name=os.path.basename(res.lock_path),
            lock_entries=res.lock_entries(edited),
            images=[f"{p.board}/{p.app}" for p in todo],
            date=date,
            base_url=base_url,
            config_path=config_path,
            signers=[options.signer],
            builder_id=options.builder_id,
        )
        plan.add(Path(options.out_dir, FILE_NAME), signed, flag="--out", under=options.out_dir)
    wrote = [str(p) for p in plan.commit()]
    return BuildReport(release=release, notices=notices, wrote=wrote, excluded=excluded, hcdf_changes=changes)


def sign_release(release: suit.Release, signer: Signer) -> tuple[bytes, int, bytes]:
    """The signed envelope, the COSE algorithm and the key id."""
    manifest, payloads = suit.encode(release)
    return sign_manifest(manifest, signer, payloads)


def sign_manifest(
    manifest: bytes, signer: Signer, payloads: dict[str, bytes] | None = None
) -> tuple[bytes, int, bytes]:
    """The envelope around ``manifest`` (and its integrated ``payloads``) with its COSE_Sign1,
    made by cwt with the signer's key.

    cwt has no detached encode: it signs ``["Signature1", protected, h'', payload]`` with
    the payload attached, and the payload is then set to nil (the signature is the same).
    Importing cwt costs a build 35–55 ms of CPU here (most of it ``cryptography.x509``,
    which cwt imports), measured with the rest of a build's imports already loaded.
    """
    import cbor2
    from cwt import COSE

    alg = COSE_ALGS[signer.kind][0]
    kid = key_id(signer.public)
    payload = suit.manifest_digest(manifest)
    tag = COSE.new(deterministic_header=True).encode_and_sign(
        payload, signer.cose_key(kid), protected={1: alg, 4: kid}, out="cbor2/CBORTag"
    )
    assert isinstance(tag, cbor2.CBORTag) and tag.tag == suit.COSE_SIGN1_TAG and tag.value[2] == payload
    tag.value[2] = None
    return suit.envelope(manifest, cbor2.dumps(tag), payloads), alg, kid


def _plan(res: Any, config: OtaConfig, notices: list[Notice]) -> list[Planned]:
    hashes = {}
    for _source, ref in res.others:
        if ref.kind is Kind.FIRMWARE and ref.element is not None:
            hashes[ref.element] = ref
    plans: dict[tuple[str, str], Planned] = {}
    for doc_url, doc in res.documents.items():
        for sw in software_elements(doc):
            line = sourceline(sw)
            comp = sw.getparent()
            app = (sw.get("name") or "").strip()
            if comp is None or comp.tag != "comp":
                notices.append(
                    Notice("not-built", f"<software name={app!r}> is not inside a <comp>", file=doc.source, line=line)
                )
                continue
            comp_name = comp.get("name") or "?"
            if not app:
                raise FirmwareError(f"comp {comp_name!r}: <software> has no name", file=doc.source, line=line)
            board = single_text(comp, "board", source=doc.source) or comp_name
            for what, value in (("board", board), ("software name", app)):
                if not _SAFE.fullmatch(value) or value in (".", ".."):
                    raise FirmwareError(
                        f"comp {comp_name!r}: {what} {value!r} cannot name a release folder",
                        file=doc.source,
                        line=line,
                        expected="letters, digits, '.', '_', '+', '-'",
                        actual=value,
                    )
            version = single_text(sw, "version", source=doc.source)
            ref = hashes.get(single(sw, "hash", source=doc.source))
            use = Use(
                comp_name,
                doc.source,
                line,
                ref.sha if ref else None,
                ref.line if ref else None,
                doc_url,
                ref.element if ref else None,
            )
            key = (board, app)
            if key in plans:
                other = plans[key]
                if (other.version_text or "").strip() != (version or "").strip():
                    raise FirmwareError(
                        f"comps {other.first.comp!r} and {comp_name!r} run {board}/{app} at different versions",
                        file=doc.source,
                        line=line,
                        expected=other.version_text,
                        actual=version,
                    )
                other.uses.append(use)
            else:
                plans[key] = Planned(board, app, version, config.image(app), [use])
    return list(plans.values())


def _build_images(todo: list[Planned], options: BuildOptions, config: OtaConfig) -> list[tuple[SignedImage, str]]:
    """Read and sign every binary in parallel; results in ``todo`` order, errors all collected."""
    jobs = options.jobs or len(os.sched_getaffinity(0))

    def one(p: Planned) -> tuple[SignedImage, str]:
        payload, intel_hex = _read_firmware(p, options.firmware_dir)
        use = p.first
        if p.settings.type == "raw":
            payload_sha = hashlib.sha256(payload).hexdigest()
            name = (p.version_text or "").strip()
            if not _SAFE.fullmatch(name):
                raise FirmwareError(
                    f"comp {use.comp!r}: raw image version {name!r} cannot name a file",
                    file=use.file,
                    line=use.line,
                    actual=name,
                )
            image = SignedImage(
                data=payload,
                image_hash=payload_sha,
                version=McubootVersion(0, 0, 0),
                security_counter=None,
                sha256=payload_sha,
            )
            return image, name
        if p.settings.mcuboot_version is not None:
            version = parse_version(
                p.settings.mcuboot_version, comp=use.comp, app=p.app, file=config.source, source="mcuboot_version"
            )
        else:
            version = parse_version(p.version_text, comp=use.comp, app=p.app, file=use.file, line=use.line)
        image = sign_image(
            payload,
            name=p.app,
            version=version,
            board=config.board(p.board),
            security_counter=p.settings.security_counter,
            create=options.signer.create,
            dependencies=p.settings.dependencies,
            intel_hex=intel_hex,
            comp=use.comp,
        )
        return image, str(version)

    with quiet(), ThreadPoolExecutor(max_workers=max(1, min(jobs, len(todo)))) as pool:
        futures = [pool.submit(one, p) for p in todo]
        results: list[tuple[SignedImage, str]] = []
        errors: list[HcdfTrustError] = []
        for f in futures:
            try:
                results.append(f.result())
            except HcdfTrustError as exc:
                errors.append(exc)
    if errors:
        raise ErrorGroup(errors)
    return results


def _read_firmware(p: Planned, firmware_dir: str) -> tuple[bytes, bool]:
    """The binary for ``p`` (confined to the firmware folder): bytes and whether it is Intel HEX."""
    use = p.first
    if p.settings.file is not None:
        candidates = [p.settings.file]
    else:
        candidates = [f"{p.board}/{p.app}.bin", f"{p.board}/{p.app}.hex", f"{p.app}.bin", f"{p.app}.hex"]
    for rel in candidates:
        path = os.path.join(firmware_dir, rel)
        try:
            fd, _ = open_checked(path, firmware_dir, file=use.file, line=use.line)
        except NotFoundError:
            continue
        try:
            data = read_bounded(fd, MAX_FIRMWARE_BYTES, source=path, what="firmware binary")
        finally:
            os.close(fd)
        return data, rel.lower().endswith(".hex")
    raise FirmwareError(
        f"comp {use.comp!r}: no binary for {p.board}/{p.app} in {firmware_dir}",
        file=use.file,
        line=use.line,
        expected=" or ".join(candidates),
        actual="none of them",
    )


def load_previous(
    source: str | None, signer: Signer, wanted: list[tuple[str, str]], *, ca_bundle: str | None = None
) -> PreviousRelease:
    """The previous release (a folder or an https URL): its manifest, verified with our key,
    if it has one, and each wanted image's latest.json (the fleet's own format is accepted).

    Raises:
        SignatureError / MalformedReleaseError: the previous manifest does not verify with our key.
        FetchError / InputError: a file that exists cannot be read or fetched.
    """
    from .verify import verify_envelope

    if source is None:
        return PreviousRelease(None, {}, "")
    reader = PreviousReader(source, ca_bundle=ca_bundle)
    try:
        release = None
        data = reader.read(MANIFEST_NAME, limit=suit.MAX_MANIFEST_BYTES, what="release manifest")
        if data is not None:
            release = verify_envelope(data, signer.public, source=reader.name(MANIFEST_NAME))
        found = {}
        for board, app in wanted:
            rel = f"{board}/{app}/latest.json"
            data = reader.read(rel, limit=MAX_LATEST_BYTES, what="latest.json")
            if data is not None:
                found[(board, app)] = latest_json.parse(data, source=reader.name(rel))
    finally:
        reader.close()
    return PreviousRelease(release, found, source)


def previous_manifest(source: str, public_key: Any, *, ca_bundle: str | None = None) -> suit.Release:
    """The verified manifest of a previous release (folder or https URL), for ``ota verify``.

    Raises:
        MalformedReleaseError: it has none. SignatureError etc.: see :func:`.verify.verify_envelope`.
    """
    from .errors import MalformedReleaseError
    from .verify import verify_envelope

    reader = PreviousReader(source, ca_bundle=ca_bundle)
    try:
        data = reader.read(MANIFEST_NAME, limit=suit.MAX_MANIFEST_BYTES, what="release manifest")
    finally:
        reader.close()
    if data is None:
        raise MalformedReleaseError("the previous release has no signed manifest", file=reader.name(MANIFEST_NAME))
    return verify_envelope(data, public_key, source=reader.name(MANIFEST_NAME))


class PreviousReader:
    """Files of a previous release by relative path: a local folder, or https (absent = HTTP 404)."""

    def __init__(self, source: str, *, ca_bundle: str | None = None) -> None:
        self.source = source
        self.fetcher: Any = None
        if "://" in source:
            from ..include.fetch import HttpFetcher

            if not source.startswith("https://"):
                raise FirmwareError("--previous must be a folder or an https:// URL", actual=source)
            self.fetcher = HttpFetcher(ca_bundle=ca_bundle, max_bytes=suit.MAX_MANIFEST_BYTES)
        elif not os.path.isdir(source):
            raise NotFoundError(f"--previous {source} is not a folder", file=source)

    def name(self, rel: str) -> str:
        return self.source.rstrip("/") + "/" + rel if self.fetcher else os.path.join(self.source, rel)

    def read(self, rel: str, *, limit: int, what: str) -> bytes | None:
        if self.fetcher is None:
            path = os.path.join(self.source, rel)
            return read_input(path, limit=limit, what=what) if os.path.lexists(path) else None
        from ..errors import FetchError

        url = self.name(rel)
        try:
            with self.fetcher.open(url) as chunks:
                data = b"".join(chunks)
        except FetchError as exc:
            if exc.message.endswith(": HTTP 404"):
                return None
            raise
        if len(data) > limit:
            raise FetchError(f"{what} is over the {limit}-byte limit", url=url)
        return data

    def close(self) -> None:
        if self.fetcher is not None:
            self.fetcher.close()


def _holds_release(out_dir: str, todo: list[Planned]) -> bool:
    if os.path.lexists(os.path.join(out_dir, MANIFEST_NAME)):
        return True
    return any(os.path.lexists(os.path.join(out_dir, p.board, p.app, "latest.json")) for p in todo)


def _sequence(config: OtaConfig, previous: PreviousRelease, errors: list[HcdfTrustError]) -> int:
    before = previous.release.sequence_number if previous.release else None
    if config.sequence_number is not None:
        if before is not None and config.sequence_number <= before:
            errors.append(
                RollbackError(
                    "sequence_number must be greater than the previous release's",
                    file=config.source,
                    expected=f"> {before}",
                    actual=str(config.sequence_number),
                )
            )
        return config.sequence_number
    return 1 if before is None else before + 1


def _protect(plan: OutputPlan, res: Any, options: BuildOptions, config_path: str | None, *, edited: set[str]) -> None:
    for url in res.documents:
        if url.startswith("file://") and url not in edited:
            plan.protect(unquote(urlsplit(url).path), what="a document of the HCDF tree")
    for art in res.artifacts.values():
        if art.location.path is not None and art.url not in edited:
            plan.protect(art.location.path, what="a verified artifact")
    if not edited:
        plan.protect(res.lock_path, what="the lock file")
    plan.protect_tree(options.firmware_dir, what="the firmware folder")
    if config_path:
        plan.protect(config_path, what="ota.toml")
    for path, what in options.inputs:
        plan.protect(path, what=what)


def _join(base: str | None, rel: str) -> str:
    return base.rstrip("/") + "/" + rel if base else rel


def _now() -> str:
    """``SOURCE_DATE_EPOCH`` (checked by :func:`hcdf_trust.clock.parse_epoch`), else the clock.

    Raises:
        InputError: ``SOURCE_DATE_EPOCH`` is refused (the CLI refuses it first, as a usage error).
    """
    from ..clock import source_date_epoch

    try:
        epoch = source_date_epoch()
    except ValueError as exc:
        raise InputError(f"SOURCE_DATE_EPOCH: {exc}", file="SOURCE_DATE_EPOCH") from None
    return format_date(epoch.timestamp() if epoch is not None else time.time())


def format_date(seconds: float) -> str:
    """How a release is dated (``latest.json``'s ``date``): UTC, to the second."""
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(int(seconds)))


def read_release(folder: str, public_key: Any) -> tuple[suit.Release, Any]:
    """The disk layer of ``ota verify``: the verified manifest of ``folder`` and the bytes
    of every file it lists, plus every ``*/*/latest.json`` found there.

    Raises:
        NotFoundError / InputError: no manifest, or a file that cannot be read.
        MalformedReleaseError / SignatureError: see :func:`.verify.verify_envelope`.
    """
    from .verify import ReleaseFiles, image_path, verify_envelope

    manifest_path = os.path.join(folder, MANIFEST_NAME)
    data = read_input(manifest_path, limit=suit.MAX_MANIFEST_BYTES, what="release manifest")
    release = verify_envelope(data, public_key, source=manifest_path)
    images: dict[str, bytes | None] = {}
    for c in release.components:
        rel = image_path(c)
        path = os.path.join(folder, rel)
        try:
            fd, _ = open_checked(path, folder, file=rel)
        except NotFoundError:
            images[rel] = None
            continue
        try:
            images[rel] = read_bounded(fd, MAX_FIRMWARE_BYTES, source=rel, what="image")
        finally:
            os.close(fd)
    found: dict[str, bytes] = {}
    for board in sorted(os.listdir(folder)):
        board_dir = os.path.join(folder, board)
        if not os.path.isdir(board_dir) or os.path.islink(board_dir):
            continue
        for app in sorted(os.listdir(board_dir)):
            path = os.path.join(board_dir, app, "latest.json")
            if os.path.lexists(path):
                rel = f"{board}/{app}/latest.json"
                fd, _ = open_checked(path, folder, file=rel)
                try:
                    found[rel] = read_bounded(fd, MAX_LATEST_BYTES, source=rel, what="latest.json")
                finally:
                    os.close(fd)
    rendering = None
    json_path = os.path.join(folder, MANIFEST_JSON_NAME)
    if os.path.lexists(json_path):
        fd, _ = open_checked(json_path, folder, file=MANIFEST_JSON_NAME)
        try:
            rendering = read_bounded(fd, suit.MAX_MANIFEST_BYTES, source=MANIFEST_JSON_NAME, what="release.suit.json")
        finally:
            os.close(fd)
    return release, ReleaseFiles(
        manifest=data, manifest_source=manifest_path, images=images, latest=found, rendering=rendering
    )
