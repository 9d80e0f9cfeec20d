"""Putting frames on links: length prefixes on streams, batches and fragments on datagram links.

Stream links (TCP, RFCOMM) carry ``u32 length | frame`` records. A length above the limit means
the stream is not ours or is corrupt: the reader refuses it and the connection is closed (never a
delimiter searched for in the payload). A frame longer than :data:`CHUNK` goes as **chunks**, so
that another topic's frame can go between them and waits at most one chunk::

    u32 CHUNKED | LAST? | n    the top bit says "a chunk"; the next one "the frame's last"
    u32 message              which frame it continues: a number the sender gives each frame
    n - 4 bytes              the next part of that frame

A reader holds at most :data:`MAX_OPEN_MESSAGES` unfinished frames and, all together, at most
twice the largest frame it takes. A whole frame's length is below 2^31, so the two never mix up;
a reader that predates chunks refuses a chunk as a length over its limit, and reconnects.

Datagram links carry frames whole (an envelope: ``"RG"``), and two kinds of datagram of their
own, told apart by their first two bytes (other packetizers' magics: :mod:`rosgate.packetizer`):

* a **batch** of frames that left together for one destination, as many as fit ``max_frame``
  (a frame alone never travels as a batch; a bare link, ``framing: none``, never batches)::

      offset size field
      0      2    magic     b"RB"
      2      4    length    u32, of the first frame
      6           frame
                  length, frame, ... to the end of the datagram (the records of a stream link)

  A length that runs past the end is counted (``bad_batch``) and ends the batch;
* a **fragment** of a frame longer than ``max_frame``, cut and put back together by the built-in
  ``fragments`` packetizer (:mod:`rosgate.builtin`)::

      offset size field
      0      2    magic     b"RF"
      2      2    index     0-based fragment number
      4      2    count     number of fragments of this frame
      6      4    topic_id  for counting a lost message against its topic
      10     4    frame_id  random per frame (see rosgate.builtin.Reassembler)
      14          chunk

Only formats here: stream records are read and written by :mod:`rosgate.streamlink`, batches by
:mod:`rosgate.links.datagram`.
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
