"""Putting frames on links: length prefixes on streams, fragments on datagram links.

Stream links (TCP, RFCOMM) carry ``u32 length | frame`` records. A length above the limit
means the stream is not ours or is corrupt: the reader refuses it and the connection is closed
(never a delimiter searched for in the payload).

A frame longer than :data:`CHUNK` goes as **chunks** instead, so that another topic's frame
can go between them and waits at most one chunk (the link's scheduler interleaves the chunks of
different topics' frames; one topic's frames go one after the other)::

    u32 CHUNKED | LAST? | n    the top bit says "a chunk"; the next one "the frame's last"
    u32 message              which frame it continues: a number the sender gives each frame
    n - 4 bytes              the next part of that frame

A reader gathers each message's chunks and hands over the frame with its last chunk; it holds
at most :data:`MAX_OPEN_MESSAGES` unfinished frames and, all together, at most twice the largest
frame it takes. A length of a whole frame is below 2^31, so the two kinds never mix up; a reader
that predates chunks refuses a chunk as a length over its limit, and reconnects.

Datagram links carry three kinds of datagram, told apart by their first two bytes (and the
kinds of loss recovery, :mod:`rosgate.wire.recovery`: ``RE``, ``RS``, ``RN``, ``RA``):

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
from collections.abc import Callable, Hashable, Iterator
from dataclasses import dataclass, field
from typing import cast

LENGTH = struct.Struct(">I")
CHUNK_HEAD = struct.Struct(">II")
CHUNK = 16 * 1024        # frames longer than this travel in chunks of this many bytes
CHUNKED = 0x80000000     # in a record's length: a chunk
LAST = 0x40000000        # ... the last of its frame
CHUNK_LENGTH = 0x3FFFFFFF
MAX_OPEN_MESSAGES = 256  # unfinished chunked frames a stream reader holds
FRAGMENT = struct.Struct(">2sHHII")
FRAGMENT_MAGIC = b"RF"
BATCH_MAGIC = b"RB"
DEFAULT_MAX_MESSAGE = 64 * 1024 * 1024
FINISHED_REMEMBERED = 4096  # frames whose late fragments are recognised and ignored
COMPACT_BELOW = 256  # links whose max_frame is below this use the compact scheme
COMPACT_START = 0x80
COMPACT_COUNTER = 0x7F
COMPACT_SOURCES = 4096  # sources remembered by a compact reassembler (oldest forgotten first)
DIRECT_ABOVE = 64 * 1024  # stream frames longer than this are read into place


class FramingError(ValueError):
    """The bytes cannot be framed (length over the limit, malformed fragment)."""


# -- streams ------------------------------------------------------------------------------
def length_prefixed(frame: bytes) -> bytes:
    return LENGTH.pack(len(frame)) + frame


def stream_records(frame: bytes, message: int, chunk: int = CHUNK) -> list[bytes]:
    """``frame`` as the records of a stream: one, or chunks of ``message`` when it is longer
    than ``chunk``."""
    if len(frame) <= chunk:
        return [length_prefixed(frame)]
    view = memoryview(frame)
    starts = range(0, len(frame), chunk)
    last = starts[-1]
    return [CHUNK_HEAD.pack(CHUNKED | (LAST if start == last else 0)
                            | (min(chunk, len(frame) - start) + 4), message & 0xFFFFFFFF)
            + view[start:start + chunk] for start in starts]


class StreamReader:
    """Cuts a byte stream into frames, chunked ones put back together. Feed it what the
    connection gives (:meth:`feed`); or, to save a copy of large frames, ask it where the
    next bytes should go (:meth:`target`), read them there and say how many (:meth:`filled`).

    With ``direct``, a frame longer than :data:`DIRECT_ABOVE` whose length is known is read
    straight into a buffer of its own, once 1/:data:`EARN_BUFFER` of it has come (so a length
    prefix alone does not make the reader zero 64 MiB), and handed on as that bytearray: the
    caller must then read into :meth:`target` while it is not None."""

    def __init__(self, max_frame: int = DEFAULT_MAX_MESSAGE, direct: bool = False):
        self.max_frame = max_frame
        self.direct = direct
        self._buffer = bytearray()
        self._open: dict[int, bytearray] = {}  # message -> what came of it
        self._open_bytes = 0
        self._frame: bytearray | None = None  # a large frame being read into place
        self._filled = 0

    def target(self) -> memoryview | None:
        """Where the next bytes go when a large frame is being read in place, else None."""
        if self._frame is None:
            return None
        return memoryview(self._frame)[self._filled:]

    def filled(self, count: int) -> bytearray | None:
        """``count`` bytes were read into :meth:`target`; the frame once it is whole."""
        self._filled += count
        frame = self._frame
        if frame is None or self._filled < len(frame):
            return None
        self._frame = None
        return frame

    def feed(self, data: bytes | memoryview) -> Iterator[bytes]:
        """Yield every complete frame; raise FramingError when a length is impossible."""
        buffer = self._buffer
        buffer += data
        start = 0
        try:
            while len(buffer) - start >= 4:
                (length,) = LENGTH.unpack_from(buffer, start)
                chunked = length & CHUNKED
                size = length & CHUNK_LENGTH if chunked else length
                if size > self.max_frame or chunked and size < 4:
                    raise FramingError(f"frame length {size} over the limit {self.max_frame}"
                                       if size > self.max_frame else "a chunk without its head")
                end = start + 4 + size
                if end > len(buffer):
                    have = len(buffer) - start - 4
                    if (self.direct and not chunked and size > DIRECT_ABOVE
                            and have * EARN_BUFFER >= size):
                        # the rest is read straight into the frame's own buffer
                        self._frame = frame = bytearray(size)
                        frame[:have] = memoryview(buffer)[start + 4:]
                        self._filled = have
                        start = len(buffer)
                    break
                if not chunked:
                    yield bytes(buffer[start + 4:end])
                else:
                    whole = self._chunk(buffer, start + 4, end, bool(length & LAST))
                    if whole is not None:
                        yield cast(bytes, whole)  # bytes-like: handlers take either
                start = end
        finally:
            del buffer[:start]

    def _chunk(self, buffer: bytearray, start: int, end: int, last: bool) -> bytearray | None:
        (message,) = LENGTH.unpack_from(buffer, start)
        part = self._open.get(message)
        if part is None:
            if len(self._open) >= MAX_OPEN_MESSAGES:
                raise FramingError(f"more than {MAX_OPEN_MESSAGES} chunked frames open at once")
            part = self._open[message] = bytearray()
        part += buffer[start + 4:end]
        self._open_bytes += end - start - 4
        if len(part) > self.max_frame or self._open_bytes > 2 * self.max_frame:
            raise FramingError(f"chunked frames over the limit {self.max_frame}")
        if not last:
            return None
        del self._open[message]
        self._open_bytes -= len(part)
        return part  # its own buffer, the handler's to keep (and cut: routes do)


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


@dataclass(slots=True)
class _Partial:
    """A frame whose fragments are coming in."""

    key: tuple
    source: Hashable
    topic_id: int
    count: int
    started: float
    have: bytearray          # one byte per fragment, set once it came
    received: int = 0        # fragments in
    size: int = 0            # their bytes
    chunk: int = 0           # the length of every fragment but the last, once one came
    last: int = -1           # the length of the last fragment, once it came
    buffer: bytearray | None = None       # the frame, once earned (see Reassembler)
    aside: dict[int, bytes] | None = None  # fragments that came before the buffer
    cost: int = 0            # bytes this partial is accounted for


@dataclass(slots=True)
class _Source:
    """What one source has pending."""

    partials: dict[tuple, None] = field(default_factory=dict)  # keys, oldest first
    cost: int = 0


#: what a partial frame costs beyond its bytes (its objects, its entries in the tables):
#: measured with tracemalloc (core/tests/test_framing.py checks the accounting covers it)
PARTIAL_COST = 1024
#: what a fragment kept aside costs beyond its bytes (a bytes object, a dict entry)
ASIDE_COST = 128
#: a partial frame gets its buffer (all of it, zeroed) once this share of it has come: a
#: fragment that claims 64 MiB does not make the receiver zero 64 MiB for it
EARN_BUFFER = 16


class Reassembler:
    """Puts fragments back together into one preallocated buffer per frame, within bounds.

    Bounds, all counted when they bite (``on_lost(topic_id, reason)``, once per frame given up):

    * time: a frame whose fragments stop coming is given up ``timeout`` seconds after its last
      one (``fragment_lost``). Partial frames are kept in the order they were last heard of, so
      expiring them looks at the expired ones and the first that is not, never at all of them;
    * per source: at most ``source_partials`` partial frames and ``source_bytes`` bytes; the
      source's oldest partial frame goes first (``reassembly_overflow``);
    * per link (this reassembler): at most ``max_partials`` and ``max_pending_bytes``; the
      oldest partial frame of any source goes first (``reassembly_overflow``).

    Bytes are what a partial frame really costs: its buffer or the fragments kept aside, plus
    :data:`PARTIAL_COST` for its bookkeeping, so a flood of one-byte fragments is bounded as
    tightly as a few large frames. A partial frame gets its buffer (``count`` times the length
    of its fragments, zeroed) once 1/:data:`EARN_BUFFER` of it has come; fragments before that
    wait aside and are copied in then. The completed frame is that buffer, a ``bytearray``,
    handed on without another copy.

    Fragments are found by (source, topic id, frame id). Senders draw frame ids at random, so a
    spoofed source cannot guess the id of a frame in progress and slip a fragment into it.
    """

    def __init__(self, on_lost: Callable[[int, str], None], timeout: float = 2.0,
                 max_pending_bytes: int = 4 * DEFAULT_MAX_MESSAGE,
                 max_message: int = DEFAULT_MAX_MESSAGE, max_partials: int = 1024,
                 source_partials: int = 128, source_bytes: int | None = None):
        self.on_lost = on_lost
        self.timeout = timeout
        self.max_pending_bytes = max_pending_bytes
        self.max_message = max_message
        self.max_partials = max_partials
        self.source_partials = source_partials
        self.source_bytes = 2 * max_message if source_bytes is None else source_bytes
        self._pending: dict[tuple, _Partial] = {}  # oldest first
        self._sources: dict[Hashable, _Source] = {}
        self._pending_bytes = 0
        # frames recently completed or given up: a late duplicate fragment of one of them is
        # ignored instead of starting a partial frame that would later count as lost
        self._finished: dict[tuple, None] = {}

    @property
    def pending(self) -> int:
        """Partial frames held now."""
        return len(self._pending)

    @property
    def pending_bytes(self) -> int:
        """What they are accounted for."""
        return self._pending_bytes

    def add(self, source: Hashable, datagram: bytes | memoryview) -> bytearray | None:
        """Take one fragment (copied: it may be a view of a receive buffer); return the whole
        frame when this fragment completes it."""
        size = len(datagram) - FRAGMENT.size
        if size <= 0:
            raise FramingError("fragment too short")
        _, index, count, topic_id, frame_id = FRAGMENT.unpack_from(datagram)
        if index >= count or count < 2:
            raise FramingError("fragment header out of range")
        now = time.monotonic()
        if self._pending:
            self.expire(now)
        key = (source, topic_id, frame_id)
        partial = self._pending.get(key)
        if partial is None:
            if key in self._finished:
                return None
            self._check_sizes(count, index, size, 0, -1)
            partial = self._start(key, source, topic_id, count, now)
            before, partial.cost = 0, PARTIAL_COST + count
        elif partial.count != count:
            raise FramingError("fragment count changed within a frame")
        else:
            if partial.have[index]:
                return None  # a duplicated datagram
            self._check_sizes(count, index, size, partial.chunk, partial.last)
            before = partial.cost
            # still coming: its time runs from now (a frame on a slow link takes long), and
            # the pending stay in the order they were last heard of
            partial.started = now
            del self._pending[key]
            self._pending[key] = partial
        if index < count - 1:
            partial.chunk = size
        else:
            partial.last = size
        partial.have[index] = 1
        partial.received += 1
        partial.size += size
        if partial.buffer is None and partial.chunk and \
                partial.size * EARN_BUFFER >= count * partial.chunk:
            self._earn_buffer(partial)
        if partial.buffer is not None:
            offset = index * partial.chunk
            partial.buffer[offset:offset + size] = datagram[FRAGMENT.size:]
        else:
            assert partial.aside is not None
            partial.aside[index] = bytes(datagram[FRAGMENT.size:])
            partial.cost += size + ASIDE_COST
        if partial.received == count:
            partial.cost = before  # what the totals hold for it
            return self._complete(partial)
        self._charge(partial, partial.cost - before)
        return None

    def _check_sizes(self, count: int, index: int, size: int, chunk: int, last: int) -> None:
        """Every fragment but the last is as long as the others; the last no longer; the frame
        they make no longer than ``max_message``."""
        if index < count - 1:
            if chunk and size != chunk:
                raise FramingError("fragment size changed within a frame")
            if last > size or (count - 1) * size + max(last, 1) > self.max_message:
                raise FramingError("fragment header out of range")
        elif (chunk and size > chunk) or (count - 1) * max(chunk, 1) + size > self.max_message:
            raise FramingError("fragment header out of range")

    def _start(self, key: tuple, source: Hashable, topic_id: int, count: int,
               now: float) -> _Partial:
        """A new partial frame (accounted by the caller), room made for it first."""
        owner = self._sources.get(source)
        if owner is not None and len(owner.partials) >= self.source_partials:
            self._give_up(next(iter(owner.partials)), "reassembly_overflow")
        if len(self._pending) >= self.max_partials:
            self._give_up(next(iter(self._pending)), "reassembly_overflow")
        owner = self._sources.setdefault(source, _Source())
        partial = self._pending[key] = _Partial(key, source, topic_id, count, now,
                                                bytearray(count), aside={})
        owner.partials[key] = None
        return partial

    def _earn_buffer(self, partial: _Partial) -> None:
        chunk, aside = partial.chunk, partial.aside
        buffer = partial.buffer = bytearray(partial.count * chunk)
        if aside:
            for index, data in aside.items():
                buffer[index * chunk:index * chunk + len(data)] = data
            partial.cost -= sum(map(len, aside.values())) + ASIDE_COST * len(aside)
        partial.aside = None
        partial.cost += len(buffer)

    def _charge(self, partial: _Partial, cost: int) -> None:
        """Add ``cost`` (already on ``partial``) to its source's and the link's totals, then
        shed to the bounds, oldest first (``partial`` itself, if it is the oldest)."""
        owner = self._sources[partial.source]
        owner.cost += cost
        self._pending_bytes += cost
        while owner.cost > self.source_bytes and owner.partials:
            self._give_up(next(iter(owner.partials)), "reassembly_overflow")
        while self._pending_bytes > self.max_pending_bytes and self._pending:
            self._give_up(next(iter(self._pending)), "reassembly_overflow")

    def _complete(self, partial: _Partial) -> bytearray:
        self._forget(partial)
        buffer = partial.buffer
        assert buffer is not None  # the last fragment in always earns it
        del buffer[(partial.count - 1) * partial.chunk + partial.last:]
        return buffer

    def _forget(self, partial: _Partial) -> None:
        del self._pending[partial.key]
        owner = self._sources[partial.source]
        del owner.partials[partial.key]
        owner.cost -= partial.cost
        self._pending_bytes -= partial.cost
        if not owner.partials:
            del self._sources[partial.source]
        self._finished[partial.key] = None
        if len(self._finished) > FINISHED_REMEMBERED:
            del self._finished[next(iter(self._finished))]

    def expire(self, now: float | None = None) -> None:
        """Give up frames whose fragments stopped coming, oldest first; stop at the first that
        is still in time."""
        now = time.monotonic() if now is None else now
        pending, deadline = self._pending, now - self.timeout
        while pending:
            oldest = next(iter(pending.values()))
            if oldest.started >= deadline:
                return
            self._give_up(oldest.key, "fragment_lost")

    def _give_up(self, key: tuple, reason: str) -> None:
        partial = self._pending[key]
        self._forget(partial)
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
    topic that ``topic_of`` (given the first 8 bytes of a frame) found, or ``None``.

    Sources with a frame in progress are kept in the order they last sent a piece, so expiring
    stalled frames looks only at the stalled ones and the first that is not; a frame in progress
    is accounted as its bytes plus :data:`PARTIAL_COST`."""

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
        self._active: dict[Hashable, _Sender] = {}  # frames in progress, least recent first
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
                oldest_source = next(iter(self._senders))
                oldest = self._senders.pop(oldest_source)
                if oldest.frame is not None:
                    self._give_up(oldest_source, oldest, "reassembly_overflow")
        elif counter == (sender.next - 1) & COMPACT_COUNTER:
            return None  # a duplicated piece
        elif counter != sender.next:
            self._give_up(source, sender, "fragment_lost")
        sender.next = (counter + 1) & COMPACT_COUNTER
        if head & COMPACT_START:
            if sender.frame is not None:  # the sender abandoned a frame half-sent
                self._give_up(source, sender, "fragment_lost")
            if self._active:
                self.expire(now)  # a stalled source is noticed even while others keep sending
            length, offset = _read_leb128(piece, 1)
            if length > self.max_message:
                raise FramingError(f"a frame of {length} bytes is over the limit "
                                   f"{self.max_message}")
            sender.frame, sender.length = bytearray(), length
            self._pending_bytes += PARTIAL_COST
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
        active = self._active
        active.pop(source, None)
        if len(frame) < sender.length:
            active[source] = sender  # now the most recent
            self._shed()
            return None
        self._pending_bytes -= len(frame) + PARTIAL_COST
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
            self._give_up(source, sender, "fragment_lost")

    def _shed(self) -> None:
        # memory bound: drop frames in progress, the longest silent first
        active = self._active
        while self._pending_bytes > self.max_pending_bytes and active:
            source, sender = next(iter(active.items()))
            self._give_up(source, sender, "reassembly_overflow")

    def _give_up(self, source: Hashable, sender: _Sender, reason: str) -> None:
        """Count one lost frame: the one in progress, or one that vanished whole."""
        if sender.frame is not None:
            self._pending_bytes -= len(sender.frame) + PARTIAL_COST
            sender.frame = None
            self._active.pop(source, None)
        self.on_lost(sender.topic_id, reason)
