"""Codecs: a ROS message to bytes and back.

A codec plugin subclasses :class:`Codec`, implements :meth:`~Codec.encode` and
:meth:`~Codec.decode`, and is registered through the ``rosgate_codecs`` hook. The core makes one
instance per topic (or service side), so all per-type work — walking the message definition,
building converters — happens once, in ``__init__``, never per message. A text or tree format
need not walk messages itself: the library ``rosgate-message-tree`` (import
``rosgate_message_tree``) maps a message to plain Python values and back, strictly.

Threads: an instance serves one topic (or one side of a service). ``encode`` runs in ROS
executor threads, ``decode`` in link threads, and either may run in several threads at once, so
keep no per-call state on the instance.

Messages built by rclpy check their fields' types only when ``ROS_PYTHON_CHECK_FIELDS=1`` is set
(Jazzy): without it a ``float64`` field can hold a string. Run your tests with it set, and make
``encode`` raise :class:`rosgate.CodecError` for a value it cannot write.
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
    #: True when ``encode`` writes exactly one MessagePack object. With ``framing: none`` the
    #: entry's name then travels with it (the microcontroller format: ``[name, args]``, or the
    #: name then the args; see rosgate.wire.names), so several topics can share a port; other
    #: codecs' bare datagrams carry the payload alone. On such entries the core sets the
    #: ``args`` and ``floats`` fields of the codec's ``Options``, when it declares them, from the
    #: entry's keys of those names.
    messagepack: ClassVar[bool] = False

    def __init__(self, msg_type: type, options: Any):
        """``msg_type`` is the ROS message class (``std_msgs.msg.String``, or a service's
        ``Request``/``Response``); ``options`` the plugin's ``Options`` instance, parsed by the
        core from its table under ``plugins:`` (a plain mapping is parsed here the same way).
        Kept as :attr:`msg_type` and :attr:`options`."""
        self.msg_type = msg_type
        self.options = as_options(type(self), options)

    @abstractmethod
    def encode(self, message: Any) -> bytes:
        """The bytes of ``message`` (serialized CDR for a ``raw`` codec). Raise
        :class:`rosgate.CodecError` for a message it cannot write: the message is dropped and
        counted against the topic."""

    @abstractmethod
    def decode(self, data: bytes) -> Any:
        """The message ``data`` holds. Raise :class:`rosgate.CodecError` for bytes that are not a
        valid message, and nothing else: the bytes come from the network (the conformance suite
        fuzzes for exactly that). A raw codec need not check the CDR it returns: the core checks
        what no cipher authenticated."""
