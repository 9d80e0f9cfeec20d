"""The nacl cipher: the kit's conformance suite, the body layout and the header bound through
the nonce (checked against PyNaCl directly), key forms, keygen, and its speed next to fernet."""

from __future__ import annotations

import base64
import hashlib
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
from nacl.secret import SecretBox
from rosgate_crypto_fernet import FernetCipher
from rosgate_crypto_nacl import NaclCipher
from rosgate_testing import CipherConformance, write_key

from rosgate import OptionError
from rosgate.wire import envelope

HEADER = envelope.pack(0, 7, 0xCAFE, 1, 1_700_000_000_000_000_000)


class TestNaclConformance(CipherConformance):
    cipher = NaclCipher


@pytest.fixture
def key() -> bytes:
    return NaclCipher.generate_key()


def cipher_for(tmp_path: Path, key: bytes) -> NaclCipher:
    write_key(tmp_path / "nacl.key", key)
    return NaclCipher({"key_file": "nacl.key"}, tmp_path)


def test_body_is_salt_then_secretbox_under_a_nonce_made_of_salt_and_header(tmp_path, key):
    body = cipher_for(tmp_path, key).seal(HEADER, b"payload")
    assert len(body) == 16 + len(b"payload") + 16
    salt = body[:16]
    nonce = hashlib.blake2b(salt + HEADER, digest_size=24).digest()
    assert SecretBox(base64.b64decode(key)).decrypt(body[16:], nonce) == b"payload"


def test_a_box_sealed_independently_with_that_nonce_opens(tmp_path, key):
    salt = os.urandom(16)
    nonce = hashlib.blake2b(salt + HEADER, digest_size=24).digest()
    box = SecretBox(base64.b64decode(key)).encrypt(b"from a microcontroller", nonce).ciphertext
    assert cipher_for(tmp_path, key).open(HEADER, salt + box) == b"from a microcontroller"


def test_key_env_opens_what_key_file_sealed(tmp_path, key, monkeypatch):
    monkeypatch.setenv("ROSGATE_TEST_NACL_KEY", key.decode())
    from_env = NaclCipher({"key_env": "ROSGATE_TEST_NACL_KEY"}, tmp_path)
    assert from_env.open(HEADER, cipher_for(tmp_path, key).seal(HEADER, b"x")) == b"x"


def test_generated_keys_are_32_random_bytes_in_base64():
    key = NaclCipher.generate_key()
    assert len(key) == 44 and len(base64.b64decode(key, validate=True)) == 32


@pytest.mark.parametrize("content", [b"hello", b"", base64.b64encode(bytes(31)),
                                     base64.b64encode(bytes(33)), b"\xff" * 44,
                                     FernetCipher.generate_key()[:-1]],
                         ids=["word", "empty", "31-byte", "33-byte", "binary", "not-base64"])
def test_a_key_that_is_not_a_nacl_key_is_an_option_error(tmp_path, content):
    (tmp_path / "bad.key").write_bytes(content)
    (tmp_path / "bad.key").chmod(0o600)
    with pytest.raises(OptionError) as info:
        NaclCipher({"key_file": "bad.key"}, tmp_path)
    assert info.value.key == "key_file"
    assert info.value.message == "the key in file 'bad.key' is not a nacl key (32 bytes in base64)"
    assert "rosgate keygen nacl" in info.value.fix


def test_missing_key_is_reported_by_the_shared_convention(tmp_path):
    with pytest.raises(OptionError, match="nacl needs exactly one of key_file or key_env"):
        NaclCipher({}, tmp_path)


def test_rosgate_keygen_nacl_writes_a_usable_key(tmp_path):
    rosgate = Path(sys.executable).with_name("rosgate")
    done = subprocess.run([str(rosgate), "keygen", "nacl", "--out", str(tmp_path / "k.key")],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "k.key").stat().st_mode & 0o777 == 0o600
    cipher = NaclCipher({"key_file": "k.key"}, tmp_path)
    assert cipher.open(HEADER, cipher.seal(HEADER, b"ok")) == b"ok"


def test_throughput_against_fernet(tmp_path, capsys):
    """Measured, not asserted: seal + open per second, nacl next to fernet."""
    ciphers = {"nacl": cipher_for(tmp_path, NaclCipher.generate_key())}
    write_key(tmp_path / "fernet.key", FernetCipher.generate_key())
    ciphers["fernet"] = FernetCipher({"key_file": "fernet.key"}, tmp_path)
    for size, label in [(1 << 20, "1 MiB"), (2500, "2.5 kB")]:
        payload = os.urandom(size)
        for name, cipher in ciphers.items():
            count, start = 0, time.perf_counter()
            while time.perf_counter() - start < 0.4:
                cipher.open(HEADER, cipher.seal(HEADER, payload))
                count += 1
            rate = count / (time.perf_counter() - start)
            with capsys.disabled():
                print(f"\n{name} seal+open {label}: {rate:,.0f}/s, {rate * size / 1e6:,.0f} MB/s")
