"""Codecs: a ROS message to bytes and back.

A codec plugin is a subclass of :class:`Codec` registered through the ``rosgate_codecs`` hook.
The core makes one instance per topic (or service side), so all per-type work — walking the
message definition, building converters — happens once, in ``__init__``, never per message.
"""

from __future__ import annotations

from typing import Any, ClassVar, Mapping


class Codec:
    """Base class of codec plugins."""

    #: the name users write in bringup.yaml (``codec: msgpack``)
    name: ClassVar[str]
    #: True: ``encode`` receives and ``decode`` returns serialized CDR ``bytes`` (no Python message
    #: objects at all: raw subscription in, raw publish out). False: ROS message objects.
    raw: ClassVar[bool] = False
    #: True when :meth:`encode_bare` puts the topic's name on the wire, so several topics with
    #: ``framing: none`` can share one port.
    names_bare_frames: ClassVar[bool] = False

    #: set by the core after construction: True when every frame this instance decodes was
    #: authenticated by the topic's cipher (it came from a key holder, unchanged), so the codec
    #: may trust its input. False (the default) means the bytes may come from anyone.
    authenticated: bool = False

    def __init__(self, msg_type: type, options: Mapping[str, Any]):
        """``msg_type`` is the ROS message class (``std_msgs.msg.String``, or a service's
        ``Request``/``Response``); ``options`` the plugin's table under ``plugins:``."""
        self.msg_type = msg_type
        self.options = dict(options)

    def encode(self, message: Any) -> bytes:
        raise NotImplementedError

    def decode(self, data: bytes) -> Any:
        """Raise :class:`rosgate.CodecError` for bytes that are not a valid message."""
        raise NotImplementedError

    # framing: none — the datagram is the codec's bytes alone, no envelope.
    def encode_bare(self, name: str, message: Any) -> bytes:
        """The datagram for ``framing: none``. Default: the encoded message alone."""
        return self.encode(message)

    @classmethod
    def split_bare(cls, datagram: bytes) -> tuple[str | None, bytes]:
        """Split a ``framing: none`` datagram into (topic name or None, rest for :meth:`decode_bare`).
        Raise :class:`rosgate.CodecError` when it cannot be split."""
        return None, datagram

    def decode_bare(self, rest: bytes) -> Any:
        return self.decode(rest)
