"""MACsec key provisioning: plan (policy → connectivity associations), key store, rotation, export.

Import the submodules directly (``hcdf_trust.macsec.plan``, ``.store``, ``.kdf``, ``.export``);
this package imports nothing heavy on its own.
"""
