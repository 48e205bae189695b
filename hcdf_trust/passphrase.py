"""The one passphrase rule, the same for every verb (docs/security-model.md, item 5).

A passphrase (``ota``'s signing keys, the ``macsec`` key store, the ``registry``'s keys) or a
PKCS#11 PIN comes from a file (``--passphrase-file``, ``--pin-file``, a PKCS#11 URI's
``pin-source=file:``), else from one environment variable per kind of secret, whatever the
verb: :data:`PASSPHRASE_ENV`, :data:`PIN_ENV`. Never from an argument.

Its value is the whole file (or variable) minus one final newline (``\\n`` or ``\\r\\n``): an
empty value, or one that still holds a line break (a file of several lines: which one did you
mean?), is refused. The file must be accessible by its owner only
(:func:`hcdf_trust.localfile.read_secret`). What is read is remembered by the secret filter
(:func:`hcdf_trust.scrub.remember`), so no message of the run can show it.
"""

from __future__ import annotations

import os

from .errors import SecretFileError
from .localfile import read_secret
from .scrub import remember

PASSPHRASE_ENV = "HCDF_TRUST_PASSPHRASE"
PIN_ENV = "HCDF_TRUST_PKCS11_PIN"
RENAMED = "HCDF_TRUST_MACSEC_PASSPHRASE"  # macsec's own variable before the one rule: named, not read
MAX_SECRET_BYTES = 4 << 10


def read_passphrase(file: str | os.PathLike[str] | None, *, required: bool = True) -> bytes | None:
    """The passphrase from ``file``, else ``$HCDF_TRUST_PASSPHRASE``; None when neither is
    given and not ``required`` (an unencrypted key).

    Raises:
        SecretFileError: none given (``required``), empty, several lines, the file readable by others.
        NotFoundError / InputError: the file is missing, not a regular file, over 4 KiB.
    """
    return _read(file, env=PASSPHRASE_ENV, what="passphrase", flag="--passphrase-file", required=required)


def read_pin(file: str | os.PathLike[str] | None) -> bytes:
    """A PKCS#11 user PIN from ``file``, else ``$HCDF_TRUST_PKCS11_PIN`` (the passphrase rule).

    Raises:
        SecretFileError, NotFoundError, InputError: as :func:`read_passphrase`.
    """
    pin = _read(file, env=PIN_ENV, what="PIN", flag="--pin-file", required=True)
    assert pin is not None
    return pin


def _read(file: str | os.PathLike[str] | None, *, env: str, what: str, flag: str, required: bool) -> bytes | None:
    if file is not None:
        source = os.fspath(file)
        data = read_secret(source, limit=MAX_SECRET_BYTES, what=f"{what} file")
    elif os.environ.get(env):
        source = env
        data = os.environ[env].encode("utf-8", "surrogateescape")
    elif required:
        renamed = f"; {RENAMED} is now {env}" if env == PASSPHRASE_ENV and os.environ.get(RENAMED) else ""
        raise SecretFileError(
            f"no {what}: give {flag} FILE or set {env} (a {what} is never taken on the command line){renamed}"
        )
    else:
        return None
    return _value(data, source=source, what=what)


def _value(data: bytes, *, source: str, what: str) -> bytes:
    """``data`` minus one final newline; refused when empty or of several lines."""
    for end in (b"\r\n", b"\n"):
        if data.endswith(end):
            data = data[: -len(end)]
            break
    if not data:
        raise SecretFileError(f"the {what} is empty", file=source)
    if b"\n" in data or b"\r" in data:
        lines = len(data.splitlines())
        raise SecretFileError(
            f"the {what} holds several lines: it is the whole file minus one final newline, so write it on one line",
            file=source,
            expected="one line",
            actual=f"{lines} lines",
        )
    remember(data)
    return data
