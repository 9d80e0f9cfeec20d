"""The fernet cipher: the plugin kit's conformance suite, then what is particular to Fernet:
standard tokens, the spare bits of its base64 padding, base64 garbage, and an OptionError at the
option for every key that is not a Fernet key (missing and unreadable keys: rosgate.keys)."""

from __future__ import annotations

import base64
import random
from pathlib import Path

import pytest
from cryptography.fernet import Fernet
from rosgate_crypto_fernet import FernetCipher
from rosgate_testing import CipherConformance, write_key

from rosgate import CipherError, OptionError
from rosgate.wire import envelope

HEADER = envelope.pack(0, 7, 0xCAFE, 1, 1_700_000_000_000_000_000)


class TestFernetConformance(CipherConformance):
    cipher = FernetCipher


@pytest.fixture
def key() -> bytes:
    return FernetCipher.generate_key()


@pytest.fixture
def cipher(tmp_path, key) -> FernetCipher:
    write_key(tmp_path / "secret.key", key)
    return FernetCipher({"key_file": "secret.key"}, tmp_path)


def option_error(options, base_dir: Path) -> OptionError:
    with pytest.raises(OptionError) as info:
        FernetCipher(options, base_dir)
    return info.value


# --- tokens --------------------------------------------------------------------------------------

@pytest.mark.parametrize("size", [16, 1000])
def test_the_payload_is_not_sent_in_clear(cipher, size):
    payload = random.Random(size).randbytes(size)
    token = cipher.seal(HEADER, payload)
    assert payload not in token and payload not in base64.urlsafe_b64decode(token)


def test_key_env_opens_what_key_file_sealed(cipher, key, tmp_path, monkeypatch):
    monkeypatch.setenv("ROSGATE_TEST_FERNET_KEY", f"  {key.decode()}\n")
    from_env = FernetCipher({"key_env": "ROSGATE_TEST_FERNET_KEY"}, tmp_path)
    assert from_env.open(HEADER, cipher.seal(HEADER, b"across")) == b"across"
    assert cipher.open(HEADER, from_env.seal(HEADER, b"back")) == b"back"


def test_the_token_is_a_standard_fernet_token_of_header_and_payload(cipher, key):
    token = cipher.seal(HEADER, b"payload")
    assert Fernet(key).decrypt(token) == HEADER + b"payload"


# --- tampering -----------------------------------------------------------------------------------

def test_every_flipped_bit_is_refused(cipher):
    # 28 + 4 bytes of plaintext: a 105-byte token, a multiple of 3, so its base64 has no padding
    # and no spare bits: every bit of the text carries a bit of the token
    payload = b"abcd"
    token = cipher.seal(HEADER, payload)
    assert len(base64.urlsafe_b64decode(token)) % 3 == 0 and not token.endswith(b"=")
    for i in range(len(token)):
        for bit in range(8):
            tampered = bytearray(token)
            tampered[i] ^= 1 << bit
            with pytest.raises(CipherError):
                cipher.open(HEADER, bytes(tampered))


@pytest.mark.parametrize("size", [0, 20, 40])
def test_flipped_bits_in_a_padded_token_never_change_the_payload(cipher, size):
    # base64 with padding has spare bits in its last character: flipping one of them decodes to
    # the same token (Fernet's encoding, not a forgery). Every other flip is refused.
    payload = bytes(range(size))
    token = cipher.seal(HEADER, payload)
    raw = base64.urlsafe_b64decode(token)
    last = len(token.rstrip(b"=")) - 1  # the only character with spare bits
    accepted = []
    for i in range(len(token)):
        for bit in range(8):
            tampered = bytearray(token)
            tampered[i] ^= 1 << bit
            try:
                opened = cipher.open(HEADER, bytes(tampered))
            except CipherError:
                continue
            accepted.append(i)
            assert base64.urlsafe_b64decode(bytes(tampered)) == raw
            assert opened == payload
    assert set(accepted) <= {last}


def test_another_header_is_refused(cipher):
    token = cipher.seal(HEADER, b"payload")
    assert cipher.open(HEADER, token) == b"payload"
    for other in [envelope.pack(0, 7, 0xCAFE, 2, 1_700_000_000_000_000_000),  # another seq
                  envelope.pack(0, 8, 0xCAFE, 1, 1_700_000_000_000_000_000),  # another topic
                  envelope.pack(1, 7, 0xCAFE, 1, 1_700_000_000_000_000_000)]:  # another flag
        with pytest.raises(CipherError, match="header"):
            cipher.open(other, token)
    for i in range(len(HEADER)):
        for bit in range(8):
            other = bytearray(HEADER)
            other[i] ^= 1 << bit
            with pytest.raises(CipherError):
                cipher.open(bytes(other), token)


def test_a_token_shorter_than_the_header_is_refused(cipher, key):
    with pytest.raises(CipherError):
        cipher.open(HEADER, Fernet(key).encrypt(HEADER[:10]))


def test_garbage_is_always_a_cipher_error(cipher):
    rng = random.Random(11)
    alphabet = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789-_="
    genuine = cipher.seal(HEADER, b"genuine")
    bodies = [b"", b"=", b"====", b"\x00", b"gAAAAA", genuine[:-4], genuine[:57], genuine + b"A",
              genuine + b"AAAA", genuine[1:], "é".encode()]
    for _ in range(300):
        bodies.append(rng.randbytes(rng.randint(0, 300)))
        bodies.append(bytes(rng.choice(alphabet) for _ in range(rng.randint(0, 300))))
        bodies.append(b"gAAAAA" + bytes(rng.choice(alphabet)
                                        for _ in range(rng.choice([114, 134, 200]))))
        bodies.append(base64.urlsafe_b64encode(b"\x80"
                                               + rng.randbytes(rng.choice([56, 72, 88, 100]))))
    for body in bodies:
        try:
            cipher.open(HEADER, body)
        except CipherError:
            continue
        pytest.fail(f"open accepted {body!r}")


def test_key_env_of_blanks_is_refused(tmp_path, monkeypatch):
    monkeypatch.setenv("ROSGATE_TEST_FERNET_KEY", "  \n")
    assert "not a Fernet key" in option_error({"key_env": "ROSGATE_TEST_FERNET_KEY"},
                                              tmp_path).message


@pytest.mark.parametrize("content", [b"hello", b"", Fernet.generate_key()[:-2], b"\xff" * 44,
                                     base64.urlsafe_b64encode(b"k" * 16)],
                         ids=["word", "empty", "truncated", "binary", "16-byte"])
def test_a_file_that_is_not_a_fernet_key(tmp_path, content):
    (tmp_path / "bad.key").write_bytes(content)
    (tmp_path / "bad.key").chmod(0o600)
    error = option_error({"key_file": "bad.key"}, tmp_path)
    assert "not a Fernet key" in error.message
    # the key itself is never shown
    if content:
        assert content.decode(errors="replace") not in f"{error.message} {error.fix}"


def test_a_bad_key_is_reported_at_the_option_that_named_it(tmp_path, monkeypatch):
    (tmp_path / "bad.key").write_bytes(b"hello")
    assert option_error({"key_file": "bad.key"}, tmp_path).key == "key_file"
    monkeypatch.setenv("ROSGATE_TEST_FERNET_KEY", "hello")
    assert option_error({"key_env": "ROSGATE_TEST_FERNET_KEY"}, tmp_path).key == "key_env"


# --- keys ----------------------------------------------------------------------------------------

def test_generate_key_makes_a_key_fernet_accepts(tmp_path):
    first, second = FernetCipher.generate_key(), FernetCipher.generate_key()
    assert first != second
    assert len(base64.urlsafe_b64decode(first)) == 32
    Fernet(first)
    write_key(tmp_path / "new.key", first)
    cipher = FernetCipher({"key_file": "new.key"}, tmp_path)
    assert cipher.open(HEADER, Fernet(first).encrypt(HEADER + b"ok")) == b"ok"
