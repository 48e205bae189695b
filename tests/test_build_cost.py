"""Issue 6 item 8: what a build step costs, pinned where a test can see it (bench/run.py measures it)."""

from __future__ import annotations

import gc

from click.testing import CliRunner

import hcdf_trust.include.resolver as resolver_module
from hcdf_trust.cli import main

from ._kill import hcdf, model, sha


def test_the_cyclic_collector_is_off_during_a_command_and_back_on_after(tmp_path, monkeypatch):
    (tmp_path / "m.glb").write_bytes(b"m")
    doc = tmp_path / "robot.hcdf"
    doc.write_text(hcdf(model("m.glb", sha(b"m"))))
    seen = []
    real = resolver_module.resolve

    def spy(*args, **kwargs):
        seen.append(gc.isenabled())
        return real(*args, **kwargs)

    monkeypatch.setattr(resolver_module, "resolve", spy)
    assert gc.isenabled()
    for args in (["resolve", doc, "--cache-dir", tmp_path / "c"], ["verify", doc, "--cache-dir", tmp_path / "c"]):
        r = CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)
        assert r.exit_code == 0, r.output
        assert gc.isenabled()
    r = CliRunner().invoke(main, ["verify", str(tmp_path / "none.hcdf")])  # a failing command restores it too
    assert r.exit_code == 3 and gc.isenabled()
    assert seen == [False, False, False]
