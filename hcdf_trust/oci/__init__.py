"""OCI distribution: releases pushed to and pulled from OCI registries, verified on every pull.

- :mod:`.reference`: ``oci://HOST[:PORT]/REPO:TAG|@sha256:…`` references.
- :mod:`.auth`: credentials (Docker config file, credential helpers, environment), never argv.
- :mod:`.client`: a thin httpx client over the distribution-spec endpoints.
- :mod:`.release`: ``ota push`` / ``ota pull``.
- :mod:`.referrers`: the SUIT, provenance and SBOM referrers of a release manifest.
- :mod:`.site`: the TUF registry site (``registry publish --oci``, ``registry verify|fetch oci://``).
"""
