"""The aead cipher: the kit's conformance suite (static keys and session secrets), the body
layout checked against ChaCha20-Poly1305 directly, and key forms."""

from __future__ import annotations

import base64
import os
from pathlib import Path

import pytest
from cryptography.hazmat.primitives.ciphers.aead import ChaCha20Poly1305
from rosgate_crypto_aead import AeadCipher
from rosgate_testing import CipherConformance, write_key

from rosgate import CipherError, OptionError
from rosgate.wire import envelope

HEADER = envelope.pack(0, 7, 0xCAFE, 1, 1_700_000_000_000_000_000)


class TestAeadConformance(CipherConformance):
    cipher = AeadCipher


def test_static_body_is_nonce_then_chacha20_poly1305_with_the_header_as_ad(tmp_path):
    key = AeadCipher.generate_key()
    write_key(tmp_path / "a.key", key)
    body = AeadCipher({"key_file": "a.key"}, tmp_path).seal(HEADER, b"payload")
    assert len(body) == 12 + 7 + 16
    plain = ChaCha20Poly1305(base64.b64decode(key)).decrypt(body[:12], body[12:], HEADER)
    assert plain == b"payload"


def test_session_body_takes_its_nonce_from_the_header_and_sends_none():
    secret = os.urandom(32)
    body = AeadCipher.from_secret(secret).seal(HEADER, b"payload")
    assert len(body) == 7 + 16
    assert ChaCha20Poly1305(secret).decrypt(HEADER[8:20], body, HEADER) == b"payload"


@pytest.mark.parametrize("content", [b"hello", b"", base64.b64encode(bytes(31))],
                         ids=["word", "empty", "31-byte"])
def test_a_key_that_is_not_an_aead_key_is_an_option_error(tmp_path: Path, content):
    (tmp_path / "bad.key").write_bytes(content)
    (tmp_path / "bad.key").chmod(0o600)
    with pytest.raises(OptionError, match="is not an aead key"):
        AeadCipher({"key_file": "bad.key"}, tmp_path)


def _ciphers(tmp_path: Path) -> list[tuple[AeadCipher, AeadCipher]]:
    """(sealer, opener) pairs: a session's (one secret) and a static key's (one key file)."""
    secret = os.urandom(32)
    write_key(tmp_path / "a.key", AeadCipher.generate_key())
    return [(AeadCipher.from_secret(secret), AeadCipher.from_secret(secret)),
            (AeadCipher({"key_file": "a.key"}, tmp_path),
             AeadCipher({"key_file": "a.key"}, tmp_path))]


@pytest.mark.skipif(not AeadCipher.in_place, reason="no encrypt_into/decrypt_into here")
@pytest.mark.parametrize("size", [0, 1, 70_000])
def test_seal_into_opens_with_open_and_open_into_opens_what_seal_made(tmp_path, size):
    payload = os.urandom(size)
    for sealer, opener in _ciphers(tmp_path):
        body = bytearray(size + sealer.overhead)
        sealer.seal_into(HEADER, payload, memoryview(body))
        assert opener.open(HEADER, bytes(body)) == payload
        sealed = bytearray(sealer.seal(HEADER, payload))
        assert len(sealed) == size + opener.overhead
        start, end = opener.open_into(HEADER, memoryview(sealed))
        assert bytes(sealed[start:end]) == payload
        assert end - start == size


@pytest.mark.skipif(not AeadCipher.in_place, reason="no encrypt_into/decrypt_into here")
def test_open_into_refuses_what_open_refuses(tmp_path):
    payload = os.urandom(1000)
    for sealer, opener in _ciphers(tmp_path):
        good = sealer.seal(HEADER, payload)
        for at in (0, len(good) // 2, len(good) - 1):
            bad = bytearray(good)
            bad[at] ^= 0x80
            with pytest.raises(CipherError, match="does not verify"):
                opener.open_into(HEADER, memoryview(bad))
        other = bytearray(HEADER)
        other[27] ^= 1
        with pytest.raises(CipherError, match="does not verify"):
            opener.open_into(bytes(other), memoryview(bytearray(good)))
        with pytest.raises(CipherError, match="at least 16 bytes"):
            opener.open_into(HEADER, memoryview(bytearray(opener.overhead - 1)))
