"""The signed release manifest: a SUIT envelope over every image of one release.

Format: **draft-ietf-suit-manifest-34** (:data:`SUIT_DRAFT`; RFC 9124's information model),
valid against the draft's CDDL with no extension: every fact the draft has a parameter
for sits in that parameter, and hcdf-trust's own facts sit in an integrated payload
(§5.5, §7.5) that the signed manifest binds by digest like any other image. Section
numbers are -34's; docs/suit.md ("Release manifest layout") says the same for users.

```
107({                                          / SUIT_Envelope_Tagged (§8.2) /
  2: << [ << [-16, h'sha256'] >>,              / authentication-wrapper (§8.3): SUIT_Digest of the /
          << 18([<<{1: alg, 4: kid}>>, {}, nil, sig]) >> ] >>,   / bstr-wrapped manifest; COSE_Sign1, detached /
  3: << {                                      / manifest (§8.4) /
    1: 1, 2: sequence-number,
    3: << { 2: [ [h'board', h'app'], ..., [h'hcdf-trust', h'release-record'] ],  / common (§8.4.5) /
            4: << [ 12, i, 20, {1: vendor-id, 2: class-id,           / shared sequence: standard /
                                 3: << [-16, sha256] >>, 14: size},  / parameters only (§8.4.8) /
                    1, 15, 2, 15, ... ] >> } >>,
    7: << [12, i, 3, 15, ...] >>,              / validate: image-match (§8.4.9.2) /
    20: << [12, i, 20, {21: "uri"}, 21, 2, 3, 15, ...] >>  / install: fetch, image-match (§7.3) /
  } >>,
  "#hcdf-release": << record >>                / integrated payload (§7.5): the last component /
})
```

Components 0…n-1 are the images: image-digest (3) is the SHA-256 of the file a device
downloads (what image-match and an MCUmgr upload's ``sha`` check), image-size (14) its
length, uri (21) where it is published, class-id (2) a UUIDv5 of the board (§8.4.8.2).
Component n is the **release record**, fetched from the envelope (uri ``#hcdf-release``)
and checked by image-match like an image. It is deterministic CBOR:

```
{ "components": [ { "changelog": tstr / nil, "comps": [* tstr],          / index i = component i /
                    "mcuboot-digest": SUIT_Digest / nil,               / MCUboot image hash /
                    "security-counter": uint / nil, "type": "mcuboot" / "raw", "version": tstr }, ... ],
  "date": tstr,                                                        / latest.json's date /
  "hcdf-lock-digest": SUIT_Digest, "hcdf-root": tstr, "hcdf-root-digest": SUIT_Digest,
  "record-version": 1 }
```

Why there: §8.4.8.16 forbids custom parameters in the shared sequence and types them
``int / bool / tstr / bstr``, and the core CDDL has no manifest-level extension keys.
Releases written before this layout (custom parameters −257…−261 in the shared
sequence, manifest keys −257…−259) are refused with a message saying so.

Parsing is strict (§8.1: maps in canonical order): one definite-length item, preferred
(shortest) heads, map keys in RFC 8949 §4.2.1 order (a duplicate key is refused as
such), no trailing bytes, bounded depth; the COSE unprotected header must be empty.
"""

from __future__ import annotations

import hashlib
import json
import uuid
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from .errors import MalformedReleaseError, ReleaseIntegrityError

SUIT_DRAFT = "draft-ietf-suit-manifest-34"
ENVELOPE_TAG = 107
COSE_SIGN1_TAG = 18
SHA256 = -16

# envelope / manifest / common keys (draft -34, §8.2–§8.4.5)
AUTHENTICATION, MANIFEST = 2, 3
VERSION, SEQUENCE_NUMBER, COMMON, REFERENCE_URI = 1, 2, 3, 4
VALIDATE, LOAD, INVOKE, PAYLOAD_FETCH, INSTALL, TEXT = 7, 8, 9, 16, 20, 23
SEVERABLE = (PAYLOAD_FETCH, INSTALL, TEXT)
COMPONENTS, SHARED_SEQUENCE = 2, 4
# commands (§8.4.9, §8.4.10)
COND_VENDOR, COND_CLASS, COND_IMAGE_MATCH = 1, 2, 3
SET_COMPONENT_INDEX, OVERRIDE_PARAMETERS, FETCH = 12, 20, 21
# parameters (§8.4.8)
P_VENDOR, P_CLASS, P_DIGEST, P_SIZE, P_URI = 1, 2, 3, 14, 21
# COSE header labels (RFC 9052 §3.1)
COSE_ALG, COSE_CRIT, COSE_KID = 1, 2, 4
COSE_LABELS = {1: "alg", 2: "crit", 3: "content type", 4: "kid", 5: "IV", 6: "Partial IV"}

VENDOR_ID = uuid.uuid5(uuid.NAMESPACE_DNS, "hcdf-trust.invalid")
RECORD_KEY = "#hcdf-release"  # integrated-payload key, also the record component's uri (§7.5)
RECORD_ID = [b"hcdf-trust", b"release-record"]
RECORD_CLASS = uuid.uuid5(VENDOR_ID, "hcdf-trust release record")
RECORD_VERSION = 1
MAX_MANIFEST_BYTES = 4 << 20
MAX_DEPTH = 16
LEGACY = (
    "this release uses hcdf-trust's layout from before draft-34 conformance (custom parameters "
    "-257…-261 in the shared sequence, manifest keys -257…-259); its facts now sit in an integrated "
    "release record (docs/suit.md): rebuild the release with this hcdf-trust "
    "(to carry its history on: move release.suit aside, set [release] sequence_number in ota.toml above its own, "
    "build with --import-unsigned-history)"
)


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
    changelog: str | None = None  # latest.json's latest.changelog

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
            "changelog": self.changelog,
            "class_id": str(class_id(self.board)),
        }


@dataclass(frozen=True)
class Release:
    sequence_number: int
    lock_sha256: str
    root: str
    root_sha256: str
    components: tuple[Component, ...]
    date: str = ""  # latest.json's latest.date

    def component(self, board: str, app: str) -> Component | None:
        return next((c for c in self.components if (c.board, c.app) == (board, app)), None)


# -- encoding ------------------------------------------------------------------------


def _enc(value: Any) -> bytes:
    import cbor2

    return cbor2.dumps(value, canonical=True)


def _suit_digest(hex_digest: str) -> list[Any]:
    return [SHA256, bytes.fromhex(hex_digest)]


def record_bytes(release: Release) -> bytes:
    """The release record (integrated payload): what the draft has no parameter for."""
    return _enc(
        {
            "record-version": RECORD_VERSION,
            "date": release.date,
            "hcdf-root": release.root,
            "hcdf-root-digest": _suit_digest(release.root_sha256),
            "hcdf-lock-digest": _suit_digest(release.lock_sha256),
            "components": [
                {
                    "type": c.type,
                    "version": c.version,
                    "comps": list(c.comps),
                    "mcuboot-digest": None if c.mcuboot_hash is None else _suit_digest(c.mcuboot_hash),
                    "security-counter": c.security_counter,
                    "changelog": c.changelog,
                }
                for c in release.components
            ],
        }
    )


def encode(release: Release) -> tuple[bytes, dict[str, bytes]]:
    """The manifest's deterministic CBOR and the envelope's integrated payloads."""
    record = record_bytes(release)
    shared: list[Any] = []
    validate: list[Any] = []
    install: list[Any] = []
    rows = [(c.board, c.sha256, c.size, c.uri) for c in release.components]
    rows.append(("", hashlib.sha256(record).hexdigest(), len(record), RECORD_KEY))
    for i, (board, sha, size, uri) in enumerate(rows):
        cls = class_id(board) if board else RECORD_CLASS
        params = {P_VENDOR: VENDOR_ID.bytes, P_CLASS: cls.bytes, P_DIGEST: _enc(_suit_digest(sha)), P_SIZE: size}
        shared += [SET_COMPONENT_INDEX, i, OVERRIDE_PARAMETERS, params, COND_VENDOR, 15, COND_CLASS, 15]
        validate += [SET_COMPONENT_INDEX, i, COND_IMAGE_MATCH, 15]
        install += [SET_COMPONENT_INDEX, i, OVERRIDE_PARAMETERS, {P_URI: uri}, FETCH, 2, COND_IMAGE_MATCH, 15]
    ids = [[c.board.encode(), c.app.encode()] for c in release.components] + [RECORD_ID]
    manifest = {
        VERSION: 1,
        SEQUENCE_NUMBER: release.sequence_number,
        COMMON: _enc({COMPONENTS: ids, SHARED_SEQUENCE: _enc(shared)}),
        VALIDATE: _enc(validate),
        INSTALL: _enc(install),
    }
    return _enc(manifest), {RECORD_KEY: record}


def manifest_digest(manifest: bytes) -> bytes:
    """The encoded SUIT_Digest over the bstr-wrapped manifest (the COSE detached payload)."""
    import cbor2

    return cbor2.dumps([SHA256, hashlib.sha256(cbor2.dumps(manifest)).digest()])


def envelope(manifest: bytes, cose_sign1: bytes, payloads: Mapping[str, bytes] | None = None) -> bytes:
    """The tagged envelope around a manifest, its detached COSE_Sign1 and integrated payloads."""
    import cbor2

    auth = cbor2.dumps([manifest_digest(manifest), cose_sign1])
    top: dict[Any, bytes] = {AUTHENTICATION: auth, MANIFEST: manifest, **(payloads or {})}
    return cbor2.dumps(cbor2.CBORTag(ENVELOPE_TAG, top), canonical=True)


def to_json(release: Release, *, alg: str, kid: str) -> dict[str, Any]:
    """The human rendering written beside the envelope: all of it derived from the signed
    envelope, so that ``ota verify`` can demand it byte for byte (:func:`render_json`)."""
    return {
        "format": f"SUIT envelope (CBOR), {SUIT_DRAFT}, COSE_Sign1 {alg} (detached)",
        "file": "release.suit",
        "sequence_number": release.sequence_number,
        "date": release.date,
        "hcdf": {"root": release.root, "root_sha256": release.root_sha256, "lock_sha256": release.lock_sha256},
        "signature": {"alg": alg, "kid": kid},
        "digests": {
            "file_sha256": "SHA-256 of the file a device downloads (SUIT image-digest; MCUmgr upload 'sha')",
            "mcuboot_hash": "MCUboot image hash over header + payload + protected TLVs "
            "(what MCUmgr 'image list' reports from a device)",
        },
        "components": [c.to_json() for c in release.components],
    }


def render_json(release: Release, *, alg: str, kid: str) -> bytes:
    """``release.suit.json``'s exact bytes."""
    return (json.dumps(to_json(release, alg=alg, kid=kid), indent=2, ensure_ascii=False) + "\n").encode()


# -- strict CBOR ---------------------------------------------------------------------


def loads(data: bytes, *, source: str, what: str) -> Any:
    """One CBOR item, decoded only after :func:`check_wellformed` accepted it.

    Raises:
        MalformedReleaseError: see :func:`check_wellformed`; or cbor2 refuses the item.
    """
    import cbor2

    check_wellformed(data, source=source, what=what)
    try:
        return cbor2.loads(data)
    except (cbor2.CBORDecodeError, ValueError, RecursionError, OverflowError, MemoryError) as exc:
        raise MalformedReleaseError(f"{what}: malformed CBOR ({exc})", file=source) from None


def check_wellformed(data: bytes, *, source: str, what: str) -> None:
    """Exactly one CBOR item in the draft's encoding (§8.1, RFC 8949 §4.2.1).

    cbor2 alone keeps the last of two equal map keys and ignores trailing bytes: an
    unsigned manifest placed before the signed one would be read. So, before decoding:
    definite lengths, preferred (shortest) argument encodings, map keys in bytewise
    order of their encodings with none repeated, no floating point, depth ≤ MAX_DEPTH,
    nothing after the item.

    Raises:
        MalformedReleaseError: the first rule broken, with its byte offset.
    """
    n = len(data)

    def fail(message: str, at: int) -> MalformedReleaseError:
        return MalformedReleaseError(f"{what}: {message} (byte {at})", file=source)

    def head(pos: int) -> tuple[int, int, int]:
        if pos >= n:
            raise fail("truncated or malformed CBOR: it ends early", pos)
        major, info = data[pos] >> 5, data[pos] & 31
        if info < 24:
            return major, info, pos + 1
        if info > 27:
            raise fail("indefinite length or reserved encoding", pos)
        size = 1 << (info - 24)
        if pos + 1 + size > n:
            raise fail("truncated or malformed CBOR: it ends early", pos)
        arg = int.from_bytes(data[pos + 1 : pos + 1 + size], "big")
        if major == 7 and info > 24:
            raise fail("floating-point value", pos)
        if arg < (24 if size == 1 else 1 << (4 * size)):
            raise fail("argument not in its shortest encoding", pos)
        return major, arg, pos + 1 + size

    def item(pos: int, depth: int) -> int:
        if depth > MAX_DEPTH:
            raise fail(f"nested deeper than {MAX_DEPTH}", pos)
        start = pos
        major, arg, pos = head(pos)
        if major in (2, 3):
            if arg > n - pos:
                raise fail("truncated or malformed CBOR: it ends early", start)
            return pos + arg
        if major == 4:
            for _ in range(arg):
                pos = item(pos, depth + 1)
            return pos
        if major == 5:
            last: bytes | None = None
            for _ in range(arg):
                key_at = pos
                pos = item(pos, depth + 1)
                key = data[key_at:pos]
                if last is not None and key == last:
                    raise fail(f"duplicate map key {key.hex()}", key_at)
                if last is not None and key < last:
                    raise fail("map keys not in canonical order", key_at)
                last = key
                pos = item(pos, depth + 1)
            return pos
        if major == 6:
            return item(pos, depth + 1)
        return pos  # 0, 1 integers; 7 simple values

    end = item(0, 0)
    if end != n:
        raise fail(f"{n - end} trailing bytes after the CBOR item", end)


# -- decoding: the draft's envelope and manifest ---------------------------------------


@dataclass(frozen=True)
class Envelope:
    """An envelope taken apart, nothing verified yet."""

    manifest: bytes  # the manifest's CBOR (inside its bstr)
    digest: bytes  # the authentication wrapper's encoded SUIT_Digest
    cose_sign1: bytes
    protected: bytes
    protected_map: dict[Any, Any]
    signature: bytes
    severable: dict[int, bytes] = field(default_factory=dict)  # severable members present in the envelope
    payloads: dict[str, bytes] = field(default_factory=dict)  # integrated payloads


@dataclass(frozen=True)
class Manifest:
    """A draft-34 manifest taken apart (after its signature was checked)."""

    sequence_number: int
    components: list[list[bytes]]
    shared: list[Any]
    sequences: dict[int, list[Any] | None]  # 7, 8, 9, 16, 20: decoded; None: severed
    text: dict[Any, Any] | None
    reference_uri: str | None


def parse_envelope(data: bytes, *, source: str) -> Envelope:
    """Take an envelope apart, strictly, without verifying it.

    Raises:
        MalformedReleaseError: not one well-formed SUIT_Envelope_Tagged of the draft (§8.2,
            §8.3): an unknown envelope key, not exactly one COSE_Sign1, a payload that is
            not detached, any label in the COSE unprotected header, a protected label
            other than alg and kid.
    """
    import cbor2

    top = loads(data, source=source, what="envelope")
    if not isinstance(top, cbor2.CBORTag) or top.tag != ENVELOPE_TAG or not isinstance(top.value, dict):
        raise MalformedReleaseError(f"not a SUIT envelope (tag {ENVELOPE_TAG} map)", file=source)
    severable: dict[int, bytes] = {}
    payloads: dict[str, bytes] = {}
    for key, value in top.value.items():
        if key in (AUTHENTICATION, MANIFEST, *SEVERABLE) or isinstance(key, str):
            if not isinstance(value, bytes):
                raise MalformedReleaseError(f"envelope member {key!r} is not a bstr", file=source)
            if isinstance(key, str):
                payloads[key] = value
            elif key in SEVERABLE:
                severable[key] = value
        else:
            raise MalformedReleaseError(
                f"envelope key {key!r} is not one of {SUIT_DRAFT}" + (f": {LEGACY}" if _private(key) else ""),
                file=source,
            )
    auth, manifest = top.value.get(AUTHENTICATION), top.value.get(MANIFEST)
    if auth is None or manifest is None:
        raise MalformedReleaseError("envelope lacks an authentication wrapper (2) or manifest (3)", file=source)
    wrapper = loads(auth, source=source, what="authentication wrapper")
    if not isinstance(wrapper, list) or len(wrapper) < 2 or not all(isinstance(w, bytes) for w in wrapper):
        raise MalformedReleaseError("authentication wrapper is not [bstr digest, bstr signature...]", file=source)
    if len(wrapper) != 2:
        raise MalformedReleaseError("authentication wrapper must hold exactly one signature", file=source)
    digest = loads(wrapper[0], source=source, what="authentication wrapper digest")
    if (
        not isinstance(digest, list)
        or len(digest) != 2
        or type(digest[0]) is not int
        or not isinstance(digest[1], bytes)
    ):
        raise MalformedReleaseError("authentication wrapper digest is not a SUIT_Digest", file=source)
    sign1 = loads(wrapper[1], source=source, what="COSE_Sign1")
    if (
        not isinstance(sign1, cbor2.CBORTag)
        or sign1.tag != COSE_SIGN1_TAG
        or not isinstance(sign1.value, list)
        or len(sign1.value) != 4
    ):
        raise MalformedReleaseError("signature is not a tagged COSE_Sign1", file=source)
    protected, unprotected, payload, signature = sign1.value
    if not isinstance(protected, bytes) or not isinstance(signature, bytes) or payload is not None:
        raise MalformedReleaseError(
            "COSE_Sign1 must have a bstr protected header, nil payload, bstr signature", file=source
        )
    if not isinstance(unprotected, dict):
        raise MalformedReleaseError("COSE unprotected header is not a map", file=source)
    if unprotected:
        raise MalformedReleaseError(
            "COSE unprotected header must be empty (nothing in it is signed): it holds "
            + ", ".join(_label(k) for k in unprotected),
            file=source,
        )
    protected_map = loads(protected, source=source, what="COSE protected header") if protected else {}
    if not isinstance(protected_map, dict):
        raise MalformedReleaseError("COSE protected header is not a map", file=source)
    unknown = [k for k in protected_map if k not in (COSE_ALG, COSE_KID)]
    if unknown:
        raise MalformedReleaseError(
            "COSE protected header holds labels this verifier does not implement: "
            + ", ".join(_label(k) for k in unknown),
            file=source,
            expected="alg (1) and kid (4) only",
        )
    return Envelope(manifest, wrapper[0], wrapper[1], protected, protected_map, signature, severable, payloads)


def parse_suit_manifest(env: Envelope, *, source: str) -> Manifest:
    """The draft-34 manifest of an envelope whose signature was checked (§6.2: not before).

    Severable members (§8.6) present in the envelope must match the digest the manifest
    holds for them; a member the manifest does not cover is refused.

    Raises:
        MalformedReleaseError: not a manifest of the draft's CDDL.
        ReleaseIntegrityError: a severable member that does not match its digest.
    """
    m = loads(env.manifest, source=source, what="manifest")
    if not isinstance(m, dict):
        raise MalformedReleaseError("manifest is not a map", file=source)
    allowed = {VERSION, SEQUENCE_NUMBER, COMMON, REFERENCE_URI, VALIDATE, LOAD, INVOKE, *SEVERABLE}
    for key in m:
        if key not in allowed:
            raise MalformedReleaseError(
                f"manifest key {key!r} is not one of {SUIT_DRAFT}" + (f": {LEGACY}" if _private(key) else ""),
                file=source,
            )
    if m.get(VERSION) != 1 or type(m.get(VERSION)) is not int:
        raise MalformedReleaseError("manifest is not a version-1 SUIT manifest", file=source)
    seq = m.get(SEQUENCE_NUMBER)
    if type(seq) is not int or seq < 0:
        raise MalformedReleaseError("manifest sequence-number is not an unsigned integer", file=source)
    uri = m.get(REFERENCE_URI)
    if uri is not None and not isinstance(uri, str):
        raise MalformedReleaseError("manifest reference-uri is not text", file=source)
    common = loads(_bstr(m.get(COMMON), source, "common"), source=source, what="common")
    if not isinstance(common, dict) or not set(common) <= {COMPONENTS, SHARED_SEQUENCE}:
        raise MalformedReleaseError(
            "manifest common is not a map of components (2) and shared-sequence (4)", file=source
        )
    ids = common.get(COMPONENTS)
    if (
        not isinstance(ids, list)
        or not ids
        or not all(isinstance(c, list) and all(isinstance(p, bytes) for p in c) for c in ids)
    ):
        raise MalformedReleaseError("manifest components is not a list of [* bstr] identifiers", file=source)
    shared = _sequence(common.get(SHARED_SEQUENCE), source, "shared-sequence")
    for key in env.severable:
        if key not in m:
            raise MalformedReleaseError(f"envelope member {key} is not covered by the manifest", file=source)
        if isinstance(m[key], bytes):
            raise MalformedReleaseError(f"member {key} is both in the manifest and in the envelope", file=source)
    sequences: dict[int, list[Any] | None] = {}
    text: dict[Any, Any] | None = None
    for key in (VALIDATE, LOAD, INVOKE, PAYLOAD_FETCH, INSTALL, TEXT):
        if key not in m:
            continue
        raw = m[key]
        if key in SEVERABLE and isinstance(raw, list):
            raw = _severed(raw, env.severable.get(key), source, key)
            if raw is None:
                if key != TEXT:
                    sequences[key] = None
                continue
        if key == TEXT:
            text = loads(_bstr(raw, source, "text"), source=source, what="text")
            if not isinstance(text, dict):
                raise MalformedReleaseError("manifest text is not a map", file=source)
        else:
            sequences[key] = _sequence(raw, source, f"command sequence {key}")
    return Manifest(seq, ids, shared, sequences, text, uri)


def _severed(digest: list[Any], member: bytes | None, source: str, key: int) -> bytes | None:
    """A severable member given by its digest: the envelope's member if it matches, None if severed."""
    import cbor2

    if len(digest) != 2 or digest[0] != SHA256 or not isinstance(digest[1], bytes):
        raise MalformedReleaseError(f"manifest member {key} is not a SHA-256 SUIT_Digest", file=source)
    if member is None:
        return None
    actual = hashlib.sha256(cbor2.dumps(member)).digest()
    if actual != digest[1]:
        raise ReleaseIntegrityError(
            f"envelope member {key} is not the one the manifest's digest names",
            file=source,
            expected=digest[1].hex(),
            actual=actual.hex(),
        )
    return member


def _sequence(raw: Any, source: str, what: str) -> list[Any]:
    seq = loads(_bstr(raw, source, what), source=source, what=what)
    if not isinstance(seq, list) or not seq or len(seq) % 2 or not all(type(op) is int for op in seq[::2]):
        raise MalformedReleaseError(f"{what} is not a SUIT command sequence", file=source)
    return seq


def _private(key: Any) -> bool:
    return type(key) is int and key <= -256


def _label(key: Any) -> str:
    return f"{COSE_LABELS[key]} ({key})" if key in COSE_LABELS else repr(key)


# -- decoding: hcdf-trust's layout ---------------------------------------------------


def parse_release(env: Envelope, *, source: str) -> Release:
    """The release a verified envelope describes, in exactly the layout :func:`encode` writes.

    Raises:
        MalformedReleaseError: not that layout (the manifest, re-encoded from what was
            read, must be the signed bytes). ReleaseIntegrityError: the record is not the
            one the manifest binds by digest.
    """
    m = parse_suit_manifest(env, source=source)
    ids = m.components
    if len(ids) < 2 or ids[-1] != RECORD_ID:
        raise MalformedReleaseError("manifest has no hcdf-trust release record component", file=source)
    n = len(ids) - 1
    shared = _by_index(m.shared, len(ids), source, "shared-sequence")
    install = _by_index(m.sequences.get(INSTALL), len(ids), source, "install")
    record_raw = env.payloads.get(RECORD_KEY)
    if record_raw is None:
        raise MalformedReleaseError(f"envelope has no release record ({RECORD_KEY!r})", file=source)
    want = _digest(shared[n].get(P_DIGEST), source, "release record", "image-digest")
    if hashlib.sha256(record_raw).hexdigest() != want or len(record_raw) != shared[n].get(P_SIZE):
        raise ReleaseIntegrityError(
            "release record is not the one the signed manifest binds (image-digest/size)",
            file=source,
            expected=want,
            actual=hashlib.sha256(record_raw).hexdigest(),
        )
    record = _record(record_raw, n, source)
    components = []
    for i in range(n):
        board, app = _utf8_id(ids[i], i, source)
        p, r = shared[i], record["components"][i]
        where = f"component {board}/{app}"
        if p.get(P_VENDOR) != VENDOR_ID.bytes or p.get(P_CLASS) != class_id(board).bytes:
            raise MalformedReleaseError(f"{where}: vendor-id/class-id do not match the component's board", file=source)
        mcuboot = r["mcuboot-digest"]
        components.append(
            Component(
                board=board,
                app=app,
                type=r["type"],
                version=r["version"],
                uri=_typed(install[i], P_URI, str, source, where, "uri"),
                size=_typed(p, P_SIZE, int, source, where, "image-size"),
                sha256=_digest(p.get(P_DIGEST), source, where, "image-digest"),
                mcuboot_hash=None if mcuboot is None else _digest(mcuboot, source, where, "mcuboot-digest"),
                security_counter=r["security-counter"],
                comps=tuple(r["comps"]),
                changelog=r["changelog"],
            )
        )
    release = Release(
        sequence_number=m.sequence_number,
        lock_sha256=_digest(record["hcdf-lock-digest"], source, "release record", "hcdf-lock-digest"),
        root=record["hcdf-root"],
        root_sha256=_digest(record["hcdf-root-digest"], source, "release record", "hcdf-root-digest"),
        components=tuple(components),
        date=record["date"],
    )
    manifest, payloads = encode(release)
    if manifest != env.manifest or payloads != env.payloads:  # (a severed member changes the manifest)
        raise MalformedReleaseError(
            f"manifest is not in the layout ota build writes ({SUIT_DRAFT}, docs/suit.md)",
            file=source,
        )
    return release


_RECORD_KEYS = {"record-version", "date", "hcdf-root", "hcdf-root-digest", "hcdf-lock-digest", "components"}
_ENTRY_TYPES: dict[str, tuple[type, ...]] = {
    "type": (str,),
    "version": (str,),
    "comps": (list,),
    "mcuboot-digest": (list, type(None)),
    "security-counter": (int, type(None)),
    "changelog": (str, type(None)),
}


def _record(data: bytes, n: int, source: str) -> dict[str, Any]:
    """The release record, every key present and of its type."""
    rec = loads(data, source=source, what="release record")
    if not isinstance(rec, dict) or set(rec) != _RECORD_KEYS or rec["record-version"] != RECORD_VERSION:
        raise MalformedReleaseError(
            f"release record is not a version-{RECORD_VERSION} record",
            file=source,
            expected=", ".join(sorted(_RECORD_KEYS)),
        )
    for key in ("date", "hcdf-root"):
        if not isinstance(rec[key], str):
            raise MalformedReleaseError(f"release record {key} is not text", file=source)
    entries = rec["components"]
    if not isinstance(entries, list) or len(entries) != n:
        raise MalformedReleaseError(
            "release record does not describe every image component", file=source, expected=str(n)
        )
    for i, e in enumerate(entries):
        if not isinstance(e, dict) or set(e) != set(_ENTRY_TYPES):
            raise MalformedReleaseError(f"release record component {i} has other keys", file=source)
        for key, kinds in _ENTRY_TYPES.items():
            if type(e[key]) not in kinds:
                raise MalformedReleaseError(
                    f"release record component {i}: {key} is not {kinds[0].__name__}", file=source
                )
        if e["type"] not in ("mcuboot", "raw") or not all(isinstance(c, str) for c in e["comps"]):
            raise MalformedReleaseError(f"release record component {i}: bad type or comps", file=source)
        if e["security-counter"] is not None and e["security-counter"] < 0:
            raise MalformedReleaseError(f"release record component {i}: negative security-counter", file=source)
    return rec


def _utf8_id(cid: list[bytes], i: int, source: str) -> tuple[str, str]:
    if len(cid) != 2:
        raise MalformedReleaseError(f"component {i} id is not [bstr board, bstr app]", file=source)
    try:
        board, app = (p.decode("utf-8") for p in cid)
    except UnicodeDecodeError:
        raise MalformedReleaseError(f"component {i} id is not UTF-8", file=source) from None
    return board, app


def _bstr(value: Any, source: str, what: str) -> bytes:
    if not isinstance(value, bytes):
        raise MalformedReleaseError(f"manifest {what} is not a bstr", file=source)
    return value


def _by_index(seq: list[Any] | None, n: int, source: str, what: str) -> list[dict[Any, Any]]:
    """Override-parameters of each component index in a flat command sequence."""
    if seq is None:
        raise MalformedReleaseError(f"manifest has no {what} sequence", file=source)
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
    value = loads(raw, source=source, what=f"{where} {name}") if isinstance(raw, bytes) else raw
    if (
        not isinstance(value, list)
        or len(value) != 2
        or value[0] != SHA256
        or not isinstance(value[1], bytes)
        or len(value[1]) != 32
    ):
        raise MalformedReleaseError(f"{where}: {name} is not a SHA-256 SUIT_Digest", file=source)
    return value[1].hex()
