"""Include resolution: fetchers, locator, resolver, lock file, flattening.

The public API of this package is :data:`__all__` (docs/api.md): :func:`resolve` and
:func:`verify` and the classes they take and return. Its submodules are internal.
They are loaded when first used (PEP 562): a verb that only fetches (``ota pull``, through
:mod:`.fetch`) does not pay for the resolver and lxml before its first request.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .resolver import Artifact, Resolution, ResolveOptions, resolve, verify

__all__ = ["Artifact", "Resolution", "ResolveOptions", "resolve", "verify"]


def __getattr__(name: str) -> Any:
    if name in __all__:
        from . import resolver

        return getattr(resolver, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
