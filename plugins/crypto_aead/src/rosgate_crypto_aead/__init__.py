"""rosgate cipher ``aead``: ChaCha20-Poly1305 (``cryptography``), the default cipher of
authenticated sessions.

The envelope header is the associated data: it travels in clear and any change to it, or to the
body, makes ``open`` raise :class:`rosgate.CipherError`. Overhead: 16 bytes (the tag) in a
session, 28 with a static key.

**In a session** (client/server with identities) the cipher is keyed by the session
(:meth:`AeadCipher.from_secret`: one key per direction, topic and key generation) and the nonce
is the header's epoch and sequence number, bytes 8..20 — exactly 12 bytes, which never repeat
under one session key — so nothing extra is sent: ``body = ciphertext | tag``.

**With a static key** (peer role, ``insecure: true``) one key serves every frame, both
directions and every restart, so the header cannot be the nonce (a service's answer echoes its
request's epoch and sequence number): a random 12-byte nonce goes in front,
``body = nonce | ciphertext | tag``. Options, exactly one of (:mod:`rosgate.keys`):

``key_file``  a file holding the key: 32 random bytes in standard base64 (44 characters).
              Create one with ``rosgate keygen aead --out aead.key`` (mode 0600).
``key_env``   the name of an environment variable holding the key in the same form.

**In place** (:attr:`rosgate.Cipher.in_place`): a large frame is sealed straight into the
buffer it is sent from (``encrypt_into``), and a reassembled one is decrypted back into the
buffer it was reassembled in (``decrypt_into``, from a copy of the ciphertext: input and output
never overlap), so no new image-sized buffer is made for the cipher on either side.
"""

from __future__ import annotations

import base64
import binascii
import os
from collections.abc import Callable
from pathlib import Path

from cryptography.exceptions import InvalidTag
from cryptography.hazmat.primitives.ciphers.aead import ChaCha20Poly1305

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

KEY_SIZE = 32
NONCE = 12
TAG = 16
NONCE_IN_HEADER = slice(8, 20)  # the envelope's epoch (u32) and sequence number (u64)


class AeadCipher(Cipher):
    name = "aead"
    Options = KeyOptions  # key_file or key_env: the convention of every rosgate cipher
    options: KeyOptions
    session_key_size = KEY_SIZE
    # encrypt_into and decrypt_into: cryptography 45 and later
    in_place = hasattr(ChaCha20Poly1305, "decrypt_into")

    def __init__(self, options: KeyOptions, base_dir: Path):
        super().__init__(options, base_dir)
        text = load_key(self.options, base_dir, self.name)
        try:
            key = base64.b64decode(text, validate=True)
        except (binascii.Error, ValueError):
            key = b""
        if len(key) != KEY_SIZE:
            raise OptionError(key_source(self.options),
                              f"the key in {describe_source(self.options)} is not an "
                              f"aead key ({KEY_SIZE} bytes in base64)",
                              "create one with 'rosgate keygen aead --out aead.key'")
        self._aead = ChaCha20Poly1305(key)
        self._nonce_in_header = False
        self.overhead = NONCE + TAG

    @classmethod
    def from_secret(cls, secret: bytes) -> AeadCipher:
        cipher = cls.__new__(cls)
        cipher.options = KeyOptions()
        cipher._aead = ChaCha20Poly1305(secret)
        cipher._nonce_in_header = True
        cipher.overhead = TAG
        return cipher

    def seal(self, header: bytes, payload: bytes) -> bytes:
        if self._nonce_in_header:
            return self._aead.encrypt(header[NONCE_IN_HEADER], payload, header)
        nonce = os.urandom(NONCE)
        return nonce + self._aead.encrypt(nonce, payload, header)

    def open(self, header: bytes, body: bytes) -> bytes:
        if self._nonce_in_header:
            nonce, sealed = header[NONCE_IN_HEADER], body
        else:
            nonce, sealed = body[:NONCE], body[NONCE:]
        if len(sealed) < TAG or len(nonce) != NONCE:
            raise CipherError(f"an aead body has at least {TAG} bytes after its nonce")
        try:
            return self._aead.decrypt(nonce, sealed, header)
        except InvalidTag:
            raise CipherError("does not verify under this key and header") from None

    def seal_into(self, header: bytes, payload: bytes, body: memoryview) -> None:
        if self._nonce_in_header:
            self._aead.encrypt_into(header[NONCE_IN_HEADER], payload, header, body)
            return
        nonce = os.urandom(NONCE)
        body[:NONCE] = nonce
        self._aead.encrypt_into(nonce, payload, header, body[NONCE:])

    def open_into(self, header: bytes | memoryview, body: memoryview) -> tuple[int, int]:
        start = 0 if self._nonce_in_header else NONCE
        nonce = header[NONCE_IN_HEADER] if self._nonce_in_header else body[:NONCE]
        end = len(body) - TAG
        if end < start or len(nonce) != NONCE:
            raise CipherError(f"an aead body has at least {TAG} bytes after its nonce")
        # the ciphertext is copied out first (one memcpy): decrypting a buffer into itself is
        # what OpenSSL allows, but not what cryptography promises, so the two never overlap
        sealed = bytes(body[start:])
        try:
            self._aead.decrypt_into(nonce, sealed, header, body[start:end])
        except InvalidTag:
            raise CipherError("does not verify under this key and header") from None
        return start, end

    @classmethod
    def generate_key(cls) -> bytes:
        return base64.b64encode(os.urandom(KEY_SIZE))


@hookimpl
def rosgate_ciphers(register: Callable[[type[Cipher]], None]) -> None:
    register(AeadCipher)
