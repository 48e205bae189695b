"""CycloneDX 1.6 JSON through cyclonedx-python-lib (imported here only: the ``sbom`` verb's).

The robot is ``metadata.component`` (a ``device``); sub-assemblies and comps are
``device`` components, firmware ``firmware``, sensor drivers ``device-driver``, model
and other files ``file`` with their SHA-256. HCDF facts without a CycloneDX field are
``hcdf:*`` properties (see :func:`properties`). ``dependencies`` is the tree:
robot → sub-assembly → comp → firmware / driver / file. A release's verified provenance is
an ``attestation`` external reference of the BOM and of each firmware the release holds.
"""

from __future__ import annotations

from typing import Any

from .. import __version__
from .model import (
    PROVENANCE_COMMENT,
    AssemblyFact,
    Facts,
    assembly_properties,
    comp_properties,
    file_properties,
    firmware_properties,
    properties,
)


def render(facts: Facts) -> bytes:
    """The BOM as CycloneDX 1.6 JSON (UTF-8, ends with a newline)."""
    from cyclonedx.contrib.license.factories import LicenseFactory
    from cyclonedx.model import ExternalReference, ExternalReferenceType, HashAlgorithm, HashType, Property, XsUri
    from cyclonedx.model.bom import Bom
    from cyclonedx.model.component import Component, ComponentType
    from cyclonedx.model.contact import OrganizationalContact
    from cyclonedx.output.json import JsonV1Dot6

    licenses = LicenseFactory()

    def props(pairs: list[tuple[str, str]]) -> list[Property]:
        return [Property(name=n, value=v) for n, v in pairs]

    def sha256(value: str | None) -> list[HashType]:
        return [HashType(alg=HashAlgorithm.SHA_256, content=value)] if value else []

    def assembly(a: AssemblyFact) -> Component:
        return Component(
            type=ComponentType.DEVICE,
            name=a.name,
            bom_ref=a.ref,
            description=a.description,
            authors=[OrganizationalContact(name=a.author)] if a.author else None,
            licenses=[licenses.make_from_string(a.license)] if a.license else None,
            hashes=sha256(a.sha256),
            properties=props(assembly_properties(a)),
        )

    def provenance() -> list[ExternalReference]:
        p = facts.provenance
        if p is None:
            return []
        ref = ExternalReference(
            type=ExternalReferenceType.ATTESTATION,
            url=XsUri(p.url),
            comment=PROVENANCE_COMMENT,
            hashes=sha256(p.sha256),
        )
        return [ref]

    bom = Bom(serial_number=facts.serial, external_references=provenance())
    bom.metadata.timestamp = facts.created
    bom.metadata.tools.components.add(
        Component(type=ComponentType.APPLICATION, name="hcdf-trust", version=__version__, bom_ref="tool/hcdf-trust")
    )
    bom.metadata.properties.update(
        props(
            properties(
                [
                    ("hcdf:lock-sha256", facts.lock_sha256),
                    ("hcdf:bundle-sha256", facts.bundle_sha256),
                    ("hcdf:release:sequence-number", facts.release_sequence),
                    ("hcdf:release:key-sha256", facts.release_key_sha256),
                ]
            )
        )
    )
    by_ref: dict[str, Component] = {}
    robot = by_ref[facts.robot.ref] = assembly(facts.robot)
    bom.metadata.component = robot
    for a in facts.assemblies:
        by_ref[a.ref] = assembly(a)
    for c in facts.comps:
        by_ref[c.ref] = Component(
            type=ComponentType.DEVICE,
            name=c.name,
            bom_ref=c.ref,
            description=c.description,
            properties=props(comp_properties(c)),
        )
    for f in facts.firmware:
        by_ref[f.ref] = Component(
            type=ComponentType.FIRMWARE,
            name=f.name,
            version=f.version,
            bom_ref=f.ref,
            hashes=sha256(f.signature.file_sha256 if f.signature else None),
            properties=props(firmware_properties(f)),
            external_references=provenance() if f.signature else None,
        )
    for d in facts.drivers:
        by_ref[d.ref] = Component(type=ComponentType.DEVICE_DRIVER, name=d.name, bom_ref=d.ref)
    for fl in facts.files:
        by_ref[fl.ref] = Component(
            type=ComponentType.FILE,
            name=fl.name,
            bom_ref=fl.ref,
            hashes=sha256(fl.sha256),
            properties=props(file_properties(fl)),
        )
    for component in by_ref.values():
        if component is not robot:
            bom.components.add(component)
    for ref, deps in facts.all_refs().items():
        bom.register_dependency(by_ref[ref], [by_ref[d] for d in deps])
    text: Any = JsonV1Dot6(bom).output_as_string(indent=2)
    return (str(text) + "\n").encode()
