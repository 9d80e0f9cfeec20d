"""The envelope: a fixed 28-byte header in front of every frame rosgate sends.

    offset size field
    0      2    magic     b"RG"
    2      1    version   1
    3      1    flags     FLAG_* below
    4      4    topic_id  which topic (or control channel 0) the frame belongs to
    8      4    epoch     random per sender start: a restarted sender starts a new sequence
    12     8    seq       per topic and epoch, starting at 1
    20     8    stamp     sender's wall clock at send, nanoseconds since the Unix epoch (with a
                          static key never earlier than before the sender's last start:
                          rosgate.keyring.ReplayRecord)
    28          body      cipher.seal(header, payload)

The header travels in clear (the receiver needs the topic id to pick the cipher) and every cipher
authenticates it together with the payload. All integers are big-endian.
"""

from __future__ import annotations

import struct
import zlib
from typing import NamedTuple

from ..drops import Drop

MAGIC = b"RG"
VERSION = 1
HEADER = struct.Struct(">2sBBIIQQ")
SIZE = HEADER.size
# the same 28 bytes read in one call: magic, version and flags as one word
_WORDS = struct.Struct(">IIIQQ")
_MAGIC_VERSION = int.from_bytes(MAGIC, "big") << 16 | VERSION << 8

FLAG_CONTROL = 0x01  # topic_id 0: a control message on the main line (JSON)
FLAG_HELLO = 0x02    # a datagram telling the server where a client's link is (topic_id = session)
FLAG_REQUEST = 0x04  # a service call: topic_id = service id, epoch + seq = the call's id
FLAG_REPLY = 0x08    # its answer: epoch and seq echoed from the request
FLAG_FAILED = 0x10   # with FLAG_REPLY: the serving side had no answer; the body is the reason
FLAG_COMPRESSED = 0x20  # the payload under the cipher: a transform's wire id, what it made
FLAG_ANNOUNCE = 0x40  # what the sending side says of an entry: its type and QoS (rosgate.announce)

CONTROL_TOPIC = 0


def topic_id_for(name: str) -> int:
    """Peer role: a topic's id is derived from its link name, so both sides agree without a
    handshake (CRC-32; 0 is kept for the control channel)."""
    return zlib.crc32(name.encode()) or 1


def topic_of(start: bytes) -> int | None:
    """The topic id in a frame's first 8 bytes, or None when they do not begin an envelope
    (lets a link count a lost frame against its topic before the frame is whole)."""
    return int.from_bytes(start[4:8], "big") if start[:2] == MAGIC and len(start) >= 8 else None


def is_hello(datagram: bytes | memoryview) -> bool:
    """Whether ``datagram`` is a whole envelope with the HELLO flag (not yet checked)."""
    return len(datagram) >= SIZE and datagram[:2] == MAGIC and bool(datagram[3] & FLAG_HELLO)


def is_control(frame: bytes) -> bool:
    """Whether ``frame`` is a control frame (a main line's message between the roles)."""
    return len(frame) > 3 and frame[:2] == MAGIC and bool(frame[3] & FLAG_CONTROL)


class EnvelopeError(ValueError):
    """Bytes that do not start with a valid envelope header; counted as its ``reason``."""

    def __init__(self, what: str, reason: Drop):
        super().__init__(what)
        self.reason = reason


class Header(NamedTuple):
    """The fixed header in front of every rosgate frame (public as
    :class:`rosgate.EnvelopeHeader`): the ``FLAG_*`` bits, the id of its topic or service
    (:func:`topic_id_for`), the sender's epoch and sequence number (a call's id for a service),
    and the time it was sent (nanoseconds since the epoch)."""

    flags: int
    topic_id: int
    epoch: int
    seq: int
    stamp: int


def pack(flags: int, topic_id: int, epoch: int, seq: int, stamp: int) -> bytes:
    return HEADER.pack(MAGIC, VERSION, flags, topic_id, epoch, seq, stamp)


def unpack(frame: bytes | bytearray | memoryview) -> Header:
    """The header of ``frame`` (public as :func:`rosgate.unpack_envelope`); the frame's body,
    sealed by its cipher, follows it. :class:`EnvelopeError` when ``frame`` is too short, not
    rosgate's or of another envelope version; its ``reason`` is the drop to count."""
    try:
        word, topic_id, epoch, seq, stamp = _WORDS.unpack_from(frame)
    except struct.error:
        raise EnvelopeError("truncated", Drop.TRUNCATED_FRAME) from None
    if word & 0xFFFFFF00 != _MAGIC_VERSION:
        if word >> 16 != _MAGIC_VERSION >> 16:
            raise EnvelopeError("foreign", Drop.FOREIGN_FRAME)
        raise EnvelopeError("version", Drop.VERSION_FRAME)
    return Header(word & 0xFF, topic_id, epoch, seq, stamp)


class ReplayWindow:
    """Accepts each (epoch, seq) once: duplicates and frames older than the window are refused.

    Each sender epoch has a 64-frame sliding window, as in IPsec, so reordered datagrams get
    through once. The last ``EPOCHS`` epochs are kept, so switching between epochs cannot replay
    frames; no epoch is refused outright, so a forged frame cannot lock the real sender out.

    Unauthenticated (no cipher vouches for the header), one forged frame must not move the
    sequence either: a frame more than ``WIDTH`` ahead of (or ``JUMP`` behind) every window of
    its epoch opens a window of its own, one of ``TRACKS`` (least recently used forgotten). The
    real sender carries on in its window, a sender that really jumped in the new one; windows
    that come within ``WIDTH`` of each other merge.

    :attr:`lost` counts sequence numbers skipped and never filled in (losses on the way).
    """

    WIDTH = 64
    EPOCHS = 8
    JUMP = 4096
    TRACKS = 4
    _MASK = (1 << WIDTH) - 1

    __slots__ = ("_windows", "authenticated", "lost")

    def __init__(self, authenticated: bool = True) -> None:
        self.authenticated = authenticated
        self.lost = 0
        # epoch -> its windows [top, seen], least recently used first; bit i of seen: seq
        # (top - i) was accepted. The first epoch (insertion order) is the one to forget.
        self._windows: dict[int, list[list[int]]] = {}

    def newest(self) -> dict[int, int]:
        """The newest sequence number taken in each epoch it keeps."""
        return {epoch: max(track[0] for track in tracks)
                for epoch, tracks in self._windows.items()}

    def accept(self, epoch: int, seq: int) -> Drop | None:
        """None when the frame is new, else why it is refused ("duplicate" or "stale")."""
        tracks = self._windows.get(epoch)
        if tracks is None:
            if len(self._windows) >= self.EPOCHS:
                del self._windows[next(iter(self._windows))]
            self._windows[epoch] = [[seq, 1]]
            return None
        if self.authenticated:
            return self._slide(tracks[0], seq)
        width = self.WIDTH
        track = tracks[-1]  # the sender's own window, nearly always
        if track[0] - width < seq <= track[0] + width:
            return self._slide(track, seq) if len(tracks) == 1 else self._in(tracks, track, seq)
        for track in reversed(tracks):
            top = track[0]
            if top - width < seq <= top + width:
                return self._in(tracks, track, seq)
        highest = max(track[0] for track in tracks)
        if any(track[0] - self.JUMP <= seq <= track[0] - width for track in tracks):
            return Drop.STALE
        if highest < seq <= highest + self.JUMP:
            self.lost += seq - highest - 1  # a real jump over lost frames, most likely
        tracks.append([seq, 1])
        if len(tracks) > self.TRACKS:
            del tracks[0]
        return None

    def _in(self, tracks: list[list[int]], track: list[int], seq: int) -> Drop | None:
        """``seq`` in ``track``, which becomes the most recently used and takes in every window
        that has come within ``WIDTH`` of it."""
        refused = self._slide(track, seq)
        tracks.remove(track)
        tracks.append(track)
        for other in tracks[:-1]:
            distance = track[0] - other[0]
            if abs(distance) >= self.WIDTH:
                continue
            if distance >= 0:
                track[1] = (track[1] | other[1] << distance) & self._MASK
            else:
                track[0], track[1] = other[0], (other[1] | track[1] << -distance) & self._MASK
            tracks.remove(other)
        return refused

    def _slide(self, window: list[int], seq: int) -> Drop | None:
        """``seq`` in one window: accepted (the window moves on) or refused."""
        top, seen = window
        if seq > top:
            shift = seq - top
            window[0] = seq
            window[1] = ((seen << shift) | 1) & self._MASK if shift < self.WIDTH else 1
            self.lost += shift - 1
            return None
        offset = top - seq
        if offset >= self.WIDTH:
            return Drop.STALE
        if seen >> offset & 1:
            return Drop.DUPLICATE
        window[1] = seen | 1 << offset
        self.lost -= 1
        return None
