"""The built-in plugins, registered through the same hooks as any other: the ``cdr`` codec, the
``none`` cipher and the ``fragments`` packetizer."""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import Any

from .cipher import Cipher
from .codec import Codec
from .errors import CodecError
from .hookspecs import hookimpl
from .packetizer import Packet, Packetizer, PacketLink
from .reassembly import CompactReassembler, Reassembler
from .transport import Address
from .wire import envelope, framing


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


class Fragments(Packetizer):
    """A frame longer than the link's ``max_frame`` as numbered fragments (``RF``, see
    :mod:`rosgate.wire.framing`), reassembled in one buffer per frame; a lost fragment loses the
    frame (counted ``fragment_lost``). What every topic without ``recovery:`` gets."""

    name = "fragments"
    magic = (framing.FRAGMENT_MAGIC,)

    @dataclass(frozen=True)
    class Options:
        """None: the link's ``max_frame`` says it all."""

    def __init__(self, link: PacketLink):
        super().__init__(link)
        self.reassembler = Reassembler(link.lost, max_message=link.max_message)

    def cut(self, frame: bytes, sender: Any, to: Address, options: Any) -> list[Packet]:
        # frame ids unpredictable: a spoofed source cannot poison a reassembly (see Reassembler)
        frame_id = int.from_bytes(os.urandom(4), "big")
        return list(framing.fragments(frame, self.link.max_frame, sender.topic_id, frame_id))

    def feed(self, packet: bytes | memoryview, source: Address, now: float) -> bytes | None:
        # the buffer it was reassembled in, the handler's to keep: a route hands it to rclpy
        # without a copy (handlers take any bytes-like frame)
        return self.reassembler.add(source, packet)  # type: ignore[return-value]

    def timer(self, now: float) -> float | None:
        if self.reassembler.pending:
            self.reassembler.expire(now)
        return None

    @classmethod
    def cost(cls, frame: int, max_frame: int, options: Any) -> tuple[int, int]:
        packets = max(1, math.ceil(frame / (max_frame - framing.FRAGMENT.size)))
        return frame + packets * framing.FRAGMENT.size, packets


class Compact(Packetizer):
    """Every frame as compact pieces (``framing.compact_fragment``), one frame at a time per
    destination: a datagram link's own scheme when its transport's frames cannot spare a
    fragment header (``max_frame`` below ``framing.COMPACT_BELOW``: CAN). Pieces carry no magic:
    on such a link every datagram is a piece, and the link feeds them all here."""

    name = "compact"
    magic = ()

    @dataclass(frozen=True)
    class Options:
        """None: the link's ``max_frame`` says it all."""

    def __init__(self, link: PacketLink):
        super().__init__(link)
        self.reassembler = CompactReassembler(link.lost, envelope.topic_of,
                                              max_message=link.max_message)
        self._counters: dict[Address, int] = {}  # the next piece's counter per destination

    def cut(self, frame: bytes, sender: Any, to: Address, options: Any) -> list[Packet]:
        counter = self._counters.get(to, 0)
        pieces = framing.compact_fragment(frame, self.link.max_frame, counter)
        self._counters[to] = (counter + len(pieces)) & framing.COMPACT_COUNTER
        # one packet, which the link sends piece by piece: pieces carry no frame id, so the
        # pieces of two frames must never interleave
        return [b"".join(pieces)]

    def feed(self, packet: bytes | memoryview, source: Address, now: float) -> bytes | None:
        return self.reassembler.add(source, packet)

    def timer(self, now: float) -> float | None:
        self.reassembler.expire(now)
        return None

    @classmethod
    def cost(cls, frame: int, max_frame: int, options: Any) -> tuple[int, int]:
        pieces = framing.compact_fragment(bytes(frame), max_frame, 0)  # rosgate check only
        return sum(map(len, pieces)), len(pieces)


@hookimpl
def rosgate_codecs(register: Any) -> None:
    register(CdrCodec)


@hookimpl
def rosgate_ciphers(register: Any) -> None:
    register(NoCipher)


@hookimpl
def rosgate_packetizers(register: Any) -> None:
    register(Fragments)
