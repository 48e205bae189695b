"""Registry errors: the source is malformed (exit 3), or what is signed does not hold (exit 1)."""

from __future__ import annotations

from ..errors import InputError, IntegrityError


class SourceError(InputError):
    """A registry source entry is malformed: the message names the file and the key."""

    code = "registry-source"


class KeyFileError(InputError):
    """A key file is missing, unreadable, or its passphrase is wrong."""

    code = "registry-key"


class RefusedError(IntegrityError):
    """The registry's rules refuse the change: not signed by the owner, a replaced version, a hijacked path."""

    code = "registry-refused"


class AttackError(IntegrityError):
    """A client check failed: the repository is lying or stale (rollback, freeze, mix-and-match, ...)."""

    code = "registry-attack"


class TransportError(InputError):
    """The registry could not be reached or a file is missing on it."""

    code = "registry-transport"
