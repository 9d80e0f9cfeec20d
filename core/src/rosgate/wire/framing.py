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

Links with small frames (CAN) cannot spend 14 bytes of every frame on that header: they cut
every frame with another packetizer (see :data:`rosgate.packetizer.SMALL_FRAME`).

Everything here is a pure format. Reading and writing stream records is
:mod:`rosgate.streamlink`'s, batches are :mod:`rosgate.links`'s, and cutting frames into
fragments and putting them back together is the built-in ``fragments`` packetizer's
(:mod:`rosgate.builtin`).
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
DIRECT_ABOVE = 64 * 1024  # stream frames longer than this are read into place
#: a large frame gets its buffer (all of it, zeroed) once this share of it has come: a length
#: that claims 64 MiB does not make the receiver zero 64 MiB for it
EARN_BUFFER = 16


class FramingError(ValueError):
    """The bytes cannot be framed (length over the limit, malformed fragment)."""
