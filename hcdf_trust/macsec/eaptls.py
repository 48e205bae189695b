"""EAP-TLS credentials for ``key-agreement="eap-tls"``: a CA per network, a key and certificate per member.

Store entries (secrets are PEM, encrypted like every other key):

* ``eap-ca:<network>``            the network's CA private key and self-signed certificate;
* ``eap-cert:<network>/<device>`` a device's private key and its certificate from that CA.

Keys are ECDSA P-256. The CA certificate is valid for :data:`CA_DAYS` days (path length 0),
device certificates for :data:`CERT_DAYS` days with both TLS client and server usage (an
MKA peer can be either side of the EAP exchange); subject CN = the device name as planned.
"""

from __future__ import annotations

from datetime import datetime, timedelta

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

CA_DAYS = 3650
CERT_DAYS = 825


def ca_id(network: str) -> str:
    return f"eap-ca:{network}"


def cert_id(network: str, device: str) -> str:
    return f"eap-cert:{network}/{device}"


def _pem_key(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )


def _name(common: str) -> x509.Name:
    return x509.Name(
        [x509.NameAttribute(NameOID.ORGANIZATION_NAME, "hcdf-trust"), x509.NameAttribute(NameOID.COMMON_NAME, common)]
    )


def make_ca(network: str, now: datetime) -> bytes:
    """A new network CA: PEM private key followed by PEM certificate."""
    key = ec.generate_private_key(ec.SECP256R1())
    name = _name(f"hcdf-trust MACsec CA {network}"[:64])
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - timedelta(minutes=5))
        .not_valid_after(now + timedelta(days=CA_DAYS))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=False,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                key_cert_sign=True,
                crl_sign=True,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )
    return _pem_key(key) + cert.public_bytes(serialization.Encoding.PEM)


def split(bundle: bytes) -> tuple[bytes, bytes]:
    """(private key PEM, certificate PEM) of a stored bundle."""
    marker = b"-----BEGIN CERTIFICATE-----"
    at = bundle.index(marker)
    return bundle[:at], bundle[at:]


def make_cert(ca_bundle: bytes, device: str, now: datetime) -> bytes:
    """A device key and certificate issued by the network CA: PEM key followed by PEM certificate."""
    ca_key_pem, ca_cert_pem = split(ca_bundle)
    ca_key = serialization.load_pem_private_key(ca_key_pem, password=None)
    assert isinstance(ca_key, ec.EllipticCurvePrivateKey)
    ca_cert = x509.load_pem_x509_certificate(ca_cert_pem)
    key = ec.generate_private_key(ec.SECP256R1())
    cert = (
        x509.CertificateBuilder()
        .subject_name(_name(device[:64]))
        .issuer_name(ca_cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - timedelta(minutes=5))
        .not_valid_after(min(now + timedelta(days=CERT_DAYS), ca_cert.not_valid_after_utc))
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(
            x509.ExtendedKeyUsage([ExtendedKeyUsageOID.CLIENT_AUTH, ExtendedKeyUsageOID.SERVER_AUTH]), critical=False
        )
        .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False)
        .sign(ca_key, hashes.SHA256())
    )
    return _pem_key(key) + cert.public_bytes(serialization.Encoding.PEM)
