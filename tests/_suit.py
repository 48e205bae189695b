"""The SUIT working group's artifacts (../shared/specs/suit-draft-34) and zcbor, a CDDL
validator nobody on this project wrote, run as its users run it."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from tests.conftest import CORPUS

DRAFT = CORPUS.parent / "specs" / "suit-draft-34"
CORE_CDDL = DRAFT / "suit34-core-z.cddl"
ZCBOR = str(Path(sys.executable).with_name("zcbor"))
EXAMPLES = [DRAFT / f"example{i}.signed.cbor" for i in range(6)]


def zcbor_validate(data: bytes, tmp_path: Path, *, name: str = "envelope") -> subprocess.CompletedProcess[str]:
    """``zcbor validate`` of ``data`` against the draft's CDDL as SUIT_Envelope_Tagged.

    Input as cborhex: zcbor 0.9.1 opens binary input with an encoding and fails.
    """
    path = tmp_path / f"{name}.cborhex"
    path.write_text(data.hex())
    return subprocess.run(
        [ZCBOR, "validate", "-c", str(CORE_CDDL), "-i", str(path), "-t", "SUIT_Envelope_Tagged"],
        capture_output=True,
        text=True,
        timeout=120,
    )
