"""The signed registry of HCDF extension domains, stream profiles and core schemas.

``registry/`` in the repository is the reviewed source (:mod:`.source`, TOML);
:mod:`.publish` turns it into a static TUF repository (python-tuf's Metadata API);
:mod:`.client` verifies and fetches from one through ``tuf.ngclient``.
Nothing here is imported by ``hcdf-trust --help``: tuf loads only inside the commands.
"""
