"""Payload transforms: a topic's payload, bytes to bytes, between the codec and the cipher.
Compression is one (``compression: zstd``, from the ``rosgate-compress-zstd`` distribution).

A transform plugin subclasses :class:`Transform`, sets :attr:`~Transform.name` and
:attr:`~Transform.wire_id`, implements :meth:`~Transform.encode` and :meth:`~Transform.decode`,
and is registered through the ``rosgate_transforms`` hook. A transmitting topic picks it by name;
its options come from ``plugins: {NAME: {...}}``, and a topic may give its own on top
(``compression: {zstd: {level: 19}}``).

On the wire a transformed payload has the envelope's ``FLAG_COMPRESSED`` set and starts with the
transform's one-byte ``wire_id``: the receiver picks the transform by that byte, so its file
needs no setting. The flag is in the header, which every cipher authenticates, so a receiver
decodes exactly what the sender transformed. A payload :meth:`~Transform.encode` leaves alone
(``None``: it would not shrink) goes as it was, flag clear.

Threads: ``encode`` runs in ROS executor threads, ``decode`` in link threads, each possibly in
several at once: lock what an instance keeps between calls (a compression context).
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
        """``options``: the plugin's ``Options`` instance (a plain mapping is parsed here the same
        way); ``limit``: the most bytes :meth:`decode` may return. Kept as :attr:`options` and
        :attr:`limit`."""
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
