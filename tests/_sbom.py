"""Helpers of the sbom tests: each format's own validator, and readers of the two outputs."""

from __future__ import annotations

import io
import json
from typing import Any


def validate_cyclonedx(text: str) -> None:
    """CycloneDX 1.6 JSON schema (cyclonedx-python-lib's strict validator); raises on any violation."""
    from cyclonedx.schema import SchemaVersion
    from cyclonedx.validation.json import JsonStrictValidator

    error = JsonStrictValidator(SchemaVersion.V1_6).validate_str(text)
    assert error is None, str(error)[:2000]


def validate_spdx(data: bytes) -> None:
    """SPDX 3.0.1 through the official validator (``spdx3-validate``, offline: JSON Schema and
    SHACL), then through the official bindings: deserialising checks every type, enum and
    IRI; serialising again checks every required property and cardinality, and must give
    the same bytes (nothing was dropped or added)."""
    from spdx_python_model import v3_0_1 as spdx

    from tests._spdx3 import spdx3_validate

    errors = spdx3_validate(data)
    assert not errors, "\n".join(errors)[:4000]

    objset = spdx.SHACLObjectSet()
    spdx.JSONLDDeserializer().read(io.BytesIO(data), objset)
    out = io.BytesIO()
    spdx.JSONLDSerializer().write(objset, out, indent=2)
    assert out.getvalue().rstrip(b"\n") == data.rstrip(b"\n")


def cdx_components(bom: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Every component by bom-ref, the metadata component included."""
    out = {c["bom-ref"]: c for c in bom.get("components", [])}
    out[bom["metadata"]["component"]["bom-ref"]] = bom["metadata"]["component"]
    return out


def cdx_props(component: dict[str, Any]) -> dict[str, str]:
    return {p["name"]: p["value"] for p in component.get("properties", [])}


def cdx_sha256(component: dict[str, Any]) -> str | None:
    hashes = [h["content"] for h in component.get("hashes", []) if h["alg"] == "SHA-256"]
    assert len(hashes) <= 1
    return hashes[0] if hashes else None


def cdx_graph(bom: dict[str, Any]) -> dict[str, set[str]]:
    return {d["ref"]: set(d.get("dependsOn", [])) for d in bom["dependencies"]}


def spdx_graph(data: bytes) -> tuple[dict[str, dict[str, Any]], dict[tuple[str, str], set[str]]]:
    """(elements by local id, {(from, relationshipType): {to}}), ids without the document prefix."""
    graph = json.loads(data)["@graph"]
    doc = next(o for o in graph if o["type"] == "SpdxDocument")
    prefix = doc["spdxId"].rsplit("/", 1)[0] + "/"

    def local(iri: str) -> str:
        assert iri.startswith(prefix), iri
        return iri[len(prefix) :]

    elements = {local(o["spdxId"]): o for o in graph if "spdxId" in o}
    rels: dict[tuple[str, str], set[str]] = {}
    for o in graph:
        if o["type"] == "Relationship":
            rels.setdefault((local(o["from"]), o["relationshipType"]), set()).update(local(t) for t in o["to"])
    return elements, rels


def spdx_props(element: dict[str, Any]) -> dict[str, str]:
    out = {}
    for ext in element.get("extension", []):
        for p in ext["extension_cdxProperty"]:
            out[p["extension_cdxPropName"]] = p["extension_cdxPropValue"]
    return out
