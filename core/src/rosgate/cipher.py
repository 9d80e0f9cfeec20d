"""Ciphers: seal a frame so that only a holder of the key can read it and nobody can alter it.

A cipher plugin is a subclass of :class:`Cipher` registered through the ``rosgate_ciphers``
hook. The core makes one instance per bridge (keys are read once). ``seal`` must authenticate the
plaintext envelope ``header`` together with the payload: the receiver passes the header it read
back to ``open``, which must raise :class:`rosgate.CipherError` if either was changed, or if the
frame was sealed under another key.

In an authenticated session (client/server with identities) a cipher is not built from a key
file: the session derives a fresh secret per direction, topic and key generation (HKDF from the
handshake) and calls :meth:`Cipher.from_secret`. A cipher that declares
:attr:`Cipher.session_key_size` can be used in sessions; one that leaves it at 0 (``none``)
cannot be keyed and is refused unless the server's policy names it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, ClassVar, Mapping


class Cipher:
    """Base class of cipher plugins."""

    #: the name users write in bringup.yaml (``cipher: fernet``)
    name: ClassVar[str]
    #: True when ``open`` proves a frame came from a key holder unchanged. Codecs may then skip
    #: checks on what they decode (the built-in cdr codec does).
    authenticates: ClassVar[bool] = True

    def __init__(self, options: Mapping[str, Any], base_dir: Path):
        """``options`` is the plugin's table under ``plugins:``; relative paths in it are relative to
        ``base_dir``, the folder of the bringup.yaml. Raise :class:`rosgate.OptionError` when a key is
        missing or unreadable (never print the key)."""
        self.options = dict(options)

    def seal(self, header: bytes, payload: bytes) -> bytes:
        raise NotImplementedError

    def open(self, header: bytes, body: bytes) -> bytes:
        raise NotImplementedError

    #: bytes of secret a session derives for this cipher; 0: it cannot be keyed from a session
    session_key_size: ClassVar[int] = 0

    @classmethod
    def from_secret(cls, secret: bytes) -> Cipher:
        """This cipher keyed from ``secret`` (``session_key_size`` bytes, derived for one
        direction of one topic in one key generation, never used for anything else).

        Under one secret the envelope header's epoch and sequence number (bytes 8..20, exactly
        12 bytes) never repeat, so a cipher may take them as its nonce instead of sending one.
        Implement it when you set :attr:`session_key_size`."""
        raise NotImplementedError(f"cipher {cls.name!r} cannot be keyed from a session")

    @classmethod
    def generate_key(cls) -> bytes | None:
        """A new key in the form the key file holds, for ``rosgate keygen NAME``; None if keyless."""
        return None
