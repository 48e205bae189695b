"""Attacks on the published TUF registry, judged by two clients: ``hcdf-trust registry``
(python-tuf's ngclient underneath, plus our own checks) and a stock ``tuf.ngclient.Updater``
that knows nothing of hcdf-trust, as the oracle.

Where TUF itself protects (rollback, freeze, mix-and-match, targets that do not match their
metadata, a role signed with keys its delegation does not name) both refuse, and the stock
client accepting the untampered site shows the refusal comes from the attack. Where the
protection is ours (a published version replaced by its own owner, a file listed under
another owner's domain), the stock client accepts: that is the attack succeeding without it.
"""

from __future__ import annotations

import datetime as dt
import shutil
from pathlib import Path

import pytest

from tests._registry import IEEE_XSD, PASSPHRASE, PROFILE, Registry, build
from tests.servers import LoopbackServer

ROS = "extensions/org.ros2/1.0.xsd"


@pytest.fixture(autouse=True)
def _passphrase(monkeypatch):
    monkeypatch.setenv("HCDF_TRUST_PASSPHRASE", PASSPHRASE)


@pytest.fixture
def reg(tmp_path, cli) -> Registry:
    return build(tmp_path, cli)


@pytest.fixture
def srv(reg):
    with LoopbackServer(root=reg.site) as server:
        yield server


class Stock:
    """A stock python-tuf client with its own metadata folder, trusting the site's first root."""

    def __init__(self, reg: Registry, base: str, home: Path) -> None:
        self.reg, self.base, self.home = reg, base, home
        (home / "metadata").mkdir(parents=True)
        (home / "targets").mkdir()
        self.root = reg.root_json.read_bytes()

    def get(self, path: str = ROS) -> bytes:
        """refresh, look the target up through the delegations, download it; raises on any refusal."""
        from tuf.ngclient import Updater

        updater = Updater(
            metadata_dir=str(self.home / "metadata"),
            metadata_base_url=self.base + "/metadata/",
            target_base_url=self.base + "/targets/",
            target_dir=str(self.home / "targets"),
            bootstrap=self.root,
        )
        updater.refresh()
        info = updater.get_targetinfo(path)
        assert info is not None, f"{path}: no such target"
        return Path(updater.download_target(info)).read_bytes()


@pytest.fixture
def stock(reg, srv, tmp_path) -> Stock:
    return Stock(reg, srv.base, tmp_path / "stock")


def _refused(res, name: str) -> None:
    assert res.exit_code == 1, (res.exit_code, res.stderr)
    assert name in res.stderr, res.stderr


def test_both_clients_accept_the_untampered_registry(reg, srv, stock):
    assert stock.get(ROS) == (reg.content / "extensions" / "hcdf-ext-ros2.xsd").read_bytes()
    assert stock.get("profiles/operational/1.0.streams.xml") == PROFILE.read_bytes()
    assert reg.verify(srv.base).exit_code == 0


def test_rollback_of_the_timestamp(reg, srv, stock):
    from tuf.api.exceptions import BadVersionNumberError

    meta = reg.site / "metadata"
    old = (meta / "timestamp.json").read_bytes()
    reg.add_domain("org.ros2", "1.1", IEEE_XSD)
    reg.publish()
    stock.get()
    assert reg.verify(srv.base).exit_code == 0  # both now trust timestamp v2
    (meta / "timestamp.json").write_bytes(old)
    with pytest.raises(BadVersionNumberError):
        stock.get()
    _refused(reg.verify(srv.base), "rollback attack")


def test_freeze_an_expired_timestamp(reg, srv, stock):
    from tuf.api.exceptions import ExpiredMetadataError
    from tuf.api.metadata import Metadata

    snap_version = Metadata.from_file(str(reg.site / "metadata" / "timestamp.json")).signed.snapshot_meta.version
    snap = Metadata.from_file(str(reg.site / "metadata" / f"{snap_version}.snapshot.json"))
    reg.resign_snapshot_timestamp(
        snap, ts_expires=dt.datetime.now(dt.UTC).replace(microsecond=0) - dt.timedelta(hours=1)
    )
    with pytest.raises(ExpiredMetadataError):
        stock.get()
    _refused(reg.verify(srv.base, cache="fresh"), "freeze attack")


def test_mix_and_match_an_old_snapshot_with_the_new_timestamp(reg, srv, stock):
    from tuf.api.exceptions import RepositoryError

    meta = reg.site / "metadata"
    reg.add_domain("org.ros2", "1.1", IEEE_XSD)
    reg.publish()
    shutil.copy(meta / "1.snapshot.json", meta / "2.snapshot.json")  # the first publication's snapshot
    with pytest.raises(RepositoryError):  # its hash is not the one the timestamp signed
        stock.get()
    _refused(reg.verify(srv.base, cache="fresh"), "mix-and-match attack")


def test_a_target_that_does_not_match_its_metadata(reg, srv, stock, tmp_path):
    from tuf.api.exceptions import LengthOrHashMismatchError

    target = reg.target_file(ROS)
    data = bytearray(target.read_bytes())
    data[100] ^= 0x01
    target.write_bytes(bytes(data))
    with pytest.raises(LengthOrHashMismatchError):
        stock.get()
    _refused(reg.fetch("org.ros2", out=tmp_path / "x.xsd", site=srv.base), "arbitrary content")
    assert not (tmp_path / "x.xsd").exists()


def test_a_domain_role_signed_with_another_owners_key(reg, srv, stock):
    from tuf.api.exceptions import UnsignedMetadataError

    def add(signed):
        signed.targets["extensions/org.ros2/2.0.xsd"] = reg.put_target("extensions/org.ros2/2.0.xsd", b"<x/>")

    reg.forge("org.ros2", add, signer=reg.owner_signer("org.gazebosim"))
    with pytest.raises(UnsignedMetadataError):
        stock.get("extensions/org.ros2/2.0.xsd")
    _refused(reg.verify(srv.base), "bad signature: org.ros2.json")


def test_a_domain_role_signed_with_the_registrys_own_targets_key(reg, srv, stock, tmp_path):
    """The registry operator (targets key) is not the domain's owner either."""
    from tuf.api.exceptions import UnsignedMetadataError

    def add(signed):
        signed.targets["extensions/org.ros2/1.1.xsd"] = reg.put_target("extensions/org.ros2/1.1.xsd", b"<x/>")

    reg.forge("org.ros2", add, signer=reg.top_signer("targets"))
    with pytest.raises(UnsignedMetadataError):
        stock.get("extensions/org.ros2/1.1.xsd")
    _refused(reg.fetch("org.ros2@1.1", out=tmp_path / "x", site=srv.base), "publisher without the owner's key")


def test_a_published_version_replaced_by_its_own_owner(reg, srv, stock, tmp_path):
    """Valid TUF (the owner's key, versions increased): the stock client takes the new bytes.
    hcdf-trust refuses: a published version's content never changes."""
    assert stock.get() == (reg.content / "extensions" / "hcdf-ext-ros2.xsd").read_bytes()
    assert reg.verify(srv.base).exit_code == 0
    evil = IEEE_XSD.read_bytes()

    def replace(signed):
        signed.targets[ROS] = reg.put_target(ROS, evil)

    reg.forge("org.ros2", replace, signer=reg.owner_signer("org.ros2"))
    assert stock.get() == evil  # the attack, without our protection
    _refused(reg.fetch("org.ros2@1.0", out=tmp_path / "x.xsd", site=srv.base), "replaced published version")
    assert not (tmp_path / "x.xsd").exists()


def test_a_file_listed_under_another_owners_domain(reg, srv, stock, tmp_path):
    """The gazebosim owner lists a file at org.ros2's path in its own role: TUF's delegation
    walk never asks gazebosim about that path, so a client cannot be fooled, and verify names it."""
    from tuf.api.exceptions import RepositoryError

    evil = b"<xs:schema xmlns:xs='http://www.w3.org/2001/XMLSchema'/>"

    def hijack(signed):
        signed.targets["extensions/org.ros2/9.0.xsd"] = reg.put_target("extensions/org.ros2/9.0.xsd", evil)

    reg.forge("org.gazebosim", hijack, signer=reg.owner_signer("org.gazebosim"))
    try:
        got = stock.get("extensions/org.ros2/9.0.xsd")
    except (AssertionError, RepositoryError):
        got = None
    assert got is None  # the stock client does not find it under org.ros2
    res = reg.verify(srv.base)
    assert res.exit_code == 1 and "org.gazebosim" in res.stderr and "org.ros2" in res.stderr, res.stderr
