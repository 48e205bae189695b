"""The registry as the source of schemas and as a check on extensions and stream profiles.

:class:`RegistrySchemaSource` implements :class:`hcdf_trust.validate.schema.SchemaSource`:
``validate --registry`` takes the core schema the document's ``version`` asks for (and the
stream-profile schema) from the registry, verified by TUF, with no ``--schema``.
:func:`check_document` checks every ``<extension domain version>`` against the registered
domains (unregistered: a warning, an error under ``strict``), validates each extension's
content against its registered schema, and checks that a referenced local stream profile
whose name and version are registered has the registered digest.
"""

from __future__ import annotations

import copy
import hashlib
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

from lxml import etree

from ..errors import HcdfTrustError
from ..validate.findings import Finding, Severity
from ..validate.schema import Schema, compile_schema
from ..xml import parse_bytes, sourceline
from .client import RegistryClient, latest

if TYPE_CHECKING:
    from tuf.api.metadata import TargetFile

PROFILE_LIMIT = 16 << 20


class RegistrySchemaSource:
    """Schemas from a registry: ``hcdf`` per document version, ``hcdf-stream-profile`` (latest)."""

    CORE = {"hcdf": "hcdf", "stream-profile": "hcdf-stream-profile"}

    def __init__(self, client: RegistryClient) -> None:
        self.client = client
        self._built: dict[str, Schema] = {}

    def schema_for(self, *, root: str, version: str | None) -> Schema | None:
        """The registered schema for this root element and version, or None if none is registered.

        Raises:
            AttackError, TransportError: the registry does not verify or cannot be reached.
            InputError: the registered schema is not a usable XSD.
        """
        qname = etree.QName(root)
        name = self.CORE.get(qname.localname) if qname.namespace is None else None
        if name is None:
            return None
        versions = self.client.artifacts("schema").get(name, {})
        if not versions:
            return None
        if qname.localname == "hcdf":
            if version not in versions:
                return None
            assert version is not None
            return self.build(versions[version])
        return self.build(versions[latest(versions)])  # a profile's version is its content's, not the schema's

    def core_xsd(self, version: str | None) -> tuple[str, bytes] | None:
        """The registered ``hcdf`` schema's name and bytes for ``version`` (what reads HCDF's
        JSON form: :func:`hcdf_trust.jsonform.use_schema_provider`), None when not registered."""
        info = self.client.artifacts("schema").get(self.CORE["hcdf"], {}).get(version or "")
        return None if info is None else (f"registry:{info.path}", self.client.download(info))

    def build(self, info: TargetFile) -> Schema:
        if info.path not in self._built:
            self._built[info.path] = compile_schema(self.client.download(info), name=f"registry:{info.path}")
        return self._built[info.path]

    def __repr__(self) -> str:
        return f"RegistrySchemaSource({self.client.site!r})"


def check_document(
    tree: etree._ElementTree, *, source: str, path: Path | None, schemas: RegistrySchemaSource, strict: bool = False
) -> list[Finding]:
    """Extension domains, versions and content, and referenced stream-profile digests.

    Raises:
        AttackError, TransportError: the registry does not verify or cannot be reached.
    """
    client = schemas.client
    unregistered: Severity = "error" if strict else "warning"
    findings: list[Finding] = []
    domains = set(client.domains())
    for ext in tree.iter("extension"):
        domain, version, line = ext.get("domain"), ext.get("version"), sourceline(ext)
        if not domain:
            continue
        if domain not in domains:
            findings.append(
                Finding(
                    "extension-unregistered",
                    unregistered,
                    f"extension domain {domain!r} is not registered",
                    file=source,
                    line=line,
                )  # fmt: skip
            )
            continue
        versions = client.versions(domain)
        if version is None or version not in versions:
            known = ", ".join(sorted(versions)) or "none"
            findings.append(
                Finding(
                    "extension-unregistered",
                    unregistered,
                    f"extension {domain} version {version!r} is not registered (registered: {known})",
                    file=source,
                    line=line,
                )
            )
            continue
        schema = schemas.build(versions[version])
        for child in ext:
            if not isinstance(child.tag, str):
                continue  # comments, processing instructions
            if not schema.declares(child.tag):
                findings.append(
                    Finding(
                        "extension-content",
                        "error",
                        f"<{child.tag}> is not an element of the {domain} {version} schema",
                        file=source,
                        line=sourceline(child),
                    )  # fmt: skip
                )
                continue
            for f in schema.validate(etree.ElementTree(copy.deepcopy(child)), source=source):
                findings.append(Finding("extension-content", f.severity, f"{domain} {version}: {f.message}",
                                        file=source, line=f.line))  # fmt: skip
    if path is not None:
        findings += _profiles(tree, source=source, folder=path.parent, client=client)
    return findings


def _profiles(tree: etree._ElementTree, *, source: str, folder: Path, client: RegistryClient) -> list[Finding]:
    """A local ``<stream-profile uri>`` whose name and version are registered must have the registered digest."""
    from ..localfile import open_checked, read_bounded

    findings: list[Finding] = []
    registered = client.artifacts("profile")
    for ref in tree.iter("stream-profile"):
        uri = ref.get("uri")
        if not uri or "://" in uri or uri.startswith("/"):
            continue  # validate never fetches; resolve checks remote ones
        line = sourceline(ref)
        target = folder / uri
        try:
            fd, _ = open_checked(os.fspath(target), folder, file=source, line=line)
            try:
                data = read_bounded(fd, PROFILE_LIMIT, source=uri, what="stream profile")
            finally:
                os.close(fd)
            root = parse_bytes(data, source=uri).getroot()
        except HcdfTrustError as exc:
            findings.append(Finding("stream-profile-unread", "warning", f"{uri}: {exc.message}", file=source,
                                    line=line))  # fmt: skip
            continue
        name, version = root.get("name"), root.get("version")
        info: Any = registered.get(name or "", {}).get(version or "")
        if info is None:
            continue
        digest = hashlib.sha256(data).hexdigest()
        if digest != info.hashes.get("sha256") or len(data) != info.length:
            findings.append(
                Finding(
                    "stream-profile-digest",
                    "error",
                    f"stream profile {uri} ({name} {version}) differs from the registered one: "
                    f"expected sha256:{info.hashes.get('sha256')} ({info.length} bytes), "
                    f"actual sha256:{digest} ({len(data)} bytes)",
                    file=source,
                    line=line,
                )
            )
    return findings
