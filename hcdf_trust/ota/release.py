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

import dataclasses
import hashlib
import os
import re
import stat
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple
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
from .errors import FirmwareError, FirmwareHashError, MalformedReleaseError, RollbackError
from .hcdf_edit import HashEdit, check_unchanged, update_tree
from .images import SignedImage, quiet, sign_image
from .read import HISTORY_NAME as HISTORY_NAME  # the read side lives in .read; its names stay importable here
from .read import MANIFEST_JSON_NAME as MANIFEST_JSON_NAME
from .read import MANIFEST_NAME as MANIFEST_NAME
from .read import MAX_FIRMWARE_BYTES as MAX_FIRMWARE_BYTES
from .read import MAX_HISTORY_BYTES as MAX_HISTORY_BYTES
from .read import MAX_LATEST_BYTES as MAX_LATEST_BYTES
from .read import FolderImages as FolderImages
from .read import read_release as read_release
from .signer import ALG_NAMES, COSE_ALGS, Signer, key_id
from .version import McubootVersion, parse_version

_SAFE = re.compile(r"[A-Za-z0-9][A-Za-z0-9._+-]*")

# The public API (docs/api.md); everything else here is internal.
__all__ = ["BuildOptions", "BuildReport", "build_release", "read_release"]


@dataclass(frozen=True)
class BuildOptions:
    """What an ``ota build`` run is told; each field is the flag of the same name (docs/ota.md).

    Attributes:
        firmware_dir: ``--firmware-dir``: where each image's binary is found.
        out_dir: ``--out``: the release folder (an earlier release there is the previous one).
        signer: who signs: :class:`~hcdf_trust.ota.signer.FileSigner` or a PKCS#11 signer.
        inputs: (path, what) of key, passphrase and PIN files, which no output may replace.
        base_url, previous, config, changelog, update_hcdf, jobs, ca_bundle, provenance,
        builder_id, allow_http, import_unsigned_history: as the flags.
        date: the release date (RFC 3339; default ``SOURCE_DATE_EPOCH``, else now).
        tree: where the description tree is found (resolve's ``--base``, ``--root``, ...).

    Example:
        >>> from hcdf_trust.ota.keys import generate
        >>> from hcdf_trust.ota.release import BuildOptions
        >>> from hcdf_trust.ota.signer import FileSigner
        >>> options = BuildOptions(firmware_dir="fw", out_dir="release", signer=FileSigner(generate("ed25519")))
        >>> options.previous is None, options.tree.offline
        (True, True)
    """

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
    allow_http: bool = False  # a plain http:// base URL
    import_unsigned_history: bool = False  # a --previous without a signed manifest (see load_previous)


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
    """What :func:`build_release` built and wrote.

    Attributes:
        release: the signed release (``sequence_number``, ``components`` with ``board``,
            ``app``, ``version``, ``mcuboot_hash``, ``sha256``…, ``lock_sha256``).
        notices: warnings (e.g. ``unsigned-history``).
        wrote: the paths written.
        excluded: ``board/app`` of the images ``ota.toml`` excluded.
        hcdf_changes: the ``<hash>`` edits ``update_hcdf`` made (file, line, comp, old, new).

    Example:
        >>> from hcdf_trust.ota.keys import generate
        >>> from hcdf_trust.ota.release import BuildOptions, build_release
        >>> from hcdf_trust.ota.signer import FileSigner
        >>> report = build_release("examples/robot/robot.hcdf", BuildOptions(
        ...     firmware_dir="examples/robot/firmware", out_dir="release", signer=FileSigner(generate("ed25519"))))
        >>> report.release.sequence_number, [c.name for c in report.release.components]
        (1, ['compute/scout-os', 'scout2_arm/arm-ctrl'])
        >>> len(report.wrote), report.excluded, report.notices
        (5, [], [])
    """

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
    envelope: bytes | None = None  # its signed release.suit
    history: tuple[bytes, ...] = ()  # its release.history, verified: the envelopes before it
    signed: tuple[suit.Release, ...] = ()  # its release, then its history's
    imported: bool = False  # --import-unsigned-history: its latest.json entries taken on the user's word


def build_release(doc_path: str, options: BuildOptions) -> BuildReport:
    """Build and write a release from ``doc_path``'s verified tree, as ``ota build`` does:
    one MCUboot (or raw) image per ``<comp>`` with ``<software>``, ``latest.json`` per
    device, and one signed SUIT manifest over all of them; all or nothing.

    Args:
        doc_path: the root HCDF document (its tree is resolved under its lock).
        options: :class:`BuildOptions`.

    Returns:
        A :class:`BuildReport`.

    Example (build, then verify as ``ota verify`` does, then tamper):

        >>> from hcdf_trust.ota.keys import generate, load_public, public_pem
        >>> from hcdf_trust.ota.release import BuildOptions, build_release, read_release
        >>> from hcdf_trust.ota.signer import FileSigner
        >>> from hcdf_trust.ota.verify import check_release
        >>> key = generate("ed25519")
        >>> _ = build_release("examples/robot/robot.hcdf", BuildOptions(
        ...     firmware_dir="examples/robot/firmware", out_dir="release", signer=FileSigner(key)))
        >>> _ = open("fw.pub.pem", "wb").write(public_pem(key))
        >>> public = load_public("fw.pub.pem")
        >>> release, files = read_release("release", public)
        >>> check_release(release, files, public)
        []
        >>> with open("release/scout2_arm/arm-ctrl/1.4.2.bin", "r+b") as image:
        ...     _ = image.seek(600), image.write(b"\\xff")
        >>> release, files = read_release("release", public)
        >>> [(e.code, e.exit_code) for e in check_release(release, files, public)]
        [('release', 1)]

    Raises:
        ErrorGroup / HcdfTrustError: the tree does not verify, an input is missing or
            malformed, a hash or counter check fails, or an output cannot be written.
    """
    from ..include.resolver import resolve

    # 1. a verified description: the tree under its lock (offline unless --online)
    res = resolve(doc_path, options.tree.resolve_options(locked=True, ca_bundle=options.ca_bundle))
    if not res.ok:
        raise ErrorGroup(res.errors)
    if res.bundle is not None and options.update_hcdf:
        raise InputError(
            f"--update-hcdf edits the description in place: {res.bundle.archive.path} is a bundle, rebuild it instead",
            file=res.bundle.archive.path,
        )
    # What pins the tree: the lock file, or the bundle the tree was read from (recorded as the lock digest)
    lock_sha = res.pins_sha256(limit=64 << 20)
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
    previous = load_previous(
        source,
        options.signer.public,
        [(p.board, p.app) for p in todo],
        ca_bundle=options.ca_bundle,
        import_unsigned=options.import_unsigned_history,
    )
    previous = carried(previous, notices)
    if previous.imported and previous.release is None:
        notices.append(
            Notice(
                "unsigned-history",
                f"{source}: no signed manifest; its latest.json history is imported on your word "
                "(--import-unsigned-history) and the sequence number starts again",
                file=source,
            )
        )

    # 4. the images
    built = _build_images(todo, options, config)
    errors: list[HcdfTrustError] = []
    base_url = options.base_url if options.base_url is not None else config.base_url
    if base_url is not None:
        check_base_url(
            base_url, allow_http=options.allow_http, what="--base-url" if options.base_url is not None else "base_url"
        )
    date = options.date or _now()
    outputs: list[tuple[Path, bytes]] = []
    hash_edits: list[HashEdit] = []
    changes: list[dict[str, Any]] = []
    components: list[suit.Component] = []
    for p, (image, version_name, _) in zip(todo, built, strict=True):
        is_raw = p.settings.type == "raw"
        computed = image.image_hash  # for a raw image: its file's SHA-256
        for use in p.uses:
            pin = parse_pin(use.hash_text, file=use.file, line=use.hash_line, element="hash") if use.hash_text else None
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
                        + " built from it; if the new image is intended, build again with --update-hcdf"
                        " (it writes the built hash into <hash>)",
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
        for before in previous.signed:  # a file name is a version: another content under it is refused
            was = before.component(p.board, p.app)
            same_latest = not is_raw and (p.board, p.app) in previous.latest  # latest_json.advance says it
            if was is not None and was.version == version_name and not same_latest:
                if (was.mcuboot_hash or was.sha256) != computed:
                    errors.append(
                        FirmwareError(
                            f"{p.board}/{p.app} version {version_name} was already released with another image "
                            f"(release {before.sequence_number}): bump the version",
                            file=p.first.file,
                            line=p.first.line,
                            expected=was.mcuboot_hash or was.sha256,
                            actual=computed,
                        )
                    )
                    break
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
    if previous.envelope is not None:  # the signed history that vouches for every previous[] entry
        import cbor2

        history = cbor2.dumps([previous.envelope, *previous.history])
        plan.add(Path(options.out_dir, HISTORY_NAME), history, flag="--out", under=options.out_dir)
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
            firmware={f"{p.board}/{p.app}": (fw.path, fw.sha256) for p, (_, _, fw) in zip(todo, built, strict=True)},
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


class FirmwareInput(NamedTuple):
    """The binary an image was built from: its path under ``--firmware-dir`` and SHA-256
    (computed only for ``--provenance``, whose resolvedDependencies list it)."""

    path: str
    sha256: str | None


def _build_images(
    todo: list[Planned], options: BuildOptions, config: OtaConfig
) -> list[tuple[SignedImage, str, FirmwareInput]]:
    """Read and sign every binary in parallel; results in ``todo`` order, errors all collected."""
    jobs = options.jobs or len(os.sched_getaffinity(0))

    def one(p: Planned) -> tuple[SignedImage, str, FirmwareInput]:
        payload, rel, intel_hex = _read_firmware(p, options.firmware_dir)
        use = p.first
        payload_sha = hashlib.sha256(payload).hexdigest() if options.provenance or p.settings.type == "raw" else None
        source = FirmwareInput(rel, payload_sha)
        if p.settings.type == "raw":
            assert payload_sha is not None
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
            return image, name, source
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
        return image, str(version), source

    with quiet(), ThreadPoolExecutor(max_workers=max(1, min(jobs, len(todo)))) as pool:
        futures = [pool.submit(one, p) for p in todo]
        results: list[tuple[SignedImage, str, FirmwareInput]] = []
        errors: list[HcdfTrustError] = []
        for f in futures:
            try:
                results.append(f.result())
            except HcdfTrustError as exc:
                errors.append(exc)
    if errors:
        raise ErrorGroup(errors)
    return results


def _read_firmware(p: Planned, firmware_dir: str) -> tuple[bytes, str, bool]:
    """The binary for ``p`` (confined to the firmware folder): bytes, path under the folder
    and whether it is Intel HEX."""
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
        return data, rel, rel.lower().endswith(".hex")
    raise FirmwareError(
        f"comp {use.comp!r}: no binary for {p.board}/{p.app} in {firmware_dir}",
        file=use.file,
        line=use.line,
        expected=" or ".join(candidates),
        actual="none of them",
    )


def load_previous(
    source: str | None,
    public_key: Any,
    wanted: list[tuple[str, str]],
    *,
    ca_bundle: str | None = None,
    import_unsigned: bool = False,
) -> PreviousRelease:
    """The previous release (a folder or an https URL): its manifest and history, verified
    with our key, and each wanted image's latest.json as it is (see :func:`carried`).

    ``import_unsigned`` (``--import-unsigned-history``, the same meaning in build and
    verify): a folder without a signed manifest (the fleet's own latest.json files, e.g.
    ``firmware_releases``) is accepted, and its latest.json entries are taken on the
    user's word. Without it such a folder is refused: nothing vouches for its history.

    Raises:
        MalformedReleaseError: no signed manifest (without ``import_unsigned``).
        SignatureError / MalformedReleaseError: the manifest or history does not verify with our key.
        FetchError / InputError: a file that exists cannot be read or fetched.
    """
    from .verify import verify_envelope, verify_history

    if source is None:
        return PreviousRelease(None, {}, "")
    reader = PreviousReader(source, ca_bundle=ca_bundle)
    try:
        release = None
        history: list[tuple[bytes, suit.Release]] = []
        data = reader.read(MANIFEST_NAME, limit=suit.MAX_MANIFEST_BYTES, what="release manifest")
        if data is None and not import_unsigned:
            raise MalformedReleaseError(
                "the previous release has no signed manifest, so nothing vouches for its history: "
                "give --import-unsigned-history to import its latest.json files on your word",
                file=reader.name(MANIFEST_NAME),
                expected=f"{MANIFEST_NAME} signed by this key",
                actual="none",
            )
        if data is not None:
            release = verify_envelope(data, public_key, source=reader.name(MANIFEST_NAME))
            raw = reader.read(HISTORY_NAME, limit=MAX_HISTORY_BYTES, what="release history")
            if raw is not None:
                history = verify_history(
                    raw, public_key, source=reader.name(HISTORY_NAME), below=release.sequence_number
                )
        found = {}
        for board, app in wanted:
            rel = f"{board}/{app}/latest.json"
            text = reader.read(rel, limit=MAX_LATEST_BYTES, what="latest.json")
            if text is not None:
                found[(board, app)] = latest_json.parse(text, source=reader.name(rel))
    finally:
        reader.close()
    signed = (release, *(r for _, r in history)) if release is not None else ()
    return PreviousRelease(
        release,
        found,
        source,
        envelope=data,
        history=tuple(e for e, _ in history),
        signed=signed,
        imported=import_unsigned,
    )


def carried(previous: PreviousRelease, notices: list[Notice]) -> PreviousRelease:
    """``previous`` with only the latest.json entries a release this key signed lists (its
    manifest or history): the rest (left by a killed build, edited on the server) is not
    carried into the new release, with a notice. With ``--import-unsigned-history`` every
    entry is carried, on the user's word."""
    from .verify import vouched

    if previous.imported:
        return previous
    kept: dict[tuple[str, str], latest_json.Latest] = {}
    for (board, app), doc in previous.latest.items():
        if (doc.board, doc.app) != (board, app):  # another device's: latest_json.advance names it
            kept[(board, app)] = doc
            continue
        entries = [e for e in (doc.latest, *doc.previous) if vouched(board, app, e, previous.signed)]
        dropped = [e.version for e in (doc.latest, *doc.previous) if e not in entries]
        if dropped:
            notices.append(
                Notice(
                    "unsigned-history",
                    f"{board}/{app}: {', '.join(dropped)} not carried into the new latest.json: no release this "
                    "key signed lists them (--import-unsigned-history carries them on your word)",
                    file=previous.source,
                )
            )
        if entries:
            kept[(board, app)] = latest_json.Latest(board, app, entries[0], tuple(entries[1:]))
    return dataclasses.replace(previous, latest=kept)


def previous_manifest(source: str, public_key: Any, *, ca_bundle: str | None = None) -> suit.Release:
    """The verified manifest of a previous release (folder or https URL): ``ota pull``'s
    rollback check. A folder without one is refused (see :func:`load_previous`)."""
    given = load_previous(source, public_key, [], ca_bundle=ca_bundle)
    assert given.release is not None  # load_previous refuses a folder without one
    return given.release


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


def check_base_url(url: str, *, allow_http: bool, what: str) -> None:
    """The URL prefix written into the signed manifest and every latest.json: https (http
    with ``--allow-http``, as resolve reads it), a host, no credentials, query or fragment
    (the image path is appended to it: after a query or fragment it would name nothing).

    Raises:
        CredentialsError: ``user:password@`` (it would be published). InputError: the rest.
    """
    from ..errors import InputError
    from ..include.locate import redact, refuse_credentials

    refuse_credentials(url, what=what)
    shown = redact(url)
    try:
        parts = urlsplit(url)
        parts.port  # noqa: B018 -- raises ValueError for a port that is not a number in 0-65535
    except ValueError as exc:
        raise InputError(f"{what} {shown!r} is not a valid URL: {exc}", actual=shown) from None
    scheme = parts.scheme.lower()
    if scheme != "https" and not (scheme == "http" and allow_http):
        hint = " (plain http needs --allow-http)" if scheme == "http" else ""
        raise InputError(f"{what} {shown!r} is not an https:// URL{hint}", expected="https://host/path", actual=shown)
    if not parts.hostname or "\\" in url or any(ord(ch) <= 32 or ord(ch) == 127 for ch in url):
        raise InputError(f"{what} {shown!r} is not a valid URL", expected=f"{scheme}://host/path", actual=shown)
    if parts.query or parts.fragment or "?" in url or "#" in url:
        bare = redact(f"{scheme}://{parts.netloc}{parts.path}")  # the query may hold a token: not shown
        raise InputError(
            f"{what} {bare!r} has a query or fragment (not shown): image paths are appended to it",
            expected=bare,
        )


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
