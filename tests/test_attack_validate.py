"""Attack: validate's include findings cannot be hidden behind another include on the same line."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

HEAD = '<?xml version="1.0"?>\n'


def _doc(path: Path, root_attrs: str, body: str) -> Path:
    path.write_text(f'{HEAD}<hcdf version="1.0" name="{path.stem}"{root_attrs}>{body}</hcdf>\n')
    return path


@pytest.mark.parametrize("newline", ["", "\n"], ids=["one-line", "two-lines"])
@pytest.mark.parametrize(
    ("first", "code"),
    [
        ('<include uri="frd.hcdf" name="s"/>', "frame-convention-mismatch"),
        ('<include uri="../../../etc/passwd" name="s"/>', "include-refused"),
        ('<include uri="fifo.hcdf" name="s"/>', "include-refused"),
    ],
)
def test_an_include_followed_by_another_on_its_line_is_still_checked(tmp_path, cli, newline, first, code):
    os.mkfifo(tmp_path / "fifo.hcdf")
    _doc(tmp_path / "frd.hcdf", ' body-frame="FRD"', '<comp name="c"/>')
    _doc(tmp_path / "ok.hcdf", "", '<comp name="d"/>')
    root = _doc(tmp_path / "a.hcdf", ' body-frame="FLU"', f'{first}{newline}<include uri="ok.hcdf" name="o"/>')
    r = cli("validate", root, "--json")
    assert r.exit_code == 1, r.stdout
    assert [f["code"] for f in r.json["errors"]] == [code]
    assert r.json["errors"][0]["line"] == 2


@pytest.mark.parametrize(
    ("include", "code"),
    [
        ('<include href="frd.hcdf" name="s"/>', "frame-convention-mismatch"),
        ('<include href="../../../etc/passwd" name="s"/>', "include-refused"),
        ('<comp name="x"><include uri="frd.hcdf" name="s"/></comp>', "frame-convention-mismatch"),
        ('<comp name="x"><include href="../../../etc/passwd" name="s"/></comp>', "include-refused"),
    ],
    ids=["href", "href-escape", "nested", "nested-href-escape"],
)
def test_validate_checks_every_include_resolve_follows(tmp_path, cli, include, code):
    """The includes validate reads are the walker's (uri or href, at any depth), the ones resolve follows."""
    _doc(tmp_path / "frd.hcdf", ' body-frame="FRD"', '<comp name="c"/>')
    root = _doc(tmp_path / "a.hcdf", ' body-frame="FLU"', include)
    r = cli("validate", root, "--json")
    assert r.exit_code == 1, r.stdout
    assert [f["code"] for f in r.json["errors"]] == [code]
    assert r.json["errors"][0]["line"] == 2


def test_validate_never_shows_the_secret_of_an_include_url(tmp_path, cli):
    secret = "s3cr3t-Passw0rd"
    root = _doc(
        tmp_path / "a.hcdf",
        "",
        f'<include uri="https://user:{secret}@127.0.0.1:9/x.hcdf" name="x"/>'
        '<comp name="c"><port name="p" type="ethernet"/></comp><network name="n"><link name="l">'
        "<wired><port>x_c/p</port><port>c/p</port></wired></link></network>",
    )
    for args in ((), ("--json",)):
        r = cli("validate", root, *args)
        assert r.exit_code == 1, r.stdout + r.stderr
        assert "include-refused" in r.stdout + r.stderr
        assert secret not in r.stdout + r.stderr
        assert "https://***@127.0.0.1:9/x.hcdf" in r.stdout + r.stderr
