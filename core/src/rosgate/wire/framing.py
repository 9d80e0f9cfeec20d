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

Everything here is a pure format. Reading and writing stream records is
:mod:`rosgate.streamlink`'s, batches are :mod:`rosgate.links`'s, and cutting frames into
fragments and pieces and putting them back together is the built-in packetizers'
(:mod:`rosgate.builtin`).

Overhead: 1 byte a piece plus the length, e.g. a 100 kB frame takes 14,287 classic CAN frames
or 1,588 CAN FD frames.
"""

from __future__ import annotations

import struct

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
