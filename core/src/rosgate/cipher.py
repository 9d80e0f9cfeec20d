"""Ciphers: seal a frame so that only a holder of the key can read it and nobody can alter it.

A cipher plugin subclasses :class:`Cipher` and registers it through ``rosgate_ciphers``. The core
makes one instance per bridge (keys are read once) and shares it between topics, whose threads
call ``seal`` and ``open`` concurrently: both must be thread-safe. Keys follow one convention:
``Options = rosgate.keys.KeyOptions`` and :func:`rosgate.keys.load_key`. In a session
(client/server with identities) the core keys the cipher itself, per direction, topic and key
generation, through :meth:`Cipher.from_secret`; a cipher that leaves
:attr:`Cipher.session_key_size` at 0 (``none``) is refused there unless the server's policy
names it.
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
    #: True when ``seal`` and ``open`` leave the payload as it is (the ``none`` cipher): the
    #: core then calls neither, the frame's body being its payload
    plain: ClassVar[bool] = False

    def __init_subclass__(cls, **kwargs: Any) -> None:
        """A subclass of a plain cipher that seals or opens on its own is not plain, unless it
        says so."""
        super().__init_subclass__(**kwargs)
        if "plain" not in vars(cls) and ("seal" in vars(cls) or "open" in vars(cls)):
            cls.plain = False

    def __init__(self, options: Any, base_dir: Path):
        """``options``: the plugin's ``Options`` (a plain mapping is parsed the same way), kept as
        :attr:`options`; paths in it are relative to ``base_dir``, the bringup.yaml's folder.
        Raise :class:`rosgate.OptionError` for a missing or unreadable key (never show it)."""
        self.options = as_options(type(self), options)

    @abstractmethod
    def seal(self, header: bytes, payload: bytes) -> bytes:
        """The body that travels after ``header`` (28 bytes, sent in clear): ``payload``
        encrypted and, together with ``header``, authenticated."""

    @abstractmethod
    def open(self, header: bytes, body: bytes) -> bytes:
        """The payload sealed in ``body`` under ``header``; :class:`rosgate.CipherError` if the
        header, the body or the key differ, and nothing else (``body`` comes from the network)."""

    #: implements :meth:`seal_into` and :meth:`open_into` (and sets :attr:`overhead`): the core
    #: then seals into the frame it sends and opens where the frame lies, copying no 1 MB image
    in_place: ClassVar[bool] = False
    #: with :attr:`in_place`: the bytes ``seal`` adds to a payload (the same for every payload)
    overhead: int = 0

    def seal_into(self, header: bytes, payload: bytes, body: memoryview) -> None:
        """What :meth:`seal` returns, written into ``body`` (``len(payload) + overhead``
        bytes) instead. Only called when :attr:`in_place` is set."""
        raise NotImplementedError(f"cipher {self.name!r} does not seal in place")

    def open_into(self, header: bytes | memoryview, body: memoryview) -> tuple[int, int]:
        """:meth:`open` where it lies: overwrites ``body`` (a writable view of the received
        frame) and returns ``(start, end)`` of the payload in it. Raises as :meth:`open` does
        (``body`` is then garbage, and dropped). Only called when :attr:`in_place` is set."""
        raise NotImplementedError(f"cipher {self.name!r} does not open in place")

    #: bytes of secret a session derives for this cipher; 0: it cannot be keyed from a session
    session_key_size: ClassVar[int] = 0

    @classmethod
    def from_secret(cls, secret: bytes) -> Cipher:
        """This cipher keyed from ``secret`` (``session_key_size`` bytes, for one direction of
        one topic in one key generation only; implement it when you set the size). Under one
        secret the header's epoch and sequence number (bytes 8..20) never repeat, so a cipher
        may take those 12 bytes as its nonce instead of sending one."""
        raise NotImplementedError(f"cipher {cls.name!r} cannot be keyed from a session")

    @classmethod
    def generate_key(cls) -> bytes | None:
        """A new key as its key file holds it (``rosgate keygen NAME``); None if keyless."""
        return None
