"""The 802.1X AES-CMAC KDF against published vectors (see shared/notes/macsec.md, section 4)."""

from __future__ import annotations

from cryptography.hazmat.primitives.ciphers.algorithms import AES
from cryptography.hazmat.primitives.cmac import CMAC
from cryptography.hazmat.primitives.keywrap import aes_key_wrap

from hcdf_trust.macsec import kdf

H = bytes.fromhex
CAK_1 = H("0123456789abcdef0123456789abcdef")
CAK_2 = H("0123456789abcdef" * 4)


def test_rfc4493_cmac_sanity():
    mac = CMAC(AES(H("2b7e151628aed2a6abf7158809cf4f3c")))
    assert mac.finalize().hex() == "bb1d6929e95937287fa37d129b756746"


def test_sak_vectors_a1_a2():
    # Android IMacsecPskPlugin VTS vectors A1, A2 (standard KDF)
    assert kdf.sak(CAK_1, H("31323334111212143132333411121214"), 16).hex() == "13d9ee5b268b44fb37633d41c8e70d93"
    assert (
        kdf.sak(CAK_2, H("31323334" * 8), 32).hex()
        == "3909366018072b5df0818145cd71c6ba1d2b87c4ef79688228d02586d363ff89"
    )


def test_kek_vectors_a3_a4():
    # A3/A4: AES-KW(KEK(CAK, CKN), SAK) as published: this checks the KEK derivation end to end
    sak1 = kdf.sak(CAK_1, H("31323334111212143132333411121214"), 16)
    assert aes_key_wrap(kdf.kek(CAK_1, b"1234"), sak1).hex() == "3b39ab4cd8da2ec5d1386a139de378d993d2a07088cbf5ec"
    sak2 = kdf.sak(CAK_2, H("31323334" * 8), 32)
    assert (
        aes_key_wrap(kdf.kek(CAK_2, b"5678"), sak2).hex()
        == "2f6a2229680e6e359164054a318d35ea958540c6ea55e5c56840ae4d6feb73cd4e2a43b1da494f0a"
    )


def test_ick_standard_icvs():
    # the standard ICVs of A5/A6 (ICK from the padded CKN): AES-CMAC(ICK, data)
    for cak, ckn, data, icv in [
        (CAK_1, b"1234", "31323334313234295152535451355459", "4406a5240ec0f0479d94543d8d6561b5"),
        (CAK_2, b"5678", "718213243182a42f5152534421355459", "a81998d6d0aac003ec8fa83d32f763e6"),
    ]:
        mac = CMAC(AES(kdf.ick(cak, ckn)))
        mac.update(H(data))
        assert mac.finalize().hex() == icv


def test_hostap_example_regression():
    ckn = H("6162636465666768696a6b6c6d6e6f707172737475767778797a303132333435")
    assert kdf.kek(CAK_1, ckn).hex() == "d1eed7b4638f373c9b5891bb6342cdb8"
    assert kdf.ick(CAK_1, ckn).hex() == "daf4c372bc50b80a86a39eb12b360517"
    assert kdf.ick(CAK_1, b"1234").hex() == "5743529abaa746e945f14b7717f342d6"
    assert len(kdf.ick(CAK_2, b"5678")) == 32


def test_key_check_value_depends_on_cak_and_first_16_ckn_octets():
    ckn = bytes(range(20))
    kcv = kdf.key_check_value(CAK_1, ckn)
    assert len(kcv) == 6 and kcv == kdf.key_check_value(CAK_1, ckn)
    assert kcv != kdf.key_check_value(CAK_2[:16][::-1], ckn)
    assert kcv != kdf.key_check_value(CAK_1, bytes(range(1, 21)))
    # octets past the 16th do not reach the KDF: why the store keeps the first 16 unique
    assert kcv == kdf.key_check_value(CAK_1, ckn[:16] + b"xxxx")
