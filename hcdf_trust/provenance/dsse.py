"""DSSE envelopes over the exact statement bytes, signed with the release key(s).

securesystemslib's :class:`~securesystemslib.dsse.Envelope` computes the PAE and checks
the threshold; around it (distribution.md §3.4) we parse the file ourselves instead of
``Envelope.from_dict`` (which consumes its input and raises ``KeyError`` on a signature
without ``keyid``), refuse duplicate keys, trailing data and unknown fields, and map
every library exception to our errors. Key ids are the hex SHA-256 of the key's DER
SubjectPublicKeyInfo, the same value as the SUIT manifest's COSE ``kid``.
"""

from __future__ import annotations

import base64
import binascii
import json
from typing import Any

from ..ota.errors import KeyFileError
from . import PAYLOAD_TYPE
from .errors import MalformedProvenanceError, ProvenanceError

MAX_ENVELOPE_BYTES = 16 << 20


def sslib_key(public: Any) -> Any:
    """The securesystemslib key of an imgtool public (or private) key, keyid = SUIT kid."""
    from cryptography.hazmat.primitives.serialization import load_der_public_key
    from securesystemslib.signer import SSlibKey

    from ..ota.signer import key_id

    return SSlibKey.from_crypto(load_der_public_key(public.get_public_bytes()), keyid=key_id(public).hex())


def sslib_signer(signer: Any) -> Any:
    """A securesystemslib signer for an ota signer: a key file, or a PKCS#11 token key.

    Raises:
        KeyFileError: a signer of another kind.
    """
    from ..ota.hsm import HsmSigner
    from ..ota.signer import FileSigner

    if isinstance(signer, FileSigner):
        from securesystemslib.signer import CryptoSigner

        return CryptoSigner(signer.key.key, sslib_key(signer.public))
    if isinstance(signer, HsmSigner):
        return _token_signer(signer)
    raise KeyFileError(f"--provenance cannot sign with a {type(signer).__name__}")


def sign(payload: bytes, signers: list[Any]) -> bytes:
    """The envelope file: ``payload`` (the exact published bytes) signed by every signer."""
    from securesystemslib.dsse import Envelope

    env = Envelope(payload, PAYLOAD_TYPE, {})
    for s in signers:
        env.sign(sslib_signer(s))
    return _render(env)


def cosign(data: bytes, signer: Any, *, source: str) -> bytes:
    """The envelope file ``data`` with ``signer``'s signature added over the same payload
    bytes (a co-signature for a threshold: nothing else of the envelope changes). Check the
    envelope first: the co-signer vouches for what it signs.

    Raises:
        MalformedProvenanceError: ``data`` is not a DSSE envelope (:func:`parse`).
        KeyFileError: this key already signed it (one key never counts twice), or cannot sign.
    """
    env = parse(data, source=source)
    ours = sslib_signer(signer)
    if ours.public_key.keyid in env.signatures:
        raise KeyFileError(
            "this key already signed the provenance: a second signature by one key does not count twice",
            file=source,
            actual=ours.public_key.keyid,
        )
    env.sign(ours)
    return _render(env)


def _render(env: Any) -> bytes:
    return (json.dumps(env.to_dict(), indent=2) + "\n").encode()


def parse(data: bytes, *, source: str) -> Any:
    """A :class:`securesystemslib.dsse.Envelope` from the file's bytes, strictly.

    Raises:
        MalformedProvenanceError: not one JSON object with exactly ``payload``,
            ``payloadType`` and ``signatures`` (each ``{"keyid", "sig"}``, base64).
    """
    from securesystemslib.dsse import Envelope
    from securesystemslib.signer import Signature

    doc = strict_json(data, source=source, what="DSSE envelope")
    if not isinstance(doc, dict) or set(doc) != {"payload", "payloadType", "signatures"}:
        keys = sorted(doc) if isinstance(doc, dict) else type(doc).__name__
        raise MalformedProvenanceError(
            "not a DSSE envelope", file=source, expected="payload, payloadType, signatures", actual=str(keys)
        )
    payload_type, sigs = doc["payloadType"], doc["signatures"]
    if not isinstance(payload_type, str):
        raise MalformedProvenanceError("payloadType is not a string", file=source + "#/payloadType")
    payload = _b64(doc["payload"], source + "#/payload")
    if not isinstance(sigs, list) or not sigs:
        raise MalformedProvenanceError("signatures is not a non-empty list", file=source + "#/signatures")
    signatures: dict[str, Any] = {}
    for i, sig in enumerate(sigs):
        where = f"{source}#/signatures/{i}"
        if not isinstance(sig, dict) or set(sig) != {"keyid", "sig"} or not isinstance(sig["keyid"], str):
            raise MalformedProvenanceError(
                "a signature is not {keyid, sig}", file=where, expected="keyid, sig", actual=str(sig)[:200]
            )
        if sig["keyid"] in signatures:
            raise MalformedProvenanceError("two signatures with one keyid", file=where, actual=sig["keyid"])
        signatures[sig["keyid"]] = Signature(sig["keyid"], _b64(sig["sig"], where + "/sig").hex())
    return Envelope(payload, payload_type, signatures)


def verify(env: Any, keys: list[Any], threshold: int, *, source: str) -> list[str]:
    """The key ids of at least ``threshold`` distinct ``keys`` whose signatures verify
    over the envelope's PAE.

    Raises:
        ProvenanceError: fewer than ``threshold`` good signatures by those keys.
        KeyFileError: a threshold that ``keys`` cannot meet (a usage error, not a forgery).
    """
    from securesystemslib.exceptions import VerificationError

    if threshold < 1 or len({k.keyid for k in keys}) < threshold:
        raise KeyFileError(f"threshold {threshold} needs at least that many distinct keys", actual=str(len(keys)))
    try:
        accepted = env.verify(keys, threshold)
    except VerificationError as exc:
        raise ProvenanceError(
            f"envelope signatures do not verify with the key(s): {exc}",
            file=source,
            expected=f"{threshold} of {', '.join(sorted(k.keyid for k in keys))}",
            actual=", ".join(sorted(env.signatures)),
        ) from None
    return sorted(accepted)


def strict_json(data: bytes, *, source: str, what: str) -> Any:
    """One JSON value through the project's one strict reader, bounded by the envelope's cap."""
    from ..localfile import parse_json

    return parse_json(data, source=source, what=what, limit=MAX_ENVELOPE_BYTES)


def _b64(value: Any, where: str) -> bytes:
    if not isinstance(value, str):
        raise MalformedProvenanceError("not a base64 string", file=where)
    try:
        return base64.b64decode(value, validate=True)
    except (binascii.Error, ValueError):
        raise MalformedProvenanceError("not standard base64", file=where) from None


def _token_signer(signer: Any) -> Any:
    """A securesystemslib signer whose signature is made by the PKCS#11 token key
    (ECDSA P-256 over SHA-256 of the PAE, DER-encoded as securesystemslib verifies it;
    Ed25519 over the PAE itself; securesystemslib's own HSMSigner has no Ed25519)."""
    import hashlib

    from cryptography.hazmat.primitives.asymmetric.utils import encode_dss_signature
    from securesystemslib.signer import Signature, Signer

    key = sslib_key(signer.public)

    class TokenSigner(Signer):
        @property
        def public_key(self) -> Any:
            return key

        @classmethod
        def from_priv_key_uri(cls, priv_key_uri: str, public_key: Any, secrets_handler: Any = None) -> Any:
            raise NotImplementedError

        def sign(self, payload: bytes) -> Any:
            if signer.kind == "ecdsa-p256":
                raw = signer._sign(hashlib.sha256(payload).digest())
                half = len(raw) // 2
                sig = encode_dss_signature(int.from_bytes(raw[:half], "big"), int.from_bytes(raw[half:], "big"))
            else:
                sig = signer._sign(payload)
            return Signature(key.keyid, sig.hex())

    return TokenSigner()
