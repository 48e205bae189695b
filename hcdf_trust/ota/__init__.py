"""``hcdf-trust ota``: MCUboot-signed images, the fleet's ``latest.json`` and one signed
SUIT release manifest, built from a verified HCDF tree.

One module per concept: :mod:`.keys` (signing keys), :mod:`.version` (MCUboot versions),
:mod:`.config` (``ota.toml``), :mod:`.images` (imgtool), :mod:`.latest` (``latest.json``),
:mod:`.suit` (the envelope), :mod:`.verify` (pure release checks), :mod:`.release` (build).
"""
