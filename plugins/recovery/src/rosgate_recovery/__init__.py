"""Loss recovery on datagram links, as two packetizers (:mod:`rosgate.packetizer`).

A message cut into fragments is lost when any fragment is: at 1 % packet loss a 921,600-byte
image in 1,200-byte datagrams (778 fragments) arrives whole 0.04 % of the time. A topic picks
how to ride that out with ``recovery:`` (a reliable topic that sets none gets ``retransmit``: the
core names it); the receiver finds the packetizer by the packets' magic and needs no setting.

* ``fec`` — forward error correction: every frame gets repair fragments (``overhead`` of them per
  data fragment, rounded up per block); any ``k`` of a block's ``k + m`` rebuild it. Costs
  bandwidth on every frame, lost or not; needs no way back. Option ``overhead`` (0.1), e.g.
  ``recovery: {fec: {overhead: 0.25}}``.
* ``retransmit`` — selective repeat: the receiver asks again for what is missing and
  acknowledges what came; the sender keeps each frame until acknowledged or 2 s after it left,
  and sends again at once a frame three later ones overtook. Costs a round trip per loss, and
  bandwidth only for what was lost. The 2 s count while the link's line is there: an outage
  the transport reports (a serial device unplugged) stops them, and what waits for its
  acknowledgement is sent again when the line is back.

The formats, and what each side keeps within bounds, are :mod:`rosgate_recovery.wire`'s.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass
from typing import Any

from rosgate import FRAGMENT, OptionError, Packetizer, PacketLink, hookimpl, option

from . import wire

__all__ = ["Fec", "Retransmit"]

_REPEAT, _NACK = wire.REPEAT_MAGIC[1], wire.NACK_MAGIC[1]


class Fec(Packetizer):
    """Forward error correction: Reed-Solomon repair fragments with every frame (zfec)."""

    name = "fec"
    magic = (wire.FEC_MAGIC,)

    @dataclass(frozen=True)
    class Options:
        overhead: float = option(0.1, "repair fragments per data fragment, > 0 (0.1: one per "
                                      "ten, rounded up, so a frame of one datagram goes twice)",
                                 maximum=1.0)

        def __post_init__(self) -> None:
            if self.overhead <= 0:
                raise OptionError("overhead", f"must be more than 0, not {self.overhead:g}",
                                  "overhead: 0.1 (or no recovery at all)")

    def __init__(self, link: PacketLink):
        super().__init__(link)
        self.defaults = self.Options()
        self.reassembler = wire.FecReassembler(link.lost, link.recovered,
                                               max_message=link.max_message)

    def cut(self, frame: bytes, sender: Any, to: Any, options: Any) -> list[Any]:
        overhead = (options or self.defaults).overhead
        return wire.fec_fragments(frame, self.link.max_frame, sender.topic_id, wire.frame_id(),
                                  overhead)

    def feed(self, packet: bytes | memoryview, source: Any, now: float) -> bytes | None:
        return self.reassembler.add(source, packet, now)

    def timer(self, now: float) -> float | None:
        self.reassembler.expire(now)
        return None

    @classmethod
    def cost(cls, frame: int, max_frame: int, options: Any) -> tuple[int, int]:
        overhead = (options or cls.Options()).overhead
        total = max(1, math.ceil(frame / (max_frame - wire.FEC.size)))  # data fragments
        size = max(1, math.ceil(frame / total))
        blocks = math.ceil(total / wire.block_limit(overhead))
        packets = sum(k + math.ceil(k * overhead)
                      for k in (total // blocks + (b < total % blocks) for b in range(blocks)))
        return packets * (size + wire.FEC.size), packets


class Retransmit(Packetizer):
    """Selective repeat: numbered fragments the receiver asks for again (NACK) and acknowledges
    (ACK); the sender keeps them until then, and probes when an ACK is overdue.

    Both of the link's threads reach the same state (the send thread cuts and probes, the
    receive thread takes fragments, NACKs and ACKs): it is held under one lock, and what it sends
    or queues on the link is done after that lock is released (the link takes its own)."""

    name = "retransmit"
    magic = (wire.REPEAT_MAGIC, wire.NACK_MAGIC, wire.ACK_MAGIC)
    resends_within = wire.DEADLINE

    @dataclass(frozen=True)
    class Options:
        """None: the deadline (2 s) and the bounds are the receiver's and the sender's own."""

    def __init__(self, link: PacketLink):
        super().__init__(link)
        self.store = wire.RetransmitStore()  # what this side may be asked to send again
        self.reassembler = wire.RepeatReassembler(link.lost, link.recovered, self._answer,
                                                  max_message=link.max_message)
        self._lock = threading.Lock()
        self._answers: list[tuple[bytes, Any]] = []  # NACKs and ACKs, sent outside the lock

    def _answer(self, datagram: bytes, to: Any) -> None:
        self._answers.append((datagram, to))

    def _flush(self) -> list[tuple[bytes, Any]]:
        answers, self._answers = self._answers, []
        return answers

    def cut(self, frame: bytes, sender: Any, to: Any, options: Any) -> list[Any]:
        fid = wire.frame_id()
        packets = wire.repeat_fragments(frame, self.link.max_frame, sender.topic_id, fid)
        with self._lock:
            forgotten = self.store.keep(to, fid, packets, sender, time.monotonic())
        for owner in forgotten:  # outside the lock: a route counts and warns
            owner.drop(wire.REPAIR_OVERFLOW, f"over the {self.store.max_bytes // 2**20} MiB a "
                       "sender keeps for re-sending: a frame lost on the way stays lost")
        return packets

    def sent(self, packet: bytes, to: Any, now: float) -> None:
        fid = FRAGMENT.unpack_from(packet)[4]  # magic, index, count, topic, frame
        with self._lock:
            self.store.sent(to, fid, now)

    def feed(self, packet: bytes | memoryview, source: Any, now: float) -> bytes | None:
        kind, frame, again = packet[1], None, None  # the magic's second byte: S, N or A
        answers: list[tuple[bytes, Any]] = []
        try:
            with self._lock:
                try:
                    if kind == _REPEAT:
                        frame = self.reassembler.add(source, packet, now)
                    elif kind == _NACK:
                        again = self.store.on_nack(source, packet)
                    else:
                        self.store.on_ack(source, packet, now)
                finally:
                    if self._answers:
                        answers = self._flush()
        finally:
            for datagram, to in answers:
                self.link.answer(datagram, to)
        if again is not None:
            self.link.repeat(again[0], source, again[1])
        return frame

    def moved(self, old: Any, new: Any) -> None:
        with self._lock:
            self.store.moved(old, new, time.monotonic())
            self.reassembler.moved(old, new)

    def resumed(self, down: float, now: float) -> None:
        with self._lock:
            self.store.resumed(down, now)
            self.reassembler.resumed(down, now)

    def timer(self, now: float) -> float | None:
        # called after every packet fed and every frame sent: most calls find nothing due
        with self._lock:
            soonest = self._soonest()
            if soonest is None or now < soonest:
                return soonest
            probes = self.store.probes(now)
            self.reassembler.poll(now)
            answers = self._flush()
            soonest = self._soonest()
        for datagram, to in answers:
            self.link.answer(datagram, to)
        for owner, to, packet in probes:
            self.link.repeat(owner, to, [packet])
        return soonest

    def _soonest(self) -> float | None:
        """When the timer has something to do, at the earliest (under the lock)."""
        probe, poll = self.store.next_probe(), self.reassembler.next_poll()
        return probe if poll is None else poll if probe is None else min(probe, poll)

    @classmethod
    def cost(cls, frame: int, max_frame: int, options: Any) -> tuple[int, int]:
        packets = max(1, math.ceil(frame / (max_frame - FRAGMENT.size)))
        return frame + packets * FRAGMENT.size, packets


@hookimpl
def rosgate_packetizers(register: Any) -> None:
    register(Fec)
    register(Retransmit)
