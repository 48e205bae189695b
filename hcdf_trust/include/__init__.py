"""Include resolution: fetchers, locator, resolver, lock file, flattening.

The public API of this package is :data:`__all__` (docs/api.md): :func:`resolve` and
:func:`verify` and the classes they take and return. Its submodules are internal.
"""

from .resolver import Artifact, Resolution, ResolveOptions, resolve, verify

__all__ = ["Artifact", "Resolution", "ResolveOptions", "resolve", "verify"]
