"""The export index: a verified plan kept beside the key store, so that ``export`` of one
device need not parse and plan a large description again when nothing in it changed.

``generate`` and ``rotate`` plan the whole description after resolving and verifying it;
they then write ``DIR/macsec-export-index.json`` (:data:`INDEX_NAME`, mode 0600) with the
store, through the same :class:`~hcdf_trust.outputs.OutputPlan`. It holds

* a header naming exactly what was verified, and by which code: :data:`INDEX_VERSION` and
  the SHA-256 of every ``.py`` file of the running hcdf_trust (:func:`code_digest`), the
  working folder (messages name files relative to it), the root document as given
  and the SHA-256 of the bytes that were parsed, the lock file and the SHA-256 of its
  bytes, and every file of the tree with the folder it was confined to and its SHA-256;
* one line per keyed association, in plan order: ``[CA_ID, KIND, KEY_REF, POLICY,
  ELEMENTS, MEMBERS, PORT_SPEEDS, IFACES]`` (:data:`ROW_FIELDS`), a member written
  ``[DEVICE,[PORT,...]]``;
* a MAC: HMAC-SHA256 under a key derived from the store's data key, over the file's
  bytes, as the store's own MAC is.

``export`` uses it only when the root document and the lock have the recorded digests
(read the way a resolve reads them, from the paths on the command line), the store opens,
the MAC matches, and every recorded file, opened with the resolver's confinement, still
has its digest: then a resolve would read the same bytes and planning them would give the
same associations, which are taken from the index. Anything else (no index, another
description, another working folder, an upgraded or edited hcdf-trust, a changed or missing
file, an index from another store or edited, a device the index does not list) falls back
to the full resolve and plan, which reports what is wrong as it always did. The index is a
cache: deleting it changes nothing but speed.

Only trees whose every file is local are indexed (nothing from the cache or a mirror), and
not a root document reached through a link stub. Nothing listed in an index is opened
before its MAC has been checked.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..digest import hash_bytes
from ..errors import HcdfTrustError
from ..localfile import absolute, hash_local, open_local, read_bounded, read_input
from .plan import Association, Element, Member, Plan, Policy
from .store import INDEX_NAME, KeyStore, line_encoder

INDEX_FORMAT = "hcdf-trust-macsec-export-index"
INDEX_VERSION = 1  # of the layout below; any change of the code is caught by code_digest
MAX_INDEX_BYTES = 512 << 20
_MAC_LABEL = b"hcdf-trust macsec export index mac"
# Association fields a row holds; tests check this against the dataclass, so a new field
# cannot be silently dropped from exports made through the index.
ROW_FIELDS = ("id", "kind", "key_ref", "policy", "elements", "members", "port_speeds_mbps", "ifaces")
_ENCODE = json.JSONEncoder(sort_keys=True, separators=(",", ":")).encode
_LINE = json.JSONEncoder(separators=(",", ":")).encode


def path_in(folder: str | os.PathLike[str]) -> str:
    return os.path.join(folder, INDEX_NAME)


@functools.cache
def code_digest() -> str:
    """SHA-256 over the path, length and bytes of every ``.py`` file of this hcdf_trust
    package (~2 ms): an index is used only by the very code that planned it, so neither an
    upgrade nor a local edit of the planner can be served a plan it would not make."""
    return tree_digest(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def tree_digest(top: str) -> str:
    """:func:`code_digest` of the package folder ``top``."""
    h = hashlib.sha256()
    for folder, subfolders, files in os.walk(top):
        subfolders[:] = sorted(d for d in subfolders if d != "__pycache__")
        for name in sorted(f for f in files if f.endswith(".py")):
            path = os.path.join(folder, name)
            with open(path, "rb") as f:
                data = f.read()
            h.update(f"{os.path.relpath(path, top)}\0{len(data)}\0".encode())
            h.update(data)
    return h.hexdigest()


def _row(ca: Association) -> list[Any]:
    p = ca.policy
    policy = None
    if p is not None:
        policy = [
            p.policy,
            p.cipher,
            p.key_agreement,
            p.confidentiality_offset,
            p.rekey_interval_sec,
            p.key_store_type,
            p.key_store_ref,
        ]
    return [
        ca.id,
        ca.kind,
        ca.key_ref,
        policy,
        [[e.kind, e.network, e.name, e.file, e.line, e.scope] for e in ca.elements],
        [[m.device, m.ports] for m in ca.members.values()],
        ca.port_speeds_mbps,
        ca.ifaces,
    ]


def _association(row: list[Any]) -> Association:
    ca_id, kind, key_ref, policy, elements, members, speeds, ifaces = row
    return Association(
        id=ca_id,
        kind=kind,
        key_ref=key_ref,
        policy=None if policy is None else Policy(*policy),
        elements=[Element(*e) for e in elements],
        members={device: Member(device, ports) for device, ports in members},
        port_speeds_mbps=speeds,
        ifaces=ifaces,
    )


def render(doc: str, p: Plan, store: KeyStore) -> bytes | None:
    """The index of plan ``p`` (of ``doc`` as given on the command line), or None when its
    tree cannot be indexed (a file from the cache or a mirror, a link stub, no lock)."""
    res = p.resolution
    given = absolute(doc)
    if res is None or res.locked is None or not res.locked.sha256 or res.root_location.path != given:
        return None
    try:
        cwd = os.getcwd()  # messages name files relative to it (it may have been removed)
    except OSError:
        return None
    files = []
    for art in res.artifacts.values():
        loc = art.location
        if art.source != "file" or loc.path is None or art.sha256 is None:
            return None
        files.append([art.kind._value_, loc.path, str(loc.root or os.path.dirname(loc.path)), art.sha256])
    head = {
        "format": INDEX_FORMAT,
        "version": INDEX_VERSION,
        "code": code_digest(),
        "store_id": store.store_id,
        "cwd": cwd,
        "document": given,
        "plan_document": p.document,
        "robot": p.robot,
        "document_sha256": hash_bytes(res.root.data).sha256,
        "lock": str(res.lock_path),
        "lock_sha256": res.locked.sha256,
        "files": files,
    }
    encode = line_encoder(sort_keys=False)  # rows are lists: their order is the layout
    lines = [_ENCODE(head), *(encode(_row(ca)) for ca in p.keyed())]
    return store.seal(("\n".join(lines) + "\n").encode(), label=_MAC_LABEL)


@dataclass
class Candidate:
    """An index whose header matches the description on the command line, and the device's
    associations as it lists them: not trusted before :meth:`plan` has checked them."""

    raw: bytes
    head: dict[str, Any]
    associations: dict[str, Association]

    def plan(self, store: KeyStore) -> Plan | None:
        """The device's plan from the index, once its MAC matches this store and every file
        it lists still has its digest; else None (plan from the description)."""
        if self.head.get("store_id") != store.store_id or not store.sealed(
            self.raw, self.head.get("mac"), label=_MAC_LABEL
        ):
            return None
        try:
            for kind, path, root, sha256 in self.head["files"]:
                if _digest(kind, path, root) != sha256:
                    return None
            document, robot = self.head["plan_document"], self.head["robot"]
        except (ValueError, TypeError, KeyError):  # sealed by this store, yet not this layout
            return None
        if not isinstance(robot, str):
            return None
        return Plan(document=document, robot=robot, associations=self.associations, resolution=None)

    def protect(self, out: Any) -> None:
        """Protect what a resolve of this tree would (see :func:`hcdf_trust.outputs.protect_inputs`)."""
        from ..outputs import artifact_role
        from ..store import default_cache_dir

        out.protect(self.head["document"], what="the root document")
        for kind, path, _root, _sha in self.head["files"]:
            out.protect(path, what=artifact_role(kind))
        out.protect_tree(default_cache_dir(), what="the cache")
        out.protect(self.head["lock"], what="the lock file")


def _digest(kind: str, path: str, root: str) -> str | None:
    """A file's SHA-256 read as the resolver reads it (an include whole and bounded, any other
    file streamed), confined to ``root``; None when it cannot be read so."""
    from ..xml import MAX_DOCUMENT_BYTES

    try:
        if kind == "include":
            with open_local(path, root) as fd:
                return hash_bytes(read_bounded(fd, MAX_DOCUMENT_BYTES, source=path)).sha256
        return hash_local(path, root).sha256
    except HcdfTrustError:
        return None


def _device_associations(raw: bytes, device: str) -> dict[str, Association] | None:
    """The keyed associations the index lists ``device`` as a member of, in plan order; None
    if none. A member is written ``[DEVICE,[`` and a JSON string holds no raw newline, so
    every line that has ``device`` as a member holds that text; a line that holds it
    elsewhere is dropped once parsed."""
    needle = b"[" + _LINE(device).encode() + b",["
    cas: dict[str, Association] = {}
    at = raw.find(needle, raw.index(b"\n"))
    while at >= 0:
        start = raw.rindex(b"\n", 0, at) + 1
        end = raw.index(b"\n", at)
        ca = _association(json.loads(raw[start:end]))
        if device in ca.members:
            cas[ca.id] = ca
        at = raw.find(needle, end)
    return cas or None


def candidate(doc: str, store_dir: str, device: str) -> Candidate | None:
    """The store folder's index if it was written for ``doc`` as it is now (root document
    and lock, read as a resolve reads them), by this very code, from this working folder,
    and lists ``device``; parsed while the store opens, checked by :meth:`Candidate.plan`.

    Reads nothing that the index itself names: that waits for the MAC."""
    from ..include import lockfile
    from ..include.resolver import link_stub_target, read_root

    try:
        raw = read_input(path_in(store_dir), limit=MAX_INDEX_BYTES, what="export index")
        head = json.loads(raw[: raw.index(b"\n")])
        if (
            not isinstance(head, dict)
            or head.get("format") != INDEX_FORMAT
            or head.get("version") != INDEX_VERSION
            or head.get("code") != code_digest()
            or head.get("cwd") != os.getcwd()
            or head.get("document") != absolute(doc)
        ):
            return None
        given = Path(head["document"])
        data = read_root(given)
        if link_stub_target(given, data) is not None or hash_bytes(data).sha256 != head.get("document_sha256"):
            return None
        lock = lockfile.default_path(given)
        if head.get("lock") != str(lock) or lockfile.load(lock).sha256 != head.get("lock_sha256"):
            return None
        cas = _device_associations(raw, device)
    except Exception:  # noqa: BLE001 -- any index this code cannot use is planned around, not reported
        return None
    return None if cas is None else Candidate(raw, head, cas)
