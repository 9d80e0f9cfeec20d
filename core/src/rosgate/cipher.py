"""Ciphers: seal a frame so that only a holder of the key can read it and nobody can alter it.

A cipher plugin subclasses :class:`Cipher`, implements :meth:`~Cipher.seal` and
:meth:`~Cipher.open`, and is registered through the ``rosgate_ciphers`` hook. The core makes one
instance per bridge (keys are read once) and shares it between topics. ``seal`` must
authenticate the plaintext envelope ``header`` together with the payload: the receiver passes
the header it read back to ``open``, which must raise :class:`rosgate.CipherError` if either was
changed, or if the frame was sealed under another key.

Threads: ``seal`` and ``open`` are called from many threads at once (every topic's), so they
must be safe to call concurrently.

Keys follow one convention: declare ``Options = rosgate.keys.KeyOptions`` (``key_file`` or
``key_env``) and read the key with :func:`rosgate.keys.load_key`.

In an authenticated session (client/server with identities) a cipher is not built from a key
file: the session derives a fresh secret per direction, topic and key generation (HKDF from the
handshake) and calls :meth:`Cipher.from_secret`. A cipher that declares
:attr:`Cipher.session_key_size` can be used in sessions; one that leaves it at 0 (``none``)
cannot be keyed and is refused unless the server's policy names it.

A cipher that can write its output into a buffer it is given sets :attr:`Cipher.in_place` and
implements :meth:`~Cipher.seal_into` and :meth:`~Cipher.open_into`: the core then seals a large
payload straight into the frame it sends, and opens a reassembled frame where it lies, so a
1 MB image is not copied on either side for the cipher's sake.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from pathlib import Path
from typing import Any, ClassVar

from .options import as_options


class Cipher(ABC):
    """Base class of cipher plugins."""

    #: the name users write in bringup.yaml (``cipher: fernet``)
    name: ClassVar[str]
    #: True when ``open`` proves a frame came from a key holder unchanged. Codecs may then skip
    #: checks on what they decode (the built-in cdr codec does).
    authenticates: ClassVar[bool] = True

    def __init__(self, options: Any, base_dir: Path):
        """``options`` is the plugin's ``Options`` instance, parsed by the core from its table
        under ``plugins:`` (a plain mapping is parsed here the same way), kept as
        :attr:`options`; relative paths in it are relative to ``base_dir``, the folder of the
        bringup.yaml. Raise :class:`rosgate.OptionError` when a key is missing or unreadable
        (never show the key)."""
        self.options = as_options(type(self), options)

    @abstractmethod
    def seal(self, header: bytes, payload: bytes) -> bytes:
        """The body that travels after ``header`` (28 bytes, sent in clear): ``payload``
        encrypted and, together with ``header``, authenticated."""

    @abstractmethod
    def open(self, header: bytes, body: bytes) -> bytes:
        """The payload sealed in ``body`` under ``header``; :class:`rosgate.CipherError` if the
        header, the body or the key differ, and nothing else (``body`` comes from the network)."""

    #: implements :meth:`seal_into` and :meth:`open_into` (and sets :attr:`overhead`)
    in_place: ClassVar[bool] = False
    #: with :attr:`in_place`: the bytes ``seal`` adds to a payload (the same for every payload)
    overhead: int = 0

    def seal_into(self, header: bytes, payload: bytes, body: memoryview) -> None:
        """What :meth:`seal` returns, written into ``body`` (``len(payload) + overhead``
        bytes) instead. Only called when :attr:`in_place` is set."""
        raise NotImplementedError(f"cipher {self.name!r} does not seal in place")

    def open_into(self, header: bytes | memoryview, body: memoryview) -> tuple[int, int]:
        """:meth:`open`, decrypted where it lies: ``body`` (a writable view of the received
        frame) is overwritten, and the payload is ``body[start:end]``; returns ``(start,
        end)``. Raises as :meth:`open` does (``body`` is then garbage, and is dropped). Only
        called when :attr:`in_place` is set."""
        raise NotImplementedError(f"cipher {self.name!r} does not open in place")

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
        """A new key in the form the key file holds, for ``rosgate keygen NAME``; None if
        keyless."""
        return None
