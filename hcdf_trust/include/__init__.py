"""Include resolution: fetchers, locator, resolver, lock file, flattening.

``from hcdf_trust.include import resolve`` is the library entry point.
"""

from .resolver import Artifact, Resolution, ResolveOptions, resolve

__all__ = ["Artifact", "Resolution", "ResolveOptions", "resolve"]
