"""The library's public API (docs/api.md): exactly ``__all__`` of the public modules, each name
documented there, each with a docstring whose example runs.

Examples run as doctests, each in a fresh folder holding a copy of ``examples/robot`` (and,
for the registry client, a published registry site in ``site/``), with an isolated cache.
"""

from __future__ import annotations

import doctest
import importlib
import inspect
import re
import shutil
from pathlib import Path

import pytest

from .conftest import PROJECT

# The stability rule of docs/api.md: these modules' __all__ are the public API.
PUBLIC_MODULES = (
    "hcdf_trust.include",
    "hcdf_trust.errors",
    "hcdf_trust.outputs",
    "hcdf_trust.ota.keys",
    "hcdf_trust.ota.signer",
    "hcdf_trust.ota.release",
    "hcdf_trust.ota.verify",
    "hcdf_trust.macsec.plan",
    "hcdf_trust.macsec.store",
    "hcdf_trust.macsec.backends",
    "hcdf_trust.macsec.rotation",
    "hcdf_trust.registry.client",
    "hcdf_trust.provenance.build",
)
API_DOC = (PROJECT / "docs" / "api.md").read_text()


def _public() -> list[tuple[str, str, object]]:
    out = []
    for name in PUBLIC_MODULES:
        module = importlib.import_module(name)
        assert isinstance(getattr(module, "__all__", None), list), f"{name} has no __all__"
        out += [(name, attr, getattr(module, attr)) for attr in module.__all__]
    return out


PUBLIC = _public()


def _needs_example(obj: object) -> bool:
    """Functions and classes; an error class that only sets ``code`` shares its base's example."""
    from hcdf_trust.errors import HcdfTrustError

    if isinstance(obj, type) and issubclass(obj, HcdfTrustError):
        return obj.__name__ in ("HcdfTrustError", "IntegrityError", "InputError")
    return inspect.isfunction(obj) or inspect.isclass(obj)


def test_docs_api_lists_exactly_the_public_names():
    listed = set(re.findall(r"^\| `(hcdf_trust[\w.]*)\.(\w+)` \|", API_DOC, re.M))
    public = {(module, attr) for module, attr, _ in PUBLIC}
    assert listed == public
    for module in PUBLIC_MODULES:
        assert f"`{module}`" in API_DOC  # named in the stability rule's list


@pytest.mark.parametrize(("module", "attr", "obj"), PUBLIC, ids=[f"{m}.{a}" for m, a, _ in PUBLIC])
def test_every_public_name_has_a_docstring_and_an_example(module, attr, obj):
    if not (inspect.isfunction(obj) or inspect.isclass(obj)):
        return  # a constant: documented in docs/api.md
    doc = inspect.getdoc(obj)
    assert doc and len(doc) > 40, f"{module}.{attr} has no real docstring"
    if _needs_example(obj):
        assert ">>> " in doc, f"{module}.{attr}: no example in its docstring"


@pytest.fixture(scope="session")
def registry_site(tmp_path_factory):
    """A registry published once (init, two domains, a profile), for the client's examples."""
    from click.testing import CliRunner

    from hcdf_trust.cli import main

    from ._registry import PASSPHRASE, Registry, build
    from .conftest import CliResult

    def cli(*args):
        r = CliRunner().invoke(main, [str(a) for a in args], env={"HCDF_TRUST_PASSPHRASE": PASSPHRASE})
        return CliResult(r.exit_code, r.stdout, r.stderr)

    reg: Registry = build(tmp_path_factory.mktemp("registry"), cli)
    return reg.site


def _doctests() -> list[tuple[str, doctest.DocTest]]:
    finder = doctest.DocTestFinder(recurse=False)
    out = []
    for module, attr, obj in PUBLIC:
        targets = [obj]
        if inspect.isclass(obj):  # its public methods' examples too
            targets += [m for n, m in vars(obj).items() if not n.startswith("_") and inspect.isfunction(m)]
        for target in targets:
            for test in finder.find(target, name=f"{module}.{attr}", globs={}):
                if test.examples:
                    out.append((f"{module}.{attr}:{test.lineno}", test))
    return out


DOCTESTS = _doctests()


@pytest.mark.parametrize(("name", "test"), DOCTESTS, ids=[n for n, _ in DOCTESTS])
def test_docstring_examples_run(name, test, tmp_path, monkeypatch, registry_site):
    shutil.copytree(PROJECT / "examples" / "robot", tmp_path / "examples" / "robot")
    if ".registry." in name:
        shutil.copytree(registry_site, tmp_path / "site")
    monkeypatch.chdir(tmp_path)
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    failures: list[str] = []

    class Out:
        def write(self, text: str) -> None:
            failures.append(text)

    result = runner.run(test, out=Out().write)
    assert result.failed == 0, "".join(failures)


def test_the_doctest_runner_reports_a_wrong_example(tmp_path, monkeypatch):
    """The oracle above fails when an example's output is wrong."""
    test = doctest.DocTestParser().get_doctest(">>> 1 + 1\n3\n", {}, "wrong", "wrong.py", 0)
    runner = doctest.DocTestRunner()
    assert runner.run(test, out=lambda _: None).failed == 1


def test_api_page_names_modules_that_exist():
    for module in set(re.findall(r"`(hcdf_trust(?:\.\w+)+)`", API_DOC)):
        try:
            importlib.import_module(module)
        except ModuleNotFoundError:
            parent, _, attr = module.rpartition(".")
            assert hasattr(importlib.import_module(parent), attr), module
    assert Path(PROJECT / "docs" / "api.md").exists()
