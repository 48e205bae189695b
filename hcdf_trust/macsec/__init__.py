"""MACsec key provisioning: plan (policy → connectivity associations), key store, rotation, export.

Import the submodules directly (``hcdf_trust.macsec.plan``, ``.store``, ``.kdf``, ``.export``);
this package imports nothing heavy on its own.
"""

from __future__ import annotations


def parse_wpa_version(text: str) -> tuple[int, int]:
    """A wpa_supplicant version such as ``2.10`` as (major, minor); here so that parsing
    ``--wpa-version`` does not import the exporters (and cryptography) before the store opens."""
    major, _, minor = text.strip().partition(".")
    if not (major.isdigit() and minor.isdigit()):
        raise ValueError(f"{text!r} is not a wpa_supplicant version like 2.10")
    return int(major), int(minor)
