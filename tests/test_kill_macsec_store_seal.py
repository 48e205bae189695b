"""Mutation killers for the key store's seal check (hcdf_trust/macsec/store.py: ``KeyStore.seal``,
``KeyStore.sealed`` and the MAC check of ``KeyStore.open``), see tests/MUTATION.md.

The seal is what makes the export index (and the store itself) trustworthy: these tests use the
public ``seal``/``sealed`` pair of a freshly created store, whose data key never leaves it.
"""

from __future__ import annotations

import json
import re

import pytest

from hcdf_trust.macsec.backends import PassphraseWrapper
from hcdf_trust.macsec.store import KeyStore

BODY = b'{"format":"x","version":1}\n["a",{"k":1}]\n'
LABEL = b"hcdf-trust test label"


@pytest.fixture(scope="module")
def stores(tmp_path_factory) -> tuple[KeyStore, KeyStore]:
    """Two stores (two data keys); creating one wraps its key once (scrypt), nothing is written."""
    folder = tmp_path_factory.mktemp("stores")
    return KeyStore.create(folder / "a", PassphraseWrapper(b"one")), KeyStore.create(
        folder / "b", PassphraseWrapper(b"two")
    )


def _mac(raw: bytes) -> str:
    mac: str = json.loads(raw.split(b"\n", 1)[0])["mac"]
    return mac


def test_a_seal_is_the_body_with_a_mac_first_in_its_header(stores):
    a, _ = stores
    raw = a.seal(BODY, label=LABEL)
    m = re.fullmatch(rb'\{"mac":"([0-9a-f]{64})",(.*)', raw, re.S)
    assert m is not None, raw
    assert b"{" + m[2] == BODY
    assert a.sealed(raw, _mac(raw), label=LABEL)
    assert a.seal(BODY, label=LABEL) == raw  # deterministic: the same body, key and label


def test_a_seal_for_one_label_is_no_seal_for_another(stores):
    """The index and the store are sealed under keys derived for their own labels: an index can
    never pass for a store (nor the reverse), whatever its bytes."""
    a, _ = stores
    raw = a.seal(BODY, label=LABEL)
    assert not a.sealed(raw, _mac(raw), label=b"another label")
    assert a.seal(BODY, label=b"another label") != raw


def test_a_seal_of_another_store_is_no_seal(stores):
    a, b = stores
    raw = b.seal(BODY, label=LABEL)
    assert not a.sealed(raw, _mac(raw), label=LABEL)
    assert a.seal(BODY, label=LABEL) != raw


@pytest.mark.parametrize("at", [0, 10, len(BODY) - 2, len(BODY) - 1])
def test_any_changed_byte_of_the_body_breaks_the_seal(stores, at):
    a, _ = stores
    raw = a.seal(BODY, label=LABEL)
    mac = _mac(raw)
    cut = len(raw) - len(BODY) + at  # the same byte of the body inside the sealed file
    changed = raw[:cut] + bytes([raw[cut] ^ 0x01]) + raw[cut + 1 :]
    assert not a.sealed(changed, mac, label=LABEL)


def test_the_mac_must_be_the_first_key_and_the_one_the_header_parses_to(stores):
    a, _ = stores
    raw = a.seal(BODY, label=LABEL)
    mac = _mac(raw)
    assert not a.sealed(raw, "0" * 64, label=LABEL)  # the parsed header names another MAC
    assert not a.sealed(raw, None, label=LABEL)
    assert not a.sealed(b" " + raw, mac, label=LABEL)  # not first
    other = mac[:-1] + ("0" if mac[-1] != "0" else "1")
    forged = raw.replace(mac.encode(), other.encode(), 1)
    assert not a.sealed(forged, other, label=LABEL)


def test_a_store_changed_outside_the_tool_is_refused_naming_the_file(tmp_path):
    """``KeyStore.open``'s MAC check: the whole message, and the store file it names."""
    from hcdf_trust.macsec.store import STORE_NAME, KeyStoreIntegrityError, now_utc
    from hcdf_trust.outputs import OutputPlan

    wrapper = PassphraseWrapper(b"one")
    store = KeyStore.create(tmp_path / "keys", wrapper)
    store.bind("robot", document="robot.hcdf")
    plan = OutputPlan()
    store.plan_write(plan, now=now_utc())
    plan.commit()
    KeyStore.open(tmp_path / "keys", wrapper)  # as written: opens
    path = tmp_path / "keys" / STORE_NAME
    path.write_bytes(path.read_bytes().replace(b'"robot":"robot"', b'"robot": "robot"', 1))
    with pytest.raises(KeyStoreIntegrityError) as caught:
        KeyStore.open(tmp_path / "keys", wrapper)
    assert caught.value.message == (
        "the key store's metadata does not match its MAC: it was changed outside hcdf-trust"
    )
    assert caught.value.file == str(path)
