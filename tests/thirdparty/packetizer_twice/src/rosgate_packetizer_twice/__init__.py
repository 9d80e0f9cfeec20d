"""A packetizer for small frames that matter (commands): each sent twice, so it survives the loss
of either copy. A frame longer than one packet is refused."""

from __future__ import annotations

import os
import struct
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

from rosgate import FramingError, Packetizer, PacketLink, hookimpl

HEADER = struct.Struct(">2sIIB")  # magic, topic id, frame id, copy (0 or 1)


class Twice(Packetizer):
    name = "twice"
    magic = (b"T2",)  # the first two bytes of its packets: unique among installed packetizers

    @dataclass(frozen=True)
    class Options:
        """None."""

    def __init__(self, link: PacketLink):
        super().__init__(link)
        self.seen: OrderedDict[Any, None] = OrderedDict()  # the latest frames: later copies go

    def cut(self, frame: bytes, sender: Any, to: Any, options: Any) -> list[Any]:
        if HEADER.size + len(frame) > self.link.max_frame:
            raise FramingError(f"twice carries frames of one packet, not of {len(frame)} bytes")
        frame_id = int.from_bytes(os.urandom(4), "big")
        return [HEADER.pack(b"T2", sender.topic_id, frame_id, copy) + frame for copy in (0, 1)]

    def feed(self, packet: Any, source: Any, now: float) -> bytes | None:
        if len(packet) < HEADER.size:
            raise FramingError("a packet shorter than its header")
        _, topic, frame_id, copy = HEADER.unpack_from(packet)
        if copy > 1:
            raise FramingError(f"copy {copy} of two")
        if (source, frame_id) in self.seen:
            return None
        self.seen[(source, frame_id)] = None
        if len(self.seen) > 4096:
            self.seen.popitem(last=False)
        if copy == 1:  # the first copy was lost (had it come late, it would now be dropped)
            self.link.recovered(topic)
        return bytes(packet[HEADER.size:])

    @classmethod
    def cost(cls, frame: int, max_frame: int, options: Any) -> tuple[int, int]:
        return 2 * (HEADER.size + frame), 2


@hookimpl
def rosgate_packetizers(register: Any) -> None:
    register(Twice)
