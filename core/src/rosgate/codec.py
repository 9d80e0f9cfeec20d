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
    #: True when ``encode`` writes exactly one MessagePack object. With ``framing: none`` the
    #: entry's name then travels in front of it as a MessagePack str (the CVRA microcontroller
    #: format), so several topics can share a port; other codecs' bare datagrams carry the
    #: payload alone.
    messagepack: ClassVar[bool] = False

    def __init__(self, msg_type: type, options: Mapping[str, Any]):
        """``msg_type`` is the ROS message class (``std_msgs.msg.String``, or a service's
        ``Request``/``Response``); ``options`` the plugin's table under ``plugins:``."""
        self.msg_type = msg_type
        self.options = dict(options)

    def encode(self, message: Any) -> bytes:
        raise NotImplementedError

    def decode(self, data: bytes) -> Any:
        """Raise :class:`rosgate.CodecError` for bytes that are not a valid message. A raw codec
        need not check the CDR it returns: the core checks what no cipher authenticated."""
        raise NotImplementedError
