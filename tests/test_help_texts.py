"""--help describes only what a verb has; messages name a file once and count in words."""

from __future__ import annotations

import hashlib
import re

import click

from hcdf_trust.cli import main


def _commands():
    def walk(group, path, ctx):
        for name in group.list_commands(ctx):
            command = group.get_command(ctx, name)
            yield [*path, name], command
            if isinstance(command, click.Group):
                yield from walk(command, [*path, name], click.Context(command, parent=ctx, info_name=name))

    return list(walk(main, [], click.Context(main, info_name="hcdf-trust")))


def _option_help(cli, *verb: str) -> dict[str, str]:
    """Each option's help text of ``hcdf-trust VERB --help``, joined onto one line."""
    r = cli(*verb, "--help")
    assert r.exit_code == 0
    text = r.stdout.split("Options:", 1)[1]
    options: dict[str, str] = {}
    for block in re.split(r"\n(?=  -)", text):
        names = re.findall(r"--[a-z0-9-]+", block.split("  ", 2)[1] if "  " in block else block)
        if names:
            options[names[0]] = " ".join(block.split())
    return options


def test_no_help_mentions_an_option_its_verb_lacks(cli):
    for path, command in _commands():
        if isinstance(command, click.Group):
            continue
        r = cli(*path, "--help")
        assert r.exit_code == 0, path
        have = {o for p in command.params for o in [*p.opts, *getattr(p, "secondary_opts", [])]}
        mentioned = set(re.findall(r"(?<![\w-])--[a-z][a-z0-9-]+", r.stdout))
        assert mentioned <= have | {"--help"}, (path, sorted(mentioned - have))


def test_verify_registry_takes_a_folder_and_resolve_a_url_or_folder(cli):
    verify = _option_help(cli, "verify")["--registry"]
    assert "--registry DIR " in verify and "URL" not in verify, verify
    resolve = _option_help(cli, "resolve")["--registry"]
    assert "URL|DIR" in resolve and "http(s) URL (not with --offline)" in resolve, resolve


def test_pkcs11_module_is_described_as_the_library_not_the_key(cli):
    for verb in ("generate", "status", "rotate", "retire", "export"):
        text = _option_help(cli, "macsec", verb)["--pkcs11-module"]
        assert text.startswith("--pkcs11-module FILE PKCS#11 library") and "Keep" not in text, text


def test_short_help_lines_end_where_a_sentence_ends():
    for path, command in _commands():
        short = command.get_short_help_str(limit=1000)
        assert short.count("(") == short.count(")"), (path, short)  # "(e.g." read as a sentence end


def test_a_missing_document_is_named_once(cli, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    for verb in ("verify", "resolve"):
        r = cli(verb, "robto.hcdf")
        assert r.exit_code == 3
        assert r.stderr.strip() == "error: robto.hcdf: no such file", r.stderr


def test_counts_are_grammatical(cli, tmp_path):
    model = b"glTF one model"
    (tmp_path / "m.glb").write_bytes(model)
    doc = tmp_path / "r.hcdf"
    doc.write_text(
        '<?xml version="1.0"?>\n<hcdf version="1.0" name="r"><comp name="c"><visual name="v">'
        f'<model href="m.glb" sha="{hashlib.sha256(model).hexdigest()}"/></visual></comp></hcdf>\n'
    )
    r = cli("resolve", doc)
    assert r.exit_code == 0, r.stderr
    assert "1 reference to 1 file:" in r.stderr, r.stderr
