"""Ciphers: seal a frame so that only a holder of the key can read it and nobody can alter it.

A cipher plugin is a subclass of :class:`Cipher` registered through the ``rosgate_ciphers``
hook. The core makes one instance per bridge (keys are read once). ``seal`` must authenticate the
plaintext envelope ``header`` together with the payload: the receiver passes the header it read
back to ``open``, which must raise :class:`rosgate.CipherError` if either was changed, or if the
frame was sealed under another key.
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

    @classmethod
    def generate_key(cls) -> bytes | None:
        """A new key in the form the key file holds, for ``rosgate keygen NAME``; None if keyless."""
        return None
