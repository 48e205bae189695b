"""``oci://HOST[:PORT]/REPO:TAG`` and ``oci://HOST[:PORT]/REPO@sha256:HEX``, parsed strictly.

The grammar is the distribution spec's (``<name>`` components, ``<reference>`` tags); anything
else (upper case, ``..``, a userinfo part, a query) is a usage error, never guessed at.
"""

from __future__ import annotations

import ipaddress
import re
from dataclasses import dataclass

from ..errors import InputError

_NAME = re.compile(r"[a-z0-9]+(?:(?:\.|_|__|-+)[a-z0-9]+)*(?:/[a-z0-9]+(?:(?:\.|_|__|-+)[a-z0-9]+)*)*")
_TAG = re.compile(r"[A-Za-z0-9_][A-Za-z0-9._-]{0,127}")
_DIGEST = re.compile(r"sha256:[0-9a-f]{64}")
_LABEL = r"[A-Za-z0-9](?:[A-Za-z0-9-]{0,61}[A-Za-z0-9])?"
_HOST = re.compile(rf"{_LABEL}(?:\.{_LABEL})*")
MAX_NAME = 255


class ReferenceError_(InputError):  # noqa: N801 -- ReferenceError is a builtin
    code = "oci-reference"


@dataclass(frozen=True)
class Reference:
    host: str  # as written (lower case), with no port
    port: int | None
    repository: str
    tag: str | None
    digest: str | None  # "sha256:<hex>"

    @property
    def netloc(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{host}:{self.port}" if self.port is not None else host

    @property
    def reference(self) -> str:
        """What goes after ``/manifests/``: the digest when pinned, else the tag."""
        return self.digest or self.tag or "latest"

    def __str__(self) -> str:
        at = f"@{self.digest}" if self.digest else f":{self.tag}"
        return f"oci://{self.netloc}/{self.repository}{at}"

    def with_digest(self, digest: str) -> Reference:
        return Reference(self.host, self.port, self.repository, None, digest)

    @property
    def loopback(self) -> bool:
        if self.host == "localhost":
            return True
        try:
            return ipaddress.ip_address(self.host).is_loopback
        except ValueError:
            return False


def parse_reference(text: str, *, need_tag: bool = False) -> Reference:
    """Raises ReferenceError_ (exit 3) for anything not in the grammar above."""

    def bad(why: str) -> ReferenceError_:
        return ReferenceError_(f"{text!r} is not an OCI reference oci://HOST[:PORT]/REPO:TAG or @sha256:HEX: {why}")

    if not text.startswith("oci://"):
        raise bad("it must start with oci://")
    rest = text[len("oci://") :]
    if any(c in rest for c in "?#@ \\") and not re.fullmatch(r"[^?#@ \\]*@sha256:[0-9a-f]{64}", rest):
        raise bad("no userinfo, query, fragment or spaces")
    hostport, _, path = rest.partition("/")
    if not path:
        raise bad("no repository")
    if hostport.startswith("["):
        host, sep, port_text = hostport[1:].partition("]")
        if not sep or (port_text and not port_text.startswith(":")):
            raise bad("bad IPv6 host")
        port_text = port_text[1:]
        try:
            ipaddress.IPv6Address(host)
        except ValueError:
            raise bad("bad IPv6 host") from None
    else:
        host, _, port_text = hostport.partition(":")
        if not _HOST.fullmatch(host):
            raise bad("bad host")
    port = None
    if port_text:
        if not port_text.isdigit() or not 0 < int(port_text) < 65536:
            raise bad("bad port")
        port = int(port_text)
    digest = tag = None
    if "@" in path:
        path, _, digest = path.partition("@")
        if not _DIGEST.fullmatch(digest):
            raise bad("the digest must be sha256: and 64 lower-case hex digits")
    else:
        last = path.rsplit("/", 1)[-1]
        if ":" in last:
            path, _, tag = path.rpartition(":")
            if not _TAG.fullmatch(tag):
                raise bad("bad tag")
    if not _NAME.fullmatch(path) or len(path) > MAX_NAME:
        raise bad("bad repository name (lower-case components separated by /)")
    if need_tag and tag is None:
        raise bad("a tag is needed here (REPO:TAG)")
    if tag is None and digest is None:
        raise bad("give a tag (REPO:TAG) or a digest (REPO@sha256:HEX)")
    return Reference(host.lower(), port, path, tag, digest)
