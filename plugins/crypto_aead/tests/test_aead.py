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

from rosgate import OptionError
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
