"""The built-in plugins, registered through the same hooks as any other: the ``cdr`` codec,
the ``none`` cipher and the ``diagnostics`` monitor."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from .cipher import Cipher
from .codec import Codec
from .diagnostics import Diagnostics
from .errors import CodecError
from .hookspecs import hookimpl


class CdrCodec(Codec):
    """The ROS wire format itself, passed through untouched.

    The subscription is raw (rclpy hands over the serialized CDR bytes) and the publisher
    publishes those bytes: no Python-level (de)serialization at all. Frames no cipher
    authenticated are checked by the core before they are published
    (:func:`rosgate.ros.cdr_checker`); authenticated ones pass straight through.
    """

    name = "cdr"
    raw = True

    @dataclass(frozen=True)
    class Options:
        """None: the bytes are ROS's own."""

    def encode(self, message: bytes) -> bytes:
        return message

    def decode(self, data: bytes) -> bytes:
        # 4-byte encapsulation header: 0x00 0x00/0x01 (CDR big/little endian) + 2 option bytes
        if len(data) < 4 or data[0] != 0 or data[1] not in (0, 1):
            raise CodecError("not a CDR-encapsulated message")
        return data


class NoCipher(Cipher):
    """No encryption, no authentication: the payload travels as it is."""

    name = "none"
    authenticates = False

    @dataclass(frozen=True)
    class Options:
        """None: there is no key."""

    def seal(self, header: bytes, payload: bytes) -> bytes:
        return payload

    def open(self, header: bytes, body: bytes) -> bytes:
        return body


@hookimpl
def rosgate_codecs(register: Any) -> None:
    register(CdrCodec)


@hookimpl
def rosgate_ciphers(register: Any) -> None:
    register(NoCipher)


@hookimpl
def rosgate_monitors(register: Any) -> None:
    register(Diagnostics)
