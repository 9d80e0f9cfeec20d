"""The envelope: a fixed 28-byte header in front of every frame rosgate sends.

    offset size field
    0      2    magic     b"RG"
    2      1    version   1
    3      1    flags     FLAG_* below
    4      4    topic_id  which topic (or control channel 0) the frame belongs to
    8      4    epoch     random per sender start: a restarted sender starts a new sequence
    12     8    seq       per topic and epoch, starting at 1
    20     8    stamp     sender's wall clock at send, nanoseconds since the Unix epoch
    28          body      cipher.seal(header, payload)

The header travels in clear (the receiver needs the topic id to pick the cipher) and every cipher
authenticates it together with the payload. All integers are big-endian.
"""

from __future__ import annotations

import struct
import zlib
from typing import NamedTuple

MAGIC = b"RG"
VERSION = 1
HEADER = struct.Struct(">2sBBIIQQ")
SIZE = HEADER.size
# the same 28 bytes read in one call: magic, version and flags as one word
_WORDS = struct.Struct(">IIIQQ")
_MAGIC_VERSION = int.from_bytes(MAGIC, "big") << 16 | VERSION << 8

FLAG_CONTROL = 0x01  # topic_id 0: a control message on the main line (JSON)
FLAG_HELLO = 0x02    # a datagram that tells the server where a client's link is (topic_id = session)
FLAG_REQUEST = 0x04  # a service call: topic_id = service id, epoch + seq = the call's id
FLAG_REPLY = 0x08    # its answer: epoch and seq echoed from the request
FLAG_FAILED = 0x10   # with FLAG_REPLY: the serving side had no answer; the body is the reason

CONTROL_TOPIC = 0


def topic_id_for(name: str) -> int:
    """Peer role: a topic's id is derived from its link name, so both sides agree without a
    handshake (CRC-32; 0 is kept for the control channel)."""
    return zlib.crc32(name.encode()) or 1


def topic_of(start: bytes) -> int | None:
    """The topic id in a frame's first 8 bytes, or None when they do not begin an envelope
    (lets a link count a lost frame against its topic before the frame is whole)."""
    return int.from_bytes(start[4:8], "big") if start[:2] == MAGIC and len(start) >= 8 else None


class EnvelopeError(ValueError):
    """Bytes that do not start with a valid envelope header."""


class Header(NamedTuple):
    flags: int
    topic_id: int
    epoch: int
    seq: int
    stamp: int


def pack(flags: int, topic_id: int, epoch: int, seq: int, stamp: int) -> bytes:
    return HEADER.pack(MAGIC, VERSION, flags, topic_id, epoch, seq, stamp)


def unpack(frame: bytes | bytearray | memoryview) -> Header:
    try:
        word, topic_id, epoch, seq, stamp = _WORDS.unpack_from(frame)
    except struct.error:
        raise EnvelopeError("truncated") from None
    if word & 0xFFFFFF00 != _MAGIC_VERSION:
        raise EnvelopeError("foreign" if word >> 16 != _MAGIC_VERSION >> 16 else "version")
    return Header(word & 0xFF, topic_id, epoch, seq, stamp)


class ReplayWindow:
    """Accepts each (epoch, seq) once: duplicates and frames older than the window are refused.

    Each sender epoch (a new one at every sender start) has a 64-frame sliding window, as in
    IPsec, so reordered datagrams get through once. Windows of the last ``EPOCHS`` epochs are
    kept, so switching back and forth between epochs cannot replay frames; no epoch is refused
    outright, so a forged frame on an unauthenticated link cannot lock the real sender out.
    Replaying frames of an epoch forgotten long ago is for an authenticated handshake to stop.
    """

    WIDTH = 64
    EPOCHS = 8

    __slots__ = ("_windows",)

    def __init__(self) -> None:
        # epoch -> [top, seen]; bit i of seen set: seq (top - i) was accepted. Insertion order
        # is age order, so the first entry is the one to forget.
        self._windows: dict[int, list[int]] = {}

    def top(self, epoch: int) -> int | None:
        """The highest sequence number accepted in ``epoch`` (None: none yet)."""
        window = self._windows.get(epoch)
        return window[0] if window is not None else None

    def accept(self, epoch: int, seq: int) -> str | None:
        """None when the frame is new, else why it is refused ("duplicate" or "stale")."""
        window = self._windows.get(epoch)
        if window is None:
            if len(self._windows) >= self.EPOCHS:
                del self._windows[next(iter(self._windows))]
            self._windows[epoch] = [seq, 1]
            return None
        top, seen = window
        if seq > top:
            shift = seq - top
            window[0] = seq
            window[1] = ((seen << shift) | 1) & ((1 << self.WIDTH) - 1) if shift < self.WIDTH else 1
            return None
        offset = top - seq
        if offset >= self.WIDTH:
            return "stale"
        if seen >> offset & 1:
            return "duplicate"
        window[1] = seen | 1 << offset
        return None
