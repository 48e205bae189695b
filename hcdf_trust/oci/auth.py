"""Registry credentials: from the environment, the Docker config file or a credential helper.

Never from the command line (it shows in ``ps`` and shell history), never printed: every
secret found is handed to the secret filter (:func:`hcdf_trust.scrub.remember`) before it is
used, and the Basic header built from it too. The order, first found wins:

1. ``HCDF_TRUST_OCI_USERNAME`` and ``HCDF_TRUST_OCI_PASSWORD`` (both, or neither), for the
   registry of this run (``HCDF_TRUST_OCI_REGISTRY``, when set, names the only host they are
   sent to: a CI job's variables then never reach another registry);
2. the Docker config file (``$DOCKER_CONFIG/config.json``, else ``~/.docker/config.json``):
   ``credHelpers[HOST]`` (runs ``docker-credential-NAME get``), ``auths[HOST]`` (``auth``
   base64 ``user:password``, or ``username``/``password``, or ``identitytoken``), ``credsStore``;
3. nothing: anonymous.
"""

from __future__ import annotations

import base64
import os
import subprocess
from dataclasses import dataclass
from typing import Any

from ..errors import InputError
from ..scrub import remember

USER_ENV = "HCDF_TRUST_OCI_USERNAME"
PASSWORD_ENV = "HCDF_TRUST_OCI_PASSWORD"
REGISTRY_ENV = "HCDF_TRUST_OCI_REGISTRY"
MAX_CONFIG_BYTES = 1 << 20
HELPER_TIMEOUT = 30.0


class RegistryCredentialsError(InputError):
    """Credentials were configured but cannot be used (a broken config file, a failing helper)."""

    code = "oci-credentials"


@dataclass(frozen=True, repr=False)
class Credentials:
    username: str
    password: str  # or the identity (refresh) token when ``identity_token``
    identity_token: bool = False
    source: str = ""  # where they came from, for messages (never the values)

    def __repr__(self) -> str:  # never the password, whatever prints this
        return f"Credentials(username={self.username!r}, source={self.source!r})"

    def basic_header(self) -> str:
        token = base64.b64encode(f"{self.username}:{self.password}".encode()).decode()
        remember(token)
        return f"Basic {token}"


def _found(username: str, password: str, *, source: str, identity_token: bool = False) -> Credentials:
    remember(password)
    remember(base64.b64encode(f"{username}:{password}".encode()).decode())
    return Credentials(username, password, identity_token, source)


def find_credentials(netloc: str) -> Credentials | None:
    """The credentials for registry ``netloc`` (``host[:port]``), or None (anonymous).

    Raises:
        RegistryCredentialsError: half the environment pair, an unreadable or malformed
            Docker config, a credential helper that fails.
    """
    user, password = os.environ.get(USER_ENV), os.environ.get(PASSWORD_ENV)
    if user or password:
        if not (user and password):
            raise RegistryCredentialsError(f"set both {USER_ENV} and {PASSWORD_ENV}, or neither")
        only = os.environ.get(REGISTRY_ENV)
        if not only or only == netloc:
            return _found(user, password, source=f"${USER_ENV}/${PASSWORD_ENV}")
    config = _docker_config()
    if config is None:
        return None
    path, doc = config
    helpers = doc.get("credHelpers")
    if isinstance(helpers, dict) and isinstance(helpers.get(netloc), str):
        return _helper(helpers[netloc], netloc)
    auths = doc.get("auths")
    if isinstance(auths, dict):
        for key in (netloc, f"https://{netloc}", f"http://{netloc}", f"https://{netloc}/v2/"):
            entry = auths.get(key)
            if isinstance(entry, dict):
                got = _auth_entry(entry, source=f"{path} auths[{key}]")
                if got is not None:
                    return got
    store = doc.get("credsStore")
    if isinstance(store, str) and store:
        return _helper(store, netloc)
    return None


def _docker_config() -> tuple[str, dict[str, Any]] | None:
    """The Docker config file's object; refused (as a key file is) when others may write it,
    or may read it while it holds a password or token (``auths``), whichever registry that is for."""
    from ..localfile import MAX_JSON_BYTES, check_private, parse_json, read_private_config

    folder = os.environ.get("DOCKER_CONFIG") or os.path.join(os.path.expanduser("~"), ".docker")
    path = os.path.join(folder, "config.json")
    if not os.path.lexists(path):
        return None
    data, st = read_private_config(path, limit=MAX_CONFIG_BYTES, what="Docker config")
    doc = parse_json(data, source=path, what="Docker config", limit=MAX_JSON_BYTES)
    if not isinstance(doc, dict):
        raise RegistryCredentialsError("the Docker config is not a JSON object", file=path)
    auths = doc.get("auths")
    if isinstance(auths, dict) and any(
        isinstance(e, dict) and any(e.get(k) for k in ("auth", "password", "identitytoken")) for e in auths.values()
    ):
        check_private(st, path, what="Docker config holding credentials (auths)")
    return path, doc


def _auth_entry(entry: dict[str, Any], *, source: str) -> Credentials | None:
    token = entry.get("identitytoken")
    auth = entry.get("auth")
    if isinstance(auth, str) and auth:
        try:
            user, sep, password = base64.b64decode(auth, validate=True).decode("utf-8").partition(":")
        except (ValueError, UnicodeDecodeError):
            raise RegistryCredentialsError(f"{source}: auth is not base64 of user:password") from None
        if not sep:
            raise RegistryCredentialsError(f"{source}: auth is not base64 of user:password")
    else:
        user, password = entry.get("username") or "", entry.get("password") or ""
    if isinstance(token, str) and token:
        return _found(user if isinstance(user, str) and user else "<token>", token, source=source, identity_token=True)
    if isinstance(user, str) and isinstance(password, str) and user and password:
        return _found(user, password, source=source)
    return None


def _helper(name: str, netloc: str) -> Credentials | None:
    from ..localfile import MAX_JSON_BYTES, parse_json

    if not name.replace("-", "").replace("_", "").replace(".", "").isalnum():
        raise RegistryCredentialsError(f"credential helper name {name!r} is not a plain name")
    program = f"docker-credential-{name}"
    try:
        done = subprocess.run(
            [program, "get"], input=netloc.encode(), capture_output=True, timeout=HELPER_TIMEOUT, check=False
        )
    except FileNotFoundError:
        raise RegistryCredentialsError(f"credential helper {program} is not installed") from None
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise RegistryCredentialsError(f"credential helper {program} failed: {exc.__class__.__name__}") from None
    if done.returncode != 0:
        # "credentials not found in native keychain": anonymous; its output is never shown (it may echo secrets)
        if b"not found" in done.stdout.lower() or b"not found" in done.stderr.lower():
            return None
        raise RegistryCredentialsError(f"credential helper {program} exited with {done.returncode}")
    doc = parse_json(done.stdout, source=program, what="credential helper output", limit=MAX_JSON_BYTES)
    if not isinstance(doc, dict) or not isinstance(doc.get("Secret"), str) or not isinstance(doc.get("Username"), str):
        raise RegistryCredentialsError(f"credential helper {program} did not print Username and Secret")
    user, secret = doc["Username"], doc["Secret"]
    return _found(user, secret, source=program, identity_token=user == "<token>")
