"""``hcdf-trust sbom``: a bill of materials of a verified HCDF tree, hardware and software.

:mod:`.model` collects the facts once (from the resolver's parsed documents and, with
a release, the verified OTA manifest); :mod:`.cyclonedx` and :mod:`.spdx` render them
through cyclonedx-python-lib and spdx-python-model, each imported only when used.
"""
