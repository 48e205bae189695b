"""Helpers for the registry tests: build a registry from the corpus, publish it, forge metadata.

Forging uses python-tuf's Metadata API directly, playing an attacker (or a publisher that
skips ``publish``'s checks) who holds the keys named in each test.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import hashlib
import json
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from tests.conftest import HCDFORMAT

PASSPHRASE = "correct horse battery staple"
ROS2_XSD = HCDFORMAT / "extensions" / "hcdf-ext-ros2.xsd"
GAZEBO_XSD = HCDFORMAT / "extensions" / "hcdf-ext-gazebo.xsd"
IEEE_XSD = HCDFORMAT / "extensions" / "hcdf-ext-1722.xsd"
PROFILE = HCDFORMAT / "examples" / "profiles" / "operational.streams.xml"


@dataclass
class Registry:
    """A registry source in ``src``, its keys, a content folder and a site, all under ``base``."""

    base: Path
    cli: Any

    @property
    def src(self) -> Path:
        return self.base / "src"

    @property
    def keys(self) -> Path:
        return self.base / "keys"

    @property
    def site(self) -> Path:
        return self.base / "site"

    @property
    def content(self) -> Path:
        return HCDFORMAT

    @property
    def root_json(self) -> Path:
        return self.site / "metadata" / "1.root.json"

    def owner_keys(self, domain: str) -> Path:
        return self.base / f"keys-{domain}"

    def run(self, *args: Any, ok: bool = True) -> Any:
        res = self.cli("registry", *args)
        if ok:
            assert res.exit_code == 0, res.stderr
        return res

    def add_domain(self, domain: str, version: str, schema: Path, *, content: Path | None = None) -> Any:
        args: list[Any] = ["add", self.src, "--domain", domain, "--version", version, "--schema", schema]
        args += ["--content", content or self.content, "--keys", self.owner_keys(domain)]
        pub = self.base / f"{domain}.pub"
        if not pub.exists():
            self.run("keygen", "--keys", self.owner_keys(domain), "-o", pub)
            args += ["--owner", f"{domain} maintainers", "--owner-key", pub]
        return self.run(*args)

    def publish(self, *extra: Any, owners: bool = True, ok: bool = True) -> Any:
        args: list[Any] = ["publish", self.src, "--keys", self.keys, "--content", self.content, "--out", self.site]
        if owners:
            for d in sorted(self.base.glob("keys-*")):
                args += ["--keys", d]
        return self.run(*args, *extra, ok=ok)

    def client_args(self, site: str | Path | None = None) -> list[Any]:
        return [site or self.site, "--trusted-root", self.root_json, "--cache-dir", self.base / "client"]

    def verify(self, site: str | Path | None = None, *, cache: str = "client") -> Any:
        res = self.cli(
            "registry",
            "verify",
            site or self.site,
            "--trusted-root",
            self.root_json,
            "--cache-dir",
            self.base / cache,
        )
        return res

    def fetch(self, *what: str, out: Path, site: str | Path | None = None, cache: str = "client") -> Any:
        return self.cli(
            "registry",
            "fetch",
            *what,
            "--from",
            site or self.site,
            "--trusted-root",
            self.root_json,
            "--cache-dir",
            self.base / cache,
            "-o",
            out,
        )

    # -- playing the attacker -----------------------------------------------------------

    def ring(self) -> Any:
        from hcdf_trust.registry.keys import KeyRing

        return KeyRing([self.keys, *sorted(self.base.glob("keys-*"))], PASSPHRASE.encode())

    def source(self) -> Any:
        from hcdf_trust.registry.source import load_source

        return load_source(self.src)

    def top_signer(self, role: str) -> Any:
        root = self.source().root
        return self.ring().signer(root.keys[root.roles[role].keyids[0]])

    def owner_signer(self, domain: str) -> Any:
        d = self.source().domains[domain]
        return self.ring().signer(next(iter(d.keys.values())))

    def forge(
        self, role: str, mutate: Callable[[Any], None], *, signer: Any, expires: dt.datetime | None = None
    ) -> None:
        """Re-sign ``role`` (after ``mutate``) with ``signer``, then snapshot and timestamp with
        the registry's own keys, as a publisher who skipped ``publish``'s checks would."""
        from tuf.api.metadata import Metadata, MetaFile

        meta = self.site / "metadata"
        ts = Metadata.from_file(str(meta / "timestamp.json"))
        snap = Metadata.from_file(str(meta / f"{ts.signed.snapshot_meta.version}.snapshot.json"))
        old_version = snap.signed.meta[f"{role}.json"].version
        md = Metadata.from_file(str(meta / f"{old_version}.{role}.json"))
        mutate(md.signed)
        md.signed.version += 1
        if expires is not None:
            md.signed.expires = expires
        md.signatures.clear()
        md.sign(signer)
        (meta / f"{md.signed.version}.{role}.json").write_bytes(md.to_bytes())
        snap.signed.meta[f"{role}.json"] = MetaFile(md.signed.version)
        self.resign_snapshot_timestamp(snap)

    def resign_snapshot_timestamp(self, snap: Any, *, ts_expires: dt.datetime | None = None) -> None:
        from tuf.api.metadata import Metadata, MetaFile

        meta = self.site / "metadata"
        ts = Metadata.from_file(str(meta / "timestamp.json"))
        snap.signed.version += 1
        snap.signatures.clear()
        snap.sign(self.top_signer("snapshot"))
        data = snap.to_bytes()
        (meta / f"{snap.signed.version}.snapshot.json").write_bytes(data)
        ts.signed.version += 1
        ts.signed.snapshot_meta = MetaFile.from_data(snap.signed.version, data, ["sha256"])
        if ts_expires is not None:
            ts.signed.expires = ts_expires
        ts.signatures.clear()
        ts.sign(self.top_signer("timestamp"))
        (meta / "timestamp.json").write_bytes(ts.to_bytes())

    def put_target(self, path: str, data: bytes) -> Any:
        """A target file entry for ``data`` at ``path``, with the content placed on the site."""
        from tuf.api.metadata import TargetFile

        digest = hashlib.sha256(data).hexdigest()
        folder, _, name = path.rpartition("/")
        dest = self.site / "targets" / folder / f"{digest}.{name}"
        dest.parent.mkdir(parents=True, exist_ok=True)
        dest.write_bytes(data)
        return TargetFile.from_data(path, data, ["sha256"])

    def target_file(self, path: str) -> Path:
        """The site file holding the published target ``path``."""
        folder, _, name = path.rpartition("/")
        files = sorted((self.site / "targets" / folder).glob(f"*.{name}"))
        assert len(files) == 1, files
        return files[0]


def build(base: Path, cli: Any) -> Registry:
    """init + two owned domains with their corpus schema + the stream profile, published once."""
    reg = Registry(base, cli)
    reg.run("init", reg.src, "--keys", reg.keys)
    reg.add_domain("org.ros2", "1.0", ROS2_XSD)
    reg.add_domain("org.gazebosim", "1.0", GAZEBO_XSD)
    reg.run("add", reg.src, "--profile", PROFILE, "--content", reg.content)
    reg.publish()
    return reg


@contextlib.contextmanager
def serve_corpus_registry(base: Path, *, core_schemas: bool = False) -> Iterator[tuple[Registry, Any]]:
    """The corpus's three domains with schemas and its stream profile (with ``core_schemas``, also
    the hcdf and hcdf-stream-profile 1.0 schemas), published once and served on 127.0.0.1.

    For module-scoped fixtures, which cannot use the function-scoped ``cli`` fixture.
    """
    from click.testing import CliRunner

    from hcdf_trust.cli import main
    from tests.conftest import CliResult
    from tests.servers import LoopbackServer

    def cli(*args: Any) -> CliResult:
        r = CliRunner().invoke(main, [str(a) for a in args], env={"HCDF_TRUST_PASSPHRASE": PASSPHRASE})
        return CliResult(r.exit_code, r.stdout, r.stderr)

    reg = Registry(base, cli)
    reg.run("init", reg.src, "--keys", reg.keys)
    reg.add_domain("org.ros2", "1.0", ROS2_XSD)
    reg.add_domain("org.gazebosim", "1.0", GAZEBO_XSD)
    reg.add_domain("org.ieee.1722", "1.0", IEEE_XSD)
    reg.run("add", reg.src, "--profile", PROFILE, "--content", reg.content)
    if core_schemas:
        for name, xsd in (("hcdf", "hcdf.xsd"), ("hcdf-stream-profile", "hcdf-stream-profile.xsd")):
            reg.run("add", reg.src, "--core", name, "--version", "1.0", "--schema", HCDFORMAT / xsd,
                    "--content", reg.content)  # fmt: skip
    reg.publish()
    with LoopbackServer(root=reg.site) as srv:
        yield reg, srv


def site_json(path: Path) -> dict[str, Any]:
    data: dict[str, Any] = json.loads(path.read_bytes())
    return data
