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
packets of whatever other packetizer a topic picks, each with magics of its own: see
:mod:`rosgate.packetizer`):

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
      10     4    frame_id  random per frame (see rosgate.builtin.Reassembler)
      14          chunk

  The built-in ``fragments`` packetizer (:mod:`rosgate.builtin`) cuts and reassembles them; a
  frame whose fragments do not all arrive within a timeout is dropped and counted once.

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

Everything here is a pure format; cutting frames into fragments and pieces and putting them
back together is the built-in packetizers' (:mod:`rosgate.builtin`).

Overhead: 1 byte a piece plus the length, e.g. a 100 kB frame takes 14,287 classic CAN frames
or 1,588 CAN FD frames.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
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
#: a large frame gets its buffer (all of it, zeroed) once this share of it has come: a length
#: that claims 64 MiB does not make the receiver zero 64 MiB for it
EARN_BUFFER = 16


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
