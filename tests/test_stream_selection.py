"""Which stream profile a robot runs, in both dialects (issue 18):

- 1.0 (corpus hcdformat e7c1eec, ``docs/stream-profiles.md``): ``<network><stream-profile uri
  active="true|false"/>``, ``active`` defaulting to true, "one is active at a time";
- upstream 05d27b58 (``examples/test-minimal.hcdf``, ``rust/hcdformat-rs/src/model/stream_profile.rs``):
  top-level ``<stream-profile uri selection-role="default"/>``, unmarked profiles not selected.

validate, audit and sbom read both with one meaning and one finding code. The oracle is the
documents as written here: which profile each names, counted by hand.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.conftest import HCDFORMAT

CODE = "stream-profile-selection"

OLD = """<hcdf version="1.0" name="bot">
  <comp name="a"/>
  <network name="backbone">
    <stream-profile uri="profiles/operational.streams.xml"{op}/>
    <stream-profile uri="profiles/calibration.streams.xml"{cal}/>
  </network>
</hcdf>
"""

NEW = """<hcdf version="1.0" name="bot">
  <comp name="a"/>
  <stream-profile uri="profiles/operational.streams.xml"{op}/>
  <stream-profile uri="profiles/calibration.streams.xml"{cal}/>
</hcdf>
"""


def robot(root: Path, template: str, op: str, cal: str) -> Path:
    (root / "profiles").mkdir(parents=True, exist_ok=True)
    for name in ("operational", "calibration"):
        (root / "profiles" / f"{name}.streams.xml").write_text(f"<stream-profile name='{name}' version='1'/>\n")
    doc = root / "robot.hcdf"
    doc.write_text(template.format(op=op, cal=cal))
    return doc


# (dialect, operational's attributes, calibration's) -> the selected profile, written both ways
GOOD = [
    (OLD, "", ' active="false"', "operational"),
    (OLD, ' active="true"', ' active="false"', "operational"),
    (OLD, ' active=" 0 "', "", "calibration"),
    (NEW, ' selection-role="default"', "", "operational"),
    (NEW, "", ' selection-role="default"', "calibration"),
    (NEW, ' selection-role="default" active="true"', "", "operational"),
]
BAD = [
    (OLD, "", "", "2 stream profiles are selected"),  # 1.0's default: both active
    (OLD, ' active="true"', ' active="1"', "2 stream profiles are selected"),
    (NEW, ' selection-role="default"', ' selection-role="default"', "2 stream profiles are selected"),
    (NEW, ' selection-role="default"', ' active="true"', "2 stream profiles are selected"),
    (NEW, ' selection-role="primary"', "", 'selection-role="primary" is not one HCDF defines'),
    (OLD, ' active="yes"', ' active="false"', 'active="yes" is not a boolean'),
    (NEW, ' selection-role="default" active="false"', "", "say opposite things"),
]


@pytest.mark.parametrize(("template", "op", "cal", "chosen"), GOOD)
def test_validate_names_the_selected_profile(cli, tmp_path, template, op, cal, chosen):
    doc = robot(tmp_path / "bot", template, op, cal)
    r = cli("validate", doc, "--json")
    assert r.exit_code == 0, r.stdout
    assert CODE not in [f["code"] for f in r.json["findings"]]
    line = (4 if template is OLD else 3) + (chosen == "calibration")  # as the templates are written
    assert [n for n in r.json["notes"] if "selected stream profile" in n] == [
        f"selected stream profile: profiles/{chosen}.streams.xml (line {line})"
    ]


@pytest.mark.parametrize(("template", "op", "cal", "said"), BAD)
def test_an_unclear_selection_is_the_same_error_everywhere(cli, tmp_path, template, op, cal, said):
    doc = robot(tmp_path / "bot", template, op, cal)
    r = cli("validate", doc, "--json")
    assert r.exit_code == 1, r.stdout
    found = [f for f in r.json["findings"] if f["code"] == CODE]
    assert len(found) == 1 and said in found[0]["message"] and found[0]["severity"] == "error"
    assert found[0]["file"].endswith("robot.hcdf") and found[0]["line"] in (3, 4, 5)

    lock = ["--lock", tmp_path / "x.lock"]
    assert cli("resolve", doc, *lock).exit_code == 0  # resolve does not choose a profile
    r = cli("audit", doc, *lock, "--json")
    assert r.exit_code == 1, r.stdout + r.stderr
    found = [f for f in r.json["findings"] if f["check"] == CODE]
    assert len(found) == 1 and said in found[0]["message"]

    r = cli("sbom", doc, *lock, "--format", "cyclonedx")
    assert r.exit_code == 3, r.stdout + r.stderr
    assert said in r.stderr and "robot.hcdf" in r.stderr
    r = cli("sbom", doc, *lock, "--format", "spdx", "--json")
    assert r.exit_code == 3 and [e["code"] for e in r.json["errors"]] == [CODE]


def selected_in_sbom(cli, doc: Path, lock: Path) -> dict[str, str]:
    """File name -> its hcdf:stream-profile-selected property, read from the CycloneDX JSON."""
    r = cli("sbom", doc, "--lock", lock, "--format", "cyclonedx")
    assert r.exit_code == 0, r.stderr
    out = {}
    for c in json.loads(r.stdout)["components"]:
        props = {p["name"]: p["value"] for p in c.get("properties", [])}
        if props.get("hcdf:kind") == "stream-profile":
            out[Path(c["name"]).name] = props["hcdf:stream-profile-selected"]
    return out


@pytest.mark.parametrize(("template", "op", "cal", "chosen"), GOOD)
def test_sbom_marks_the_selected_profile(cli, tmp_path, template, op, cal, chosen):
    doc = robot(tmp_path / "bot", template, op, cal)
    lock = tmp_path / "x.lock"
    assert cli("resolve", doc, "--lock", lock).exit_code == 0
    other = "calibration" if chosen == "operational" else "operational"
    assert selected_in_sbom(cli, doc, lock) == {
        f"{chosen}.streams.xml": "true",
        f"{other}.streams.xml": "false",
    }


def test_one_robot_in_both_dialects_selects_the_same_profile(cli, tmp_path):
    """operational selected, calibration listed: 1.0 writes active, the newer model selection-role."""
    old = robot(tmp_path / "old", OLD, ' active="true"', ' active="false"')
    new = robot(tmp_path / "new", NEW, ' selection-role="default"', "")
    notes = []
    for doc in (old, new):
        r = cli("validate", doc, "--json")
        assert r.exit_code == 0
        notes.append([n.split(" (line")[0] for n in r.json["notes"] if "selected stream profile" in n])
    assert notes[0] == notes[1] == ["selected stream profile: profiles/operational.streams.xml"]


def test_corpus_humanoid_one_active_profile_per_network(cli):
    """The 1.0 humanoid lists operational in two networks, active in each: one per scope, no finding."""
    r = cli("validate", HCDFORMAT / "examples" / "humanoid-mobile-base.hcdf", "--json")
    assert CODE not in [f["code"] for f in r.json["findings"]], r.stdout
