"""The audit policy file: format, threshold and exit code, hostile files."""

from __future__ import annotations

import os
import tomllib

import pytest

from hcdf_trust.audit.policy import CHECKS, DEFAULT, PolicyError, load

from ._hostile import fifo_watchdog
from .conftest import PROJECT

ROBOT = PROJECT / "examples" / "robot" / "robot.hcdf"  # 1 error (firmware-no-hash), 3 warnings


def _policy(tmp_path, text: str):
    path = tmp_path / "policy.toml"
    path.write_text(text)
    return path


def test_threshold_decides_the_exit_code(cli, tmp_path):
    assert cli("audit", ROBOT).exit_code == 1  # built-in threshold: error
    warn = _policy(tmp_path, 'threshold = "warning"\n[checks.firmware-no-hash]\nseverity = "info"\n')
    r = cli("audit", ROBOT, "--policy", warn, "--json")
    assert r.exit_code == 1 and len(r.json["errors"]) == 3 and r.json["threshold"] == "warning"
    demoted = _policy(tmp_path, '[checks.firmware-no-hash]\nseverity = "warning"\n')
    r = cli("audit", ROBOT, "--policy", demoted, "--json")
    assert r.exit_code == 0 and r.json["ok"] is True and r.json["errors"] == []
    assert r.json["counts"] == {"error": 0, "warning": 4, "info": 0}
    off = _policy(tmp_path, "[checks.firmware-no-hash]\nenabled = false\n")
    r = cli("audit", ROBOT, "--policy", off, "--json")
    assert r.exit_code == 0 and "firmware-no-hash" not in {f["code"] for f in r.json["findings"]}
    info = _policy(tmp_path, 'threshold = "info"\n[checks.firmware-no-hash]\nseverity = "info"\n')
    assert cli("audit", ROBOT, "--policy", info).exit_code == 1  # an info finding, at an info threshold


def test_the_built_in_default_is_the_documented_one():
    section = (PROJECT / "docs" / "audit.md").read_text()
    block = section.split("```toml\n", 1)[1].split("```", 1)[0]
    rules = (PROJECT / "docs" / "audit-rules.md").read_text()
    written = load_text(block)
    assert written == DEFAULT.to_dict() | {"source": "README"}
    for name in CHECKS:
        assert f"`{name}`" in rules, name  # every check is documented


def load_text(text: str) -> dict:
    raw = tomllib.loads(text)
    from hcdf_trust.audit.policy import _policy

    return _policy(raw, "README").to_dict()


@pytest.mark.parametrize(
    ("text", "key"),
    [
        ("threshold = 'fatal'\n", "threshold"),
        ("threshold = 3\n", "threshold"),
        ("colour = 'red'\n", "colour"),
        ("[macsec]\nminimum-cipher = 'des'\n", "macsec.minimum-cipher"),
        ("[macsec]\nmax-cipher = 'gcm-aes-256'\n", "macsec.max-cipher"),
        ("macsec = 1\n", "macsec"),
        ("[checks.no-such-check]\nenabled = false\n", "checks.no-such-check"),
        ("[checks.unpinned]\nenabled = 'no'\n", "checks.unpinned.enabled"),
        ("[checks.unpinned]\nseverity = 'fatal'\n", "checks.unpinned.severity"),
        ("[checks.unpinned]\nlevel = 'error'\n", "checks.unpinned.level"),
        ("[checks]\nunpinned = true\n", "checks.unpinned"),
    ],
)
def test_unknown_keys_and_values_name_file_and_key(cli, tmp_path, text, key):
    path = _policy(tmp_path, text)
    with pytest.raises(PolicyError) as exc:
        load(str(path))
    assert exc.value.message.startswith(f"{key}:") and exc.value.file == str(path)
    assert exc.value.expected and exc.value.expected != "None"
    r = cli("audit", ROBOT, "--policy", path, "--json")
    assert r.exit_code == 3
    (error,) = r.json["errors"]
    assert error["code"] == "audit-policy" and key in error["message"] and error["file"].endswith("policy.toml")


def test_bad_toml_names_the_line(cli, tmp_path):
    path = _policy(tmp_path, 'threshold = "error"\n[checks.unpinned\n')
    r = cli("audit", ROBOT, "--policy", path)
    assert r.exit_code == 3 and "policy.toml" in r.stderr and "not valid TOML" in r.stderr and "line 2" in r.stderr
    path.write_bytes(b'threshold = "\xff"\n')
    r = cli("audit", ROBOT, "--policy", path)
    assert r.exit_code == 3 and "not UTF-8" in r.stderr


def test_a_fifo_policy_is_refused_without_blocking(cli, tmp_path):
    fifo = tmp_path / "policy.toml"
    os.mkfifo(fifo)
    with fifo_watchdog(fifo) as state:
        r = cli("audit", ROBOT, "--policy", fifo)
    assert not state["hung"]
    assert r.exit_code == 3 and "policy.toml" in r.stderr and "Traceback" not in r.stderr


def test_missing_huge_and_directory_policies(cli, tmp_path):
    assert cli("audit", ROBOT, "--policy", tmp_path / "none.toml").exit_code == 3
    huge = tmp_path / "huge.toml"
    huge.write_bytes(b"# " + b"x" * (2 << 20) + b"\n")
    r = cli("audit", ROBOT, "--policy", huge)
    assert r.exit_code == 3 and "huge.toml" in r.stderr
    assert cli("audit", ROBOT, "--policy", tmp_path).exit_code == 2  # click: a folder is not a FILE


def test_the_documented_json_shape_is_the_real_one(cli):
    import json

    section = (PROJECT / "docs" / "audit.md").read_text()
    documented = json.loads(section.split("```json\n", 1)[1].split("```", 1)[0])
    real = cli("audit", ROBOT, "--json").json
    assert set(documented) == set(real)
    assert set(documented["findings"][0]) == set(real["findings"][0]) == set(real["errors"][0])
    assert documented["counts"] == real["counts"] and documented["checked"] == real["checked"]
    shown, (error,) = documented["findings"][0], real["errors"]
    assert (shown["code"], shown["line"]) == (error["code"], error["line"])
    assert error["file"].endswith(shown["file"])
