"""Codecs: a ROS message to bytes and back. A plugin subclasses :class:`Codec` and registers it
through the ``rosgate_codecs`` hook (docs/plugins.md, "Codec"; a tree format can use the
library ``rosgate_message_tree``).

One instance per topic (or service side): per-type work goes in ``__init__``, never per message.
``encode`` runs in executor threads, ``decode`` in link threads, several at once: keep no
per-call state. Test with ``ROS_PYTHON_CHECK_FIELDS=1``: without it a ``float64`` field can hold
a string, for which ``encode`` must raise :class:`rosgate.CodecError`.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any, ClassVar

from .options import as_options


class Codec(ABC):
    """Base class of codec plugins."""

    #: the name users write in bringup.yaml (``codec: msgpack``)
    name: ClassVar[str]
    #: True: ``encode`` receives and ``decode`` returns serialized CDR ``bytes`` (no Python message
    #: objects at all: raw subscription in, raw publish out). False: ROS message objects.
    raw: ClassVar[bool] = False
    #: True when ``encode`` writes exactly one MessagePack object: with ``framing: none`` the
    #: entry's name then travels with it (rosgate.wire.names), so topics can share a port, and
    #: the core sets the ``Options`` fields ``args`` and ``floats``, if declared, from the entry.
    messagepack: ClassVar[bool] = False

    def __init__(self, msg_type: type, options: Any):
        """Kept as :attr:`msg_type`, the ROS message class (or a service's ``Request`` or
        ``Response``), and :attr:`options`, the plugin's ``Options`` (a mapping is parsed)."""
        self.msg_type = msg_type
        self.options = as_options(type(self), options)

    @abstractmethod
    def encode(self, message: Any) -> bytes:
        """The bytes of ``message`` (serialized CDR for a ``raw`` codec). Raise
        :class:`rosgate.CodecError` for a message it cannot write: the message is dropped and
        counted against the topic."""

    @abstractmethod
    def decode(self, data: bytes) -> Any:
        """The message ``data`` holds. Raise :class:`rosgate.CodecError`, and nothing else, for
        bytes that are not one: they come from the network (the conformance suite fuzzes it). A
        raw codec need not check its CDR: the core checks what no cipher authenticated."""
