"""Putting frames on links: length prefixes on streams, fragments on datagram links.

Stream links (TCP, RFCOMM) carry ``u32 length | frame`` records. A length above the limit
means the stream is not ours or is corrupt: the reader refuses it and the connection is closed
(never a delimiter searched for in the payload).

Datagram links carry a frame whole when it fits ``max_frame``; otherwise fragments::

    offset size field
    0      2    magic     b"RF"
    2      2    index     0-based fragment number
    4      2    count     number of fragments of this frame
    6      4    topic_id  for counting a lost message against its topic
    10     4    frame_id  per sending link
    14          chunk

A frame whose fragments do not all arrive within ``timeout`` is dropped and counted once.
"""

from __future__ import annotations

import struct
import time
from dataclasses import dataclass, field
from typing import Callable, Hashable, Iterator

LENGTH = struct.Struct(">I")
FRAGMENT = struct.Struct(">2sHHII")
FRAGMENT_MAGIC = b"RF"
DEFAULT_MAX_MESSAGE = 64 * 1024 * 1024
FINISHED_REMEMBERED = 4096  # frames whose late fragments are recognised and ignored


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
def fragment(frame: bytes, max_frame: int, topic_id: int, frame_id: int) -> list[bytes]:
    """Split ``frame`` into datagrams of at most ``max_frame`` bytes (one when it fits)."""
    if len(frame) <= max_frame:
        return [frame]
    chunk = max_frame - FRAGMENT.size
    if chunk <= 0:
        raise FramingError(f"a datagram of {max_frame} bytes cannot carry a fragment header")
    count = -(-len(frame) // chunk)
    if count > 0xFFFF:
        raise FramingError(f"a frame of {len(frame)} bytes needs more than 65535 fragments")
    view = memoryview(frame)
    return [FRAGMENT.pack(FRAGMENT_MAGIC, i, count, topic_id, frame_id) + view[i * chunk:(i + 1) * chunk]
            for i in range(count)]


def is_fragment(datagram: bytes) -> bool:
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

    def add(self, source: Hashable, datagram: bytes) -> bytes | None:
        """Take one fragment; return the whole frame when this fragment completes it."""
        if len(datagram) <= FRAGMENT.size:
            raise FramingError("fragment too short")
        _, index, count, topic_id, frame_id = FRAGMENT.unpack_from(datagram)
        chunk = datagram[FRAGMENT.size:]
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
