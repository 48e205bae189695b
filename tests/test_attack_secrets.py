"""Attack: a URL with a password in a reference that is refused for another reason first.

The credentials check runs when a reference is located; a malformed sha, whitespace
around the uri or a second, different href is refused earlier, by the walker or the
digest parser, and those messages quoted the uri as written, secret and all.
"""

from __future__ import annotations

import pytest

SECRET = "s3cr3t-Passw0rd"
URL = f"https://user:{SECRET}@127.0.0.1:9/m.glb"


@pytest.mark.parametrize(
    "element",
    [
        f'<model uri="{URL}" sha="abc"/>',  # malformed digest
        f'<model uri="{URL}" sha="{"z" * 64}"/>',
        f'<model uri=" {URL}"/>',  # whitespace around the uri
        f'<model uri="{URL}\u200b"/>',  # an invisible character
        f'<model uri="{URL}" href="https://user:{SECRET}@127.0.0.1:9/other.glb"/>',  # two references
        f'<model uri="a.glb">{URL}</model>',  # text inside a reference element
    ],
    ids=["short-sha", "non-hex-sha", "whitespace", "zero-width", "uri-and-href", "text"],
)
@pytest.mark.parametrize("verb", ["resolve", "verify", "pin", "validate"])
def test_no_message_shows_the_secret_of_a_refused_reference(cli, tmp_path, element, verb):
    doc = tmp_path / "robot.hcdf"
    doc.write_text(
        f'<?xml version="1.0"?>\n<hcdf version="1.0" name="r"><comp name="c"><visual name="v">{element}'
        "</visual></comp></hcdf>\n",
        encoding="utf-8",
    )
    for extra in ((), ("--json",)):
        r = cli(verb, doc, *extra)
        checks_digests = verb != "validate" or "sha=" not in element  # validate leaves sha formats to the XSD
        assert r.exit_code == (3 if checks_digests else 0), r.stdout + r.stderr
        assert SECRET not in r.stdout + r.stderr
