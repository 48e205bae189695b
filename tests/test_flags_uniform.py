"""One set of rules a user learns once (issue 16 §8): the same flag means the same thing, and
reads the same in --help, in every verb.

- Every verb that reads a description tree takes resolve's ``--base``, ``--mirror``, ``--root``,
  ``--cache-dir``, ``--lock``, ``--ca-bundle`` and ``--offline`` (validate, which reads local
  files only, the first three), with resolve's help text.
- Every verb takes ``--json``; every verb that writes spells its output ``-o``/``--out``.
- Options are accepted before or after the positional arguments.
"""

from __future__ import annotations

import hashlib
import json
import shutil

import click
import pytest

from hcdf_trust.cli import main

from .conftest import PROJECT


def _leaves(cmd: click.Command, path: tuple[str, ...] = ()) -> list[tuple[str, click.Command]]:
    if not isinstance(cmd, click.Group):
        return [(" ".join(path), cmd)]
    ctx = click.Context(cmd)
    out = []
    for name in cmd.list_commands(ctx):
        sub = cmd.get_command(ctx, name)
        assert sub is not None
        out += _leaves(sub, (*path, name))
    return out


VERBS = dict(_leaves(main))
TREE_VERBS = [
    "bundle write",  # also `bundle DOC OUT`
    "audit",
    "sbom",
    "ota build",
    "fleet status",
    "fleet update",
    "fleet confirm",
    *(f"macsec {v}" for v in ("plan", "generate", "status", "rotate", "export")),
]
LOCATION_FLAGS = ["--base", "--mirror", "--root"]
TREE_FLAGS = [*LOCATION_FLAGS, "--cache-dir", "--lock", "--ca-bundle"]


def _option(cmd: click.Command, flag: str) -> click.Option | None:
    for p in cmd.params:
        if isinstance(p, click.Option) and (flag in p.opts or flag in p.secondary_opts):
            return p
    return None


def test_the_verbs_are_all_found():
    assert {"resolve", "verify", "pin", "validate", "audit", "sbom", "ota build", "registry init"} <= set(VERBS)
    assert len(VERBS) >= 23


@pytest.mark.parametrize("verb", [*TREE_VERBS, "validate"])
def test_tree_verbs_take_resolves_flags_with_resolves_help(verb):
    flags = LOCATION_FLAGS if verb == "validate" else TREE_FLAGS
    for flag in flags:
        ours, theirs = _option(VERBS[verb], flag), _option(VERBS["resolve"], flag)
        assert ours is not None, f"{verb} has no {flag}"
        assert theirs is not None
        assert ours.help == theirs.help, flag
        assert ours.multiple == theirs.multiple and ours.metavar == theirs.metavar, flag


@pytest.mark.parametrize("verb", ["sbom", "audit", "macsec plan"])
def test_online_tree_verbs_trust_the_ca_bundle_they_are_given(cli, https_server, tls, tmp_path, verb):
    """--online fetches over https with --ca-bundle's CAs, in every tree verb (sbom and macsec had none)."""
    data = b"model bytes"
    url = https_server.add("/a.glb", data)
    doc = tmp_path / "r.hcdf"
    doc.write_text(
        '<?xml version="1.0"?>\n<hcdf version="1.0" name="r">\n<comp name="a"><visual>'
        f'<model uri="{url}" sha="{hashlib.sha256(data).hexdigest()}"/></visual></comp>\n</hcdf>\n'
    )
    assert cli("resolve", doc, "--ca-bundle", tls.ca_pem, "--cache-dir", tmp_path / "warm").exit_code == 0
    extra = ["--format", "cyclonedx"] if verb == "sbom" else []
    args = (*verb.split(), doc, *extra, "--online", "--cache-dir", tmp_path / "cold", "--json")
    untrusted = cli(*args)
    assert untrusted.exit_code == (1 if verb == "audit" else 3), untrusted.stdout  # audit: a finding
    assert "certificate" in json.dumps(untrusted.json["errors"]).lower()
    trusted = cli(*args, "--ca-bundle", tls.ca_pem)
    assert trusted.exit_code in (0, 1) and not any(  # audit may find other things; none about the fetch
        "certificate" in json.dumps(e).lower() for e in trusted.json.get("errors", [])
    ), trusted.stdout
    assert https_server.hits["/a.glb"] == 2  # resolve's, then the trusted run's (the untrusted one never got it)


@pytest.mark.parametrize("verb", TREE_VERBS)
def test_tree_verbs_are_offline_unless_told_with_resolves_wording(verb):
    offline = _option(VERBS[verb], "--offline")
    assert offline is not None and offline.secondary_opts == ["--online"]
    assert offline.default is True
    resolve_offline = _option(VERBS["resolve"], "--offline")
    assert resolve_offline is not None and resolve_offline.help
    assert offline.help is not None and offline.help.startswith(resolve_offline.help)


@pytest.mark.parametrize("verb", sorted(VERBS))
def test_every_verb_takes_json_with_one_wording(verb):
    option = _option(VERBS[verb], "--json")
    assert option is not None, f"{verb} has no --json"
    assert option.is_flag and option.name == "as_json"
    assert option.help is not None and option.help.startswith("Print one JSON object on stdout")


@pytest.mark.parametrize("verb", sorted(VERBS))
def test_outputs_are_spelled_o_and_out(verb):
    for flag in ("-o", "--out"):
        option = _option(VERBS[verb], flag)
        if option is not None:
            assert sorted(option.opts) == ["--out", "-o"], (verb, option.opts)


def _value(p: click.Parameter) -> str:
    """A value the parser accepts for ``p``: an existing file "f" or folder "d" (cwd), a choice."""
    if isinstance(p.type, click.Choice):
        return str(p.type.choices[0])
    if isinstance(p.type, click.Path) and not p.type.file_okay:
        return "d"
    return "f"


@pytest.mark.parametrize("verb", sorted(VERBS))
def test_options_are_accepted_before_or_after_the_positional_argument(verb, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "f").write_text("")
    (tmp_path / "d").mkdir()
    cmd = VERBS[verb]
    positional = [_value(p) for p in cmd.params if isinstance(p, click.Argument)]
    options = [w for p in cmd.params if isinstance(p, click.Option) and p.required for w in (p.opts[-1], _value(p))]
    options.append("--json")
    after = cmd.make_context(verb, [*positional, *options])
    before = cmd.make_context(verb, [*options, *positional])
    assert before.params == after.params
    assert after.params["as_json"] is True


@pytest.mark.parametrize("order", ["after", "before"])
@pytest.mark.parametrize("update", [(), ("models/arm.glb",)])
def test_resolve_update_before_or_after_doc(tmp_path, monkeypatch, cli, order, update):
    # --update's value is optional; given before DOC it used to swallow DOC ("Missing argument").
    shutil.copytree(PROJECT / "examples" / "robot", tmp_path / "robot")
    monkeypatch.chdir(tmp_path)
    flags = ["--update", *update]
    args = ["robot/robot.hcdf", *flags] if order == "after" else [*flags, "robot/robot.hcdf"]
    r = cli("resolve", *args, "--no-lock", "--json")
    if update:  # a uri the lock does not have: named as such, whatever the order
        assert r.exit_code == 3, r.stderr
        assert "models/arm.glb" in r.stdout
    else:
        assert r.exit_code == 0, r.stderr
        assert json.loads(r.stdout)["ok"] is True


def _shape(r, *keys: str) -> dict:
    """The --json rules of docs/commands.md: exit 0, one JSON object on stdout, ok true, errors [], the keys."""
    assert r.exit_code == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["ok"] is True and out["errors"] == []
    assert set(keys) <= set(out), (keys, sorted(out))
    return out


def test_the_registry_verbs_print_one_json_object(cli, tmp_path, monkeypatch):
    from tests._registry import PASSPHRASE, PROFILE, ROS2_XSD

    from .conftest import HCDFORMAT

    monkeypatch.setenv("HCDF_TRUST_PASSPHRASE", PASSPHRASE)
    src, keys, owner = tmp_path / "src", tmp_path / "keys", tmp_path / "keys-ros2"
    init = _shape(cli("registry", "init", src, "--keys", keys, "--json"), "roles")
    assert set(init["roles"]) == {"root", "targets", "snapshot", "timestamp"}
    keygen = _shape(cli("registry", "keygen", "--keys", owner, "-o", tmp_path / "ros2.pub", "--json"), "keyid")
    assert (owner / f"{keygen['keyid']}.key").is_file()
    add = ["registry", "add", src, "--domain", "org.ros2", "--version", "1.0", "--schema", ROS2_XSD]
    add += ["--content", HCDFORMAT, "--keys", owner, "--owner", "ROS 2", "--owner-key", tmp_path / "ros2.pub"]
    assert _shape(cli(*add, "--json"), "recorded")["unchanged"] is False
    profile = ["registry", "add", src, "--profile", PROFILE, "--content", HCDFORMAT, "--json"]
    _shape(cli(*profile), "recorded")
    assert _shape(cli(*profile), "recorded")["unchanged"] is True  # again: nothing to record
    statement = ["registry", "statement", "--domain", "org.ros2", "--version", "1.0", "--schema", ROS2_XSD]
    stmt = _shape(cli(*statement, "--content", HCDFORMAT, "-o", tmp_path / "s.json", "--json"), "wrote")
    assert stmt["wrote"] == [str(tmp_path / "s.json")] and (tmp_path / "s.json").is_file()
    site = tmp_path / "site"
    publish = ["registry", "publish", src, "--keys", keys, "--keys", owner, "--content", HCDFORMAT, "-o", site]
    _shape(cli(*publish, "--json"), "versions")
    client = ["--from", site, "--trusted-root", site / "metadata" / "1.root.json", "--cache-dir", tmp_path / "c"]
    fetched = _shape(cli("registry", "fetch", "org.ros2", *client, "-o", tmp_path / "ros2.xsd", "--json"), "size")
    assert fetched["size"] == len(ROS2_XSD.read_bytes()) == len((tmp_path / "ros2.xsd").read_bytes())
    rotated = _shape(cli("registry", "rotate", src, "--role", "timestamp", "--keys", keys, "--json"), "keyid")
    assert rotated["role"] == "timestamp" and rotated["keyid"] != init["roles"]["timestamp"]


@pytest.mark.parametrize("fmt", ["cyclonedx", "spdx"])
def test_sbom_json_holds_the_sbom_or_names_the_file(cli, tmp_path, monkeypatch, fmt):
    shutil.copytree(PROJECT / "examples" / "robot", tmp_path / "robot")
    monkeypatch.chdir(tmp_path)
    plain = cli("sbom", "robot/robot.hcdf", "--format", fmt)
    assert plain.exit_code == 0, plain.stderr
    inline = _shape(cli("sbom", "robot/robot.hcdf", "--format", fmt, "--json"), "sbom", "warnings", "wrote")
    assert inline["sbom"] == json.loads(plain.stdout) and inline["wrote"] == []
    written = _shape(cli("sbom", "robot/robot.hcdf", "--format", fmt, "-o", "bom.json", "--json"), "wrote")
    assert written["wrote"] == ["bom.json"] and "sbom" not in written
    assert json.loads((tmp_path / "bom.json").read_bytes()) == inline["sbom"]


def test_every_json_object_has_ok_and_errors(cli, tmp_path, monkeypatch):
    # emit_json adds docs/commands.md's "errors" to a payload that lacks it (macsec plan did).
    shutil.copytree(PROJECT / "examples" / "robot", tmp_path / "robot")
    monkeypatch.chdir(tmp_path)
    _shape(cli("macsec", "plan", "robot/robot.hcdf", "--json"), "associations")
    _shape(cli("verify", "robot/robot.hcdf", "--json"), "artifacts")


def test_provenance_key_and_threshold_are_one_pair_of_options():
    """--provenance-key and --threshold come from one decorator (cli/params.py): the same type,
    bounds and default in every verb that verifies a provenance; the help differs only where
    the verb has a release --key that counts as a signer too (ota verify, ota pull)."""
    besides_key = {"ota verify", "ota pull"}
    verbs = [*sorted(besides_key), "verify", "bundle pull", "bundle push"]
    helps: dict[bool, set[tuple[str | None, str | None]]] = {True: set(), False: set()}
    for verb in verbs:
        key, threshold = _option(VERBS[verb], "--provenance-key"), _option(VERBS[verb], "--threshold")
        assert key is not None and threshold is not None, verb
        assert key.multiple and key.name == "provenance_keys", verb
        assert isinstance(threshold.type, click.IntRange), verb
        assert (threshold.type.min, threshold.type.max, threshold.default) == (1, 64, 1), verb
        helps[verb in besides_key].add((key.help, threshold.help))
    assert len(helps[True]) == 1 and len(helps[False]) == 1, helps
    [(with_key, _)] = helps[True]
    [(without_key, _)] = helps[False]
    assert "besides --key" in (with_key or "") and "--key" not in (without_key or "")
