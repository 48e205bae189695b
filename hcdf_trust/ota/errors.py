"""Errors of the ota verbs, in the two families of :mod:`hcdf_trust.errors`."""

from __future__ import annotations

from ..errors import InputError, IntegrityError


class KeyFileError(InputError):
    """A signing or verifying key cannot be used: missing or wrong passphrase, unknown type."""

    code = "key"


class OtaConfigError(InputError):
    """``ota.toml`` is malformed or asks for something impossible."""

    code = "ota-config"


class FirmwareError(InputError):
    """A firmware input is missing or cannot be turned into an image (binary, version)."""

    code = "firmware"


class MalformedReleaseError(InputError):
    """A release file (manifest, ``latest.json``, image) is truncated or malformed."""

    code = "malformed-release"


class FirmwareHashError(IntegrityError):
    """The HCDF's ``<software><hash>`` is not the hash of the image built from it."""

    code = "firmware-hash"


class ReleaseIntegrityError(IntegrityError):
    """A release does not verify: signature, digest, size, version, URL or binding."""

    code = "release"


class SignatureError(ReleaseIntegrityError):
    code = "bad-signature"


class RollbackError(ReleaseIntegrityError):
    """A sequence number or security counter that did not go up."""

    code = "rollback"
