"""SPDX 3.0.1 JSON-LD through the official spdx-python-model bindings (imported here only).

One ``SpdxDocument`` holding one ``software_Sbom`` whose root is the robot. Robot,
sub-assemblies and comps are ``software_Package`` with purpose ``device``, firmware
``firmware``, drivers ``deviceDriver``; model and other files are ``software_File`` with
their SHA-256. Authors are ``originatedBy`` agents, licenses ``hasDeclaredLicense``
relationships to license expressions, the tree ``contains`` relationships
(robot → sub-assembly → comp → firmware / driver / file; firmware → its manifest file).
HCDF facts without an SPDX field are CycloneDX-style properties
(``extension_CdxPropertiesExtension``), named as in the CycloneDX output. A release's
verified provenance is a ``buildMeta`` external reference of the Sbom and of each firmware
the release holds (ExternalRef has no hash: its SHA-256 is in the comment).
"""

from __future__ import annotations

import io
import re
from typing import Any

from .. import __version__
from .model import PROVENANCE_COMMENT, Facts, assembly_properties, comp_properties, file_properties, firmware_properties

_NOT_IN_IDSTRING = re.compile(r"[^A-Za-z0-9.-]+")


def render(facts: Facts) -> bytes:
    """The BOM as SPDX 3.0.1 JSON-LD (UTF-8, ends with a newline)."""
    from license_expression import ExpressionError, get_spdx_licensing
    from spdx_python_model import v3_0_1 as spdx

    ns = f"https://spdx.org/spdxdocs/hcdf-trust-{facts.serial}/"
    info = spdx.CreationInfo(specVersion="3.0.1", created=facts.created)
    objects: list[Any] = []

    def add(obj: Any) -> Any:
        objects.append(obj)
        return obj

    tool = add(spdx.Tool(spdxId=ns + "tool/hcdf-trust", name=f"hcdf-trust {__version__}", creationInfo=info))
    agent = add(spdx.SoftwareAgent(spdxId=ns + "agent/hcdf-trust", name="hcdf-trust", creationInfo=info))
    info.createdBy = [agent]
    info.createdUsing = [tool]
    licensing = get_spdx_licensing()
    agents: dict[str, Any] = {}
    license_of: dict[str, Any] = {}
    packages: dict[str, Any] = {}
    relationships: list[tuple[str, str, list[Any]]] = []  # (id, from ref, to)

    def extension(pairs: list[tuple[str, str]]) -> list[Any]:
        if not pairs:
            return []
        entries = [spdx.extension_CdxPropertyEntry(extension_cdxPropName=n, extension_cdxPropValue=v) for n, v in pairs]
        return [spdx.extension_CdxPropertiesExtension(extension_cdxProperty=entries)]

    def sha256(value: str | None) -> list[Any]:
        return [spdx.Hash(algorithm=spdx.HashAlgorithm.sha256, hashValue=value)] if value else []

    def author(name: str) -> Any:
        if name not in agents:
            agents[name] = add(spdx.Agent(spdxId=f"{ns}agent/{len(agents) + 1}", name=name, creationInfo=info))
        return agents[name]

    def declared(text: str) -> Any:
        if text not in license_of:
            try:
                expr = str(licensing.parse(text, validate=True, strict=True))
                comment = None
            except ExpressionError:  # not an SPDX expression: a LicenseRef, the text kept as written
                expr = "LicenseRef-" + (_NOT_IN_IDSTRING.sub("-", text).strip("-") or "unknown")
                comment = f"<license> as written: {text}"
            license_of[text] = add(
                spdx.simplelicensing_LicenseExpression(
                    spdxId=f"{ns}license/{len(license_of) + 1}",
                    simplelicensing_licenseExpression=expr,
                    creationInfo=info,
                    **_given(comment=comment),
                )
            )
        return license_of[text]

    def package(ref: str, name: str, purpose: Any, **kw: Any) -> None:
        packages[ref] = add(
            spdx.software_Package(
                spdxId=ns + ref, name=name, software_primaryPurpose=purpose, creationInfo=info, **_given(**kw)
            )
        )

    purpose = spdx.software_SoftwarePurpose
    for a in (facts.robot, *facts.assemblies):
        package(
            a.ref,
            a.name,
            purpose.device,
            description=a.description,
            verifiedUsing=sha256(a.sha256),
            originatedBy=[author(a.author)] if a.author else [],
            extension=extension(assembly_properties(a)),
        )
        if a.license:
            relationships.append((f"{a.ref}/license", a.ref, [declared(a.license)]))
    for c in facts.comps:
        package(c.ref, c.name, purpose.device, description=c.description, extension=extension(comp_properties(c)))

    def provenance() -> list[Any]:
        p = facts.provenance
        if p is None:
            return []
        comment = f"{PROVENANCE_COMMENT}; SHA-256 {p.sha256}"
        return [spdx.ExternalRef(externalRefType=spdx.ExternalRefType.buildMeta, locator=[p.url], comment=comment)]

    for f in facts.firmware:
        package(
            f.ref,
            f.name,
            purpose.firmware,
            software_packageVersion=f.version,
            verifiedUsing=sha256(f.signature.file_sha256 if f.signature else None),
            extension=extension(firmware_properties(f)),
            externalRef=provenance() if f.signature else [],
        )
    for d in facts.drivers:
        package(d.ref, d.name, purpose.deviceDriver)
    for fl in facts.files:
        packages[fl.ref] = add(
            spdx.software_File(
                spdxId=ns + fl.ref,
                name=fl.name,
                software_primaryPurpose=purpose.configuration if fl.kind == "stream-profile" else purpose.data,
                verifiedUsing=sha256(fl.sha256),
                creationInfo=info,
                extension=extension(file_properties(fl)),
            )
        )
    for ref, deps in facts.all_refs().items():
        if deps:
            relationships.append((f"{ref}/contains", ref, [packages[d] for d in deps]))
    for rid, source, to in relationships:
        kind = spdx.RelationshipType.hasDeclaredLicense if rid.endswith("/license") else spdx.RelationshipType.contains
        add(
            spdx.Relationship(
                spdxId=f"{ns}relationship/{rid}",
                from_=packages[source],
                relationshipType=kind,
                to=to,
                creationInfo=info,
            )
        )
    elements = [o for o in objects if o is not agent and o is not tool]
    sbom = add(
        spdx.software_Sbom(
            spdxId=ns + "sbom",
            name=f"{facts.robot.name} bill of materials",
            rootElement=[packages[facts.robot.ref]],
            element=elements,
            software_sbomType=[spdx.software_SbomType.design],
            creationInfo=info,
            **_given(externalRef=provenance()),
        )
    )
    # The CycloneDX properties use the Extension profile's classes, but the profile is not listed:
    # in 3.0.1 JSON the only value the JSON Schema allows for it, "extension", is also a term of
    # the JSON-LD context (the Core `extension` property) and expands to that property's IRI, so
    # the SHACL stage of the official validator refuses it, and the compact IRI that would expand
    # right is refused by the JSON Schema. profileConformance is informative; the classes are not.
    profiles = spdx.ProfileIdentifierType
    doc = spdx.SpdxDocument(
        spdxId=ns + "document",
        name=f"{facts.robot.name} bill of materials",
        rootElement=[sbom],
        element=[*elements, sbom, agent, tool],
        profileConformance=[profiles.core, profiles.software, profiles.simpleLicensing],
        creationInfo=info,
    )
    objset = spdx.SHACLObjectSet()
    for obj in (doc, *objects):
        objset.add(obj)
    out = io.BytesIO()
    spdx.JSONLDSerializer().write(objset, out, indent=2)
    return out.getvalue().rstrip(b"\n") + b"\n"


def _given(**kw: Any) -> dict[str, Any]:
    """The keyword arguments with a value (the bindings refuse None for an absent property)."""
    return {k: v for k, v in kw.items() if v is not None and v != []}
