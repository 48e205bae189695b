"""``hcdf-trust validate``: XSD and HCDF semantic rules (hcdf_trust.validate)."""

from __future__ import annotations

import sys
from typing import Any

import click

from ..errors import counted
from . import (
    CA_BUNDLE_OPTION,
    INSECURE_REGISTRY_OPTION,
    SCHEMA_ENV,
    emit_json,
    handle_errors,
    say,
    tree_location_options,
    use_schemas,
)
from .params import ConfigOption


@click.command()
@click.argument("doc", type=click.Path(dir_okay=False))
@click.option(
    "--schema",
    "schemas",
    multiple=True,
    type=click.Path(dir_okay=False),
    envvar=SCHEMA_ENV,
    callback=use_schemas,
    help="XSD to validate against (the official schemas are not shipped), and that a document in HCDF's JSON "
    "form is read through; repeatable: the one that declares the document's root and version is used, and "
    f"reported with its SHA-256 [env: {SCHEMA_ENV}].",
)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object on stdout.")
@click.option(
    "--registry",
    "registry_site",
    cls=ConfigOption,
    config_key="registry.site",
    help="Registry (https URL, oci:// artifact or folder): schemas, extensions, stream profiles.",
)
@click.option(
    "--trusted-root",
    cls=ConfigOption,
    config_key="registry.trusted-root",
    type=click.Path(dir_okay=False),
    help="The registry's root.json you trust.",
)
@click.option("--strict", is_flag=True, help="With --registry: unregistered extension domains/versions are errors.")
@CA_BUNDLE_OPTION  # for an https or oci:// --registry, as in every verb that talks https
@INSECURE_REGISTRY_OPTION
@tree_location_options
@handle_errors
def validate(
    doc: str,
    schemas: tuple[str, ...],
    as_json: bool,
    registry_site: str | None,
    trusted_root: str | None,
    strict: bool,
    ca_bundle: str | None,
    insecure_registries: tuple[str, ...],
    tree: Any,
) -> None:
    """Validate DOC against an XSD and check the HCDF semantic rules the XSD cannot express.

    Exits 1 if any error was found; every finding is listed, not just the first. Includes are
    read from local files only (--base, --mirror and --root as resolve's; nothing is fetched).
    """
    from ..validate import SchemaChoiceError, validate_document

    try:
        if registry_site:
            from .registry import validate_with_registry

            report = validate_with_registry(
                doc,
                schema=schemas,
                site=registry_site,
                trusted_root=trusted_root,
                strict=strict,
                tree=tree,
                ca_bundle=ca_bundle,
                insecure_registries=insecure_registries,
            )
        else:
            report = validate_document(doc, schema=schemas, tree_options=tree)
    except SchemaChoiceError as exc:
        raise click.UsageError(exc.message) from None
    if as_json:
        emit_json(
            {
                "ok": report.ok,
                "checked": report.checked,
                "schema": report.schema,
                "schema_sha256": report.schema_sha256,
                "notes": list(report.notes),
                "findings": [f.to_dict() for f in report.findings],
                "errors": [f.to_dict() for f in report.findings if f.severity == "error"],
            }
        )
    else:
        for f in report.findings:
            say(str(f), always=True)
        for n in report.notes:
            say(f"note: {n}")
        if report.schema is None:
            say("note: no --schema given: only the semantic rules were checked")
        else:
            say(f"validated against {report.schema} (sha256 {report.schema_sha256})")
        errors = sum(1 for f in report.findings if f.severity == "error")
        say(f"{counted(errors, 'error')}, {counted(len(report.findings) - errors, 'warning')}")
    sys.exit(0 if report.ok else 1)
