"""The per-project config file ``hcdf-trust.toml`` (hcdf_trust/config.py, applied by
hcdf_trust/cli/params.py): found beside DOC or in a parent folder up to a repository root or
$HOME, overridden by flags, refused when unsafe or unknown, reported by --json.

The oracle of most tests is a reference that resolves only when ``base`` points at the folder
holding it: without the config, the resolve fails with not-found (exit 3)."""

from __future__ import annotations

import hashlib
import os

import pytest

HEAD = '<?xml version="1.0"?>\n<hcdf version="1.0" name="r">\n'


def model(uri: str, pin: str | None = None) -> str:
    sha = f' sha="{pin}"' if pin else ""
    return f'<comp name="c"><visual name="v"><model uri="{uri}"{sha}/></visual></comp>\n'


@pytest.fixture
def project(tmp_path, monkeypatch):
    """proj/ (a git checkout) with robot/robot.hcdf referencing m.glb, which lies in proj/assets."""
    monkeypatch.delenv("HCDF_TRUST_NO_CONFIG", raising=False)
    proj = tmp_path / "proj"
    (proj / ".git").mkdir(parents=True)
    (proj / "assets").mkdir()
    (proj / "assets" / "m.glb").write_bytes(b"mesh")
    (proj / "robot").mkdir()
    doc = proj / "robot" / "robot.hcdf"
    pin = hashlib.sha256(b"mesh").hexdigest()
    doc.write_text(HEAD + model("m.glb", pin) + "</hcdf>\n")
    return proj


def config(folder, text: str, mode: int = 0o644):
    path = folder / "hcdf-trust.toml"
    path.write_text(text)
    path.chmod(mode)
    return path


def verify(cli, proj, *extra):
    return cli("resolve", proj / "robot" / "robot.hcdf", "--no-lock", "--json", *extra)


def test_found_in_a_parent_folder_paths_relative_to_it_reported_by_json(cli, project, tmp_path, monkeypatch):
    assert verify(cli, project).exit_code == 3  # the oracle: m.glb is not beside the document
    config(project, 'base = "assets"\nroot = "."\n')
    monkeypatch.chdir(tmp_path)  # paths in the file are relative to the file, not to the working folder
    r = verify(cli, project)
    assert r.exit_code == 0, r.stdout
    assert os.path.abspath(r.json["config"]) == str(project / "hcdf-trust.toml")
    assert [a["source"] for a in r.json["artifacts"]] == ["file"]


def test_flags_override_the_file_and_the_file_can_be_turned_off(cli, project, monkeypatch):
    config(project, 'base = "assets"\nroot = "."\n')
    (project / "other").mkdir()
    r = verify(cli, project, "--base", project / "other")  # the flag wins: m.glb is not in other/
    assert r.exit_code == 3 and r.json["errors"][0]["code"] == "not-found"
    r = verify(cli, project, "--no-project-config")
    assert r.exit_code == 3 and r.json["config"] is None
    monkeypatch.setenv("HCDF_TRUST_NO_CONFIG", "1")
    assert verify(cli, project).exit_code == 3
    r = verify(cli, project, "--project-config", project / "hcdf-trust.toml")  # named explicitly: read
    assert r.exit_code == 0


def test_the_search_stops_at_the_repository_root_and_at_home(cli, project, tmp_path, monkeypatch):
    config(tmp_path, 'base = "proj/assets"\nroot = "."\n')  # above the checkout's .git: not this project's
    r = verify(cli, project)
    assert r.exit_code == 3 and r.json["config"] is None
    (project / ".git").rmdir()
    monkeypatch.setenv("HOME", str(project))  # $HOME ends the search as a repository root does
    assert verify(cli, project).json["config"] is None
    monkeypatch.setenv("HOME", str(tmp_path / "elsewhere"))
    r = verify(cli, project)  # no marker, home elsewhere: the parent's file governs
    assert r.exit_code == 0 and os.path.abspath(r.json["config"]) == str(tmp_path / "hcdf-trust.toml")


def test_an_unknown_key_or_a_bad_value_names_the_file_and_the_key(cli, project):
    path = config(project, 'base = "assets"\n[audit]\npolicy = "p.toml"\nthreshold = "error"\n')
    r = verify(cli, project)
    assert r.exit_code == 3
    (err,) = r.json["errors"]
    assert err["code"] == "config" and os.path.abspath(err["file"]) == str(path)
    assert "'audit.threshold'" in err["message"]
    config(project, 'root = "no-such-folder"\n')
    r = cli("verify", project / "robot" / "robot.hcdf")
    assert r.exit_code == 3 and "hcdf-trust.toml: root: " in r.stderr and "does not exist" in r.stderr
    config(project, 'mirror = "https://x.example/=assets"\n')  # a list, like the repeatable flag
    r = verify(cli, project)
    assert r.exit_code == 3 and "'mirror' must be a list of strings" in r.json["errors"][0]["message"]


def test_mirrors_from_the_file(cli, project):
    doc = project / "robot" / "robot.hcdf"
    pin = hashlib.sha256(b"mesh").hexdigest()
    doc.write_text(HEAD + model("https://models.example.com/m.glb", pin) + "</hcdf>\n")
    config(project, 'mirror = ["https://models.example.com/=assets"]\n')
    r = cli("resolve", doc, "--no-lock", "--offline", "--json")
    assert r.exit_code == 0, r.stdout
    assert r.json["artifacts"][0]["source"] == "mirror"


@pytest.mark.parametrize("case", ["writable by others", "folder writable by others", "symlink", "other owner"])
def test_a_config_someone_else_could_have_written_is_refused(cli, project, tmp_path, case):
    if case == "other owner" and os.geteuid() != 0:
        pytest.skip("needs root to give the file to another user (chown)")
    real = config(tmp_path, 'base = "assets"\n')
    if case == "symlink":
        (project / "hcdf-trust.toml").symlink_to(real)
    else:
        path = config(project, 'base = "assets"\n', mode=0o646 if case == "writable by others" else 0o644)
        if case == "folder writable by others":
            project.chmod(0o777)
        if case == "other owner":
            os.chown(path, 65534, 65534)
    r = verify(cli, project)
    assert r.exit_code == 3, r.stdout
    (err,) = r.json["errors"]
    assert err["code"] == "config" and "--no-project-config" in err["message"]
    if case == "folder writable by others":
        project.chmod(0o1777)  # sticky, like /tmp: others cannot replace the owner's file
        assert verify(cli, project).exit_code == 0


def test_a_cache_dir_pointed_at_a_key_folder_is_still_protected_from_outputs(cli, project):
    keys = project / "keys"
    keys.mkdir(mode=0o700)
    key = keys / "signing.pem"
    key.write_bytes(b"-----BEGIN PRIVATE KEY-----\nsecret\n-----END PRIVATE KEY-----\n")
    config(project, 'base = "assets"\nroot = "."\ncache-dir = "keys"\n')
    doc = project / "robot" / "robot.hcdf"
    r = cli("resolve", doc, "--no-lock", "--out", keys / "flat.hcdf")
    assert r.exit_code == 3 and "the cache" in r.stderr, r.stderr  # the file's cache-dir is protected as the cache
    assert sorted(p.name for p in keys.iterdir()) == ["signing.pem"]
    assert key.read_bytes().startswith(b"-----BEGIN PRIVATE KEY")
    r = cli("resolve", doc, "--no-lock", "--out", keys / "flat.hcdf", "--cache-dir", project / "cache")
    assert r.exit_code == 0, r.stderr  # the oracle: the refusal came from the file's cache-dir


def test_acknowledged_warnings_are_not_said_but_listed(cli, project):
    doc = project / "robot" / "robot.hcdf"
    doc.write_text(HEAD + model("m.glb", hashlib.sha256(b"mesh").hexdigest()[:8]) + "</hcdf>\n")
    config(project, 'base = "assets"\n')
    r = cli("resolve", doc, "--no-lock")
    assert r.exit_code == 0 and "warning: robot/robot.hcdf:3: m.glb has a weak pin" in r.stderr.replace(
        str(project) + "/", ""
    ), r.stderr
    config(project, 'base = "assets"\n[warnings]\nacknowledge = ["weak-pin"]\n')
    r = cli("resolve", doc, "--no-lock")
    assert r.exit_code == 0 and "warning" not in r.stderr, r.stderr
    r = cli("resolve", doc, "--no-lock", "--json")
    assert [w["code"] for w in r.json["warnings"]] == ["weak-pin"]


def test_the_documented_example_is_a_config_the_reader_accepts(tmp_path):
    """docs/config.md's example holds every key, and only keys, that the reader knows."""
    import re
    from pathlib import Path

    from hcdf_trust import config as project_config

    page = (Path(__file__).resolve().parent.parent / "docs" / "config.md").read_text()
    (example,) = re.findall(r"^```toml\n(.*?)^```", page, re.S | re.M)
    path = tmp_path / "hcdf-trust.toml"
    path.write_text(example)
    path.chmod(0o644)
    loaded = project_config.load(str(path))
    assert set(loaded.values) == {
        "base",
        "root",
        "cache-dir",
        "mirror",
        "registry.site",
        "registry.trusted-root",
        "audit.policy",
    }
    assert loaded.values["base"] == str(tmp_path / "models") and loaded.acknowledge == {"mesh-without-sha"}
    assert loaded.values["mirror"] == ("https://models.example.com/=" + str(tmp_path / "vendor"),)


@pytest.mark.parametrize("setting", ['root = ".."', 'base = "../elsewhere"', 'base = "/"'])
def test_a_config_cannot_open_files_above_its_own_folder(cli, project, tmp_path, setting):
    """The file comes with the tree it sits in (perhaps someone else's checkout): root, and base
    (which root defaults to), stay inside its folder; the command line may go wider."""
    (tmp_path / "elsewhere").mkdir()
    config(project, setting + "\n")
    r = verify(cli, project)
    assert r.exit_code == 3, r.stdout
    (err,) = r.json["errors"]
    assert err["code"] == "config" and "outside the folder this file governs" in err["message"]
    config(project, 'root = "."\n')
    assert verify(cli, project, "--root", tmp_path, "--base", project / "assets").exit_code == 0
