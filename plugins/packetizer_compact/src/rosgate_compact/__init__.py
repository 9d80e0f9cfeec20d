"""The ``compact`` packetizer: frames on datagram links whose packets are too small to spare a
fragment header (``max_frame`` below 256 bytes: CAN's 8 and CAN FD's 64).

A datagram link takes this packetizer as its own when its transport's ``max_frame`` is below
:data:`rosgate.packetizer.SMALL_FRAME` (a link of larger packets takes ``fragments``). It cuts
**every** frame, even one that would fit a packet, into pieces::

    first piece:  1    head     0x80 | counter
                  1-5  length   the frame's length, unsigned LEB128 (7 bits a byte, low first)
                       chunk    as much of the frame as fits
    other pieces: 1    head     counter (high bit clear)
                       chunk

Every piece but a frame's last fills ``max_frame``. ``counter`` (7 bits) counts every piece a
link sends to one destination, across frames, so the receiver, which keeps one reassembly per
source, sees consecutive values. No magic, topic or frame id travels: such a link carries
nothing but pieces, the source (on CAN the arbitration id) says which sender's frame a piece
continues, and the topic is read from the envelope once its first 8 bytes are in. Pieces must
arrive in the order they were sent, as a CAN bus keeps them per arbitration id, and the pieces
of two frames to one destination never interleave (the link sends one frame's pieces back to
back). The receiver:

* completes a frame when ``length`` bytes are in; bytes past them in the last piece are padding
  (a CAN FD frame has 12, 16, 20, 24, 32, 48 or 64 data bytes) and are ignored;
* on a counter gap drops the frame in progress, or the frames that vanished whole, counting one
  lost frame (``fragment_lost``) against the topic of the frame in progress or else of the last
  frame from that source, and ignores pieces that continue a frame whose first piece it never
  saw; a gap among them, before the next first piece, is the same frame's and is not counted
  again (so the count is exact while no loss spans the end of one frame and the start of the
  next);
* ignores a piece that repeats the previous counter (a duplicated frame);
* drops a frame whose pieces stop coming for ``timeout`` seconds (counted as a gap is);
* holds at most ``max_pending_bytes`` of frames in progress (the longest silent is dropped,
  ``reassembly_overflow``) and remembers at most :data:`SOURCES` sources.

Overhead: 1 byte a piece plus the length, e.g. a 100 kB frame takes 14,287 classic CAN frames
or 1,588 CAN FD frames. Topics on such a link take no ``recovery:``: its pieces carry no
fragment numbers to repair or ask for.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Hashable
from dataclasses import dataclass
from typing import Any

from rosgate import (
    DEFAULT_MAX_MESSAGE,
    PARTIAL_COST,
    Address,
    Drop,
    FramingError,
    Packet,
    Packetizer,
    PacketLink,
    Reason,
    hookimpl,
    topic_of,
)

__all__ = ["Compact", "CompactReassembler", "compact_fragment"]

START = 0x80  # in a head: the frame's first piece
COUNTER = 0x7F
SOURCES = 4096  # sources remembered by a reassembler (oldest forgotten first)


def compact_fragment(frame: bytes, max_frame: int, counter: int) -> list[bytes]:
    """Cut ``frame`` into compact pieces of at most ``max_frame`` bytes, the first numbered
    ``counter``; the caller's counter for this destination moves on by the number of pieces."""
    length = _leb128(len(frame))
    first = max_frame - 1 - len(length)
    if first < 0 or max_frame < 2:
        raise FramingError(f"a datagram of {max_frame} bytes cannot carry a compact header "
                           f"for a frame of {len(frame)} bytes")
    view = memoryview(frame)
    step = max_frame - 1
    pieces = [bytes([START | counter & COUNTER]) + length + view[:first]]
    for number, start in enumerate(range(first, len(frame), step), counter + 1):
        pieces.append(bytes([number & COUNTER]) + view[start:start + step])
    return pieces


def _leb128(value: int) -> bytes:
    out = bytearray()
    while value > 0x7F:
        out.append(value & 0x7F | 0x80)
        value >>= 7
    out.append(value)
    return bytes(out)


def read_leb128(data: bytes | memoryview, start: int) -> tuple[int, int]:
    """(value, offset after it); at most 5 bytes, enough for any frame this side accepts."""
    value = 0
    for i, byte in enumerate(data[start:start + 5]):
        value |= (byte & 0x7F) << 7 * i
        if not byte & 0x80:
            return value, start + i + 1
    raise FramingError("first piece without a complete length")


@dataclass
class _Sender:
    """What a reassembler knows about one source."""

    next: int                       # the counter its next piece should carry
    topic_id: int | None = None     # of the frame in progress, else of its last frame
    frame: bytearray | None = None  # the frame in progress
    length: int = 0                 # its announced length
    last: float = 0.0               # when its last piece came
    skipping: bool = False          # the rest of a frame given up comes: its gaps are its own


class CompactReassembler:
    """Puts pieces back together, one frame at a time per source. ``on_lost(topic_id, reason)``
    is called once for every frame given up, with the topic that ``topic_of`` (given the first
    8 bytes of a frame) found, or ``None``.

    Sources with a frame in progress are kept in the order they last sent a piece, so expiring
    stalled frames looks only at the stalled ones and the first that is not; a frame in progress
    is accounted as its bytes plus :data:`rosgate.builtin.PARTIAL_COST`."""

    def __init__(self, on_lost: Callable[[int | None, Reason], None],
                 topic_of: Callable[[bytes], int | None] = lambda start: None,
                 timeout: float = 2.0, max_pending_bytes: int = 4 * DEFAULT_MAX_MESSAGE,
                 max_message: int = DEFAULT_MAX_MESSAGE):
        self.on_lost = on_lost
        self.topic_of = topic_of
        self.timeout = timeout
        self.max_pending_bytes = max_pending_bytes
        self.max_message = max_message
        self._senders: dict[Hashable, _Sender] = {}
        self._active: dict[Hashable, _Sender] = {}  # frames in progress, least recent first
        self.pending_bytes = 0

    def add(self, source: Hashable, piece: bytes | memoryview) -> bytes | None:
        """Take one piece (copied: it may be a view of a receive buffer); return the whole frame
        when this piece completes it."""
        if not piece:
            raise FramingError("empty piece")
        head, now = piece[0], time.monotonic()
        counter = head & COUNTER
        sender = self._senders.get(source)
        if sender is None:
            sender = self._senders[source] = _Sender(counter)
            if len(self._senders) > SOURCES:
                oldest_source = next(iter(self._senders))
                oldest = self._senders.pop(oldest_source)
                if oldest.frame is not None:
                    self._give_up(oldest_source, oldest, Drop.REASSEMBLY_OVERFLOW)
        elif counter == (sender.next - 1) & COUNTER:
            return None  # a duplicated piece
        elif counter != sender.next and not sender.skipping:
            self._give_up(source, sender, Drop.FRAGMENT_LOST)
        sender.next = (counter + 1) & COUNTER
        if head & START:
            if sender.frame is not None:  # the sender abandoned a frame half-sent
                self._give_up(source, sender, Drop.FRAGMENT_LOST)
            sender.skipping = False
            if self._active:
                self.expire(now)  # a stalled source is noticed even while others keep sending
            length, offset = read_leb128(piece, 1)
            if length > self.max_message:
                raise FramingError(f"a frame of {length} bytes is over the limit "
                                   f"{self.max_message}")
            sender.frame, sender.length = bytearray(), length
            self.pending_bytes += PARTIAL_COST
        elif sender.frame is None:
            return None  # continues a frame whose first piece never came: already counted
        else:
            offset = 1
        frame = sender.frame
        had = len(frame)
        frame += piece[offset:offset + sender.length - had]  # past the length: padding
        self.pending_bytes += len(frame) - had
        sender.last = now
        if had < 8 <= len(frame):
            sender.topic_id = self.topic_of(bytes(frame[:8])) or sender.topic_id
        active = self._active
        active.pop(source, None)
        if len(frame) < sender.length:
            active[source] = sender  # now the most recent
            self._shed()
            return None
        self.pending_bytes -= len(frame) + PARTIAL_COST
        sender.frame = None
        return bytes(frame)

    def expire(self, now: float | None = None) -> None:
        """Give up frames whose pieces stopped coming, the longest silent first; stop at the
        first source that is still sending."""
        now = time.monotonic() if now is None else now
        active, deadline = self._active, now - self.timeout
        while active:
            source, sender = next(iter(active.items()))
            if sender.last >= deadline:
                return
            self._give_up(source, sender, Drop.FRAGMENT_LOST)

    def _shed(self) -> None:
        # memory bound: drop frames in progress, the longest silent first
        active = self._active
        while self.pending_bytes > self.max_pending_bytes and active:
            source, sender = next(iter(active.items()))
            self._give_up(source, sender, Drop.REASSEMBLY_OVERFLOW)

    def _give_up(self, source: Hashable, sender: _Sender, reason: Reason) -> None:
        """Count one lost frame: the one in progress, or one that vanished whole."""
        if sender.frame is not None:
            self.pending_bytes -= len(sender.frame) + PARTIAL_COST
            sender.frame = None
            self._active.pop(source, None)
        sender.skipping = True
        self.on_lost(sender.topic_id, reason)


class Compact(Packetizer):
    """Every frame as compact pieces (:func:`compact_fragment`), one frame at a time per
    destination (the format: this module's docstring)."""

    name = "compact"
    magic = ()
    cuts_every_frame = True

    @dataclass(frozen=True)
    class Options:
        """None: the link's ``max_frame`` says it all."""

    def __init__(self, link: PacketLink):
        super().__init__(link)
        self.reassembler = CompactReassembler(link.lost, topic_of,
                                              max_message=link.max_message)
        self._counters: dict[Address, int] = {}  # the next piece's counter per destination

    def cut(self, frame: bytes, sender: Any, to: Address, options: Any) -> list[Packet]:
        counter = self._counters.get(to, 0)
        pieces = compact_fragment(frame, self.link.max_frame, counter)
        self._counters[to] = (counter + len(pieces)) & COUNTER
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
        pieces = compact_fragment(bytes(frame), max_frame, 0)  # rosgate check only
        return sum(map(len, pieces)), len(pieces)


@hookimpl
def rosgate_packetizers(register: Any) -> None:
    register(Compact)
