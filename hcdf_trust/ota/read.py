"""Reading a release folder: the disk layer of ``ota verify`` (and of ``ota pull``'s staged release).

Apart from :mod:`.release` (which builds releases: the resolver, the HCDF editor, lxml), so a
verb that only reads a release imports only what reading needs.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Mapping
from typing import TYPE_CHECKING, Any

from ..errors import NotFoundError
from ..localfile import open_checked, read_bounded, read_input, stream_bounded
from . import latest as latest_json
from . import suit

if TYPE_CHECKING:
    from .mcuboot import ImageStream

MAX_FIRMWARE_BYTES = 256 << 20
MAX_LATEST_BYTES = latest_json.MAX_BYTES
MANIFEST_NAME = "release.suit"
MANIFEST_JSON_NAME = "release.suit.json"
HISTORY_NAME = "release.history"  # the earlier signed envelopes, newest first (verify.verify_history)
MAX_HISTORY_BYTES = 64 << 20


def read_release(
    folder: str,
    public_key: Any,
    *,
    previous: str | None = None,
    ca_bundle: str | None = None,
    import_unsigned: bool = False,
) -> tuple[suit.Release, Any]:
    """The disk layer of ``ota verify``: the verified manifest of ``folder``, its verified
    history, the bytes of every file they list, every ``*/*/latest.json`` found there, and
    every file or folder nothing accounts for. ``previous`` (``--previous``) adds its signed
    releases to the history (and, imported on the user's word, its latest.json entries).

    An image whose size is not the signed one is not read (``ReleaseFiles.sizes``).

    Returns:
        The verified :class:`~hcdf_trust.ota.suit.Release` and the folder's
        :class:`~hcdf_trust.ota.verify.ReleaseFiles`, for :func:`~hcdf_trust.ota.verify.check_release`.

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

    Raises:
        NotFoundError / InputError: no manifest, or a file that cannot be read.
        MalformedReleaseError / SignatureError: see :func:`.verify.verify_envelope`.
    """
    from .verify import ReleaseFiles, image_path, verify_envelope, verify_history

    manifest_path = os.path.join(folder, MANIFEST_NAME)
    data = read_input(manifest_path, limit=suit.MAX_MANIFEST_BYTES, what="release manifest")
    release = verify_envelope(data, public_key, source=manifest_path)
    history: list[suit.Release] = []
    history_path = os.path.join(folder, HISTORY_NAME)
    if os.path.lexists(history_path):
        raw = _read_in(history_path, folder, HISTORY_NAME, MAX_HISTORY_BYTES, "release history")
        history = [r for _, r in verify_history(raw, public_key, source=HISTORY_NAME, below=release.sequence_number)]
    unsigned: dict[tuple[str, str], tuple[latest_json.Entry, ...]] = {}
    before = None
    if previous is not None:
        # its latest.json files count only as history imported on the user's word
        wanted = [(c.board, c.app) for c in release.components if c.type == "mcuboot" and import_unsigned]
        from .release import load_previous  # (the build module: only for --previous)

        given = load_previous(previous, public_key, wanted, ca_bundle=ca_bundle, import_unsigned=import_unsigned)
        before = given.release
        history += [r for r in given.signed if r not in history]  # it may hold release.history's too
        if given.imported:
            unsigned = {k: (doc.latest, *doc.previous) for k, doc in given.latest.items()}
    images = FolderImages(folder)
    sizes: dict[str, int] = {}
    entries = _walk(folder)
    linked = [rel for rel, kind in entries if kind == "link"]  # refused; nothing is read through them

    def through_link(rel: str) -> bool:
        return any(rel.startswith(link + "/") for link in linked)

    signed_sizes = {c.size for c in release.components}
    for c in release.components:
        rel = image_path(c)
        images.add(rel, not through_link(rel) and _image_readable(folder, rel, c.size, sizes, signed_sizes))
    history_images = FolderImages(folder)
    for r in history:
        for c in r.components:
            rel = image_path(c)
            if rel not in images and rel not in history_images and os.path.lexists(os.path.join(folder, rel)):
                if not through_link(rel):
                    history_images.add(rel, _image_readable(folder, rel, c.size, sizes, set()))
    from ..provenance import FILE_NAME as PROVENANCE_NAME  # checked by verify --provenance

    accounted = {MANIFEST_NAME, MANIFEST_JSON_NAME, HISTORY_NAME, PROVENANCE_NAME, *images, *history_images}
    accounted.update(f"{c.board}/{c.app}/latest.json" for c in release.components if c.type == "mcuboot")
    # images of history imported on the user's word (--import-unsigned-history): theirs too, unchecked
    accounted.update(f"{b}/{a}/{e.version}.bin" for (b, a), entries in unsigned.items() for e in entries)
    found: dict[str, bytes] = {}
    unaccounted: list[str] = []
    for rel, kind in entries:
        if kind == "link":
            continue
        if rel.count("/") == 2 and rel.endswith("/latest.json") and kind == "file":
            found[rel] = _read_in(os.path.join(folder, rel), folder, rel, MAX_LATEST_BYTES, "latest.json")
        elif rel not in accounted:
            unaccounted.append(rel)
    rendering = None
    if os.path.lexists(os.path.join(folder, MANIFEST_JSON_NAME)):
        rendering = _read_in(
            os.path.join(folder, MANIFEST_JSON_NAME), folder, MANIFEST_JSON_NAME, suit.MAX_MANIFEST_BYTES, "rendering"
        )
    return release, ReleaseFiles(
        manifest=data,
        manifest_source=manifest_path,
        images=images,
        latest=found,
        rendering=rendering,
        sizes=sizes,
        history=tuple(history),
        history_images=history_images,
        unsigned=unsigned,
        unaccounted=tuple(unaccounted),
        linked=tuple(linked),
        previous=before,
    )


def _read_in(path: str, folder: str, rel: str, limit: int, what: str) -> bytes:
    fd, _ = open_checked(path, folder, file=rel)
    try:
        return read_bounded(fd, limit, source=rel, what=what)
    finally:
        os.close(fd)


def _image_readable(folder: str, rel: str, size: int, sizes: dict[str, int], signed: set[int]) -> bool:
    """Is the image at ``rel`` to be read (it exists, and has the signed ``size``)? A size other
    than the signed ``size`` goes into ``sizes``, and the file is read only if its size is
    another signed image's (to name a mix-and-match): a sparse 2 GB file in place of an image
    is what it is, not what was signed (exit 1), never "over a limit"."""
    try:
        fd, st = open_checked(os.path.join(folder, rel), folder, file=rel)
    except NotFoundError:
        return False
    os.close(fd)
    if st.st_size != size:
        sizes[rel] = st.st_size
        return st.st_size in signed
    return True


class FolderImages(Mapping[str, "bytes | None"]):
    """The images of a release folder, each read (bounded, confined) only when it is checked,
    and not kept: ``ota verify`` holds one image at a time, whatever the release's size.
    A key mapped to None was missing or not to be read (see :func:`_image_readable`)."""

    def __init__(self, folder: str) -> None:
        self.folder = folder
        self._readable: dict[str, bool] = {}

    def add(self, rel: str, readable: bool) -> None:
        self._readable[rel] = readable

    def _open(self, rel: str) -> int | None:
        """The image's descriptor, confined to the folder; None: missing or not to be read."""
        if not self._readable[rel]:
            return None
        try:
            fd, _ = open_checked(os.path.join(self.folder, rel), self.folder, file=rel)
        except NotFoundError:  # removed since it was listed: missing
            return None
        return fd

    def __getitem__(self, rel: str) -> bytes | None:
        fd = self._open(rel)
        if fd is None:
            return None
        try:
            return read_bounded(fd, MAX_FIRMWARE_BYTES, source=rel, what="image")
        finally:
            os.close(fd)

    def scan(self, rel: str) -> ImageStream | None:
        """The image at ``rel`` streamed once from disk through an :class:`ImageStream` (hashed
        and ready to verify, never whole in memory); None as for a lookup."""
        from .mcuboot import ImageStream

        fd = self._open(rel)
        if fd is None:
            return None
        try:
            stream = ImageStream()
            for chunk in stream_bounded(fd, MAX_FIRMWARE_BYTES, source=rel, what="image"):
                stream.update(chunk)
            return stream
        finally:
            os.close(fd)

    def __iter__(self) -> Iterator[str]:
        return iter(self._readable)

    def __len__(self) -> int:
        return len(self._readable)


def _walk(folder: str) -> list[tuple[str, str]]:
    """Every entry under ``folder`` (relative path, "file" | "link" | "other"), not entering
    symlinks: a symlinked folder is reported, never skipped or followed. Sorted."""
    out: list[tuple[str, str]] = []
    pending = [""]
    while pending:
        prefix = pending.pop()
        with os.scandir(os.path.join(folder, prefix) if prefix else folder) as it:
            for entry in it:
                rel = f"{prefix}{entry.name}"
                if entry.is_symlink():
                    out.append((rel, "link" if entry.is_dir() else "file"))
                elif entry.is_dir(follow_symlinks=False):
                    pending.append(rel + "/")
                else:
                    out.append((rel, "file" if entry.is_file(follow_symlinks=False) else "other"))
    return sorted(out)
