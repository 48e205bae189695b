"""Attack: poses that Python's float() reads but an XML reader (xs:double) does not.

float() accepts "1_0" (ten), Arabic-Indic digits ("١" is one) and splits on any
Unicode space (U+2003); xs:double and XML lists do not. Flattening composes such a
pose into numbers no other reader of the document would see: it must refuse it.
"""

from __future__ import annotations

import pytest


@pytest.mark.parametrize(
    "pose",
    ["1_0 0 0 0 0 0", "\u0661 0 0 0 0 0", "1\u20032 3 0 0 0", "1\u00a02 3 0 0 0", "\uff11 0 0 0 0 0"],
    ids=["underscore", "arabic-indic", "em-space", "nbsp", "fullwidth"],
)
def test_a_pose_that_is_not_six_xml_numbers_is_refused(cli, tmp_path, pose):
    (tmp_path / "s.hcdf").write_text('<?xml version="1.0"?>\n<hcdf version="1.0" name="s"><comp name="c"/></hcdf>\n')
    root = tmp_path / "r.hcdf"
    root.write_text(
        f'<?xml version="1.0"?>\n<hcdf version="1.0" name="r"><include uri="s.hcdf" name="a" pose="{pose}"/></hcdf>\n',
        encoding="utf-8",
    )
    r = cli("resolve", root, "--no-lock", "--out", tmp_path / "flat.hcdf")
    assert r.exit_code == 3, r.stderr
    assert "is not six numbers" in r.stderr
    assert not (tmp_path / "flat.hcdf").exists()


@pytest.mark.parametrize("pose", ["1 2 3 0 0 0", "-1.5e-3 +2. .5 0 0 1E2", "\t1\n2  3 0 0 0 "])
def test_plain_xml_numbers_are_accepted(cli, tmp_path, pose):
    (tmp_path / "s.hcdf").write_text('<?xml version="1.0"?>\n<hcdf version="1.0" name="s"><comp name="c"/></hcdf>\n')
    root = tmp_path / "r.hcdf"
    root.write_text(
        f'<?xml version="1.0"?>\n<hcdf version="1.0" name="r"><include uri="s.hcdf" name="a" pose="{pose}"/></hcdf>\n'
    )
    r = cli("resolve", root, "--no-lock", "--out", tmp_path / "flat.hcdf")
    assert r.exit_code == 0, r.stderr
