"""Advisory file locks (``flock``), imported only when a run really locks something.

``fcntl`` exists on Linux, macOS and the BSDs but not on Windows; importing it at module level
made even ``hcdf-trust --help`` die there. Every lock goes through :func:`flock`, which says
which platform feature is missing instead of a bare ``ModuleNotFoundError``."""

from __future__ import annotations

from .errors import InputError


def flock(fd: int, *, shared: bool = False, wait: bool = True) -> None:
    """Lock the open file ``fd`` (exclusive unless ``shared``). Without ``wait``, a lock held
    elsewhere raises ``BlockingIOError`` (an ``OSError``) at once, as ``fcntl.flock`` does."""
    try:
        import fcntl
    except ModuleNotFoundError:
        raise InputError(
            "this command locks files with flock(2), which this platform lacks "
            "(hcdf-trust writes stores and outputs on Linux and macOS)"
        ) from None
    op = fcntl.LOCK_SH if shared else fcntl.LOCK_EX
    fcntl.flock(fd, op if wait else op | fcntl.LOCK_NB)
