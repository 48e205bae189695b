"""``hcdf-trust convert IN OUT``: an HCDF document from XML to its JSON form or back (hcdf_trust.jsonform)."""

from __future__ import annotations

import os

import click

from ..errors import counted
from . import JSON_OPTION, SCHEMA_OPTION, emit_json, handle_errors, say


@click.command()
@click.argument("source", metavar="IN", type=click.Path(dir_okay=False))
@click.argument("dest", metavar="OUT", type=click.Path(dir_okay=False, allow_dash=True))
@SCHEMA_OPTION
@JSON_OPTION
@handle_errors
def convert(source: str, dest: str, as_json: bool) -> None:
    """Convert IN (XML, or HCDF's JSON form) to the other form, written to OUT (- for stdout).

    The direction is IN's: JSON (its first character is "{") becomes XML, XML becomes JSON;
    OUT's name must agree (.json for JSON, anything else for XML). Both forms are read through
    the HCDF schema (--schema) as every verb reads them, and the output is read back: a
    conversion that would change any reference or pin is refused (exit 3), nothing written.
    The JSON form drops comments and the order between differently named elements: see
    docs/json-form.md.
    """
    from ..bundle import is_bundle
    from ..document import is_json_form
    from ..include.locate import display_path
    from ..jsonform import convert as do_convert
    from ..localfile import absolute
    from ..outputs import DOCUMENT, ORDINARY, OutputPlan
    from ..validate.includes import read_local

    if is_bundle(source):  # a ZIP of many documents: read as XML it would only be "malformed XML"
        raise click.UsageError(
            f"{source}: a bundle (.hcdfz) holds a whole tree, and convert converts one document: convert the "
            "root document the bundle was written from; resolve, validate and verify read the bundle as it is"
        )
    if is_bundle(dest):  # every verb would read it as a ZIP: bundles are written by `bundle`
        raise click.UsageError(
            f"{dest}: a converted document is XML or JSON, not a bundle (hcdf-trust bundle writes those)"
        )
    if as_json and dest == "-":
        raise click.UsageError("--json and OUT - would both write to stdout: name an OUT file")
    path = absolute(source)
    shown = display_path(path)
    plan = OutputPlan()
    plan.protect(path, what="the input document")
    data = read_local(path, os.path.dirname(path), source=shown)
    to = "xml" if is_json_form(data) else "json"
    if dest != "-" and dest.lower().endswith(".json") != (to == "json"):
        wanted = "a name ending in .json" if to == "json" else "a name not ending in .json (.hcdf)"
        raise click.UsageError(
            f"{shown} is {'XML' if to == 'json' else 'JSON'}, so it converts to {to.upper()}: give OUT {wanted}, or -"
        )
    result = do_convert(data, source=shown)
    plan.add(dest, result.data, flag="OUT", stdout=True, if_changed=True, replaces=(ORDINARY, DOCUMENT))
    wrote = plan.commit()
    if as_json:
        emit_json(
            {
                "ok": True,
                "input": shown,
                "output": dest if dest == "-" else display_path(absolute(dest)),
                "to": result.to,
                "written": bool(wrote),
                "schema": result.schema,
                "schema_sha256": result.schema_sha256,
                "references": result.references,
                "losses": result.losses,
            }
        )
        return
    where = "stdout" if dest == "-" else display_path(absolute(dest))
    say(
        f"converted {shown} to {result.to.upper()} ({where}) through {result.schema} (sha256 {result.schema_sha256}): "
        f"{counted(result.references, 'reference')} unchanged"
    )
    if result.losses:
        say(f"note: the JSON form does not keep {', '.join(result.losses)}")
