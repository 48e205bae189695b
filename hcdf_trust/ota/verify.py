"""``ota verify``: decide, in pure functions over bytes, whether a release is what was signed.

:func:`verify_envelope` takes the manifest apart and checks its signature;
:func:`check_release` then checks every image and ``latest.json`` against it and,
given the previous release, that nothing went backwards. The steps, as in
python-tuf's trusted metadata set, run in order and name the device and field of
every violation:

1. The envelope is one well-formed, deterministically encoded SUIT_Envelope of the
   pinned draft (:func:`.suit.parse_envelope`: no trailing bytes, no duplicate map
   key, nothing in the COSE unprotected header; else exit 3).
2. The COSE ``alg`` is one bound to the verifying key's type, and the ``kid`` is
   that key's (a manifest signed by another key, or relabelled, is refused).
3. The authentication wrapper's digest is over this manifest, and the COSE_Sign1
   verifies over that digest with the key.
4. Each image: present, the size and SHA-256 the manifest lists (a file that is
   another component's image is named a mix-and-match), it verifies as an MCUboot
   image *with the key* (:mod:`.mcuboot`, hashing each byte once), its MCUboot hash,
   header version and security counter are the listed ones.
5. Each ``latest.json``: for a component of the manifest, and its version, hash,
   size, URL, date and changelog are the signed ones (the last two from the release
   record); ``release.suit.json`` is byte for byte the rendering of the envelope.
6. Against the previous release: a greater sequence number, and no security
   counter lower than before.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from ..errors import HcdfTrustError
from . import latest as latest_json
from . import suit
from .errors import MalformedReleaseError, ReleaseIntegrityError, RollbackError, SignatureError
from .images import IMAGE_MAGIC
from .mcuboot import ImageStream
from .signer import ALG_NAMES, COSE_ALGS, CWT_ALG, key_id

# The public API (docs/api.md); everything else here is internal.
__all__ = ["ReleaseFiles", "check_release"]


@dataclass(frozen=True)
class ReleaseFiles:
    """The bytes of one release folder, as :func:`~hcdf_trust.ota.release.read_release`
    reads them (bounded), for :func:`check_release`.

    Example:
        >>> from hcdf_trust.ota.verify import ReleaseFiles
        >>> ReleaseFiles(manifest=b"", manifest_source="release/release.suit").unaccounted
        ()
    """

    manifest: bytes
    manifest_source: str
    # relative path -> bytes (None: missing), read when looked up (ota.release.FolderImages)
    images: Mapping[str, bytes | None] = field(default_factory=dict)
    latest: dict[str, bytes] = field(default_factory=dict)  # "board/app/latest.json" -> bytes
    rendering: bytes | None = None  # release.suit.json, the unsigned rendering for people
    # Images whose size is not the signed one, left unread: relative path -> size on disk.
    sizes: dict[str, int] = field(default_factory=dict)
    # The earlier releases this key signed (release.history, then --previous), newest first,
    # and the bytes of their images still in the folder (None: not read, its size is wrong).
    history: tuple[suit.Release, ...] = ()
    history_images: Mapping[str, bytes | None] = field(default_factory=dict)
    # latest.json entries taken on the user's word (--import-unsigned-history): (board, app) -> entries
    unsigned: dict[tuple[str, str], tuple[latest_json.Entry, ...]] = field(default_factory=dict)
    unaccounted: tuple[str, ...] = ()  # files and folders that no signed release accounts for
    linked: tuple[str, ...] = ()  # folders that are symlinks
    previous: suit.Release | None = None  # --previous's signed release (rollback: step 6)
    # Images the caller already streamed through an ImageStream, exactly these files' bytes
    # (ota pull: each blob as it arrived; what lands in --out is hashed against the same
    # digest): not read again
    scanned: Mapping[str, ImageStream] = field(default_factory=dict)


def image_path(c: suit.Component) -> str:
    """Where a component's file lies in its release folder."""
    return f"{c.board}/{c.app}/{c.version}.bin"


def verify_envelope(data: bytes, public_key: Any, *, source: str) -> suit.Release:
    """Steps 1–3: the release an envelope signed with ``public_key`` describes.

    Raises:
        MalformedReleaseError: step 1. SignatureError / ReleaseIntegrityError: steps 2–3.
    """
    env = open_envelope(data, public_key, source=source)
    return suit.parse_release(env, source=source)


def open_envelope(data: bytes, public_key: Any, *, source: str, require_kid: bool = True) -> suit.Envelope:
    """Steps 1–3 for any draft-34 envelope: taken apart strictly, then its signature checked.

    ``require_kid=False`` accepts a protected header without a ``kid`` (the working
    group's examples have none); a ``kid`` that is present must still be the key's.

    Raises:
        MalformedReleaseError: step 1. SignatureError / ReleaseIntegrityError: steps 2–3.
    """
    import cbor2
    from cwt import COSE, COSEKey
    from cwt.exceptions import CWTError

    from .keys import key_type

    env = suit.parse_envelope(data, source=source)
    kind = key_type(public_key)
    alg: Any = env.protected_map.get(suit.COSE_ALG)
    allowed = COSE_ALGS[kind][1]
    if alg not in allowed:
        raise SignatureError(
            f"manifest COSE alg {ALG_NAMES.get(alg, alg)!r} is not bound to the {kind} key",
            file=source,
            expected=" or ".join(ALG_NAMES[a] for a in sorted(allowed)),
            actual=str(ALG_NAMES.get(alg, alg)),
        )
    kid = key_id(public_key)
    got = env.protected_map.get(suit.COSE_KID)
    if got != kid and (require_kid or got is not None):
        raise SignatureError(
            "manifest was signed by another key (COSE kid)",
            file=source,
            expected=kid.hex(),
            actual=got.hex() if isinstance(got, bytes) else repr(got),
        )
    want = suit.manifest_digest(env.manifest)
    if env.digest != want:
        alg, got_hash = cbor2.loads(env.digest)  # a SUIT_Digest: parse_envelope checked its shape
        raise ReleaseIntegrityError(
            "authentication wrapper digest is not the manifest's",
            file=source,
            expected=f"SHA-256 {cbor2.loads(want)[1].hex()}",
            actual=f"{'SHA-256' if alg == suit.SHA256 else f'algorithm {alg}'} {got_hash.hex()}",
        )
    cose_key = COSEKey.from_pem(public_key.get_public_pem(), alg=CWT_ALG[kind], kid=kid)
    try:
        COSE.new().decode(env.cose_sign1, cose_key, detached_payload=env.digest)
    except (CWTError, ValueError) as exc:
        raise SignatureError(f"manifest signature does not verify with the key: {exc}", file=source) from None
    return env


def check_release(
    release: suit.Release, files: ReleaseFiles, public_key: Any, *, previous: suit.Release | None = None
) -> list[HcdfTrustError]:
    """Steps 4–6 of ``ota verify``: every violation, each naming its device (board/app) and
    field, as a list (empty: the release is what was signed). Pure: reads nothing.

    Args:
        release, files: from :func:`~hcdf_trust.ota.release.read_release`.
        public_key: from :func:`~hcdf_trust.ota.keys.load_public`.
        previous: a previous release to check rollback against (else ``files.previous``).

    Example:

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
    """
    errors: list[HcdfTrustError] = []
    for rel in files.linked:
        errors.append(
            ReleaseIntegrityError(
                f"{rel} is a symlink: a release folder holds its files itself (a link can hide another "
                "latest.json from this check)",
                file=rel,
            )
        )
    for rel in files.unaccounted:
        errors.append(
            ReleaseIntegrityError(
                f"{rel} is in the release folder but no signed release accounts for it",
                file=rel,
                expected="release.suit, release.suit.json, release.history and the files the manifests list",
            )
        )
    by_sha = {c.sha256: c for c in release.components}
    for c in release.components:
        errors += _check_image(c, files, public_key, by_sha)
    errors += _check_history_images(release, files)
    listed = {f"{c.board}/{c.app}/latest.json": c for c in release.components if c.type == "mcuboot"}
    for rel, data in sorted(files.latest.items()):
        comp = listed.get(rel)
        if comp is None:
            errors.append(
                ReleaseIntegrityError(f"{rel}: no such component in the signed manifest (mix-and-match)", file=rel)
            )
            continue
        errors += _check_latest(comp, data, rel, files, date=release.date)
    for rel in sorted(set(listed) - set(files.latest)):
        errors.append(ReleaseIntegrityError(f"{listed[rel].name}: latest.json is missing", file=rel))
    if files.rendering is not None:
        errors += _check_rendering(release, files, public_key)
    for before in files.history:  # a version names one content, in every release
        for c in release.components:
            was = before.component(c.board, c.app)
            if was is not None and was.version == c.version and content_id(was) != content_id(c):
                errors.append(
                    RollbackError(
                        f"{c.name}: version {c.version} was already released with another image "
                        f"(release {before.sequence_number})",
                        file=files.manifest_source,
                        expected=content_id(was),
                        actual=content_id(c),
                    )
                )
    previous = previous or files.previous
    if previous is not None:
        errors += check_rollback(release, previous, source=files.manifest_source)
    return errors


def content_id(c: suit.Component) -> str:
    """What identifies an image's content across rebuilds: the MCUboot image hash (a re-signed
    file differs, ECDSA signatures being random), the file's SHA-256 for a raw image."""
    return c.mcuboot_hash or c.sha256


def vouched(board: str, app: str, entry: latest_json.Entry, signed: tuple[suit.Release, ...]) -> bool:
    """Is ``entry`` the ``board/app`` image of one of the ``signed`` releases (version,
    ``mcuboot_hash``, size, URL, and the date and changelog its release record signed)?"""
    for r in signed:
        c = r.component(board, app)
        if c is not None and (c.version, c.mcuboot_hash, c.size, c.uri, r.date, c.changelog) == (
            entry.version,
            entry.mcuboot_hash,
            entry.size,
            entry.url,
            entry.date,
            entry.changelog,
        ):
            return True
    return False


def check_history(
    doc: latest_json.Latest,
    signed: tuple[suit.Release, ...],
    *,
    rel: str,
    entries: tuple[tuple[str, latest_json.Entry], ...],
    unsigned: tuple[latest_json.Entry, ...] = (),
) -> list[HcdfTrustError]:
    """Each of ``entries`` (``(where, entry)`` of ``doc``) is a release this key signed, or
    one of the ``unsigned`` entries the user chose to import. Pure."""
    errors: list[HcdfTrustError] = []
    for where, entry in entries:
        if vouched(doc.board, doc.app, entry, signed) or entry in unsigned:
            continue
        errors.append(
            ReleaseIntegrityError(
                f"{doc.board}/{doc.app}: latest.json {where} ({entry.version}) is not a release this key signed",
                file=rel,
                expected="an image of an earlier signed release (release.history or --previous); history "
                "imported from an unsigned folder needs --previous DIR --import-unsigned-history",
                actual=f"{entry.version} {entry.mcuboot_hash} {entry.size} {entry.url}",
            )
        )
    return errors


def verify_history(data: bytes, public_key: Any, *, source: str, below: int) -> list[tuple[bytes, suit.Release]]:
    """``release.history``: a CBOR array of the earlier signed envelopes, newest first, each
    verified with ``public_key`` (steps 1–3) and with a sequence number below the one before.

    Raises:
        MalformedReleaseError: not such an array. SignatureError etc.: an envelope that does not verify.
        RollbackError: the sequence numbers do not go down.
    """
    import io

    import cbor2

    stream = io.BytesIO(data)
    try:
        items = cbor2.CBORDecoder(stream).decode()
    except (cbor2.CBORDecodeError, ValueError, RecursionError, EOFError) as exc:
        raise MalformedReleaseError(f"release history is not CBOR: {exc}", file=source) from None
    if stream.tell() != len(data) or not isinstance(items, list) or not all(isinstance(i, bytes) for i in items):
        raise MalformedReleaseError("release history is not one CBOR array of envelopes", file=source)
    out: list[tuple[bytes, suit.Release]] = []
    for i, envelope in enumerate(items):
        where = f"{source}[{i}]"
        release = verify_envelope(envelope, public_key, source=where)
        if release.sequence_number >= below:
            raise RollbackError(
                "release history is not in decreasing sequence-number order",
                file=where,
                expected=f"< {below}",
                actual=str(release.sequence_number),
            )
        below = release.sequence_number
        out.append((envelope, release))
    return out


def _check_history_images(release: suit.Release, files: ReleaseFiles) -> list[HcdfTrustError]:
    """An earlier release's image still in the folder (previous[] URLs name it) is the one signed."""
    errors: list[HcdfTrustError] = []
    current = {image_path(c) for c in release.components}
    for r in files.history:
        for c in r.components:
            rel = image_path(c)
            if rel in current or rel not in files.history_images:
                continue
            current.add(rel)
            stream = _scan(files.history_images, rel)
            if stream is None:  # not read: its size is not the signed one, or it cannot be opened (a dangling link)
                size = files.sizes.get(rel)
                actual = "(missing)" if size is None else f"(not read) ({size} bytes)"
            else:
                sha = stream.hexdigest()
                if (sha, stream.size) == (c.sha256, c.size):
                    continue
                actual = f"{sha} ({stream.size} bytes)"
            errors.append(
                ReleaseIntegrityError(
                    f"{c.name}: image {rel} of release {r.sequence_number} is not the one that release signed",
                    file=rel,
                    expected=f"{c.sha256} ({c.size} bytes)",
                    actual=actual,
                )
            )
    return errors


def _check_rendering(release: suit.Release, files: ReleaseFiles, public_key: Any) -> list[HcdfTrustError]:
    """The unsigned ``release.suit.json`` is, byte for byte, what ``ota build`` renders from
    the signed envelope (people read it): anything else is refused, not merely compared."""
    name = "release.suit.json"
    assert files.rendering is not None
    alg: Any = suit.parse_envelope(files.manifest, source=files.manifest_source).protected_map.get(suit.COSE_ALG)
    want = suit.render_json(release, alg=ALG_NAMES.get(alg, str(alg)), kid=key_id(public_key).hex())
    if files.rendering == want:
        return []
    got_lines = files.rendering.decode("utf-8", "replace").splitlines()
    want_lines = want.decode().splitlines()
    line = next(
        (i for i, (a, b) in enumerate(zip(got_lines, want_lines, strict=False)) if a != b),
        min(len(got_lines), len(want_lines)),
    )
    return [
        ReleaseIntegrityError(
            f"{name} is not the rendering of the signed manifest (delete it, or rebuild the release)",
            file=name,
            line=line + 1,
            expected=want_lines[line].strip()[:200] if line < len(want_lines) else "end of file",
            actual=got_lines[line].strip()[:200] if line < len(got_lines) else "end of file",
        )
    ]


def check_rollback(release: suit.Release, previous: suit.Release, *, source: str) -> list[HcdfTrustError]:
    """Step 6. Pure."""
    errors: list[HcdfTrustError] = []
    if release.sequence_number <= previous.sequence_number:
        errors.append(
            RollbackError(
                "manifest sequence-number is not greater than the previous release's",
                file=source,
                expected=f"> {previous.sequence_number}",
                actual=str(release.sequence_number),
            )
        )
    for c in release.components:
        before = previous.component(c.board, c.app)
        if before is None or before.security_counter is None:
            continue
        if c.security_counter is None or c.security_counter < before.security_counter:
            errors.append(
                RollbackError(
                    f"{c.name}: security_counter went down since the previous release",
                    file=source,
                    expected=f"≥ {before.security_counter}",
                    actual=str(c.security_counter),
                )
            )
    return errors


def _check_image(
    c: suit.Component, files: ReleaseFiles, public_key: Any, by_sha: dict[str, suit.Component]
) -> list[HcdfTrustError]:
    rel = image_path(c)
    stream = files.scanned[rel] if rel in files.scanned else _scan(files.images, rel)
    if rel in files.sizes and stream is None:  # the size, checked before reading: a 2 GB file is not what was signed
        return [
            ReleaseIntegrityError(
                f"{c.name}: size differs from the signed manifest (the file was not read)",
                file=rel,
                expected=str(c.size),
                actual=str(files.sizes[rel]),
            )
        ]
    if stream is None:
        return [ReleaseIntegrityError(f"{c.name}: image {rel} is missing", file=rel)]
    if not c.uri.endswith(rel):
        return [ReleaseIntegrityError(f"{c.name}: uri does not name {rel}", file=rel, expected=rel, actual=c.uri)]
    errors: list[HcdfTrustError] = []
    sha = stream.hexdigest()
    if sha != c.sha256:
        other = by_sha.get(sha)
        why = f" (mix-and-match: it is the image of {other.name})" if other is not None and other is not c else ""
        errors.append(
            ReleaseIntegrityError(
                f"{c.name}: file_sha256 differs from the signed manifest{why}", file=rel, expected=c.sha256, actual=sha
            )
        )
    if stream.size != c.size:
        errors.append(
            ReleaseIntegrityError(
                f"{c.name}: size differs from the signed manifest",
                file=rel,
                expected=str(c.size),
                actual=str(stream.size),
            )
        )
    if c.type != "mcuboot" or errors:
        return errors
    verdict = stream.verify(public_key)
    if verdict.info is None:  # not even its header and protected TLVs could be read
        if verdict.result == "INVALID_MAGIC":
            return [
                MalformedReleaseError(
                    f"{c.name}: not an MCUboot image (header magic)",
                    file=rel,
                    expected=f"{IMAGE_MAGIC:#010x}",
                    actual=f"{stream.magic:#010x}",
                )
            ]
        return [MalformedReleaseError(f"{c.name}: not an MCUboot image ({verdict.result})", file=rel)]
    info, digest = verdict.info, verdict.image_hash
    if not verdict.ok:
        errors.append(
            SignatureError(f"{c.name}: MCUboot image does not verify with the key ({verdict.result})", file=rel)
        )
        return errors
    if digest != c.mcuboot_hash:
        errors.append(
            ReleaseIntegrityError(
                f"{c.name}: mcuboot_hash differs from the signed manifest",
                file=rel,
                expected=c.mcuboot_hash,
                actual=digest,
            )
        )
    if str(info.version) != c.version:
        errors.append(
            ReleaseIntegrityError(
                f"{c.name}: image header version differs from the signed manifest",
                file=rel,
                expected=c.version,
                actual=str(info.version),
            )
        )
    if info.security_counter != c.security_counter:
        errors.append(
            ReleaseIntegrityError(
                f"{c.name}: image security_counter differs from the signed manifest",
                file=rel,
                expected=str(c.security_counter),
                actual=str(info.security_counter),
            )
        )
    return errors


def _scan(images: Mapping[str, bytes | None], rel: str) -> ImageStream | None:
    """The file at ``rel`` through an :class:`ImageStream` (None: missing or not to be read):
    streamed from disk when ``images`` can (:class:`~hcdf_trust.ota.read.FolderImages`: never
    whole in memory), else its bytes fed at once."""
    scan = getattr(images, "scan", None)
    if scan is not None:
        stream: ImageStream | None = scan(rel)
        return stream
    data = images.get(rel)
    if data is None:
        return None
    stream = ImageStream()
    stream.update(data)
    return stream


def _check_latest(c: suit.Component, data: bytes, rel: str, files: ReleaseFiles, *, date: str) -> list[HcdfTrustError]:
    try:
        doc = latest_json.parse(data, source=rel)
    except MalformedReleaseError as exc:
        return [exc]
    errors = check_history(
        doc,
        files.history,
        rel=rel,
        entries=tuple((f"previous[{i}]", e) for i, e in enumerate(doc.previous)),
        unsigned=files.unsigned.get((c.board, c.app), ()),
    )
    checks = (
        ("board", doc.board, c.board),
        ("app", doc.app, c.app),
        ("latest.version", doc.latest.version, c.version),
        ("latest.mcuboot_hash", doc.latest.mcuboot_hash, c.mcuboot_hash),
        ("latest.size", str(doc.latest.size), str(c.size)),
        ("latest.url", doc.latest.url, c.uri),
        ("latest.date", doc.latest.date, date),
        ("latest.changelog", doc.latest.changelog, c.changelog),
    )
    for name, actual, expected in checks:
        if actual != expected:
            errors.append(
                ReleaseIntegrityError(
                    f"{c.name}: latest.json {name} differs from the signed manifest",
                    file=rel,
                    expected=_text(expected),
                    actual=_text(actual),
                )
            )
    return errors


def _text(value: str | None) -> str:
    """A field's value for a message: an absent field is named, not printed as ``None``."""
    return "(absent)" if value is None else value
