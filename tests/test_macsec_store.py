"""macsec generate / status / rotate / retire: the encrypted key store and its lifecycle."""

from __future__ import annotations

import json
import os
import stat
import subprocess
import sys
from datetime import UTC, datetime
from pathlib import Path

import pytest

from hcdf_trust.macsec.backends import PassphraseWrapper, WrongCredentialError
from hcdf_trust.macsec.store import INDEX_NAME, STORE_NAME, Entries, KeyStore, KeyStoreIntegrityError

from ._macsec import KILLER, comp, hcdf, link, port, store_lines, tree, write_store_lines

PROJECT = Path(__file__).resolve().parents[1]
T0 = "2026-01-01T00:00:00Z"
PASS = b"correct horse battery staple"
CIPHERS = ("gcm-aes-128", "gcm-aes-256", "gcm-aes-xpn-128", "gcm-aes-xpn-256")


def _doc(tmp: Path, rekey: str = "", extra_links: str = "") -> Path:
    all_ciphers = CIPHERS
    devices = comp("a", *(port(f"p{i}", *all_ciphers) for i in range(6))) + comp(
        "b", *(port(f"p{i}", *all_ciphers) for i in range(6))
    )
    links = [
        link(f"l{i}", f"a/p{i}", f"b/p{i}", f'<macsec policy="must-secure" cipher="{c}" key-ref="k{i}"/>')
        for i, c in enumerate(CIPHERS)
    ]
    body = [
        devices,
        '<network name="n">',
        *links,
        link("plain", "a/p4", "b/p4"),
        extra_links,
        f'<mesh name="m" standard="802.15.4" network-key-ref="mesh"><node device="a" antenna="x"/></mesh>'
        f'<macsec policy="should-secure"{rekey}/>',
        "</network>",
    ]
    return tree(tmp, {"robot.hcdf": hcdf(*body)})


@pytest.fixture
def env(tmp_path, cli):
    """A described robot, a passphrase file and a store folder."""
    doc = _doc(tmp_path)
    pp = tmp_path / "pass"
    pp.write_bytes(PASS + b"\n")
    store = tmp_path / "keys"

    def run(verb: str, *args: str | os.PathLike[str], passphrase: Path = pp, with_doc: bool = True):
        head = [verb, doc] if with_doc else [verb]
        return cli("macsec", *head, "--store", store, "--passphrase-file", passphrase, *args)

    return doc, store, run


def _open(store: Path) -> KeyStore:
    return KeyStore.open(store, PassphraseWrapper(PASS))


def _all_keys(store: Path) -> list[str]:
    ks = _open(store)
    return [ks.key(e, g).hex() for e in ks.entries.values() for g in e.generations]


def test_key_lengths_ckns_and_mode(env):
    _doc_path, store, run = env
    r = run("generate", "--now", T0, "--json")
    assert r.exit_code == 0, r.stderr
    created = set(r.json["created"])
    assert created == {"key-ref:k0", "key-ref:k1", "key-ref:k2", "key-ref:k3", "link:n/plain", "mesh-key:mesh"}
    ks = _open(store)
    lengths = {ca: len(ks.key(e, e.generations[0])) for ca, e in ks.entries.items()}
    assert lengths == {
        "key-ref:k0": 16,
        "key-ref:k1": 32,
        "key-ref:k2": 16,
        "key-ref:k3": 32,
        "link:n/plain": 16,
        "mesh-key:mesh": 16,
    }
    ckns = [g.ckn for e in ks.entries.values() for g in e.generations]
    assert all(len(c) == 16 for c in ckns) and len({c[:16] for c in ckns}) == len(ckns)
    keys = [ks.key(e, g) for e in ks.entries.values() for g in e.generations]
    assert len(set(keys)) == len(keys)
    assert stat.S_IMODE(os.stat(store / STORE_NAME).st_mode) == 0o600
    assert stat.S_IMODE(os.stat(store).st_mode) == 0o700
    entry = ks.entries["key-ref:k1"]
    assert entry.source_file.endswith("robot.hcdf") and entry.source_line == 6
    g = entry.generations[0]
    assert (g.generation, g.created, g.activation, g.expiry) == (1, datetime(2026, 1, 1, tzinfo=UTC), g.created, None)


def test_generate_twice_changes_nothing(env):
    _doc_path, store, run = env
    assert run("generate").exit_code == 0
    path = store / STORE_NAME
    before, st = path.read_bytes(), os.stat(path)
    r = run("generate", "--json")
    assert r.exit_code == 0 and r.json["created"] == []
    after = os.stat(path)
    assert path.read_bytes() == before and (after.st_ino, after.st_mtime_ns) == (st.st_ino, st.st_mtime_ns)


def test_wrong_passphrase_is_exit_3_and_changes_nothing(env, tmp_path):
    _doc_path, store, run = env
    assert run("generate", "--now", T0).exit_code == 0
    before = (store / STORE_NAME).read_bytes()
    wrong = tmp_path / "wrong"
    wrong.write_text("Tr0ub4dor&3\n")
    for verb, args in [("generate", ()), ("rotate", ("--now", T0)), ("status", ())]:
        r = run(verb, *args, passphrase=wrong)
        assert r.exit_code == 3, (verb, r.stderr)
        assert "wrong passphrase" in r.stderr
    assert run("retire", passphrase=wrong, with_doc=False).exit_code == 3
    assert (store / STORE_NAME).read_bytes() == before


def test_a_failing_description_is_reported_before_a_wrong_passphrase(env, tmp_path):
    # status and export open the store while the description is verified: the description's
    # error still comes first, as when the store is opened afterwards
    doc, store, run = env
    assert run("generate", "--now", T0).exit_code == 0
    wrong = tmp_path / "wrong"
    wrong.write_text("Tr0ub4dor&3\n")
    doc.write_text(doc.read_text().replace('policy="must-secure"', 'policy="bogus"'))
    for verb, args in [("status", ()), ("export", ("--device", "a", "--format", "json", "--out", tmp_path / "o"))]:
        for passphrase in (wrong, tmp_path / "missing"):
            r = run(verb, *args, passphrase=passphrase)
            assert r.exit_code == 3 and "<macsec policy> is not one of" in r.stderr, (verb, r.stderr)
            assert "passphrase" not in r.stderr and STORE_NAME not in r.stderr
    assert not (tmp_path / "o").exists()


def test_generate_for_a_failing_description_makes_no_store(env, tmp_path):
    # the new store's data key is wrapped while the description is verified: nothing is written
    doc, store, run = env
    doc.write_text(doc.read_text().replace('policy="must-secure"', 'policy="bogus"'))
    r = run("generate")
    assert r.exit_code == 3 and "<macsec policy> is not one of" in r.stderr
    assert not (store / STORE_NAME).exists()
    r = run("generate", passphrase=tmp_path / "missing")
    assert r.exit_code == 3 and "<macsec policy> is not one of" in r.stderr and "passphrase" not in r.stderr


def test_passphrase_sources(env, cli, monkeypatch):
    doc, store, _run = env
    monkeypatch.delenv("HCDF_TRUST_PASSPHRASE", raising=False)
    r = cli("macsec", "generate", doc, "--store", store)
    assert r.exit_code == 3 and "never taken on the command line" in r.stderr
    assert not store.exists()
    monkeypatch.setenv("HCDF_TRUST_PASSPHRASE", PASS.decode())
    assert cli("macsec", "generate", doc, "--store", store).exit_code == 0
    assert _open(store).entries  # same passphrase, from the environment
    # no --passphrase option exists: a secret on the command line is a usage error
    assert cli("macsec", "status", doc, "--store", store, "--passphrase", "x").exit_code == 2


def test_no_key_material_in_any_output(env):
    _doc_path, store, run = env
    outputs = [run("generate", "--now", T0), run("generate", "--now", T0, "--json")]
    outputs += [run("rotate", "--now", T0, "--key-ref", "k1", "--json"), run("status", "--now", T0, "--json")]
    outputs += [run("status", "--now", T0)]
    keys = _all_keys(store)
    assert len(keys) == 7
    outputs += [run("retire", "--now", "2027-01-01T00:00:00Z", with_doc=False)]
    for r in outputs:
        assert r.exit_code == 0, r.stderr
        for key in keys:
            for text in (r.stdout, r.stderr):
                assert key not in text.lower() and key[:16] not in text.lower()


def test_tampered_store_is_an_integrity_error(env):
    _doc_path, store, run = env
    assert run("generate", "--now", T0).exit_code == 0
    path = store / STORE_NAME
    head, assocs = store_lines(path)
    assocs["key-ref:k0"]["generations"][0]["activation"] = "2030-01-01T00:00:00Z"
    write_store_lines(path, head, assocs)
    r = run("status")
    assert r.exit_code == 1 and "changed outside" in r.stderr


def test_every_byte_is_authenticated(env):
    # the MAC covers the file's bytes, not a re-serialisation: a change json.loads cannot see
    # (a space, a reordered key) is refused like a changed time
    _doc_path, store, run = env
    assert run("generate", "--now", T0).exit_code == 0
    path = store / STORE_NAME
    good = path.read_bytes()
    at = good.index(b'"created":"2026-01-01T00:00:00Z"')
    changes = [
        good[:at] + b'"created": "2026-01-01T00:00:00Z"' + good[at + 32 :],  # one space: same JSON
        good.replace(b'"cipher":"gcm-aes-128","generations"', b'"generations"', 1).replace(
            b'"key_bytes":16,', b'"key_bytes":16,"cipher":"gcm-aes-128",', 1
        ),
        good[:at] + b'"created":"2026-01-01T00:00:01Z"' + good[at + 32 :],
        good.replace(b'{"mac":"', b'{ "mac":"', 1),
        good + b"\n",
    ]
    for data in changes:
        assert data != good and all(json.loads(line) for line in data.splitlines() if line)
        path.write_bytes(data)
        r = run("status")
        assert r.exit_code == 1 and "changed outside" in r.stderr, r.stderr
    path.write_bytes(good)
    assert run("status").exit_code == 0


def test_open_parses_only_the_associations_used(env):
    _doc_path, store, run = env
    assert run("generate", "--now", T0).exit_code == 0
    ks = _open(store)
    entries = ks.entries
    assert isinstance(entries, Entries) and len(entries) == 6 and not entries._parsed  # 5 links, 1 mesh
    entry = entries["key-ref:k1"]
    assert list(entries._parsed) == ["key-ref:k1"] and ks.key(entry, entry.generations[0])
    assert "mesh-key:mesh" in entries and len(entries._parsed) == 1


def test_a_version_1_store_is_refused_with_a_reason(env):
    _doc_path, store, run = env
    store.mkdir()
    (store / STORE_NAME).write_text(json.dumps({"format": "hcdf-trust-macsec-store", "version": 1, "mac": "00"}))
    r = run("status")
    assert r.exit_code == 3 and "format version 1 is not read" in r.stderr and "macsec generate" in r.stderr


def test_a_ciphertext_moved_to_another_association_does_not_decrypt(env):
    _doc_path, store, run = env
    assert run("generate").exit_code == 0
    ks = _open(store)
    a, b = ks.entries["key-ref:k0"], ks.entries["link:n/plain"]
    a.generations[0].ciphertext, a.generations[0].nonce = b.generations[0].ciphertext, b.generations[0].nonce
    with pytest.raises(KeyStoreIntegrityError):
        ks.key(a, a.generations[0])


@pytest.mark.parametrize(
    "content",
    [
        b"",
        b"[]",
        b"[" * 100_000 + b"]" * 100_000,
        b'{"format": "hcdf-trust-macsec-store", "version": 3}',
        b'{"format": "hcdf-trust-macsec-store", "version": 2}',
        b'{"format": "hcdf-trust-macsec-store", "version": 2, "store_id": "x", "wrap": {"method": "scrypt", '
        b'"n": 1073741824, "r": 8, "p": 1, "salt": "", "nonce": "", "wrapped_key": ""}}',
        b'{"format": "hcdf-trust-macsec-store", "version": 2, "store_id": "x", "wrap": {"method": "pkcs99"}}',
    ],
)
def test_hostile_store_files(env, content):
    _doc_path, store, run = env
    store.mkdir()
    (store / STORE_NAME).write_bytes(content)
    r = run("status")
    assert r.exit_code == 3, r.stderr
    assert "Traceback" not in r.stderr and STORE_NAME in r.stderr


def test_fifo_store_is_refused_at_once(env):
    _doc_path, store, run = env
    store.mkdir()
    os.mkfifo(store / STORE_NAME)
    r = run("status")
    assert r.exit_code == 3
    assert "not a regular file (a FIFO)" in r.stderr


# --- rotation ----------------------------------------------------------------------------


def _entries(store: Path) -> dict[str, dict]:
    return store_lines(store / STORE_NAME)[1]


def test_rotate_overlap_retire_lifecycle(env):
    _doc_path, store, run = env
    assert run("generate", "--now", T0).exit_code == 0
    before = _entries(store)
    r = run("rotate", "--now", T0, "--key-ref", "k1", "--overlap", "600", "--json")
    assert r.exit_code == 0, r.stderr
    assert r.json["rotated"] == [{"id": "key-ref:k1", "generation": 2, "activation": "2026-01-01T00:10:00Z"}]
    after = _entries(store)
    # one entry's ciphertext written: every other entry and generation 1 are byte-identical
    assert {k: v for k, v in after.items() if k != "key-ref:k1"} == {
        k: v for k, v in before.items() if k != "key-ref:k1"
    }
    g1_before, (g1, g2) = before["key-ref:k1"]["generations"][0], after["key-ref:k1"]["generations"]
    assert (g1["ciphertext"], g1["nonce"], g1["ckn"]) == (g1_before["ciphertext"], g1_before["nonce"], g1_before["ckn"])
    assert g1["expiry"] == "2026-01-01T00:20:00Z" and g2["state"] == "pending" and g2["ckn"] != g1["ckn"]

    def states(now: str) -> list[str]:
        row = next(r for r in run("status", "--now", now, "--json").json["associations"] if r["id"] == "key-ref:k1")
        return [g["state"] for g in row["generations"]]

    assert states("2026-01-01T00:05:00Z") == ["active", "pending"]
    assert states("2026-01-01T00:15:00Z") == ["active", "active"]  # overlap: both accepted
    assert states("2026-01-01T00:25:00Z") == ["retired", "active"]
    # a second rotation while one is pending is refused
    assert run("rotate", "--now", "2026-01-01T00:05:00Z", "--key-ref", "k1").exit_code == 3
    # retire removes only what is past its overlap
    r = run("retire", "--now", "2026-01-01T00:15:00Z", "--json", with_doc=False)
    assert r.exit_code == 0 and r.json["retired"] == []
    r = run("retire", "--now", "2026-01-01T00:25:00Z", "--json", with_doc=False)
    assert r.json["retired"] == [{"id": "key-ref:k1", "generation": 1}]
    assert [g["generation"] for g in _entries(store)["key-ref:k1"]["generations"]] == [2]


def test_rotate_due_follows_rekey_interval(tmp_path, cli):
    doc = _doc(tmp_path, rekey=' rekey-interval-sec="100"')
    pp = tmp_path / "pass"
    pp.write_bytes(PASS)
    store = tmp_path / "keys"
    base = ["--store", store, "--passphrase-file", pp]
    assert cli("macsec", "generate", doc, *base, "--now", T0).exit_code == 0

    def due(now: str) -> set[str]:
        rows = cli("macsec", "status", doc, *base, "--now", now, "--json").json["associations"]
        return {r["id"] for r in rows if r["due"]}

    # the network-wide interval reaches every link (overrides inherit it); a mesh key has none
    macsec_cas = {"key-ref:k0", "key-ref:k1", "key-ref:k2", "key-ref:k3", "link:n/plain"}
    assert due("2026-01-01T00:01:00Z") == set()
    assert due("2026-01-01T00:02:00Z") == macsec_cas
    r = cli("macsec", "rotate", doc, *base, "--now", "2026-01-01T00:01:00Z", "--due", "--json")
    assert r.json["rotated"] == []
    r = cli("macsec", "rotate", doc, *base, "--now", "2026-01-01T00:02:00Z", "--due", "--network", "n", "--json")
    assert {x["id"] for x in r.json["rotated"]} == macsec_cas
    assert due("2026-01-01T00:02:30Z") == set()  # pending: not due again


def test_status_missing_and_orphaned(env, tmp_path):
    doc, store, run = env
    assert run("generate", "--now", T0).exit_code == 0
    from ._macsec import lock

    text = doc.read_text().replace(link("plain", "a/p4", "b/p4"), link("fresh", "a/p5", "b/p5"))
    doc.write_text(text)
    lock(doc)
    out = run("status", "--json").json
    assert out["missing"] == ["link:n/fresh"] and out["orphaned"] == ["link:n/plain"]


# --- interrupted writes ------------------------------------------------------------------


@pytest.mark.parametrize("when", ["before", "after"])
def test_killed_rotation_leaves_the_store_before_or_after(env, tmp_path, when):
    doc, store, run = env
    assert run("generate", "--now", T0).exit_code == 0
    before = (store / STORE_NAME).read_bytes()
    args = ["macsec", "rotate", str(doc), "--store", str(store), "--passphrase-file", str(tmp_path / "pass")]
    cmd = [sys.executable, "-c", KILLER, when, STORE_NAME, *args, "--now", T0]
    proc = subprocess.run(cmd, cwd=PROJECT, capture_output=True, timeout=60)
    assert proc.returncode == -9, proc.stderr
    after = (store / STORE_NAME).read_bytes()
    ks = _open(store)  # opens and verifies either way: never in between
    gens = {ca: [g.generation for g in e.generations] for ca, e in ks.entries.items()}
    if when == "before":
        assert after == before and set(map(len, gens.values())) == {1}
    else:
        assert after != before and set(map(len, gens.values())) == {2}
    for e in ks.entries.values():
        for g in e.generations:
            ks.key(e, g)


@pytest.mark.parametrize("when", ["before", "after"])
def test_killed_generate_and_retire_leave_the_store_before_or_after(env, tmp_path, when):
    doc, store, _run = env
    pp = str(tmp_path / "pass")

    def killed(*args: str) -> None:
        store_flags = ["--store", str(store), "--passphrase-file", pp]
        cmd = [sys.executable, "-c", KILLER, when, STORE_NAME, "macsec", *args, *store_flags]
        proc = subprocess.run(cmd, cwd=PROJECT, capture_output=True, timeout=60)
        assert proc.returncode == -9, proc.stderr

    killed("generate", str(doc), "--now", T0)  # a first generate: no store before, a whole store after
    assert (store / STORE_NAME).exists() == (when == "after")
    assert _run("generate", "--now", T0).exit_code == 0
    # a killed run's temporaries are cleaned
    assert sorted(os.listdir(store)) == [".macsec-keys.lock", INDEX_NAME, STORE_NAME]
    assert _run("rotate", "--now", T0, "--overlap", "60").exit_code == 0
    before = (store / STORE_NAME).read_bytes()
    killed("retire", "--now", "2026-01-02T00:00:00Z")
    ks = _open(store)
    counts = {len(e.generations) for e in ks.entries.values()}
    if when == "before":
        assert (store / STORE_NAME).read_bytes() == before and counts == {2}
    else:
        assert counts == {1}
    for e in ks.entries.values():  # every remaining key decrypts: a device's key is never lost
        assert e.current(datetime(2026, 1, 2, tzinfo=UTC)) is not None
        for g in e.generations:
            ks.key(e, g)


def test_failed_write_is_exit_3_and_leaves_nothing(env, monkeypatch):
    _doc_path, store, run = env
    assert run("generate", "--now", T0).exit_code == 0
    before = (store / STORE_NAME).read_bytes()
    import hcdf_trust.outputs as outputs

    def full(fd: int) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(outputs.os, "fsync", full)
    r = run("rotate", "--now", T0)
    monkeypatch.undo()
    assert r.exit_code == 3 and "No space left" in r.stderr
    assert (store / STORE_NAME).read_bytes() == before
    assert sorted(os.listdir(store)) == [".macsec-keys.lock", INDEX_NAME, STORE_NAME]


def test_store_never_over_an_input(env, cli, tmp_path):
    doc, _store, _run = env
    pp = tmp_path / "pass"
    r = cli("macsec", "generate", doc, "--store", doc.parent, "--passphrase-file", pp)
    assert r.exit_code == 0  # the folder of the document is fine: the store file is not an input
    os.unlink(doc.parent / STORE_NAME)
    os.symlink(doc, doc.parent / STORE_NAME)
    text = doc.read_bytes()
    r = cli("macsec", "generate", doc, "--store", doc.parent, "--passphrase-file", pp)
    assert r.exit_code == 3
    assert doc.read_bytes() == text


# --- two runs on one store ---------------------------------------------------------------


def test_concurrent_generates_never_lose_a_key(tmp_path):
    """Two processes generating for two robots into one store: both robots' keys survive."""
    docs = []
    for name in ("r1", "r2"):
        folder = tmp_path / name
        docs.append(_doc(folder))
        text = docs[-1].read_text().replace('name="n"', f'name="{name}"')
        docs[-1].write_text(text)
        from ._macsec import lock

        lock(docs[-1])
    pp = tmp_path / "pass"
    pp.write_bytes(PASS)
    store = tmp_path / "shared-keys"
    env = dict(os.environ, XDG_CACHE_HOME=str(tmp_path / "cache"))
    cmd = [sys.executable, "-m", "hcdf_trust.cli", "macsec", "generate"]
    procs = [
        subprocess.Popen([*cmd, str(d), "--store", str(store), "--passphrase-file", str(pp)], cwd=PROJECT, env=env)
        for d in docs
    ]
    assert [p.wait(timeout=120) for p in procs] == [0, 0]
    ids = set(_open(store).entries)
    assert {"link:r1/plain", "link:r2/plain"} <= ids


def test_a_held_lock_is_waited_for_then_refused(env, monkeypatch):
    import fcntl

    import hcdf_trust.macsec.store as store_mod

    _doc_path, store, run = env
    assert run("generate").exit_code == 0
    monkeypatch.setattr(store_mod, "LOCK_WAIT_SEC", 0.3)
    with open(store / ".macsec-keys.lock", "rb+") as held:
        fcntl.flock(held, fcntl.LOCK_EX)
        r = run("rotate")
    assert r.exit_code == 3 and "locked by another run" in r.stderr


def test_a_colliding_ckn_is_drawn_again(env, monkeypatch):
    """The CSPRNG repeating a CKN's first 16 octets (forced here) never yields two equal CKNs."""
    _doc_path, store, run = env
    assert run("generate").exit_code == 0
    ks = _open(store)
    taken = next(iter(ks.entries.values())).generations[0].ckn
    import hcdf_trust.macsec.store as store_mod

    real = os.urandom
    forced = [taken]

    def urandom(n: int) -> bytes:
        return forced.pop() if n == 16 and forced else real(n)

    monkeypatch.setattr(store_mod.os, "urandom", urandom)
    entry = ks.entries["key-ref:k0"]
    gen = ks.new_generation(entry, now=entry.generations[0].created, activation=entry.generations[0].created)
    assert not forced and gen.ckn != taken and gen.ckn[:16] not in {taken[:16]}


@pytest.mark.parametrize("value", ["yesterday", "2026-01-01T00:00:00"])
def test_bad_now_is_a_usage_error(env, value):
    _doc_path, _store, run = env
    r = run("status", "--now", value)
    assert r.exit_code == 2 and "ISO 8601" in r.stderr and "None" not in r.stderr


def test_a_passphrase_wrapper_runs_scrypt_once_per_salt(tmp_path, monkeypatch):
    # rotate opens the store twice (while the description is verified, then under the lock):
    # one wrapper keeps the derived key per (salt, n, r, p), so a second store is not opened with the first's key
    from cryptography.hazmat.primitives.kdf import scrypt

    from hcdf_trust.outputs import OutputPlan

    maker = PassphraseWrapper(PASS)
    for name in ("a", "b"):
        store = KeyStore.create(tmp_path / name, maker)
        store.bind("t", document="robot.hcdf")  # a store is written only once bound to its robot
        out = OutputPlan()
        store.plan_write(out, now=datetime(2026, 1, 1, tzinfo=UTC))
        (tmp_path / name).mkdir()
        out.commit()
    runs: list[bytes] = []
    real = scrypt.Scrypt

    def counting(*, salt: bytes, **kw: int) -> object:
        runs.append(salt)
        return real(salt=salt, **kw)

    monkeypatch.setattr(scrypt, "Scrypt", counting)
    wrapper = PassphraseWrapper(PASS)
    first = KeyStore.open(tmp_path / "a", wrapper)
    assert KeyStore.open(tmp_path / "a", wrapper).store_id == first.store_id
    assert len(runs) == 1
    assert KeyStore.open(tmp_path / "b", wrapper).store_id != first.store_id
    assert len(runs) == 2 and runs[0] != runs[1]
    wrong = PassphraseWrapper(b"not the passphrase")
    for _ in range(2):
        with pytest.raises(WrongCredentialError):
            KeyStore.open(tmp_path / "a", wrong)


@pytest.mark.parametrize("bad", [b'{"x":1}', b"[1,{}]", b'["link:n/plain",{}]'])
def test_a_sealed_store_with_a_malformed_line_is_refused_after_the_credential(env, bad):
    """A line that is not an association is refused even under a valid MAC (re-sealed here with
    the store's own data key), and only once the credential has opened the store: the lines are
    indexed while scrypt runs, yet a wrong passphrase is still the error a user sees first."""
    from hcdf_trust.macsec.backends import WrongCredentialError
    from hcdf_trust.macsec.store import _STORE_MAC, KeyStoreFormatError

    _doc, store, run = env
    assert run("generate", "--now", T0).exit_code == 0
    ks = _open(store)
    path = store / STORE_NAME
    raw = path.read_bytes()
    body = b"{" + raw[raw.index(b",") + 1 :]  # without its "mac"
    head, _, lines = body.partition(b"\n")
    if bad.startswith(b'["link:n/plain"'):  # the same CA twice
        lines += bad.replace(b"{}", b'{"generations":[]}') + b"\n"
    else:
        lines += bad + b"\n"
    path.write_bytes(ks.seal(head + b"\n" + lines, label=_STORE_MAC))
    with pytest.raises(KeyStoreFormatError, match="not an association"):
        _open(store)
    with pytest.raises(WrongCredentialError):
        KeyStore.open(store, PassphraseWrapper(b"wrong"))
