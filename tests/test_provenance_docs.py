"""docs/provenance.md: its statement of the example robot is the real one (built here with the
key and date the page names), every field of it is explained on the page, and the build type
the page defines is the one the code writes and verifies."""

from __future__ import annotations

import base64
import json
import re
import shutil

from hcdf_trust.provenance import BUILD_TYPE, FILE_NAME

from .conftest import PROJECT

PAGE = PROJECT / "docs" / "provenance.md"
EPOCH = "1780000000"  # 2026-05-28T20:26:40Z, as the page says
SEED = bytes(range(32))  # the page's Ed25519 key: private bytes 00 01 … 1f (a test key, public on purpose)


def _statement_block() -> dict:
    text = PAGE.read_text()
    marker = "<!-- docs-test: the example robot's statement (tests/test_provenance_docs.py) -->"
    assert marker in text
    return json.loads(text.split(marker, 1)[1].split("```json\n", 1)[1].split("```", 1)[0])


def render(stmt: dict) -> str:
    """The statement as the page shows it (one subject or dependency per line)."""

    def one(value: object) -> str:
        if isinstance(value, dict) and "digest" in value:  # name, uri first: what the digest is of
            value = dict(sorted(value.items(), key=lambda kv: ["name", "uri", "digest"].index(kv[0])))
        return json.dumps(value, ensure_ascii=False)

    b, r = stmt["predicate"]["buildDefinition"], stmt["predicate"]["runDetails"]
    deps = ",\n".join(f"        {one(d)}" for d in b["resolvedDependencies"])
    subjects = ",\n".join(f"    {one(s)}" for s in stmt["subject"])
    return (
        "{\n"
        f'  "_type": {one(stmt["_type"])},\n'
        f'  "subject": [\n{subjects}\n  ],\n'
        f'  "predicateType": {one(stmt["predicateType"])},\n'
        '  "predicate": {\n'
        '    "buildDefinition": {\n'
        f'      "buildType": {one(b["buildType"])},\n'
        f'      "externalParameters": {one(b["externalParameters"])},\n'
        f'      "resolvedDependencies": [\n{deps}\n      ]\n'
        "    },\n"
        '    "runDetails": {\n'
        f'      "builder": {one(r["builder"])},\n'
        f'      "metadata": {one(r["metadata"])}\n'
        "    }\n"
        "  }\n"
        "}\n"
    )


def build_example(tmp_path, cli, monkeypatch) -> dict:
    from cryptography.hazmat.primitives import serialization as s
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

    monkeypatch.setenv("SOURCE_DATE_EPOCH", EPOCH)
    for name in ("GITHUB_SERVER_URL", "GITHUB_REPOSITORY", "GITHUB_RUN_ID"):
        monkeypatch.delenv(name, raising=False)
    robot = tmp_path / "robot"
    shutil.copytree(PROJECT / "examples" / "robot", robot)
    key = tmp_path / "k.pem"
    private = Ed25519PrivateKey.from_private_bytes(SEED)
    key.write_bytes(private.private_bytes(s.Encoding.PEM, s.PrivateFormat.PKCS8, s.NoEncryption()))
    key.chmod(0o600)
    out = tmp_path / "release"
    r = cli("ota", "build", robot / "robot.hcdf", "--firmware-dir", robot / "firmware", "--key", key,
            "--out", out, "--base-url", "https://firmware.example.com/scout2", "--provenance")  # fmt: skip
    assert r.exit_code == 0, r.stderr
    return json.loads(base64.b64decode(json.loads((out / FILE_NAME).read_bytes())["payload"]))


def test_the_pages_statement_is_the_example_robots(tmp_path, cli, monkeypatch):
    real = build_example(tmp_path, cli, monkeypatch)
    assert _statement_block() == real, "docs/provenance.md's statement is stale; the real one:\n" + render(real)
    assert json.loads(render(real)) == real  # the renderer drops nothing


def test_every_field_of_the_statement_is_explained():
    text = PAGE.read_text()
    stmt = _statement_block()
    b = stmt["predicate"]["buildDefinition"]
    fields = [*stmt, *stmt["predicate"], *b, *b["externalParameters"], *stmt["predicate"]["runDetails"]]
    fields += ["id", "invocationId", "startedOn", "finishedOn", "digest", "uri", "name"]
    fields += ["hcdf-root", "hcdf-lock", "hcdf-firmware:", "payloadType", "payload", "signatures", "keyid", "sig"]
    for field in fields:
        assert re.search(rf"^ *(- |\| )`{re.escape(field)}`", text, re.M), (
            f"{field} is not explained (a list or table entry)"
        )


def test_the_page_defines_the_build_type_the_code_uses():
    text = PAGE.read_text()
    assert f"## The build type `{BUILD_TYPE}`" in text
