"""A private, offline Sigstore instance that makes real bundles for the tests.

A Fulcio-like CA, a CT log and a Rekor log, each an ECDSA P-256 key made here; ``sign``
issues a short-lived code-signing certificate for an identity (with an embedded SCT),
signs the artifact, and logs a ``hashedrekord`` 0.0.1 entry (inclusion promise and a
one-leaf inclusion proof with a signed checkpoint). ``trusted_root()`` is the matching
sigstore trusted root. sigstore-python verifies these bundles like real ones; nothing
here touches the network.
"""

from __future__ import annotations

import base64
import datetime as dt
import hashlib
import json
import struct
from typing import Any

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

SCT_LIST = x509.ObjectIdentifier("1.3.6.1.4.1.11129.2.4.2")
OIDC_ISSUER_V1 = x509.ObjectIdentifier("1.3.6.1.4.1.57264.1.1")  # raw string
OIDC_ISSUER_V2 = x509.ObjectIdentifier("1.3.6.1.4.1.57264.1.8")  # DER UTF8String
ECDSA = ec.ECDSA(hashes.SHA256())


def _b64(data: bytes) -> str:
    return base64.b64encode(data).decode()


def _spki(key: Any) -> bytes:
    return key.public_bytes(serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo)


def _der_length(n: int) -> bytes:
    if n < 0x80:
        return bytes([n])
    raw = n.to_bytes((n.bit_length() + 7) // 8, "big")
    return bytes([0x80 | len(raw)]) + raw


def _der(tag: int, content: bytes) -> bytes:
    return bytes([tag]) + _der_length(len(content)) + content


def _json(obj: Any) -> bytes:
    return json.dumps(obj, separators=(",", ":"), sort_keys=True).encode()


class FakeSigstore:
    def __init__(self) -> None:
        self.now = dt.datetime.now(dt.UTC).replace(microsecond=0)
        self.ca_key = ec.generate_private_key(ec.SECP256R1())
        self.ct_key = ec.generate_private_key(ec.SECP256R1())
        self.rekor_key = ec.generate_private_key(ec.SECP256R1())
        name = x509.Name(
            [x509.NameAttribute(NameOID.ORGANIZATION_NAME, "test"), x509.NameAttribute(NameOID.COMMON_NAME, "fulcio")]
        )
        self.ca = (
            x509.CertificateBuilder()
            .subject_name(name)
            .issuer_name(name)
            .public_key(self.ca_key.public_key())
            .serial_number(1)
            .not_valid_before(self.now - dt.timedelta(days=1))
            .not_valid_after(self.now + dt.timedelta(days=365))
            .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
            .add_extension(x509.KeyUsage(False, False, False, False, False, True, True, False, False), critical=True)
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(self.ca_key.public_key()), critical=False)
            .sign(self.ca_key, hashes.SHA256())
        )

    def trusted_root(self) -> dict[str, Any]:
        start = {"start": (self.now - dt.timedelta(days=1)).strftime("%Y-%m-%dT%H:%M:%SZ")}

        def log(key: Any, url: str) -> dict[str, Any]:
            public = _spki(key.public_key())
            return {
                "baseUrl": url,
                "hashAlgorithm": "SHA2_256",
                "publicKey": {"rawBytes": _b64(public), "keyDetails": "PKIX_ECDSA_P256_SHA_256", "validFor": start},
                "logId": {"keyId": _b64(hashlib.sha256(public).digest())},
            }

        ca_der = self.ca.public_bytes(serialization.Encoding.DER)
        return {
            "mediaType": "application/vnd.dev.sigstore.trustedroot+json;version=0.1",
            "tlogs": [log(self.rekor_key, "https://rekor.test")],
            "certificateAuthorities": [
                {
                    "subject": {"organization": "test", "commonName": "fulcio"},
                    "uri": "https://fulcio.test",
                    "certChain": {"certificates": [{"rawBytes": _b64(ca_der)}]},
                    "validFor": start,
                }
            ],
            "ctlogs": [log(self.ct_key, "https://ctfe.test")],
            "timestampAuthorities": [],
        }

    def _leaf(self, key: Any, identity: str, issuer: str, sct: x509.UnrecognizedExtension | None) -> x509.Certificate:
        builder = (
            x509.CertificateBuilder()
            .subject_name(x509.Name([]))
            .issuer_name(self.ca.subject)
            .public_key(key.public_key())
            .serial_number(12345)
            .not_valid_before(self.now - dt.timedelta(minutes=1))
            .not_valid_after(self.now + dt.timedelta(minutes=10))
            .add_extension(x509.KeyUsage(True, False, False, False, False, False, False, False, False), critical=True)
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.CODE_SIGNING]), critical=False)
            .add_extension(x509.SubjectAlternativeName([x509.RFC822Name(identity)]), critical=True)
            .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(self.ca_key.public_key()), critical=False)
            .add_extension(x509.UnrecognizedExtension(OIDC_ISSUER_V1, issuer.encode()), critical=False)
            .add_extension(x509.UnrecognizedExtension(OIDC_ISSUER_V2, _der(0x0C, issuer.encode())), critical=False)
        )
        if sct is not None:
            builder = builder.add_extension(sct, critical=False)
        return builder.sign(self.ca_key, hashes.SHA256())

    def _sct(self, precert: x509.Certificate) -> x509.UnrecognizedExtension:
        """An RFC 6962 SCT over the precertificate, as the embedded SCT-list extension."""
        log_id = hashlib.sha256(_spki(self.ct_key.public_key())).digest()
        ms = int(self.now.timestamp() * 1000)
        tbs = precert.tbs_certificate_bytes
        issuer_key_hash = hashlib.sha256(_spki(self.ca_key.public_key())).digest()
        signed = struct.pack("!BBQH", 0, 0, ms, 1) + issuer_key_hash + len(tbs).to_bytes(3, "big") + tbs + b"\0\0"
        sig = self.ct_key.sign(signed, ECDSA)
        sct = bytes([0]) + log_id + struct.pack("!QH", ms, 0) + bytes([4, 3]) + struct.pack("!H", len(sig)) + sig
        sct_list = struct.pack("!H", len(sct) + 2) + struct.pack("!H", len(sct)) + sct
        return x509.UnrecognizedExtension(SCT_LIST, _der(0x04, sct_list))

    def sign(self, artifact: bytes, *, identity: str, issuer: str) -> str:
        """A bundle (v0.1 JSON) for ``artifact`` signed as ``identity``."""
        key = ec.generate_private_key(ec.SECP256R1())
        precert = self._leaf(key, identity, issuer, None)
        cert = self._leaf(key, identity, issuer, self._sct(precert))
        assert cert.tbs_precertificate_bytes == precert.tbs_certificate_bytes
        digest = hashlib.sha256(artifact).digest()
        sig = key.sign(artifact, ECDSA)
        cert_pem = cert.public_bytes(serialization.Encoding.PEM)
        body = _json(
            {
                "apiVersion": "0.0.1",
                "kind": "hashedrekord",
                "spec": {
                    "data": {"hash": {"algorithm": "sha256", "value": digest.hex()}},
                    "signature": {"content": _b64(sig), "publicKey": {"content": _b64(cert_pem)}},
                },
            }
        )
        log_id = hashlib.sha256(_spki(self.rekor_key.public_key())).digest()
        integrated = int(self.now.timestamp())
        promise = _json({"body": _b64(body), "integratedTime": integrated, "logID": log_id.hex(), "logIndex": 0})
        leaf = hashlib.sha256(b"\0" + body).digest()  # a one-entry log: the leaf hash is the root
        note = f"rekor.test - 1\n1\n{_b64(leaf)}\n"
        checkpoint = note + f"\n\u2014 rekor.test {_b64(log_id[:4] + self.rekor_key.sign(note.encode(), ECDSA))}\n"
        entry = {
            "logIndex": "0",
            "logId": {"keyId": _b64(log_id)},
            "kindVersion": {"kind": "hashedrekord", "version": "0.0.1"},
            "integratedTime": str(integrated),
            "inclusionPromise": {"signedEntryTimestamp": _b64(self.rekor_key.sign(promise, ECDSA))},
            "inclusionProof": {
                "logIndex": "0",
                "rootHash": _b64(leaf),
                "treeSize": "1",
                "hashes": [],
                "checkpoint": {"envelope": checkpoint},
            },
            "canonicalizedBody": _b64(body),
        }
        cert_der = cert.public_bytes(serialization.Encoding.DER)
        return json.dumps(
            {
                "mediaType": "application/vnd.dev.sigstore.bundle+json;version=0.1",
                "verificationMaterial": {
                    "x509CertificateChain": {"certificates": [{"rawBytes": _b64(cert_der)}]},
                    "tlogEntries": [entry],
                },
                "messageSignature": {
                    "messageDigest": {"algorithm": "SHA2_256", "digest": _b64(digest)},
                    "signature": _b64(sig),
                },
            }
        )
