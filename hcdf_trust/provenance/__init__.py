"""Signed build provenance for a release: an in-toto Statement v1 with a SLSA Provenance v1
predicate, in a DSSE envelope signed with the release key (issue 21).

:mod:`.statement` says how a release was built and from what (subjects, buildType,
externalParameters, resolvedDependencies); :mod:`.dsse` signs and parses the envelope;
:mod:`.verify` checks a release folder's ``provenance.intoto.json`` step by step.
"""

FILE_NAME = "provenance.intoto.json"
PAYLOAD_TYPE = "application/vnd.in-toto+json"
STATEMENT_TYPE = "https://in-toto.io/Statement/v1"
PREDICATE_TYPE = "https://slsa.dev/provenance/v1"
# Ours: what the fields of a statement of this build type mean is documented in README.md
# ("ota build --provenance"); a new meaning gets a new version.
BUILD_TYPE = "https://hcdf.cognipilot.org/hcdf-trust/buildtypes/ota-build/v1"
DEFAULT_BUILDER_ID = "https://hcdf.cognipilot.org/hcdf-trust/builders/local@v1"
