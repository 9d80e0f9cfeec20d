"""rosgate cipher ``fernet``: Fernet tokens (AES-128-CBC + HMAC-SHA256), as ros2_socket_bridge used.

Kept for compatibility and familiarity; for speed prefer an AEAD cipher (Fernet is ~160 MB/s
on a 1 MiB frame and adds 57+ bytes plus base64 growth of a third).

The envelope header is authenticated by sealing it inside the token with the payload; ``open``
refuses a token whose inner header differs from the one that came in clear.

Options (``plugins: {fernet: {...}}``), exactly one of (the key convention of every rosgate
cipher, :mod:`rosgate.keys`):

``key_file``  path of a file holding the key (relative to the bringup.yaml). Create one with
              ``rosgate keygen fernet --out secret.key`` (mode 0600).
``key_env``   name of an environment variable holding the key.

The key is never taken from the command line, where other users could read it in ``ps``.

In an authenticated session the key is not read from a file: the session derives 32 bytes per
direction, topic and key generation, and :meth:`FernetCipher.from_secret` makes them a Fernet
key (16 for HMAC-SHA256, 16 for AES-128).
"""

from __future__ import annotations

import base64
from pathlib import Path

from cryptography.fernet import Fernet, InvalidToken

from rosgate import (
    Cipher,
    CipherError,
    KeyOptions,
    OptionError,
    describe_source,
    hookimpl,
    key_source,
    load_key,
)


class FernetCipher(Cipher):
    name = "fernet"
    Options = KeyOptions  # key_file or key_env: the convention of every rosgate cipher
    options: KeyOptions
    session_key_size = 32

    def __init__(self, options: KeyOptions, base_dir: Path):
        super().__init__(options, base_dir)
        key = load_key(self.options, base_dir, self.name)
        try:
            self._fernet = Fernet(key)
        except (ValueError, TypeError):
            raise OptionError(key_source(self.options),
                              f"the key in {describe_source(self.options)} is not a "
                              "Fernet key (32 url-safe base64-encoded bytes)",
                              "create one with 'rosgate keygen fernet --out secret.key'") from None

    @classmethod
    def from_secret(cls, secret: bytes) -> FernetCipher:
        cipher = cls.__new__(cls)
        cipher.options = KeyOptions()
        cipher._fernet = Fernet(base64.urlsafe_b64encode(secret))
        return cipher

    def seal(self, header: bytes, payload: bytes) -> bytes:
        return self._fernet.encrypt(header + payload)

    def open(self, header: bytes, body: bytes) -> bytes:
        try:
            plain = self._fernet.decrypt(body)
        except (InvalidToken, ValueError, TypeError):
            raise CipherError("not a valid token for this key") from None
        if plain[:len(header)] != header:
            raise CipherError("header does not match the sealed one")
        return plain[len(header):]

    @classmethod
    def generate_key(cls) -> bytes:
        return Fernet.generate_key()


@hookimpl
def rosgate_ciphers(register):
    register(FernetCipher)
