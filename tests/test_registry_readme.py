"""The `hcdf-trust registry` example of docs/registry.md runs as written (paths mapped to a temporary folder)."""

from __future__ import annotations

import re
import shlex
import shutil

from tests._oci import running_registry
from tests._registry import PASSPHRASE
from tests.conftest import HCDFORMAT, PROJECT
from tests.servers import LoopbackServer


def _block() -> list[list[str]]:
    section = (PROJECT / "docs" / "registry.md").read_text()
    block = re.search(r"```sh\n(.*?)```", section, re.S)
    assert block is not None
    text = block.group(1).replace("\\\n", " ")
    return [shlex.split(line, comments=True) for line in text.splitlines() if line.strip()]


def test_readme_registry_example_runs(cli, tmp_path, monkeypatch):
    monkeypatch.setenv("HCDF_TRUST_PASSPHRASE", PASSPHRASE)
    monkeypatch.chdir(tmp_path)
    (tmp_path / "hcdformat").symlink_to(HCDFORMAT)
    ran = 0
    # the CNCF distribution server on 127.0.0.1 stands for oci://registry.example/
    with running_registry(tmp_path / "oci-registry") as oci, LoopbackServer(root=tmp_path / "site") as srv:
        for argv in _block():
            argv = [
                a.replace("~/", f"{tmp_path}/")
                .replace("https://registry.example/", srv.base)
                .replace("oci://registry.example/", f"oci://{oci.netloc}/")
                for a in argv
            ]
            if argv[0] == "export":
                continue
            if argv[0] == "cp":
                shutil.copy(argv[1], argv[2])
                continue
            assert argv[0] == "hcdf-trust", argv
            res = cli(*argv[1:])
            assert res.exit_code == 0, (argv, res.stderr)
            ran += 1
    assert ran == 9
    assert (tmp_path / "ros2.xsd").read_bytes() == (HCDFORMAT / "extensions" / "hcdf-ext-ros2.xsd").read_bytes()
    assert (tmp_path / "op.xml").read_bytes() == (HCDFORMAT / "examples/profiles/operational.streams.xml").read_bytes()
