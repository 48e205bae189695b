"""``python -m hcdf_trust.cli``: the same command as the ``hcdf-trust`` script."""

from . import main

main()
