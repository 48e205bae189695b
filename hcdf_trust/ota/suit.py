"""The signed release manifest: a SUIT envelope over every image of one release.

Format: the CBOR serialisation of **draft-ietf-suit-manifest-34** (:data:`SUIT_DRAFT`;
the RFC 9124 information model; label numbers moved between drafts, these are -34's):

```
107({                                          / SUIT_Envelope_Tagged /
  2: << [ << [-16, h'sha256'] >>,              / authentication-wrapper: SUIT_Digest of the /
          << 18([<<{1: alg, 4: kid}>>, {}, nil, sig]) >> ] >>,   / bstr-wrapped manifest; COSE_Sign1, detached /
  3: << {                                      / manifest /
    1: 1, 2: sequence-number,
    3: << { 2: [ [h'board', h'app'], ... ],    / common: components /
            4: << [ 12, i, 20, {1: vendor-id, 2: class-id, 3: << [-16, file-sha256] >>, 14: size,
                                 -257: << [-16, mcuboot-image-hash] >>, -258: security-counter,
                                 -259: "version", -260: "mcuboot"|"raw", -261: ["comp", ...]},
                    1, 15, 2, 15, ... ] >> } >>,
    7: << [12, i, 3, 15, ...] >>,              / validate: image-match /
    20: << [12, i, 20, {21: "uri"}, 21, 2, 3, 15, ...] >>,   / install: fetch, image-match /
    -257: << [-16, lock-sha256] >>,            / hcdf-trust: the resolved lock file /
    -258: "root document", -259: << [-16, root-document-sha256] >>
  } >>
})
```
The COSE_Sign1 payload is detached: it is the encoded SUIT_Digest, so the signature
covers ``["Signature1", protected, h'', SUIT_Digest]``; the digest is over the manifest
*bstr-wrapped* (its CBOR encoding as a byte string, header included).

Two digests per image, on purpose: **image-digest (3)** is the SHA-256 of the file a
device downloads (what a SUIT processor's image-match and an MCUmgr upload's ``sha``
check); **mcuboot-image-hash (-257)** is MCUboot's hash over header + payload +
protected TLVs, what MCUmgr's image list reports from a device afterwards. Labels below
-256 are hcdf-trust's own (negative labels are the draft's custom space).
"""

from __future__ import annotations

import hashlib
import uuid
from dataclasses import dataclass
from typing import Any

from .errors import MalformedReleaseError

SUIT_DRAFT = "draft-ietf-suit-manifest-34"
ENVELOPE_TAG = 107
COSE_SIGN1_TAG = 18
SHA256 = -16

# envelope / manifest / common keys (draft -34)
AUTHENTICATION, MANIFEST = 2, 3
VERSION, SEQUENCE_NUMBER, COMMON, VALIDATE, INSTALL = 1, 2, 3, 7, 20
COMPONENTS, SHARED_SEQUENCE = 2, 4
# commands
COND_VENDOR, COND_CLASS, COND_IMAGE_MATCH = 1, 2, 3
SET_COMPONENT_INDEX, OVERRIDE_PARAMETERS, FETCH = 12, 20, 21
# parameters
P_VENDOR, P_CLASS, P_DIGEST, P_SIZE, P_URI = 1, 2, 3, 14, 21
# hcdf-trust extensions (custom labels)
P_MCUBOOT_HASH, P_SECURITY_COUNTER, P_VERSION, P_TYPE, P_COMPS = -257, -258, -259, -260, -261
M_LOCK_DIGEST, M_ROOT, M_ROOT_DIGEST = -257, -258, -259

VENDOR_ID = uuid.uuid5(uuid.NAMESPACE_DNS, "hcdf-trust.invalid")
MAX_MANIFEST_BYTES = 4 << 20


def class_id(board: str) -> uuid.UUID:
    """One class per board: a device of another board refuses the component (mix-and-match)."""
    return uuid.uuid5(VENDOR_ID, board)


@dataclass(frozen=True)
class Component:
    board: str
    app: str
    type: str  # "mcuboot" | "raw"
    version: str
    uri: str
    size: int
    sha256: str  # the file a device downloads
    mcuboot_hash: str | None  # MCUboot image hash (what MCUmgr reports); None for raw
    security_counter: int | None
    comps: tuple[str, ...]

    @property
    def name(self) -> str:
        return f"{self.board}/{self.app}"

    def to_json(self) -> dict[str, Any]:
        return {
            "component_id": [self.board, self.app],
            "comps": list(self.comps),
            "type": self.type,
            "version": self.version,
            "uri": self.uri,
            "size": self.size,
            "file_sha256": self.sha256,
            "mcuboot_hash": self.mcuboot_hash,
            "security_counter": self.security_counter,
            "class_id": str(class_id(self.board)),
        }


@dataclass(frozen=True)
class Release:
    sequence_number: int
    lock_sha256: str
    root: str
    root_sha256: str
    components: tuple[Component, ...]

    def component(self, board: str, app: str) -> Component | None:
        return next((c for c in self.components if (c.board, c.app) == (board, app)), None)


# -- encoding ------------------------------------------------------------------------


def manifest_bytes(release: Release) -> bytes:
    """The manifest's deterministic CBOR encoding (canonical map order)."""
    import cbor2

    def enc(value: Any) -> bytes:
        return cbor2.dumps(value, canonical=True)

    shared: list[Any] = []
    validate: list[Any] = []
    install: list[Any] = []
    for i, c in enumerate(release.components):
        params: dict[int, Any] = {
            P_VENDOR: VENDOR_ID.bytes,
            P_CLASS: class_id(c.board).bytes,
            P_DIGEST: enc([SHA256, bytes.fromhex(c.sha256)]),
            P_SIZE: c.size,
            P_VERSION: c.version,
            P_TYPE: c.type,
            P_COMPS: list(c.comps),
        }
        if c.mcuboot_hash is not None:
            params[P_MCUBOOT_HASH] = enc([SHA256, bytes.fromhex(c.mcuboot_hash)])
        if c.security_counter is not None:
            params[P_SECURITY_COUNTER] = c.security_counter
        shared += [SET_COMPONENT_INDEX, i, OVERRIDE_PARAMETERS, params, COND_VENDOR, 15, COND_CLASS, 15]
        validate += [SET_COMPONENT_INDEX, i, COND_IMAGE_MATCH, 15]
        install += [SET_COMPONENT_INDEX, i, OVERRIDE_PARAMETERS, {P_URI: c.uri}, FETCH, 2, COND_IMAGE_MATCH, 15]
    common = {
        COMPONENTS: [[c.board.encode(), c.app.encode()] for c in release.components],
        SHARED_SEQUENCE: enc(shared),
    }
    manifest = {
        VERSION: 1,
        SEQUENCE_NUMBER: release.sequence_number,
        COMMON: enc(common),
        VALIDATE: enc(validate),
        INSTALL: enc(install),
        M_LOCK_DIGEST: enc([SHA256, bytes.fromhex(release.lock_sha256)]),
        M_ROOT: release.root,
        M_ROOT_DIGEST: enc([SHA256, bytes.fromhex(release.root_sha256)]),
    }
    return enc(manifest)


def manifest_digest(manifest: bytes) -> bytes:
    """The encoded SUIT_Digest over the bstr-wrapped manifest (the COSE detached payload)."""
    import cbor2

    return cbor2.dumps([SHA256, hashlib.sha256(cbor2.dumps(manifest)).digest()])


def envelope(manifest: bytes, cose_sign1: bytes) -> bytes:
    """The tagged envelope around a manifest and its detached COSE_Sign1."""
    import cbor2

    auth = cbor2.dumps([manifest_digest(manifest), cose_sign1])
    return cbor2.dumps(cbor2.CBORTag(ENVELOPE_TAG, {AUTHENTICATION: auth, MANIFEST: manifest}), canonical=True)


def to_json(release: Release, *, alg: str, kid: str) -> dict[str, Any]:
    """The human rendering written beside the envelope (not signed: the envelope is)."""
    return {
        "format": f"SUIT envelope (CBOR), {SUIT_DRAFT}, COSE_Sign1 {alg} (detached)",
        "file": "release.suit",
        "sequence_number": release.sequence_number,
        "hcdf": {"root": release.root, "root_sha256": release.root_sha256, "lock_sha256": release.lock_sha256},
        "signature": {"alg": alg, "kid": kid},
        "digests": {
            "file_sha256": "SHA-256 of the file a device downloads (SUIT image-digest; MCUmgr upload 'sha')",
            "mcuboot_hash": "MCUboot image hash over header + payload + protected TLVs "
            "(what MCUmgr 'image list' reports from a device)",
        },
        "components": [c.to_json() for c in release.components],
    }


# -- decoding ------------------------------------------------------------------------


@dataclass(frozen=True)
class Envelope:
    """An envelope taken apart, nothing verified yet."""

    manifest: bytes  # the manifest's CBOR (inside its bstr)
    digest: bytes  # the authentication wrapper's encoded SUIT_Digest
    cose_sign1: bytes
    protected: bytes
    protected_map: dict[Any, Any]
    signature: bytes


def parse_envelope(data: bytes, *, source: str) -> Envelope:
    """Take an envelope apart (no verification).

    Raises:
        MalformedReleaseError: truncated or malformed CBOR, or not the pinned draft's shape.
    """
    import cbor2

    top = _loads(data, source, "envelope")
    if not isinstance(top, cbor2.CBORTag) or top.tag != ENVELOPE_TAG or not isinstance(top.value, dict):
        raise MalformedReleaseError(f"not a SUIT envelope (tag {ENVELOPE_TAG} map)", file=source)
    auth, manifest = top.value.get(AUTHENTICATION), top.value.get(MANIFEST)
    if not isinstance(auth, bytes) or not isinstance(manifest, bytes):
        raise MalformedReleaseError("envelope lacks a bstr authentication wrapper (2) or manifest (3)", file=source)
    wrapper = _loads(auth, source, "authentication wrapper")
    if not isinstance(wrapper, list) or len(wrapper) < 2 or not all(isinstance(w, bytes) for w in wrapper):
        raise MalformedReleaseError("authentication wrapper is not [bstr digest, bstr signature...]", file=source)
    if len(wrapper) != 2:
        raise MalformedReleaseError("authentication wrapper must hold exactly one signature", file=source)
    sign1 = _loads(wrapper[1], source, "COSE_Sign1")
    if (
        not isinstance(sign1, cbor2.CBORTag)
        or sign1.tag != COSE_SIGN1_TAG
        or not isinstance(sign1.value, list)
        or len(sign1.value) != 4
    ):
        raise MalformedReleaseError("signature is not a tagged COSE_Sign1", file=source)
    protected, _unprotected, payload, signature = sign1.value
    if not isinstance(protected, bytes) or not isinstance(signature, bytes) or payload is not None:
        raise MalformedReleaseError(
            "COSE_Sign1 must have a bstr protected header, nil payload, bstr signature", file=source
        )
    protected_map = _loads(protected, source, "COSE protected header") if protected else {}
    if not isinstance(protected_map, dict):
        raise MalformedReleaseError("COSE protected header is not a map", file=source)
    return Envelope(manifest, wrapper[0], wrapper[1], protected, protected_map, signature)


def parse_manifest(manifest: bytes, *, source: str) -> Release:
    """The release a (verified) manifest describes.

    Raises:
        MalformedReleaseError: not the shape :func:`manifest_bytes` writes.
    """
    m = _loads(manifest, source, "manifest")
    if not isinstance(m, dict) or m.get(VERSION) != 1:
        raise MalformedReleaseError("manifest is not a version-1 SUIT manifest map", file=source)
    seq = m.get(SEQUENCE_NUMBER)
    if type(seq) is not int or seq < 0:
        raise MalformedReleaseError("manifest sequence-number is not an unsigned integer", file=source)
    common = _loads(_bstr(m, COMMON, source, "common"), source, "common")
    if not isinstance(common, dict):
        raise MalformedReleaseError("manifest common is not a map", file=source)
    ids = common.get(COMPONENTS)
    if not isinstance(ids, list) or not ids:
        raise MalformedReleaseError("manifest has no components", file=source)
    shared = _loads(_bstr(common, SHARED_SEQUENCE, source, "shared-sequence"), source, "shared-sequence")
    install = _loads(_bstr(m, INSTALL, source, "install"), source, "install")
    params = _by_index(shared, len(ids), source, "shared-sequence")
    uris = _by_index(install, len(ids), source, "install")
    components = []
    for i, cid in enumerate(ids):
        if not isinstance(cid, list) or len(cid) != 2 or not all(isinstance(p, bytes) for p in cid):
            raise MalformedReleaseError(f"component {i} id is not [bstr board, bstr app]", file=source)
        board, app = (p.decode("utf-8", "replace") for p in cid)
        p = params[i]
        where = f"component {board}/{app}"
        mcuboot = p.get(P_MCUBOOT_HASH)
        counter = p.get(P_SECURITY_COUNTER)
        comps = p.get(P_COMPS, [])
        if counter is not None and type(counter) is not int:
            raise MalformedReleaseError(f"{where}: security-counter is not an integer", file=source)
        if not isinstance(comps, list) or not all(isinstance(x, str) for x in comps):
            raise MalformedReleaseError(f"{where}: comps is not a list of text", file=source)
        if p.get(P_VENDOR) != VENDOR_ID.bytes or p.get(P_CLASS) != class_id(board).bytes:
            raise MalformedReleaseError(f"{where}: vendor-id/class-id do not match the component's board", file=source)
        components.append(
            Component(
                board=board,
                app=app,
                type=_typed(p, P_TYPE, str, source, where, "type"),
                version=_typed(p, P_VERSION, str, source, where, "version"),
                uri=_typed(uris[i], P_URI, str, source, where, "uri"),
                size=_typed(p, P_SIZE, int, source, where, "image-size"),
                sha256=_digest(p.get(P_DIGEST), source, where, "image-digest"),
                mcuboot_hash=None if mcuboot is None else _digest(mcuboot, source, where, "mcuboot-image-hash"),
                security_counter=counter,
                comps=tuple(comps),
            )
        )
    root = m.get(M_ROOT)
    if not isinstance(root, str):
        raise MalformedReleaseError("manifest has no hcdf root (-258)", file=source)
    return Release(
        sequence_number=seq,
        lock_sha256=_digest(m.get(M_LOCK_DIGEST), source, "manifest", "hcdf lock digest"),
        root=root,
        root_sha256=_digest(m.get(M_ROOT_DIGEST), source, "manifest", "hcdf root digest"),
        components=tuple(components),
    )


def _loads(data: bytes, source: str, what: str) -> Any:
    import cbor2

    try:
        return cbor2.loads(data)
    except (cbor2.CBORDecodeError, ValueError, RecursionError, OverflowError, MemoryError) as exc:
        raise MalformedReleaseError(f"{what}: truncated or malformed CBOR ({exc})", file=source) from None


def _bstr(m: dict[Any, Any], key: int, source: str, what: str) -> bytes:
    value = m.get(key)
    if not isinstance(value, bytes):
        raise MalformedReleaseError(f"manifest {what} ({key}) is not a bstr", file=source)
    return value


def _by_index(seq: Any, n: int, source: str, what: str) -> list[dict[Any, Any]]:
    """Override-parameters of each component index in a flat command sequence."""
    if not isinstance(seq, list) or len(seq) % 2:
        raise MalformedReleaseError(f"{what} is not a command sequence", file=source)
    out: list[dict[Any, Any]] = [{} for _ in range(n)]
    index = None
    for op, arg in zip(seq[::2], seq[1::2], strict=True):
        if op == SET_COMPONENT_INDEX:
            if type(arg) is not int or not 0 <= arg < n:
                raise MalformedReleaseError(f"{what}: component index {arg!r} out of range", file=source)
            index = arg
        elif op == OVERRIDE_PARAMETERS:
            if index is None or not isinstance(arg, dict):
                raise MalformedReleaseError(f"{what}: parameters without a component index", file=source)
            out[index].update(arg)
    return out


def _typed(p: dict[Any, Any], key: int, kind: type, source: str, where: str, name: str) -> Any:
    value = p.get(key)
    if type(value) is not kind:
        raise MalformedReleaseError(f"{where}: {name} is missing or not {kind.__name__}", file=source)
    return value


def _digest(raw: Any, source: str, where: str, name: str) -> str:
    value = _loads(raw, source, f"{where} {name}") if isinstance(raw, bytes) else raw
    if (
        not isinstance(value, list)
        or len(value) != 2
        or value[0] != SHA256
        or not isinstance(value[1], bytes)
        or len(value[1]) != 32
    ):
        raise MalformedReleaseError(f"{where}: {name} is not a SHA-256 SUIT_Digest", file=source)
    return value[1].hex()
