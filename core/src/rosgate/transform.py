"""Payload transforms (compression): a topic's payload, bytes to bytes, between the codec and
the cipher. A plugin subclasses :class:`Transform` and registers it through the
``rosgate_transforms`` hook (docs/plugins.md, "A compressor and a packetizer").

A transformed payload starts with the transform's ``wire_id``, under the envelope's
``FLAG_COMPRESSED`` (authenticated by every cipher): the receiver needs no setting. ``encode``
runs in executor threads, ``decode`` in link threads, several at once: lock what an instance
keeps between calls (a compression context).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any, ClassVar

from .errors import RosgateError
from .options import as_options


class TransformError(RosgateError):
    """Bytes a transform cannot decode (within its bound). The frame is dropped and counted
    ``decompression_error`` against its topic."""


class Transform(ABC):
    """Base class of payload transform plugins."""

    #: the name users write in bringup.yaml (``compression: zstd``)
    name: ClassVar[str]
    #: 1..255, the byte in front of every payload it transformed; unique among installed
    #: transforms (a second one with the same id is reported and skipped)
    wire_id: ClassVar[int]

    def __init__(self, options: Any, limit: int):
        """Kept as :attr:`options`, the plugin's ``Options`` (a plain mapping is parsed here),
        and :attr:`limit`, the most bytes :meth:`decode` may return."""
        self.options = as_options(type(self), options)
        self.limit = limit

    @abstractmethod
    def encode(self, payload: bytes) -> bytes | None:
        """``payload`` transformed; ``None`` to send it as it is (it would not get smaller)."""

    @abstractmethod
    def decode(self, data: bytes) -> bytes:
        """What :meth:`encode` made ``data`` from. ``data`` comes from the network: raise
        :class:`TransformError` for anything else, and for a result over :attr:`limit` bytes —
        before allocating it."""
