"""docs/ and the README checked against the code, so neither can go stale.

Every fenced example in README.md and docs/*.md has an oracle: Python runs, every
``hcdf-trust`` command line names a real verb and only options that verb has, TOML, JSON, XML
and YAML parse (and the tests named in ``ORACLES`` read them further), the source layout names
files that exist. Every relative link resolves, anchors included; every page is in the table of
contents; the README's tour is the ``make demo`` recipe; the tables of ``ota.toml`` keys and audit
checks are the code's.
"""

from __future__ import annotations

import json
import re
import shlex
import shutil
import textwrap
import tomllib
from dataclasses import dataclass, fields
from pathlib import Path

import click
import pytest
import yaml
from lxml import etree

from hcdf_trust.cli import main

from .conftest import PROJECT
from .test_flatten_root import demo_lines

DOCS = PROJECT / "docs"
PAGES = sorted(DOCS.glob("*.md"))
ALL = [PROJECT / "README.md", *PAGES]
ILLUSTRATIVE = "<!-- docs-test: illustrative"  # a block shortened with "…": parsed by no one, says why


@dataclass(frozen=True)
class Block:
    path: Path
    line: int  # of the opening fence, 1-based
    lang: str
    text: str
    before: str  # the last non-blank line before the fence

    def __str__(self) -> str:
        return f"{self.path.relative_to(PROJECT)}:{self.line} ({self.lang or 'no language'})"


def blocks(path: Path) -> list[Block]:
    out: list[Block] = []
    lines = path.read_text().splitlines()
    i = 0
    while i < len(lines):
        m = re.match(r"^( *)```(\S*)\s*$", lines[i])
        if not m:
            i += 1
            continue
        indent, lang, start = len(m.group(1)), m.group(2), i
        i += 1
        body: list[str] = []
        while not re.match(rf"^ {{{indent}}}```\s*$", lines[i]):
            body.append(lines[i])
            i += 1
        before = next((ln for ln in reversed(lines[:start]) if ln.strip()), "")
        out.append(Block(path, start + 1, lang, textwrap.dedent("\n".join(body)) + "\n", before.strip()))
        i += 1
    return out


ALL_BLOCKS = [b for p in ALL for b in blocks(p)]


def _prose(path: Path) -> str:
    """The page without its fenced blocks and inline code (where links are not links)."""
    text = re.sub(r"^( *)```.*?^\1```", "", path.read_text(), flags=re.S | re.M)
    return re.sub(r"`[^`\n]*`", "", text)


def _slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def _anchors(path: Path) -> set[str]:
    headings = [m.group(1) for m in re.finditer(r"^#{1,6} (.*)$", _prose_keep_code(path), re.M)]
    return {_slug(h) for h in headings}


def _prose_keep_code(path: Path) -> str:
    return re.sub(r"^( *)```.*?^\1```", "", path.read_text(), flags=re.S | re.M)


# ---------------------------------------------------------------------------- structure


def test_every_page_is_in_the_table_of_contents():
    toc = (DOCS / "README.md").read_text()
    for page in PAGES:
        if page.name != "README.md":
            assert f"]({page.name})" in toc, f"{page.name} is not linked from docs/README.md"
    readme = (PROJECT / "README.md").read_text()
    assert "](docs/README.md)" in readme


@pytest.mark.parametrize("path", ALL, ids=lambda p: str(p.relative_to(PROJECT)))
def test_every_relative_link_resolves(path):
    broken = []
    for m in re.finditer(r"\[[^\]]*\]\(([^)\s]+)\)", _prose(path)):
        target = m.group(1)
        if re.match(r"^[a-z][a-z0-9+.-]*:", target):  # https:, mailto:: not ours to check
            continue
        file, _, anchor = target.partition("#")
        dest = (path.parent / file).resolve() if file else path
        if not dest.exists():
            broken.append(f"{target}: no such file")
        elif anchor and dest.suffix == ".md" and anchor not in _anchors(dest):
            broken.append(f"{target}: no heading with anchor #{anchor} in {dest.name}")
    assert not broken, broken


def test_the_link_checker_finds_a_broken_link_and_anchor(tmp_path):
    """The oracle above, on a page with known breakage (so it cannot pass vacuously)."""
    page = tmp_path / "p.md"
    page.write_text("# Title\n\n[a](missing.md) [b](p.md#nowhere) [c](p.md#title) [d](https://x.example/)\n")
    found = [m.group(1) for m in re.finditer(r"\[[^\]]*\]\(([^)\s]+)\)", _prose(page))]
    assert found == ["missing.md", "p.md#nowhere", "p.md#title", "https://x.example/"]
    assert _anchors(page) == {"title"}
    assert _slug("`hcdf-trust ota push | pull` (OCI registries)") == "hcdf-trust-ota-push--pull-oci-registries"


def test_the_tour_is_the_demo_recipe():
    """README's tour lists exactly the ``make demo`` commands, in order (test_pipeline runs them)."""
    readme = (PROJECT / "README.md").read_text()
    tour = readme.split("## A ten-minute tour", 1)[1].split("\n## ", 1)[0]
    shown: list[str | list[str]] = []
    for block in blocks_of_text(tour, "sh"):
        for line in block.splitlines():
            if line.startswith("hcdf-trust "):
                shown.append(shlex.split(line)[1:])
            elif line.strip() and not line.startswith("rm -rf "):
                shown.append(line.strip())
    assert shown == demo_lines(Path("$CORPUS"))
    assert "rm -rf examples/out" in tour


def blocks_of_text(text: str, lang: str) -> list[str]:
    return re.findall(rf"^```{lang}\n(.*?)^```", text, re.S | re.M)


# ---------------------------------------------------------------------------- every example has an oracle

# What reads each kind of block beyond the generic checks below (parse, options exist, runs).
ORACLES = {
    "python": "run here (test_python_examples_run)",
    "sh": "hcdf-trust lines checked against the CLI here; the tour is run by test_pipeline, "
    "registry.md's block by test_registry_readme",
    "bash": "as sh",
    "console": "as sh (a shell session: its hcdf-trust lines are checked)",
    "toml": "parsed here; audit.md's is the built-in policy (test_audit_policy), ota-toml.md's load as ota.toml",
    "json": "parsed here; audit.md's is the real --json shape (test_audit_policy)",
    "xml": "parsed here; macsec.md's two robots are planned and compared (test_macsec_upstream)",
    "yaml": "parsed here, its hcdf-trust lines checked against the CLI",
    "cmake": "built with CMake and Ninja (test_integrations)",
    "": "a command synopsis (options checked against the CLI) or the source layout (paths exist)",
}


@pytest.mark.parametrize("block", ALL_BLOCKS, ids=str)
def test_every_example_has_an_oracle(block):
    assert block.lang in ORACLES, f"{block}: no test reads {block.lang!r} examples: add one to tests/test_docs.py"
    if block.before.startswith(ILLUSTRATIVE):
        assert "…" in block.text, f"{block}: marked illustrative but complete: check it instead"
        return
    if block.lang == "toml":
        tomllib.loads(block.text)
    elif block.lang == "json":
        json.loads(block.text)
    elif block.lang == "xml":
        etree.fromstring(block.text.encode())
    elif block.lang == "yaml":
        yaml.safe_load(block.text)
    elif block.lang == "":
        if block.text.startswith("hcdf_trust/"):  # the source layout
            for line in block.text.splitlines():
                path = line.split()[0]
                if "/" in path:
                    assert (PROJECT / path).exists(), f"{block}: {path} does not exist"
        else:
            assert block.text.startswith("hcdf-trust "), f"{block}: not a synopsis nor the layout"
    if block.lang in ("sh", "bash", "console", "yaml", ""):
        assert all(not problem for problem in command_problems(block.text)), (str(block), command_problems(block.text))


@pytest.mark.parametrize("block", [b for b in ALL_BLOCKS if b.lang == "python"], ids=str)
def test_python_examples_run(block, tmp_path, monkeypatch, capsys):
    shutil.copytree(PROJECT / "examples" / "robot", tmp_path / "examples" / "robot")
    monkeypatch.chdir(tmp_path)
    exec(compile(block.text, str(block.path), "exec"), {})


# ---------------------------------------------------------------------------- command lines


def _names(cmd: click.Command) -> set[str]:
    names = {"--help"}
    for p in cmd.params:
        if isinstance(p, click.Option):
            names.update(p.opts, p.secondary_opts)
    return names


def command_problems(text: str) -> list[str]:
    """Each ``hcdf-trust`` invocation in shell text: its verb exists and every option it
    writes is one of that verb's. Synopsis punctuation (``[``, ``]``, ``|``) is ignored."""
    problems = []
    joined = re.sub(r"\\\n\s*", " ", text)
    joined = re.sub(r"\n\s+(?=[\[|-])", " ", joined)  # a synopsis continued on an indented line
    for line in joined.splitlines():
        try:
            tokens = shlex.split(line, comments=True)
        except ValueError:
            tokens = line.split()
        while "hcdf-trust" in tokens:
            tokens = tokens[tokens.index("hcdf-trust") + 1 :]
            end = next((i for i, t in enumerate(tokens) if t in ("&&", "||", ";", "|", ">", "2>")), len(tokens))
            args, tokens = tokens[:end], tokens[end:]
            problems += _check_invocation(args, line)
    return problems


def _check_invocation(args: list[str], line: str) -> list[str]:
    cmd: click.Command = main
    path = ["hcdf-trust"]
    problems = []
    words = [w.strip("[]|") for w in args]
    i = 0
    while isinstance(cmd, click.Group) and i < len(words):
        word = words[i]
        default = getattr(cmd, "default_command", None)  # `bundle DOC OUT` is `bundle write DOC OUT`
        if default and word not in cmd.list_commands(click.Context(cmd)) and word not in ("-h", "--help"):
            cmd, path = cmd.get_command(click.Context(cmd), default), [*path, default]
            break
        if word.startswith("-"):
            if word.split("=")[0] not in _names(cmd):
                problems.append(f"{' '.join(path)}: no option {word} ({line.strip()})")
            i += 1
            continue
        sub = cmd.get_command(click.Context(cmd), word)
        if sub is None:
            return [f"{' '.join(path)}: no verb {word!r} ({line.strip()})"]
        cmd, path = sub, [*path, word]
        i += 1
    names = _names(cmd)
    for word in words[i:]:
        if word.startswith("-") and len(word) > 1 and not re.match(r"^-\d", word):
            if word.split("=")[0] not in names:
                problems.append(f"{' '.join(path)}: no option {word} ({line.strip()})")
    return problems


def test_the_command_checker_finds_a_wrong_verb_and_option():
    assert command_problems("hcdf-trust resolve robot.hcdf --locked --strict\n") == []
    assert command_problems("hcdf-trust pin robot.hcdf --registry x\n") == [
        "hcdf-trust pin: no option --registry (hcdf-trust pin robot.hcdf --registry x)"
    ]
    assert command_problems("hcdf-trust ota sing x\n")[0].startswith("hcdf-trust ota: no verb 'sing'")
    assert command_problems("hcdf-trust macsec status DOC --store DIR\n    [--json] [--bogus]\n") == [
        "hcdf-trust macsec status: no option --bogus (hcdf-trust macsec status DOC --store DIR [--json] [--bogus])"
    ]


# ---------------------------------------------------------------------------- reference tables


def test_ota_toml_page_names_every_key_and_its_example_loads(tmp_path):
    from hcdf_trust.ota.config import BoardSettings, ImageSettings, OtaConfig, load_config

    page = DOCS / "ota-toml.md"
    text = page.read_text()
    example, robot = blocks_of_text(text, "toml")
    (tmp_path / "ota.toml").write_text(example)
    config = load_config(tmp_path / "ota.toml")
    assert config.sequence_number == 12 and config.boards["default"].max_align == 8
    assert config.images["arm-ctrl"].dependencies[0].image == 1
    assert robot == (PROJECT / "examples" / "robot" / "ota.toml").read_text()

    def table(heading: str) -> list[str]:
        section = text.split(f"## `{heading}`", 1)[1].split("\n## ", 1)[0]
        return re.findall(r"^\| `([a-z_]+)` \|", section, re.M)

    release = [f.name for f in fields(OtaConfig) if f.name not in ("source", "boards", "images")]
    assert table("[release]") == release
    assert table("[boards.NAME]") == [f.name for f in fields(BoardSettings)]
    assert table("[images.APP]") == [f.name for f in fields(ImageSettings)]


def test_validate_rules_table_is_the_codes_rules():
    from hcdf_trust.validate.semantic import RULES

    text = (DOCS / "validate-rules.md").read_text()
    table = text.split("<!-- rules:begin -->\n", 1)[1].split("<!-- rules:end -->", 1)[0]
    rows = ["| code | what the rule checks |", "|---|---|"]
    rows += [f"| `{code}` | {what.replace('|', chr(92) + '|')} |" for code, what in RULES.items()]
    assert table == "\n".join(rows) + "\n", "regenerate the table between the markers from RULES"


def test_the_readme_stays_a_tour():
    """Reference goes to docs/ (one page per command group), not back into the README."""
    readme = (PROJECT / "README.md").read_text()
    assert len(readme.splitlines()) <= 200, "README.md is the newcomer's tour: put reference text in docs/"
    headings = re.findall(r"^## (.*)$", readme, re.M)
    assert headings == ["Install", "A ten-minute tour on the example robot", "Where to go next"]


def test_audit_rules_table_is_the_codes_checks():
    from hcdf_trust.audit.policy import CHECKS

    text = (DOCS / "audit-rules.md").read_text()
    rows = re.findall(r"^\| `([a-z-]+)` \| ([a-z-]+) \| ([a-z]+) \|", text, re.M)
    assert rows == [(name, c.area, c.severity) for name, c in CHECKS.items()]


# ---------------------------------------------------------------------------- verbs and options


def _verbs() -> dict[str, click.Command]:
    def walk(cmd: click.Command, path: tuple[str, ...]) -> list[tuple[str, click.Command]]:
        if not isinstance(cmd, click.Group):
            return [(" ".join(path), cmd)]
        ctx = click.Context(cmd)
        return [leaf for name in cmd.list_commands(ctx) for leaf in walk(cmd.get_command(ctx, name), (*path, name))]

    return dict(walk(main, ()))


# Options of other programs that the docs name: not ours, and not to be mistaken for ours.
FOREIGN = {
    "--no-deps": "pip wheel",
    "--repeat": "bench/*.py",
    "--before": "bench/oci.py, bench/oci_bundle.py",
    "--ours": "git checkout",
    "--theirs": "git checkout",
    "--align": "imgtool",
    "--max-align": "imgtool",
    "--require-provenance": "ota pull, named as not yet built (issue 22)",
    "--vendor-remote": "upstream's hcdf bundle (docs/bundles.md)",
    "--keep-remote": "upstream's hcdf bundle (docs/bundles.md)",
}
DOC_TEXT = "\n".join(p.read_text() for p in ALL)


def test_every_flag_the_docs_write_is_an_option_of_some_verb():
    """Every ``--flag`` anywhere in README/docs (prose too) exists; in examples, on that very verb
    (test_every_example_has_an_oracle)."""
    ours = set(_names(main)) | {n for cmd in _verbs().values() for n in _names(cmd)}
    written = set(re.findall(r"(?<![\w-])--[a-z][a-z0-9-]*", DOC_TEXT))
    assert sorted(written - ours - set(FOREIGN)) == []


def test_the_docs_mention_every_verb_and_every_option():
    headings = [h for h in re.findall(r"^#+ (.*)$", DOC_TEXT, re.M) if "hcdf-trust" in h]
    missing = []
    for verb, cmd in _verbs().items():
        group, _, leaf = verb.rpartition(" ")
        named = f"hcdf-trust {verb}" in DOC_TEXT or any(
            f"hcdf-trust {group} " in h and re.search(rf"(?<![\w-]){leaf}(?![\w-])", h) for h in headings if group
        )
        if not named:
            missing.append(verb)
        for p in cmd.params:
            longs = [o for o in p.opts if o.startswith("--")] if isinstance(p, click.Option) else []
            if longs and not any(o in DOC_TEXT for o in longs):
                missing.append(f"{verb} {longs[0]}")
    assert missing == []


def _all_commands() -> list[tuple[str, click.Command]]:
    def walk(cmd: click.Command, path: tuple[str, ...]) -> list[tuple[str, click.Command]]:
        out = [(" ".join(("hcdf-trust", *path)), cmd)]
        if isinstance(cmd, click.Group):
            ctx = click.Context(cmd)
            out += [c for name in cmd.list_commands(ctx) for c in walk(cmd.get_command(ctx, name), (*path, name))]
        return out

    return walk(main, ())


def test_every_option_a_help_text_names_is_one_of_that_command():
    """The raw help strings (before click wraps them, so a flag split at a line end is still
    seen), of groups too: a help may only name the options of its own command."""
    wrong = []
    for path, cmd in _all_commands():
        texts = [cmd.help or "", cmd.short_help or "", cmd.epilog or ""]
        texts += [p.help or "" for p in cmd.params if isinstance(p, click.Option)]
        for flag in sorted({f for text in texts for f in re.findall(r"(?<![\w-])--[a-z][a-z0-9-]*", text)}):
            if flag not in _names(cmd):
                wrong.append(f"{path}: {flag}")
    assert wrong == []
