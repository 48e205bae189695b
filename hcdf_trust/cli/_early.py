"""Imported first by the CLI: start hashing a plain ``resolve DOC``'s large files before the
rest of the CLI (click and its dependencies: ~30 ms on one core) is imported. See
:func:`hcdf_trust.include.prefetch.start_early`; any other command line imports nothing here."""

import os
import sys

if os.path.basename(sys.argv[0] if sys.argv else "") == "hcdf-trust" and sys.argv[1:2] in (["resolve"], ["verify"]):
    from ..include.prefetch import start_early

    start_early(sys.argv)
