"""The one secret filter: every message, ``--json`` object and click usage error is passed
through :func:`scrub` before it is printed (by ``hcdf_trust.cli``: ``say``, ``emit_json``
and the ``hcdf-trust`` group's handling of click's own errors).

Whatever option or file a secret came through, what is printed never holds:

- a URL's ``user:password@`` or query string: ``https://***@host/path?***``
  (:func:`hcdf_trust.errors.redact`, applied to every URL in the text);
- a private key: PEM ``… PRIVATE KEY …`` blocks, ``AGE-SECRET-KEY-1…``, age plugin identities;
- 32 or 64 hex digits (a CAK, SAK or PSK) after a key word (``cak``, ``mka_cak``, ``psk``,
  ``secret``, ``key=``, ``Key:``, iproute2's ``key 01 HEX``);
- a passphrase or PIN this run has read (:func:`remember`, called by the one passphrase reader).

With ``controls=True`` (human messages) every control character, newline included, and the
Unicode line separators and bidirectional overrides are escaped (``\\n``, ``\\x1b``, ``\\u202e``):
a name with a newline cannot forge a line of a CI log, nor an ANSI escape repaint the terminal.
Multi-line messages are printed as several lines, each scrubbed on its own.
"""

from __future__ import annotations

import json
import re
from typing import Any

from .errors import redact

SHOWN = "***"

# URL-like words: anything with "scheme://", http(s) written loosely ("https:u:pw@h",
# "https:\\h") and PKCS#11 URIs (``?pin-value=``); they end at a space, a quote or a
# bracket (messages quote them that way).
_URL = r"(?:\b[A-Za-z][A-Za-z0-9+.-]*://|\b[Hh][Tt][Tt][Pp][Ss]?:|\b[Pp][Kk][Cc][Ss]11:)[^\s'\"<>\[\]]*"
# A PEM private key, to its END line, or (cut short in a message) to the end of its base64.
_PEM = r"-----BEGIN (?P<pem>[A-Z0-9 ]*PRIVATE KEY[A-Z0-9 ]*)-----(?:.*?-----END (?P=pem)-----|[A-Za-z0-9+/=\s\\:,-]*)"
_AGE = r"(?i:AGE-(?:SECRET-KEY|PLUGIN-[A-Z0-9-]+?)-1[02-9AC-HJ-NP-Z]+)"
# 32 or 64 hex digits after a key word. "key" alone needs "=" or ":" (registry messages say
# "key <keyid>" of public keys); iproute2 writes "key <key-id> <hex>".
_HEX = r"(?:[0-9A-Fa-f]{64}|[0-9A-Fa-f]{32})(?![0-9A-Fa-f])"
_KEYED = (
    r"(?i:\b(?P<word>(?:mka_)?cak|sak|psk|secret|passphrase|password|pin)\b[\"']?\s{0,3}[=:]?\s{0,3}[\"']?"
    r"|\b(?:private[ _-]?)?key\b[\"']?\s{0,3}[=:]\s{0,3}[\"']?"
    r"|\bkey\s{1,3}[0-9A-Fa-f]{1,2}\s{1,3})"
    rf"(?P<hex>{_HEX})"
)
_SECRET = re.compile(rf"(?P<url>{_URL})|(?P<key>{_PEM})|(?P<age>{_AGE})|(?P<keyed>{_KEYED})", re.S)
# What every match of _SECRET contains (hex only after a key word): a text without any is
# left as it is, at the cost of one search.
_HINT = re.compile(
    r"(?i)://|https?:|pkcs11:|PRIVATE KEY|AGE-"
    r"|(?:cak|sak|psk|secret|passphrase|password|pin|key)[^0-9a-z]{0,9}(?:[0-9a-f]{1,2}\s{1,3})?[0-9a-f]{32}"
)

# C0 and C1 controls, DEL, the Unicode line and paragraph separators, bidirectional overrides.
_CONTROLS = re.compile("[\x00-\x1f\x7f-\x9f\u2028\u2029\u202a-\u202e\u2066-\u2069]")
_NAMED = {"\n": "\\n", "\r": "\\r", "\t": "\\t"}

# Passphrases and PINs read by this run (remember); cleared when a command starts.
_remembered: set[str] = set()
MIN_REMEMBERED = 8  # shorter ones would blank ordinary words ("wrong") and numbers


def remember(secret: bytes | str) -> None:
    """Hide ``secret`` (a passphrase or PIN just read) from every message of this run."""
    text = secret.decode("utf-8", "replace") if isinstance(secret, bytes) else secret
    if len(text) >= MIN_REMEMBERED:
        _remembered.add(text)
        _remembered.add(json.dumps(text)[1:-1])  # as it would appear inside a JSON string


def forget_all() -> None:
    """Start a new run: forget the passphrases of the previous one (in-process callers)."""
    _remembered.clear()


def _replace(m: re.Match[str]) -> str:
    if m.group("url") is not None:
        return redact(m.group("url"))
    if m.group("key") is not None:
        return f"[{m.group('pem')} redacted]"
    if m.group("age") is not None:
        return m.group("age").split("-1", 1)[0] + "-1" + SHOWN
    return m.group("keyed")[: -len(m.group("hex"))] + SHOWN


def escape_controls(text: str) -> str:
    """``text`` with every control character (newline included) written as an escape."""
    return _CONTROLS.sub(_escape, text)


def _escape(m: re.Match[str]) -> str:
    ch = m.group()
    return _NAMED.get(ch) or (f"\\x{ord(ch):02x}" if ord(ch) < 0x100 else f"\\u{ord(ch):04x}")


def scrub(text: str, *, controls: bool = True) -> str:
    """``text`` as it may be printed: secrets hidden; with ``controls``, control characters escaped."""
    if _HINT.search(text) is not None:
        text = _SECRET.sub(_replace, text)
    for secret in _remembered:
        if secret in text:
            text = text.replace(secret, SHOWN)
    return escape_controls(text) if controls else text


def scrub_json(value: Any) -> Any:
    """A ``--json`` payload with every string scrubbed (JSON escapes control characters itself).

    Each distinct string is looked at once, and the payload is rebuilt only when one of them
    changed: a 10,000-association plan is 145,000 strings, few of them distinct, none a secret.
    """
    strings: set[str] = set()
    stack = [value]
    pop, push, more, add = stack.pop, stack.append, stack.extend, strings.add
    while stack:  # exact types (what json.dumps is given), checked the fastest way
        item = pop()
        kind = type(item)
        if kind is str:
            add(item)
        elif kind is dict:
            more(item.values())
        elif kind is list or kind is tuple:
            more(item)
        elif isinstance(item, str):  # a str enum: json writes its text
            add(str.__str__(item))
        elif isinstance(item, dict | list | tuple):  # a subclass: rare
            push(dict(item) if isinstance(item, dict) else list(item))
    changed = {text: shown for text in strings if (shown := scrub(text, controls=False)) != text}
    return _replaced(value, changed) if changed else value


def _replaced(value: Any, changed: dict[str, str]) -> Any:
    if isinstance(value, str):
        return changed.get(str.__str__(value), value)
    if isinstance(value, dict):
        return {k: _replaced(v, changed) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_replaced(v, changed) for v in value]
    return value
