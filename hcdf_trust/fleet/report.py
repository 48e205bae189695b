"""``fleet status --report``: the fleet's reported state, signed by the host that asked.

A DSSE envelope (securesystemslib) over a JSON statement, in the spirit of Uptane's ECU
version report — but SMP gives no ECU key, nonce or time, so the only signature is the
host's: the report says plainly that it is a *host-attested* version report, never device
attestation. ``audit --fleet-report`` verifies it with the host's public key and flags
every device that does not run the release.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from typing import Any

from ..errors import InputError, IntegrityError

PAYLOAD_TYPE = "application/vnd.hcdf-trust.fleet-report+json"
REPORT_TYPE = "hcdf-trust fleet version report v1"
STATEMENT = (
    "host-attested version report: each device's image state was read over MCUmgr (SMP), which is "
    "unauthenticated and carries no nonce and no device signature; this report is signed by the host "
    "that asked, not by the devices. It is not device attestation."
)
MAX_REPORT_BYTES = 16 << 20


class FleetReportError(IntegrityError):
    code = "fleet-report"


class MalformedFleetReport(InputError):
    code = "fleet-report"


def payload(report: Any, *, release_dir: str, root_sha256: str, host_keyid: str) -> dict[str, Any]:
    """The statement: what was asked, what each device said, the verdicts."""
    from ..localfile import read_input
    from ..ota import suit
    from ..ota.release import MANIFEST_NAME

    manifest = read_input(os.path.join(release_dir, MANIFEST_NAME), limit=suit.MAX_MANIFEST_BYTES, what="manifest")
    epoch = os.environ.get("SOURCE_DATE_EPOCH")
    created = int(epoch) if epoch and epoch.isdigit() else int(time.time())
    return {
        "type": REPORT_TYPE,
        "statement": STATEMENT,
        "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(created)),
        "host_keyid": host_keyid,
        "description": {"sha256": root_sha256},
        "release": {
            "sequence_number": report.release.sequence_number,
            "lock_sha256": report.release.lock_sha256,
            "manifest_sha256": hashlib.sha256(manifest).hexdigest(),
        },
        "devices": [d.to_json() for d in report.devices],
        "all_current": report.exit_code == 0,
    }


def host_signer(private_key: Any) -> Any:
    """A securesystemslib signer for an ``ota keygen`` key (ECDSA P-256 or Ed25519)."""
    from securesystemslib.signer import CryptoSigner

    return CryptoSigner(getattr(private_key, "key", private_key))


def token_signer(hsm: Any) -> Any:
    """A securesystemslib signer whose signatures are made in a PKCS#11 token, through
    ``ota``'s one token session (:class:`hcdf_trust.ota.hsm.HsmSigner`): ECDSA P-256 signs
    SHA-256 of the DSSE PAE (the token's raw r‖s, DER-encoded as securesystemslib's
    ``ecdsa-sha2-nistp256`` scheme verifies it), Ed25519 the PAE itself."""
    from cryptography.hazmat.primitives.asymmetric.utils import encode_dss_signature
    from securesystemslib.signer import Signature, Signer, SSlibKey

    public = SSlibKey.from_crypto(hsm.public.key if hasattr(hsm.public, "key") else hsm.public)

    class TokenSigner(Signer):
        @property
        def public_key(self) -> Any:
            return public

        @classmethod
        def from_priv_key_uri(cls, priv_key_uri: str, public_key: Any, secrets_handler: Any = None) -> Any:
            raise NotImplementedError("made from an open token session only")

        def sign(self, payload: bytes) -> Signature:
            if hsm.kind == "ecdsa-p256":
                raw = hsm._sign(hashlib.sha256(payload).digest())
                half = len(raw) // 2
                sig = encode_dss_signature(int.from_bytes(raw[:half], "big"), int.from_bytes(raw[half:], "big"))
            else:
                sig = hsm._sign(payload)
            return Signature(public.keyid, sig.hex())

    return TokenSigner()


def sign(statement: dict[str, Any], signer: Any) -> bytes:
    """The DSSE envelope over ``statement``, as JSON bytes."""
    from securesystemslib.dsse import Envelope

    body = json.dumps(statement, sort_keys=True, separators=(",", ":")).encode()
    env = Envelope(payload=body, payload_type=PAYLOAD_TYPE, signatures={})
    env.sign(signer)
    return (json.dumps(env.to_dict(), indent=2, sort_keys=True) + "\n").encode()


def verify(data: bytes, public_key: Any, *, source: str) -> dict[str, Any]:
    """The statement of a report signed by ``public_key``.

    Raises:
        MalformedFleetReport: not a DSSE envelope of this payload type (exit 3).
        FleetReportError: the signature does not verify with the key (exit 1).
    """
    from securesystemslib.dsse import Envelope
    from securesystemslib.exceptions import VerificationError
    from securesystemslib.signer import SSlibKey

    doc = _strict_json(data, source)
    if not isinstance(doc, dict) or doc.get("payloadType") != PAYLOAD_TYPE:
        raise MalformedFleetReport(
            "not a fleet report (DSSE envelope)",
            file=source,
            expected=PAYLOAD_TYPE,
            actual=str(doc.get("payloadType") if isinstance(doc, dict) else type(doc).__name__)[:80],
        )
    try:
        env = Envelope.from_dict(dict(doc))
    except (KeyError, TypeError, ValueError) as exc:
        raise MalformedFleetReport(f"malformed DSSE envelope ({exc})", file=source) from None
    key = SSlibKey.from_crypto(getattr(public_key, "key", public_key))
    try:
        env.verify([key], 1)
    except VerificationError:
        raise FleetReportError(
            "the fleet report's signature does not verify with the host key", file=source, expected=key.keyid
        ) from None
    statement = _strict_json(env.payload, source)
    if not isinstance(statement, dict) or statement.get("type") != REPORT_TYPE:
        raise MalformedFleetReport("signed payload is not a fleet version report", file=source)
    devices = statement.get("devices")
    if not isinstance(devices, list) or not all(
        isinstance(d, dict) and isinstance(d.get("comp"), str) and isinstance(d.get("verdict"), str) for d in devices
    ):
        raise MalformedFleetReport("fleet report: devices[] without comp and verdict", file=source)
    return statement


def read(path: str, public_key: Any) -> dict[str, Any]:
    from ..localfile import read_input

    return verify(read_input(path, limit=MAX_REPORT_BYTES, what="fleet report"), public_key, source=path)


def _strict_json(data: bytes, source: str) -> Any:
    """The report and its payload through the project's one strict JSON reader."""
    from ..localfile import parse_json

    return parse_json(data, source=source, what="fleet report", limit=MAX_REPORT_BYTES)
