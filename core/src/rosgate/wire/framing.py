"""Putting frames on links: length prefixes on streams, fragments on datagram links.

Stream links (TCP, RFCOMM) carry ``u32 length | frame`` records. A length above the limit
means the stream is not ours or is corrupt: the reader refuses it and the connection is closed
(never a delimiter searched for in the payload).

Datagram links carry three kinds of datagram, told apart by their first two bytes:

* a frame, whole (an envelope: ``"RG"``), when it fits ``max_frame`` and leaves alone;
* a **batch** of frames that left together for one destination, as many as fit
  ``max_frame``::

      offset size field
      0      2    magic     b"RB"
      2      4    length    u32, of the first frame
      6           frame
                  length, frame, ... to the end of the datagram (the records of a stream link)

  A receiver splits it; a length that runs past the end is counted (``bad_batch``) and ends
  the batch, the frames before it delivered. A frame alone never travels as a batch, so a
  receiver that predates batches reads a quiet link's datagrams (not a busy one's);
* a **fragment** of a frame longer than ``max_frame``::

      offset size field
      0      2    magic     b"RF"
      2      2    index     0-based fragment number
      4      2    count     number of fragments of this frame
      6      4    topic_id  for counting a lost message against its topic
      10     4    frame_id  random per frame (see Reassembler)
      14          chunk

  A frame whose fragments do not all arrive within ``timeout`` is dropped and counted once.

On a bare link (``framing: none``) every datagram is one message, never batched.

Links with small frames (``max_frame`` below :data:`COMPACT_BELOW`: CAN's 8 and CAN FD's 64
bytes) cannot spend 14 bytes of every frame on that header, so they use the **compact** scheme
instead. Every frame of such a link, even one that would fit, travels as pieces::

    first piece:  1  head     0x80 | counter
                  1-5 length   the frame's length, unsigned LEB128 (7 bits a byte, low first)
                      chunk    as much of the frame as fits
    other pieces: 1  head     counter (high bit clear)
                      chunk

``counter`` (7 bits) counts every piece a link sends to one destination, across frames, so the
receiver, which keeps one reassembly per source, sees consecutive values. No topic or frame id
travels: the source (on CAN the arbitration id) says which sender's frame a piece continues,
and the topic is read from the envelope once its first 8 bytes are in. Pieces must arrive in
the order they were sent, as a CAN bus keeps them per arbitration id. The receiver:

* completes a frame when ``length`` bytes are in; bytes past them in the last piece are padding
  (a CAN FD frame has 12, 16, 20, 24, 32, 48 or 64 data bytes) and are ignored;
* on a counter gap drops the frame in progress, or the frames that vanished whole, counting one
  lost frame against the topic of the frame in progress or else of the last frame from that
  source, and ignores pieces that continue a frame whose first piece it never saw;
* ignores a piece that repeats the previous counter (a duplicated frame);
* drops a frame whose pieces stop coming for ``timeout`` seconds (counted as a gap is).

Overhead: 1 byte a piece plus the length, e.g. a 100 kB frame takes 14,287 classic CAN frames
or 1,588 CAN FD frames.
"""

from __future__ import annotations

import struct
import time
from dataclasses import dataclass, field
from typing import Callable, Hashable, Iterator

LENGTH = struct.Struct(">I")
FRAGMENT = struct.Struct(">2sHHII")
FRAGMENT_MAGIC = b"RF"
BATCH_MAGIC = b"RB"
DEFAULT_MAX_MESSAGE = 64 * 1024 * 1024
FINISHED_REMEMBERED = 4096  # frames whose late fragments are recognised and ignored
COMPACT_BELOW = 256  # links whose max_frame is below this use the compact scheme
COMPACT_START = 0x80
COMPACT_COUNTER = 0x7F
COMPACT_SOURCES = 4096  # sources remembered by a compact reassembler (oldest forgotten first)


class FramingError(ValueError):
    """The bytes cannot be framed (length over the limit, malformed fragment)."""


# -- streams ------------------------------------------------------------------------------
def length_prefixed(frame: bytes) -> bytes:
    return LENGTH.pack(len(frame)) + frame


class StreamReader:
    """Cuts a byte stream into frames. Feed it what the connection gives."""

    def __init__(self, max_frame: int = DEFAULT_MAX_MESSAGE):
        self.max_frame = max_frame
        self._buffer = bytearray()

    def feed(self, data: bytes) -> Iterator[bytes]:
        """Yield every complete frame; raise FramingError when a length is impossible."""
        buffer = self._buffer
        buffer += data
        start = 0
        try:
            while len(buffer) - start >= 4:
                (length,) = LENGTH.unpack_from(buffer, start)
                if length > self.max_frame:
                    raise FramingError(f"frame length {length} over the limit {self.max_frame}")
                end = start + 4 + length
                if end > len(buffer):
                    break
                yield bytes(buffer[start + 4:end])
                start = end
        finally:
            del buffer[:start]


# -- datagrams ----------------------------------------------------------------------------
def fragments(frame: bytes | bytearray, max_frame: int, topic_id: int,
              frame_id: int) -> list[tuple[bytes, memoryview]]:
    """The fragments of ``frame`` (longer than ``max_frame``) as (header, chunk) pairs: each
    chunk a view of ``frame``, for scatter-gather sending without joining them."""
    chunk = max_frame - FRAGMENT.size
    if chunk <= 0:
        raise FramingError(f"a datagram of {max_frame} bytes cannot carry a fragment header")
    count = -(-len(frame) // chunk)
    if count > 0xFFFF:
        raise FramingError(f"a frame of {len(frame)} bytes needs more than 65535 fragments")
    view = memoryview(frame)
    pack = FRAGMENT.pack
    return [(pack(FRAGMENT_MAGIC, i, count, topic_id, frame_id), view[i * chunk:(i + 1) * chunk])
            for i in range(count)]


def fragment(frame: bytes, max_frame: int, topic_id: int, frame_id: int) -> list[bytes]:
    """Split ``frame`` into datagrams of at most ``max_frame`` bytes (one when it fits)."""
    if len(frame) <= max_frame:
        return [frame]
    return [header + chunk for header, chunk in fragments(frame, max_frame, topic_id, frame_id)]


def batch(frames: list[bytes]) -> list[bytes | memoryview]:
    """The parts of one datagram carrying ``frames``: ``"RB"``, then ``u32 length | frame`` for
    each (the records of a stream link). Its size is :func:`batch_size`."""
    parts: list[bytes | memoryview] = [BATCH_MAGIC]
    pack = LENGTH.pack
    for frame in frames:
        parts += (pack(len(frame)), frame)
    return parts


def batch_size(sizes: int, count: int) -> int:
    """The size of a batch of ``count`` frames of ``sizes`` bytes in all."""
    return len(BATCH_MAGIC) + count * LENGTH.size + sizes


def unbatch(datagram: bytes | memoryview) -> Iterator[bytes | memoryview]:
    """The frames of a batch, as slices of ``datagram``; FramingError at a length that runs past
    its end (after yielding the frames before it)."""
    end, offset = len(datagram), len(BATCH_MAGIC)
    unpack = LENGTH.unpack_from
    while offset < end:
        if offset + LENGTH.size > end:
            raise FramingError("a batch ends inside a length")
        (length,) = unpack(datagram, offset)
        offset += LENGTH.size
        if offset + length > end:
            raise FramingError(f"a batch's frame of {length} bytes runs past its end")
        yield datagram[offset:offset + length]
        offset += length


def is_fragment(datagram: bytes | memoryview) -> bool:
    return datagram[:2] == FRAGMENT_MAGIC


@dataclass
class _Partial:
    topic_id: int
    count: int
    started: float
    parts: dict[int, bytes] = field(default_factory=dict)
    size: int = 0


class Reassembler:
    """Puts fragments back together, within bounds on time and memory.

    ``on_lost(topic_id, reason)`` is called once for every frame given up.
    """

    def __init__(self, on_lost: Callable[[int, str], None], timeout: float = 2.0,
                 max_pending_bytes: int = 4 * DEFAULT_MAX_MESSAGE,
                 max_message: int = DEFAULT_MAX_MESSAGE):
        self.on_lost = on_lost
        self.timeout = timeout
        self.max_pending_bytes = max_pending_bytes
        self.max_message = max_message
        self._pending: dict[Hashable, _Partial] = {}
        self._pending_bytes = 0
        # frames recently completed or given up: a late duplicate fragment of one of them is
        # ignored instead of starting a partial frame that would later count as lost
        self._finished: dict[Hashable, None] = {}

    def add(self, source: Hashable, datagram: bytes | memoryview) -> bytes | None:
        """Take one fragment (copied: it may be a view of a receive buffer); return the whole
        frame when this fragment completes it."""
        if len(datagram) <= FRAGMENT.size:
            raise FramingError("fragment too short")
        _, index, count, topic_id, frame_id = FRAGMENT.unpack_from(datagram)
        chunk = bytes(datagram[FRAGMENT.size:])
        if index >= count or count < 2 or count * len(chunk) > self.max_message + len(chunk):
            raise FramingError("fragment header out of range")
        now = time.monotonic()
        key = (source, topic_id, frame_id)
        partial = self._pending.get(key)
        if partial is None and key in self._finished:
            return None
        if partial is None:
            self.expire(now)
            partial = self._pending[key] = _Partial(topic_id, count, now)
        elif partial.count != count:
            raise FramingError("fragment count changed within a frame")
        if index in partial.parts:
            return None  # a duplicated datagram
        partial.parts[index] = chunk
        partial.size += len(chunk)
        self._pending_bytes += len(chunk)
        if len(partial.parts) < count:
            self._shed(now)
            return None
        del self._pending[key]
        self._pending_bytes -= partial.size
        self._finish(key)
        return b"".join(partial.parts[i] for i in range(count))

    def _finish(self, key: Hashable) -> None:
        self._finished[key] = None
        if len(self._finished) > FINISHED_REMEMBERED:
            del self._finished[next(iter(self._finished))]

    def expire(self, now: float | None = None) -> None:
        """Give up frames whose fragments stopped coming."""
        now = time.monotonic() if now is None else now
        for key in [k for k, p in self._pending.items() if now - p.started > self.timeout]:
            self._give_up(key, "fragment_lost")

    def _shed(self, now: float) -> None:
        # memory bound: drop the oldest partial frames first
        while self._pending_bytes > self.max_pending_bytes and self._pending:
            self._give_up(next(iter(self._pending)), "reassembly_overflow")

    def _give_up(self, key: Hashable, reason: str) -> None:
        partial = self._pending.pop(key)
        self._pending_bytes -= partial.size
        self._finish(key)
        self.on_lost(partial.topic_id, reason)


# -- compact pieces, for links with small frames (CAN) --------------------------------------
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
    pieces = [bytes([COMPACT_START | counter & COMPACT_COUNTER]) + length + view[:first]]
    for number, start in enumerate(range(first, len(frame), step), counter + 1):
        pieces.append(bytes([number & COMPACT_COUNTER]) + view[start:start + step])
    return pieces


def _leb128(value: int) -> bytes:
    out = bytearray()
    while value > 0x7F:
        out.append(value & 0x7F | 0x80)
        value >>= 7
    out.append(value)
    return bytes(out)


def _read_leb128(data: bytes | memoryview, start: int) -> tuple[int, int]:
    """(value, offset after it); at most 5 bytes, enough for any frame this side accepts."""
    value = 0
    for i, byte in enumerate(data[start:start + 5]):
        value |= (byte & 0x7F) << 7 * i
        if not byte & 0x80:
            return value, start + i + 1
    raise FramingError("first piece without a complete length")


@dataclass
class _Sender:
    """What a compact reassembler knows about one source."""

    next: int                       # the counter its next piece should carry
    topic_id: int | None = None     # of the frame in progress, else of its last frame
    frame: bytearray | None = None  # the frame in progress
    length: int = 0                 # its announced length
    last: float = 0.0               # when its last piece came


class CompactReassembler:
    """Puts compact pieces back together, one frame at a time per source (see the module's
    docstring). ``on_lost(topic_id, reason)`` is called once for every frame given up, with the
    topic that ``topic_of`` (given the first 8 bytes of a frame) found, or ``None``."""

    def __init__(self, on_lost: Callable[[int | None, str], None],
                 topic_of: Callable[[bytes], int | None] = lambda start: None,
                 timeout: float = 2.0, max_pending_bytes: int = 4 * DEFAULT_MAX_MESSAGE,
                 max_message: int = DEFAULT_MAX_MESSAGE):
        self.on_lost = on_lost
        self.topic_of = topic_of
        self.timeout = timeout
        self.max_pending_bytes = max_pending_bytes
        self.max_message = max_message
        self._senders: dict[Hashable, _Sender] = {}
        self._pending_bytes = 0

    def add(self, source: Hashable, piece: bytes | memoryview) -> bytes | None:
        """Take one piece (copied: it may be a view of a receive buffer); return the whole frame
        when this piece completes it."""
        if not piece:
            raise FramingError("empty piece")
        head, now = piece[0], time.monotonic()
        counter = head & COMPACT_COUNTER
        sender = self._senders.get(source)
        if sender is None:
            sender = self._senders[source] = _Sender(counter)
            if len(self._senders) > COMPACT_SOURCES:
                oldest = self._senders.pop(next(iter(self._senders)))
                if oldest.frame is not None:
                    self._give_up(oldest, "reassembly_overflow")
        elif counter == (sender.next - 1) & COMPACT_COUNTER:
            return None  # a duplicated piece
        elif counter != sender.next:
            self._give_up(sender, "fragment_lost")
        sender.next = (counter + 1) & COMPACT_COUNTER
        if head & COMPACT_START:
            if sender.frame is not None:  # the sender abandoned a frame half-sent
                self._give_up(sender, "fragment_lost")
            self.expire(now)  # a stalled source is noticed even while others keep sending
            length, offset = _read_leb128(piece, 1)
            if length > self.max_message:
                raise FramingError(f"a frame of {length} bytes is over the limit {self.max_message}")
            sender.frame, sender.length = bytearray(), length
        elif sender.frame is None:
            return None  # continues a frame whose first piece never came: already counted
        else:
            offset = 1
        frame = sender.frame
        had = len(frame)
        frame += piece[offset:offset + sender.length - had]  # past the length: padding
        self._pending_bytes += len(frame) - had
        sender.last = now
        if had < 8 <= len(frame):
            sender.topic_id = self.topic_of(bytes(frame[:8])) or sender.topic_id
        if len(frame) < sender.length:
            self._shed()
            return None
        self._pending_bytes -= len(frame)
        sender.frame = None
        return bytes(frame)

    def expire(self, now: float | None = None) -> None:
        """Give up frames whose pieces stopped coming."""
        now = time.monotonic() if now is None else now
        for sender in self._senders.values():
            if sender.frame is not None and now - sender.last > self.timeout:
                self._give_up(sender, "fragment_lost")

    def _shed(self) -> None:
        # memory bound: drop frames in progress, the longest-known source first
        for sender in list(self._senders.values()):
            if self._pending_bytes <= self.max_pending_bytes:
                return
            if sender.frame is not None:
                self._give_up(sender, "reassembly_overflow")

    def _give_up(self, sender: _Sender, reason: str) -> None:
        """Count one lost frame: the one in progress, or one that vanished whole."""
        if sender.frame is not None:
            self._pending_bytes -= len(sender.frame)
            sender.frame = None
        self.on_lost(sender.topic_id, reason)
