"""The fernet cipher: round trips, every kind of tampering refused with CipherError (and nothing
else), and one OptionError naming the option for every way the key can be missing or wrong."""

from __future__ import annotations

import base64
import logging
import random
from pathlib import Path

import pytest
from cryptography.fernet import Fernet

from rosgate import CipherError, OptionError, envelope
from rosgate.plugins import Plugins
import rosgate_crypto_fernet
from rosgate_crypto_fernet import FernetCipher

HEADER = envelope.pack(0, 7, 0xCAFE, 1, 1_700_000_000_000_000_000)


def write_key(path: Path, key: bytes, mode: int = 0o600) -> Path:
    path.write_bytes(key + b"\n")
    path.chmod(mode)
    return path


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


# --- round trips -------------------------------------------------------------------------------------

@pytest.mark.parametrize("size", [0, 1, 28, 1000, 1_000_000])
def test_round_trip(cipher, size):
    payload = random.Random(size).randbytes(size)
    token = cipher.seal(HEADER, payload)
    assert cipher.open(HEADER, token) == payload
    if size >= 16:
        assert payload not in token  # not sent in clear


def test_each_seal_is_different(cipher):
    assert cipher.seal(HEADER, b"same") != cipher.seal(HEADER, b"same")


def test_key_env_opens_what_key_file_sealed(cipher, key, tmp_path, monkeypatch):
    monkeypatch.setenv("ROSGATE_TEST_FERNET_KEY", f"  {key.decode()}\n")
    from_env = FernetCipher({"key_env": "ROSGATE_TEST_FERNET_KEY"}, tmp_path)
    assert from_env.open(HEADER, cipher.seal(HEADER, b"across")) == b"across"
    assert cipher.open(HEADER, from_env.seal(HEADER, b"back")) == b"back"


def test_key_file_is_relative_to_the_base_dir_or_absolute(tmp_path, key):
    (tmp_path / "keys").mkdir()
    write_key(tmp_path / "keys" / "a.key", key)
    relative = FernetCipher({"key_file": "keys/a.key"}, tmp_path)
    absolute = FernetCipher({"key_file": str(tmp_path / "keys" / "a.key")}, Path("/nonexistent"))
    assert absolute.open(HEADER, relative.seal(HEADER, b"x")) == b"x"


def test_the_token_is_a_standard_fernet_token_of_header_and_payload(cipher, key):
    token = cipher.seal(HEADER, b"payload")
    assert Fernet(key).decrypt(token) == HEADER + b"payload"


# --- tampering ---------------------------------------------------------------------------------------

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


def test_another_key_is_refused(cipher, tmp_path):
    write_key(tmp_path / "other.key", Fernet.generate_key())
    other = FernetCipher({"key_file": "other.key"}, tmp_path)
    with pytest.raises(CipherError, match="not a valid token"):
        other.open(HEADER, cipher.seal(HEADER, b"secret"))


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
        bodies.append(b"gAAAAA" + bytes(rng.choice(alphabet) for _ in range(rng.choice([114, 134, 200]))))
        bodies.append(base64.urlsafe_b64encode(b"\x80" + rng.randbytes(rng.choice([56, 72, 88, 100]))))
    for body in bodies:
        try:
            cipher.open(HEADER, body)
        except CipherError:
            continue
        pytest.fail(f"open accepted {body!r}")


# --- options ---------------------------------------------------------------------------------------

def test_neither_key_file_nor_key_env(tmp_path):
    error = option_error({}, tmp_path)
    assert error.key is None
    assert error.message == "fernet needs exactly one of key_file or key_env"
    assert "rosgate keygen fernet" in error.fix


def test_both_key_file_and_key_env(tmp_path, key, monkeypatch):
    write_key(tmp_path / "secret.key", key)
    monkeypatch.setenv("ROSGATE_TEST_FERNET_KEY", key.decode())
    error = option_error({"key_file": "secret.key", "key_env": "ROSGATE_TEST_FERNET_KEY"}, tmp_path)
    assert error.key is None
    assert "exactly one of key_file or key_env" in error.message


def test_unknown_option(tmp_path, key):
    write_key(tmp_path / "secret.key", key)
    error = option_error({"key_file": "secret.key", "keyfile": "secret.key", "mode": 1}, tmp_path)
    assert error.key == "keyfile"  # the first unknown one, alphabetically
    assert error.message == "unknown option of fernet"
    assert error.fix == "valid options are key_file and key_env"


def test_missing_key_file_names_the_path(tmp_path):
    error = option_error({"key_file": "nope.key"}, tmp_path)
    assert error.key == "key_file"
    assert str(tmp_path / "nope.key") in error.message
    assert "No such file or directory" in error.message


def test_key_file_that_is_a_directory(tmp_path):
    (tmp_path / "dir.key").mkdir()
    error = option_error({"key_file": "dir.key"}, tmp_path)
    assert error.key == "key_file"
    assert str(tmp_path / "dir.key") in error.message


@pytest.mark.parametrize("value", [None, ""], ids=["unset", "empty"])
def test_key_env_unset_or_empty(tmp_path, monkeypatch, value):
    if value is None:
        monkeypatch.delenv("ROSGATE_TEST_FERNET_KEY", raising=False)
    else:
        monkeypatch.setenv("ROSGATE_TEST_FERNET_KEY", value)
    error = option_error({"key_env": "ROSGATE_TEST_FERNET_KEY"}, tmp_path)
    assert error.key == "key_env"
    assert error.message == "environment variable 'ROSGATE_TEST_FERNET_KEY' is not set or empty"
    assert error.fix.startswith("export ROSGATE_TEST_FERNET_KEY=")


def test_key_env_of_blanks_is_refused(tmp_path, monkeypatch):
    monkeypatch.setenv("ROSGATE_TEST_FERNET_KEY", "  \n")
    assert "not a Fernet key" in option_error({"key_env": "ROSGATE_TEST_FERNET_KEY"}, tmp_path).message


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


# --- keys -----------------------------------------------------------------------------------------------

def test_generate_key_makes_a_key_fernet_accepts(tmp_path):
    first, second = FernetCipher.generate_key(), FernetCipher.generate_key()
    assert first != second
    assert len(base64.urlsafe_b64decode(first)) == 32
    Fernet(first)
    write_key(tmp_path / "new.key", first)
    cipher = FernetCipher({"key_file": "new.key"}, tmp_path)
    assert cipher.open(HEADER, Fernet(first).encrypt(HEADER + b"ok")) == b"ok"


@pytest.mark.parametrize("mode", [0o644, 0o640, 0o604, 0o660])
def test_a_key_file_others_can_read_logs_a_warning(tmp_path, key, caplog, mode):
    path = write_key(tmp_path / "open.key", key, mode)
    with caplog.at_level(logging.WARNING, logger="rosgate"):
        FernetCipher({"key_file": "open.key"}, tmp_path)
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING and r.name == "rosgate"]
    assert len(warnings) == 1
    assert str(path) in warnings[0].getMessage()
    assert "chmod 600" in warnings[0].getMessage()


def test_a_private_key_file_logs_nothing(tmp_path, key, caplog):
    write_key(tmp_path / "private.key", key, 0o600)
    with caplog.at_level(logging.DEBUG, logger="rosgate"):
        FernetCipher({"key_file": "private.key"}, tmp_path)
    assert [r for r in caplog.records if r.name.startswith("rosgate")] == []


def test_registered_through_its_hook():
    plugins = Plugins()
    plugins.add(rosgate_crypto_fernet, "fernet", "rosgate-crypto-fernet", "0.1.0")
    assert plugins.failures == []
    assert plugins.get("cipher", "fernet").cls is FernetCipher
    assert FernetCipher.authenticates is True
