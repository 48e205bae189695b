"""Key lifecycle over a plan and a store: generate, status, rotate, retire (no I/O here).

The key-chain model (send and accept lifetimes, as in Cisco/Juniper MACsec key chains):
``rotate`` adds generation N+1 as *pending* with ``activation = now + overlap`` and sets
the current generation's ``expiry = activation + overlap``. Exports made in between carry
both generations, so every device holds the new key before anyone sends with it and still
accepts the old one after. ``retire`` removes only generations past their expiry, and only
when a newer generation is already active: never the key a device may still be using.

``rekey-interval-sec`` is applied as the CAK rotation cadence (``status`` says *due*,
``rotate --due`` acts): wpa_supplicant has no periodic SAK rekey, it rekeys the SAK itself
on packet-number exhaustion and on peer changes.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from datetime import datetime, timedelta
from typing import Any

from ..errors import HcdfTrustError, InputError, IntegrityError, Notice
from .kdf import key_check_value
from .plan import Association, Plan
from .store import BLOB_KINDS, Entry, KeyStore, fmt_time

DEFAULT_OVERLAP_SEC = 3600

# The public API (docs/api.md); everything else here is internal.
__all__ = ["Status", "generate", "retire", "rotate", "status"]


class RotationError(InputError):
    code = "macsec-rotation"


class NoUsableKeyError(IntegrityError):
    """A described association has no generation devices can send with now (``status`` exits 1)."""

    code = "macsec-no-key"


def _new_entry(ca: Association) -> Entry:
    return Entry(
        ca_id=ca.id,
        kind=ca.kind,
        cipher=ca.policy.cipher if ca.policy else None,
        key_bytes=ca.key_bytes,
        source_file=ca.file,
        source_line=ca.line,
        generations=[],
    )


def _supported(ca: Association) -> bool:
    return ca.policy is None or ca.policy.key_agreement == "psk"


def generate(store: KeyStore, plan: Plan, *, now: datetime) -> tuple[list[str], list[Notice]]:
    """Create every missing key; return the CA ids keyed now and notices. Existing keys are untouched.
    The store changes in memory: write it with :meth:`KeyStore.plan_write` and commit.

    Raises:
        KeyStoreRobotError: the store was generated for another robot (a new store is bound to this one).

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
    store.bind(plan.robot, document=plan.document)
    created: list[str] = []
    notices: list[Notice] = []
    taken = store.known_ckns()
    for ca in plan.keyed():
        if not _supported(ca):
            created += _eap_tls(store, ca, now=now, ckns=taken)
            continue
        entry = store.entries.get(ca.id)
        if entry is None:
            entry = store.entries[ca.id] = _new_entry(ca)
        if not entry.generations:
            store.new_generation(entry, now=now, activation=now, ckns=taken)
            created.append(ca.id)
        elif entry.key_bytes != ca.key_bytes:
            notices.append(
                Notice(
                    "macsec-cipher-changed",
                    f"{ca.id}: the description now asks for {ca.key_bytes}-byte keys ({entry.cipher} → "
                    f"{ca.policy.cipher if ca.policy else '?'}); run `macsec rotate --key-ref`/`--network` for it",
                    file=ca.file,
                    line=ca.line,
                )
            )
    return created, notices


def _eap_tls(store: KeyStore, ca: Association, *, now: datetime, ckns: set[bytes]) -> list[str]:
    """The network CA and each member's certificate for an eap-tls association, made when missing."""
    from . import eaptls
    from .store import Entry

    made = []
    network = ca.elements[0].network

    def entry(entry_id: str, kind: str) -> Entry:
        found = store.entries.get(entry_id)
        if found is None:
            found = store.entries[entry_id] = Entry(entry_id, kind, None, 0, ca.file, ca.line, [])
        return found

    ca_entry = entry(eaptls.ca_id(network), "eap-tls-ca")
    if not ca_entry.generations:
        store.new_generation(ca_entry, now=now, activation=now, ckns=ckns, secret=eaptls.make_ca(network, now))
        made.append(ca_entry.ca_id)
    ca_bundle = store.key(ca_entry, ca_entry.generations[-1])
    for device in ca.members:
        dev_entry = entry(eaptls.cert_id(network, device), "eap-tls-cert")
        if not dev_entry.generations:
            secret = eaptls.make_cert(ca_bundle, device, now)
            store.new_generation(dev_entry, now=now, activation=now, ckns=ckns, secret=secret)
            made.append(dev_entry.ca_id)
    return made


def eap_ids(ca: Association) -> list[str]:
    """The store entries an eap-tls association needs."""
    from . import eaptls

    network = ca.elements[0].network
    return [eaptls.ca_id(network), *(eaptls.cert_id(network, d) for d in ca.members)]


def is_due(entry: Entry, ca: Association | None, now: datetime) -> bool:
    current = entry.current(now)
    if current is None or ca is None or ca.policy is None or not ca.policy.rekey_interval_sec:
        return False
    pending = any(g.state_at(now) == "pending" for g in entry.generations)
    age = (now - current.activation).total_seconds()
    return not pending and age >= ca.policy.rekey_interval_sec


def select(plan: Plan, *, network: str | None, key_ref: str | None) -> list[Association]:
    """The keyed associations ``rotate`` is asked for (all when neither filter is given)."""
    out = []
    for ca in plan.keyed():
        if not _supported(ca):
            continue  # eap-tls: certificates, renewed by re-issuing, not by CAK rotation
        if network is not None and not any(e.network == network for e in ca.elements):
            continue
        if key_ref is not None and ca.key_ref != key_ref:
            continue
        out.append(ca)
    if not out:
        what = " and ".join(
            x for x in (f"network {network!r}" if network else "", f"key-ref {key_ref!r}" if key_ref else "") if x
        )
        raise RotationError(f"no psk association matches {what or 'the description'}", file=plan.document)
    return out


def rotate(
    store: KeyStore,
    cas: list[Association],
    *,
    now: datetime,
    overlap: int = DEFAULT_OVERLAP_SEC,
    due_only: bool = False,
) -> list[tuple[str, int, datetime]]:
    """Add a pending generation to each CA in ``cas``; return (ca id, generation, activation).
    Activation is ``now + overlap`` seconds; the current generation expires ``overlap`` later.

    Raises:
        RotationError: a CA has no key yet, or already has a pending generation.

    Example (after :func:`generate`, below; write the store again as there):

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
        >>> from hcdf_trust.macsec.rotation import rotate
        >>> store = KeyStore.open("keys", wrapper)
        >>> [(ca_id, gen) for ca_id, gen, _ in rotate(store, [p.associations["key-ref:head-link"]], now=now)]
        [('key-ref:head-link', 2)]
    """
    errors: list[HcdfTrustError] = []
    todo: list[tuple[Association, Entry]] = []
    for ca in cas:
        entry = store.entries.get(ca.id)
        if entry is None or not entry.generations:
            errors.append(
                RotationError(f"{ca.id} has no key yet: run `macsec generate` first", file=ca.file, line=ca.line)
            )
            continue
        if due_only and not is_due(entry, ca, now):
            continue
        pending = [g for g in entry.generations if g.state_at(now) == "pending"]
        if pending:
            errors.append(
                RotationError(
                    f"{ca.id} already has generation {pending[0].generation} pending until "
                    f"{fmt_time(pending[0].activation)}",
                    file=ca.file,
                    line=ca.line,
                )
            )
            continue
        todo.append((ca, entry))
    if errors:
        from ..errors import ErrorGroup

        raise ErrorGroup(errors)
    done = []
    taken = store.known_ckns()
    for ca, entry in todo:
        activation = now + timedelta(seconds=overlap)
        accept_until = activation + timedelta(seconds=overlap)
        for old in entry.generations:
            if old.expiry is None or old.expiry > accept_until:
                old.expiry = accept_until
        entry.key_bytes = ca.key_bytes
        entry.cipher = ca.policy.cipher if ca.policy else None
        gen = store.new_generation(entry, now=now, activation=activation, ckns=taken)
        done.append((ca.id, gen.generation, activation))
    return done


def retire(store: KeyStore, *, now: datetime, real_now: datetime | None = None) -> list[tuple[str, int]]:
    """Remove generations past their expiry whose successor is active; return what was removed.

    ``now`` (``--now``) can only make retiring more careful, never less: a generation is
    removed only if it is retired, and a successor active, both at ``now`` and at the real
    current time (``real_now``, the clock by default). Retirement is monotone in time, so
    that is the earlier of the two: ``retire --now <future>`` never removes the key devices
    send with today.

    Example (right after a rotation nothing can be retired yet):

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
        >>> from hcdf_trust.macsec.rotation import retire, rotate
        >>> store = KeyStore.open("keys", wrapper)
        >>> _ = rotate(store, p.keyed(), now=now)
        >>> retire(store, now=now)
        []
    """
    from .store import now_utc

    real = now_utc() if real_now is None else real_now
    now = min(now, real)
    removed = []
    for entry in store.entries.values():
        if entry.current(now) is None:
            continue  # never leave an association without the key devices use
        keep = []
        for g in entry.generations:
            if g.state_at(now) == "retired":
                removed.append((entry.ca_id, g.generation))
            else:
                keep.append(g)
        if len(keep) != len(entry.generations):
            entry.generations = keep
            store.changed = True
    return removed


def _check_value(store: KeyStore, entry: Entry, gen: Any) -> str:
    """A key check value; for a certificate entry, the certificate's SHA-256 (first 3 octets)."""
    secret = store.key(entry, gen)
    if entry.kind in BLOB_KINDS:
        import hashlib

        from .eaptls import split

        return hashlib.sha256(split(secret)[1]).hexdigest()[:6]
    return key_check_value(secret, gen.ckn)


@dataclass
class Status:
    """What ``macsec status`` reports: one row per association with a key (``id``,
    ``active_generation``, ``age_sec``, ``due``, ``generations`` with key check values), the
    described ones without a key (``missing``), keys no longer described (``orphaned``), and
    the errors that make ``macsec status`` exit 1 (``problems``; ``ok`` when none).

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

    rows: list[dict[str, Any]] = field(default_factory=list)
    missing: list[str] = field(default_factory=list)  # in the description, no key
    orphaned: list[str] = field(default_factory=list)  # keys for associations no longer described
    problems: list[HcdfTrustError] = field(default_factory=list)  # described, and no usable key now

    @property
    def ok(self) -> bool:
        return not self.problems

    def to_dict(self) -> dict[str, Any]:
        return {"associations": self.rows, "missing": self.missing, "orphaned": self.orphaned}


def status(store: KeyStore, plan: Plan, *, now: datetime) -> Status:
    """Per CA: the active generation, its age, whether it is due, pending ones, key check values.

    Raises:
        KeyStoreRobotError: the store was generated for another robot.

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
    store.bind(plan.robot, document=plan.document)
    out = Status()
    described = {ca.id: ca for ca in plan.keyed() if _supported(ca)}
    eap = {i for ca in plan.keyed() if not _supported(ca) for i in eap_ids(ca)}
    where = {ca.id: ca for ca in plan.keyed()}
    for ca_id in [*described, *sorted(eap)]:
        ca = described.get(ca_id) or next((c for c in where.values() if ca_id in eap_ids(c)), None)
        file, line = (ca.file, ca.line) if ca is not None else (plan.document, None)
        if ca_id not in store.entries or not store.entries[ca_id].generations:
            out.missing.append(ca_id)
            out.problems.append(NoUsableKeyError(f"{ca_id} has no key: run `macsec generate`", file=file, line=line))
        elif store.entries[ca_id].current(now) is None:
            states = ", ".join(f"g{g.generation} {g.state_at(now)}" for g in store.entries[ca_id].generations)
            out.problems.append(
                NoUsableKeyError(
                    f"{ca_id} has no generation active at {fmt_time(now)} ({states}): its devices have no key "
                    f"to send with; run `macsec rotate` for it and export again",
                    file=file,
                    line=line,
                )
            )
    for ca_id, entry in sorted(store.entries.items()):
        ca = described.get(ca_id)
        if ca is None and ca_id not in eap:
            out.orphaned.append(ca_id)
        current = entry.current(now)
        gens = []
        for g in entry.generations:
            gens.append(
                {
                    "generation": g.generation,
                    "state": g.state_at(now),
                    "created": fmt_time(g.created),
                    "activation": fmt_time(g.activation),
                    "expiry": fmt_time(g.expiry) if g.expiry else None,
                    "kcv": _check_value(store, entry, g),
                }
            )
        out.rows.append(
            {
                "id": ca_id,
                "described": ca is not None or ca_id in eap,
                "cipher": entry.cipher,
                "active_generation": current.generation if current else None,
                "age_sec": int((now - current.activation).total_seconds()) if current else None,
                "rekey_interval_sec": ca.policy.rekey_interval_sec if ca and ca.policy else None,
                "due": is_due(entry, ca, now),
                "source": {"file": entry.source_file, "line": entry.source_line},
                "generations": gens,
            }
        )
    return out
