"""The MACsec key store: one file, every key encrypted on its own, written all or nothing.

Layout of ``DIR/macsec-keys.json`` (:data:`STORE_NAME`, mode 0600, format version
:data:`FORMAT_VERSION`): JSON Lines, compact and key-sorted, a header then one line per
association, sorted by CA id::

    {"mac":HEX,"format":"hcdf-trust-macsec-store","robot":NAME,"store_id":HEX,"version":2,
     "wrap":{"method":"scrypt" | "pkcs11" | "tpm",...}}        # the wrapped 256-bit data key
    [CA_ID,{"cipher","generations":[{"activation","ciphertext","ckn","created","expiry",
            "generation","nonce","state"}],"key_bytes","kind","source":{"file","line"[,"pointer"]}}]
    ...

Opening reads the header and indexes the lines by CA id; an association's line is parsed
only when it is used (an export touches a handful of 10,000).

* Each key (CAK or mesh network key) is AES-256-GCM encrypted under the data key with a
  fresh nonce and, as associated data, the store id, CA id, generation and CKN: an entry
  moved to another CA or generation does not decrypt. Adding or rotating one key encrypts
  that key only; nothing else is re-encrypted or re-derived.
* ``mac`` is HMAC-SHA256 (a key derived from the data key) over the exact bytes of the
  rest of the file (``{`` + every byte after ``{"mac":HEX,``), so it is checked without
  re-serialising anything: any changed byte (an activation time, a dropped generation, a
  reformatted line) is an integrity error (exit 1). Version 1 (one JSON object, its MAC
  over a re-serialisation) is refused with a message saying so.
* ``robot`` is the identity of the robot the store was generated for: the ``name`` of the
  root document's ``<hcdf>`` (see :meth:`KeyStore.bind`). It is covered by the MAC, so it
  cannot be edited; every verb that reads a description refuses a store of another robot
  (exit 1, both names), so one robot's CAKs never reach another robot's devices. A store
  without it (made before robots were recorded) is refused: make a new one.
* CKNs are 16 random octets, unique across the store: only the first 16 octets of a CKN
  reach the 802.1X KDF.
* The file is read through :func:`hcdf_trust.localfile.read_input` (bounded, regular file
  only) and replaced through :class:`hcdf_trust.outputs.OutputPlan` (0600 from the first
  byte, renamed into place only when fully written), so a crash leaves it as it was
  before or as it is after.

Times are UTC, ISO 8601 with a ``Z``. A generation is *pending* before its activation,
*active* from then until its expiry (``null``: none yet) and *retired* after it.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import hmac
import json
import os
import re
import stat
import threading
import time
from collections.abc import Callable, Iterator, MutableMapping
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from ..errors import InputError, IntegrityError, Pointer, json_locations
from ..flock import flock
from ..localfile import JsonError, parse_json, read_input
from ..outputs import KEY_STORE, OutputPlan, sweep_folder
from .backends import KeyStoreFormatError, Wrapper, b64, unb64

STORE_NAME = "macsec-keys.json"
INDEX_NAME = "macsec-export-index.json"  # beside the store: see hcdf_trust.macsec.index
LOCK_NAME = ".macsec-keys.lock"
LOCK_WAIT_SEC = 30.0
# Entries whose secret is a PEM bundle (EAP-TLS CA or device key and certificate), not an AES key.
BLOB_KINDS = ("eap-tls-ca", "eap-tls-cert")
MAX_BLOB_BYTES = 64 << 10
FORMAT = "hcdf-trust-macsec-store"
FORMAT_VERSION = 2
MAX_STORE_BYTES = 512 << 20
CKN_BYTES = 16


# The public API (docs/api.md); everything else here is internal.
__all__ = ["KeyStore", "locked", "now_utc"]


class KeyStoreIntegrityError(IntegrityError):
    """The key store's metadata or a key's ciphertext was changed outside this tool."""

    code = "key-store-integrity"


class KeyStoreRobotError(IntegrityError):
    """The key store was generated for another robot than the description names."""

    code = "key-store-robot"


@contextlib.contextmanager
def locked(folder: str | os.PathLike[str]) -> Iterator[None]:
    """Hold the store folder's lock (``flock`` on :data:`LOCK_NAME`) for one read-modify-write.

    Two runs on one store never interleave (the second waits up to :data:`LOCK_WAIT_SEC`).
    The folder is made 0700 if missing; a lock path that is not a regular file is refused.

    Raises:
        InputError: the folder cannot be made, the lock is not a regular file, or it stays held.

    Example (generate keys into a new store, write it, read it back):

        >>> import os
        >>> from hcdf_trust.macsec.backends import PassphraseWrapper
        >>> from hcdf_trust.macsec.plan import plan
        >>> from hcdf_trust.macsec.rotation import generate, status
        >>> from hcdf_trust.macsec.store import KeyStore, locked, now_utc
        >>> from hcdf_trust.outputs import OutputPlan
        >>> p = plan("examples/robot/robot.hcdf")
        >>> wrapper = PassphraseWrapper(b"correct horse battery staple")
        >>> now = now_utc()
        >>> with locked("keys"):  # one read-modify-write of the store at a time
        ...     store = KeyStore.open("keys", wrapper) if KeyStore.exists("keys") else KeyStore.create("keys", wrapper)
        ...     created, notices = generate(store, p, now=now)
        ...     out = OutputPlan()
        ...     store.plan_write(out, now=now)
        ...     written = out.commit()
        >>> created
        ['key-ref:head-link', 'key-ref:arm-links']
        >>> st = status(KeyStore.open("keys", wrapper), p, now=now)
        >>> st.ok, [(row["id"], row["active_generation"]) for row in st.rows]
        (True, [('key-ref:arm-links', 1), ('key-ref:head-link', 1)])
    """
    path = Path(os.path.abspath(folder)) / LOCK_NAME
    try:
        os.makedirs(path.parent, mode=0o700, exist_ok=True)
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC, 0o600)
    except OSError as exc:
        raise InputError(f"cannot lock the key store: {exc.strerror or exc}", file=str(path)) from None
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise InputError("the key store lock is not a regular file", file=str(path))
        deadline = time.monotonic() + LOCK_WAIT_SEC
        while True:
            try:
                flock(fd, wait=False)
                break
            except BlockingIOError:
                if time.monotonic() >= deadline:
                    raise InputError(
                        f"the key store is locked by another run (waited {LOCK_WAIT_SEC:g} s)", file=str(path)
                    ) from None
                time.sleep(0.05)
        sweep_folder(path.parent)  # a killed run's staged store and its link to the previous one
        yield
    finally:
        os.close(fd)


def now_utc() -> datetime:
    """The current time, UTC, to the second: the ``now`` the key lifecycle functions take.

    Example:
        >>> from hcdf_trust.macsec.store import now_utc
        >>> now_utc().tzinfo is not None and now_utc().microsecond == 0
        True
    """
    return datetime.now(UTC).replace(microsecond=0)


@functools.lru_cache(maxsize=4096)  # a store's 10,000 generations were mostly made at one instant
def fmt_time(t: datetime) -> str:
    """``t`` in UTC, to the second (equal instants in any zone give the same text)."""
    return t.astimezone(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


def parse_time(text: Any, *, what: str, source: str) -> datetime:
    if not isinstance(text, str):
        raise KeyStoreFormatError(f"{what} is not a time string", file=source, actual=repr(text)[:40])
    try:
        t = datetime.fromisoformat(text)
    except ValueError:
        raise KeyStoreFormatError(f"{what} is not an ISO 8601 time", file=source, actual=text[:40]) from None
    if t.tzinfo is None:
        raise KeyStoreFormatError(f"{what} has no time zone", file=source, actual=text[:40])
    return t


@dataclass
class Generation:
    generation: int
    ckn: bytes
    created: datetime
    activation: datetime
    expiry: datetime | None
    nonce: bytes
    ciphertext: bytes

    def state_at(self, now: datetime) -> str:
        if now < self.activation:
            return "pending"
        if self.expiry is not None and now >= self.expiry:
            return "retired"
        return "active"

    def to_json(self, now: datetime) -> dict[str, Any]:
        return {
            "generation": self.generation,
            "ckn": self.ckn.hex(),
            "created": fmt_time(self.created),
            "activation": fmt_time(self.activation),
            "expiry": fmt_time(self.expiry) if self.expiry else None,
            "state": self.state_at(now),
            "nonce": b64(self.nonce),
            "ciphertext": b64(self.ciphertext),
        }


@dataclass
class Entry:
    """One association's key chain: its generations, oldest first."""

    ca_id: str
    kind: str
    cipher: str | None
    key_bytes: int
    source_file: str
    source_line: int | None
    generations: list[Generation]

    def current(self, now: datetime) -> Generation | None:
        """The generation devices send with at ``now``: the newest active one."""
        active = [g for g in self.generations if g.state_at(now) == "active"]
        return active[-1] if active else None

    def live(self, now: datetime) -> list[Generation]:
        """Generations a device may use at ``now`` (pending ones are distributed ahead)."""
        return [g for g in self.generations if g.state_at(now) != "retired"]


class Entries(MutableMapping[str, Entry]):
    """The store's associations, each parsed from its JSON only when first used.

    An export touches a handful of a large store's entries; everything else stays raw.
    """

    def __init__(self, raw: dict[str, str], *, source: str) -> None:
        self._raw = raw
        self._parsed: dict[str, Entry] = {}
        self._source = source

    def __getitem__(self, ca_id: str) -> Entry:
        entry = self._parsed.get(ca_id)
        if entry is None:
            if ca_id not in self._raw:
                raise KeyError(ca_id)
            entry = self._parsed[ca_id] = _entry(
                ca_id, _line(ca_id, self._raw.pop(ca_id), self._source), source=self._source
            )
        return entry

    def __setitem__(self, ca_id: str, entry: Entry) -> None:
        self._raw.pop(ca_id, None)
        self._parsed[ca_id] = entry

    def __delitem__(self, ca_id: str) -> None:
        if self._raw.pop(ca_id, None) is None:
            del self._parsed[ca_id]

    def __iter__(self) -> Iterator[str]:
        yield from list(self._parsed)
        yield from list(self._raw)

    def __len__(self) -> int:
        return len(self._parsed) + len(self._raw)

    def __contains__(self, ca_id: object) -> bool:
        return ca_id in self._parsed or ca_id in self._raw


class Background:
    """Run ``fn`` in a thread at once; :meth:`result` waits for it and returns or raises what it did.

    Opening a store is mostly scrypt and hashing, which release the GIL, so it overlaps with
    resolving and verifying the description. Nothing changes in what is checked or in which
    error comes first: the caller asks for the store only once the description is verified
    and planned (a description error is reported as when the store is opened afterwards),
    and no key is decrypted before that.
    """

    def __init__(self, fn: Callable[[], Any]) -> None:
        self._value: Any = None
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, args=(fn,), name="hcdf-trust-open-store", daemon=True)
        self._thread.start()

    def _run(self, fn: Callable[[], Any]) -> None:
        try:
            self._value = fn()
        except BaseException as exc:  # re-raised in the caller's thread by result()
            self._error = exc

    def result(self) -> Any:
        self._thread.join()
        if self._error is not None:
            raise self._error
        return self._value


def _aad(store_id: str, ca_id: str, generation: int, ckn: bytes) -> bytes:
    """Associated data binding a key to its place: NUL-separated (XML names cannot hold NUL)."""
    return f"{FORMAT}\0{store_id}\0{ca_id}\0{generation}\0{ckn.hex()}".encode()


class KeyStore:
    """An opened key store: metadata in memory, the data key unwrapped, keys decrypted on demand.

    :meth:`create` makes a new one (written by :meth:`plan_write` and the plan's commit),
    :meth:`open` reads one (a wrong passphrase raises, changing nothing). Hold :func:`locked`
    around a read-modify-write. Key bytes never leave it except through the exporters.

    Example:

        >>> import os
        >>> from hcdf_trust.macsec.backends import PassphraseWrapper
        >>> from hcdf_trust.macsec.plan import plan
        >>> from hcdf_trust.macsec.rotation import generate, status
        >>> from hcdf_trust.macsec.store import KeyStore, locked, now_utc
        >>> from hcdf_trust.outputs import OutputPlan
        >>> p = plan("examples/robot/robot.hcdf")
        >>> wrapper = PassphraseWrapper(b"correct horse battery staple")
        >>> now = now_utc()
        >>> with locked("keys"):  # one read-modify-write of the store at a time
        ...     store = KeyStore.open("keys", wrapper) if KeyStore.exists("keys") else KeyStore.create("keys", wrapper)
        ...     created, notices = generate(store, p, now=now)
        ...     out = OutputPlan()
        ...     store.plan_write(out, now=now)
        ...     written = out.commit()
        >>> created
        ['key-ref:head-link', 'key-ref:arm-links']
        >>> st = status(KeyStore.open("keys", wrapper), p, now=now)
        >>> st.ok, [(row["id"], row["active_generation"]) for row in st.rows]
        (True, [('key-ref:arm-links', 1), ('key-ref:head-link', 1)])
    """

    def __init__(
        self, path: Path, *, store_id: str, wrap: dict[str, Any], dek: bytes, robot: str | None = None
    ) -> None:
        self.path = path
        self.store_id = store_id
        self.robot = robot  # None only for a store being created, until :meth:`bind`
        self.wrap = wrap
        self._dek = dek
        self._aead: Any = None
        self.entries: MutableMapping[str, Entry] = {}
        self.changed = False

    # -- open / create ---------------------------------------------------------------------

    @staticmethod
    def file_in(folder: str | os.PathLike[str]) -> Path:
        """The store file in ``folder``, named as the user gave the folder (messages show it so)."""
        return Path(folder) / STORE_NAME

    @classmethod
    def exists(cls, folder: str | os.PathLike[str]) -> bool:
        return os.path.lexists(cls.file_in(folder))

    @classmethod
    def create(cls, folder: str | os.PathLike[str], wrapper: Wrapper) -> KeyStore:
        store_id = os.urandom(16).hex()
        dek = os.urandom(32)
        wrap = wrapper.wrap(dek, _wrap_aad(store_id))
        store = cls(cls.file_in(folder), store_id=store_id, wrap=wrap, dek=dek)
        store.changed = True
        return store

    @classmethod
    def open(cls, folder: str | os.PathLike[str], wrapper: Wrapper) -> KeyStore:
        """Read, unwrap and check a store.

        Raises:
            NotFoundError / InputError: no store, not a regular file, too large.
            KeyStoreFormatError: not a key store of a known format version.
            WrongCredentialError: the passphrase or token key does not open it.
            KeyStoreIntegrityError: its metadata was changed outside this tool.
        """
        path = cls.file_in(folder)
        source = str(path)
        raw = read_input(path, limit=MAX_STORE_BYTES, what="key store")
        header, _, lines = raw.partition(b"\n")
        try:
            doc = parse_json(header, source=source, what="key store header", limit=MAX_STORE_BYTES)
        except JsonError:
            raise KeyStoreFormatError("the key store does not start with a JSON header", file=source) from None
        if not isinstance(doc, dict) or doc.get("format") != FORMAT:
            raise KeyStoreFormatError("not an hcdf-trust MACsec key store", file=source, expected=FORMAT)
        if doc.get("version") == 1:
            raise KeyStoreFormatError(
                "key store format version 1 is not read by this hcdf-trust (version 2 authenticates the "
                "file's bytes): make a new store with `macsec generate --store NEW_DIR` and export the devices again",
                file=source,
                expected=str(FORMAT_VERSION),
                actual="1",
            )
        if doc.get("version") != FORMAT_VERSION:
            raise KeyStoreFormatError(
                "unknown key store format version",
                file=source,
                expected=str(FORMAT_VERSION),
                actual=repr(doc.get("version"))[:40],
            )
        store_id, wrap, robot = doc.get("store_id"), doc.get("wrap"), doc.get("robot")
        if not isinstance(store_id, str) or not isinstance(wrap, dict):
            raise KeyStoreFormatError("the key store has no store_id or wrap section", file=source)
        if not isinstance(robot, str) or not robot:
            raise KeyStoreFormatError(
                "the key store does not record which robot it was generated for (made by an earlier "
                "hcdf-trust): make a new store with `macsec generate --store NEW_DIR` and export the devices again",
                file=source,
                expected="a robot name",
                actual=repr(robot)[:40],
            )
        if wrap.get("method") != wrapper.method:
            raise KeyStoreFormatError(
                "the key store is protected by another backend",
                file=source,
                expected=str(wrap.get("method"))[:40],
                actual=wrapper.method,
            )
        # The lines are indexed (~23 ms for 10,000) while the data key is unwrapped (scrypt or a
        # token, without the GIL); the errors still come in the order wrong credential, MAC, format.
        unwrapping = Background(lambda: wrapper.unwrap(wrap, _wrap_aad(store_id), source=source))
        index: dict[str, str] | KeyStoreFormatError
        try:
            index = _index(lines, source=source)
        except KeyStoreFormatError as exc:
            index = exc
        dek = unwrapping.result()
        if not _mac_matches(dek, raw, doc.get("mac"), label=_STORE_MAC):
            raise KeyStoreIntegrityError(
                "the key store's metadata does not match its MAC: it was changed outside hcdf-trust", file=source
            )
        if isinstance(index, KeyStoreFormatError):
            raise index
        store = cls(path, store_id=store_id, wrap=wrap, dek=dek, robot=robot)
        store.entries = Entries(index, source=source)
        return store

    def bind(self, robot: str, *, document: str) -> None:
        """Check that this store belongs to ``robot`` (the root document's ``<hcdf name>``), or,
        for a store being created, record it.

        Raises:
            KeyStoreRobotError: the store was generated for another robot (exit 1).
            KeyStoreFormatError: a new store for a description whose root has no name.
        """
        if self.robot is None:
            if not robot:
                raise KeyStoreFormatError(
                    "the root <hcdf> has no name: a key store is bound to the robot it is generated for, by that name",
                    file=document,
                    expected="<hcdf name=...>",
                    actual="(missing)",
                )
            self.robot = robot
            self.changed = True
        elif robot != self.robot:
            raise KeyStoreRobotError(
                f"the key store was generated for robot {self.robot!r}, not for robot {robot!r} that "
                f"{document} describes: one robot's keys never go to another's devices (use that robot's store)",
                file=str(self.path),
                expected=self.robot,
                actual=robot or "(no name)",
            )

    # -- keys --------------------------------------------------------------------------------

    def _cipher(self) -> Any:
        if self._aead is None:
            from cryptography.hazmat.primitives.ciphers.aead import AESGCM

            self._aead = AESGCM(self._dek)
        return self._aead

    def known_ckns(self) -> set[bytes]:
        return {g.ckn[:16] for e in self.entries.values() for g in e.generations}

    def new_generation(
        self,
        entry: Entry,
        *,
        now: datetime,
        activation: datetime,
        ckns: set[bytes] | None = None,
        secret: bytes | None = None,
    ) -> Generation:
        """Add generation N+1 to ``entry`` with a fresh key and a CKN unique in its first 16 octets."""
        taken = ckns if ckns is not None else self.known_ckns()
        ckn = os.urandom(CKN_BYTES)
        while ckn[:16] in taken:
            ckn = os.urandom(CKN_BYTES)
        taken.add(ckn[:16])
        number = (entry.generations[-1].generation + 1) if entry.generations else 1
        nonce = os.urandom(12)
        key = os.urandom(entry.key_bytes) if secret is None else secret
        ciphertext = self._cipher().encrypt(nonce, key, _aad(self.store_id, entry.ca_id, number, ckn))
        gen = Generation(number, ckn, now, activation, None, nonce, ciphertext)
        entry.generations.append(gen)
        self.changed = True
        return gen

    def key(self, entry: Entry, gen: Generation) -> bytes:
        """Decrypt one generation's key.

        Raises:
            KeyStoreIntegrityError: the ciphertext was changed or moved.
        """
        from cryptography.exceptions import InvalidTag

        try:
            key: bytes = self._cipher().decrypt(
                gen.nonce, gen.ciphertext, _aad(self.store_id, entry.ca_id, gen.generation, gen.ckn)
            )
        except InvalidTag:
            raise KeyStoreIntegrityError(
                f"{entry.ca_id} generation {gen.generation}: the key does not decrypt (changed or moved)",
                file=str(self.path),
            ) from None
        if entry.kind in BLOB_KINDS:
            return key
        if len(key) not in (16, 32):  # a generation made before a cipher change keeps its own length
            raise KeyStoreIntegrityError(
                f"{entry.ca_id} generation {gen.generation}: the key has the wrong length",
                file=str(self.path),
                expected="16 or 32",
                actual=str(len(key)),
            )
        return key

    # -- write -----------------------------------------------------------------------------

    def serialize(self, now: datetime) -> bytes:
        if self.robot is None:  # every verb that creates a store binds it first (rotation.generate)
            raise KeyStoreFormatError("a key store is written only once bound to a robot", file=str(self.path))
        head = {
            "format": FORMAT,
            "version": FORMAT_VERSION,
            "robot": self.robot,
            "store_id": self.store_id,
            "wrap": self.wrap,
        }
        encode = line_encoder(sort_keys=True)
        lines = [encode(head)]
        for e in sorted(self.entries.values(), key=lambda e: e.ca_id):
            entry = {
                "kind": e.kind,
                "cipher": e.cipher,
                "key_bytes": e.key_bytes,
                "source": json_locations({"file": e.source_file, "line": e.source_line}),
                "generations": [g.to_json(now) for g in e.generations],
            }
            lines.append(encode([e.ca_id, entry]))
        return _seal(self._dek, ("\n".join(lines) + "\n").encode(), label=_STORE_MAC)

    def seal(self, body: bytes, *, label: bytes) -> bytes:
        """``body`` (JSON Lines, a header object first) with a ``"mac"`` first in its header:
        HMAC-SHA256 of the body under a key derived from the data key for ``label`` (a file
        other than the store, e.g. the export index, uses its own label)."""
        return _seal(self._dek, body, label=label)

    def sealed(self, raw: bytes, parsed_mac: Any, *, label: bytes) -> bool:
        """Whether :meth:`seal` of this store made ``raw`` (whose header's ``mac`` is ``parsed_mac``)."""
        return _mac_matches(self._dek, raw, parsed_mac, label=label)

    def plan_write(self, plan: OutputPlan, *, now: datetime) -> None:
        """Add the store file to ``plan`` (mode 0600); the caller commits."""
        plan.add(self.path, self.serialize(now), flag="--store", mode=0o600, replaces=(KEY_STORE,))


def line_encoder(*, sort_keys: bool) -> Callable[[Any], str]:
    """``json.JSONEncoder(sort_keys=sort_keys, separators=(",", ":")).encode``, the same text,
    for files of 10,000 short lines: ``encode`` builds json's C encoder at every call (half the
    time of a short line), this builds it once. Compact, since ``indent`` is pure Python."""
    from json.encoder import c_make_encoder, encode_basestring_ascii  # type: ignore[attr-defined]

    if c_make_encoder is None:  # an interpreter without json's C accelerator
        return json.JSONEncoder(sort_keys=sort_keys, separators=(",", ":")).encode
    # (markers, default, encoder, indent, key_separator, item_separator, sort_keys, skipkeys, allow_nan)
    chunks = c_make_encoder(None, None, encode_basestring_ascii, None, ":", ",", sort_keys, False, True)
    return lambda value: "".join(chunks(value, 0))


def _wrap_aad(store_id: str) -> bytes:
    return json.dumps([FORMAT, FORMAT_VERSION, store_id]).encode()


_STORE_MAC = b"hcdf-trust macsec store mac"


def _mac(dek: bytes, body: bytes, *, label: bytes) -> str:
    """HMAC-SHA256 of a serialised body (the file without its ``mac``), under a key derived from the data key."""
    mac_key = hmac.new(dek, label, hashlib.sha256).digest()
    return hmac.new(mac_key, body, hashlib.sha256).hexdigest()


def _seal(dek: bytes, body: bytes, *, label: bytes) -> bytes:
    return b'{"mac":"' + _mac(dek, body, label=label).encode() + b'",' + body[1:]


_MAC_FIRST = re.compile(rb'\{"mac":"([0-9a-f]{64})",')


def _mac_matches(dek: bytes, raw: bytes, parsed_mac: Any, *, label: bytes) -> bool:
    """Whether ``raw`` is ``{"mac":HEX,`` followed by the rest of a body (``{`` + that rest) whose MAC is HEX."""
    head = _MAC_FIRST.match(raw)
    if head is None or parsed_mac != head.group(1).decode():
        return False
    return hmac.compare_digest(head.group(1).decode(), _mac(dek, b"{" + raw[head.end() :], label=label))


_ID = json.JSONDecoder()


def _index(lines: bytes, *, source: str) -> dict[str, str]:
    """CA id -> its (still unparsed) line, for the association lines after the header."""
    try:
        text = lines.decode()
    except UnicodeDecodeError:
        raise KeyStoreFormatError("the key store is not UTF-8", file=source) from None
    if not text.endswith("\n") and text:
        raise KeyStoreFormatError("the key store does not end with a newline", file=source)
    out: dict[str, str] = {}
    for number, line in enumerate(text[:-1].split("\n") if text else [], start=2):
        try:
            ca_id = _ID.raw_decode(line, 1)[0] if line.startswith('["') else None
        except ValueError:
            ca_id = None
        if not isinstance(ca_id, str) or ca_id in out:
            raise KeyStoreFormatError(f"line {number} of the key store is not an association", file=source)
        out[ca_id] = line
    return out


def _line(ca_id: str, line: str, source: str) -> Any:
    """The association object of one ``[CA_ID, {...}]`` line."""
    try:
        item = parse_json(line.encode(), source=source, limit=MAX_STORE_BYTES)
    except JsonError:
        item = None
    if not isinstance(item, list) or len(item) != 2 or item[0] != ca_id:
        raise KeyStoreFormatError(f"association {ca_id!r} is malformed", file=source)
    return item[1]


def _source_line(line: Any, pointer: Any) -> int | None:
    """Where the association is described: a line (XML), or the JSON Pointer a JSON document's
    element was written at (``"line": null, "pointer": "/hcdf/..."``, as ``--json`` writes it).
    The store keeps no document order: the Pointer is 1, so that it is set and prints."""
    if type(line) is int:
        return line
    return Pointer(1, pointer) if isinstance(pointer, str) and pointer.startswith("/") else None


def _entry(ca_id: str, raw: Any, *, source: str) -> Entry:
    where = f"association {ca_id!r}"
    if not isinstance(raw, dict) or not isinstance(raw.get("generations"), list):
        raise KeyStoreFormatError(f"{where} is malformed", file=source)
    key_bytes = raw.get("key_bytes")
    if key_bytes not in (16, 32) and not (raw.get("kind") in BLOB_KINDS and key_bytes == 0):
        raise KeyStoreFormatError(f"{where}: key_bytes is not 16 or 32", file=source, actual=repr(key_bytes)[:40])
    src_raw = raw.get("source")
    src: dict[str, Any] = src_raw if isinstance(src_raw, dict) else {}
    line = src.get("line")
    gens = []
    for g in raw["generations"]:
        if not isinstance(g, dict) or type(g.get("generation")) is not int:
            raise KeyStoreFormatError(f"{where}: a generation is malformed", file=source)
        label = f"{where} generation {g['generation']}"
        ckn_text = g.get("ckn")
        try:
            ckn = bytes.fromhex(ckn_text) if isinstance(ckn_text, str) else b""
        except ValueError:
            ckn = b""
        if not 1 <= len(ckn) <= 32:
            raise KeyStoreFormatError(f"{label}: ckn is not 1..32 octets of hex", file=source)
        expiry = g.get("expiry")
        gens.append(
            Generation(
                generation=g["generation"],
                ckn=ckn,
                created=parse_time(g.get("created"), what=f"{label} created", source=source),
                activation=parse_time(g.get("activation"), what=f"{label} activation", source=source),
                expiry=None if expiry is None else parse_time(expiry, what=f"{label} expiry", source=source),
                nonce=unb64(g.get("nonce"), what=f"{label} nonce", source=source),
                ciphertext=unb64(g.get("ciphertext"), what=f"{label} ciphertext", source=source),
            )
        )
    return Entry(
        ca_id=ca_id,
        kind=str(raw.get("kind")),
        cipher=raw.get("cipher") if isinstance(raw.get("cipher"), str) else None,
        key_bytes=key_bytes,
        source_file=str(src.get("file")),
        source_line=_source_line(line, src.get("pointer")),
        generations=gens,
    )
