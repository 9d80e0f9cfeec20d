"""The built-in plugins, registered through the same hooks as any other: the ``cdr`` codec, the
``none`` cipher and the datagram links' own packetizer, ``fragments`` (``RF``, the format of
:mod:`rosgate.wire.framing`)."""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Hashable
from dataclasses import dataclass, field
from typing import Any

from .cipher import Cipher
from .codec import Codec
from .drops import Drop, Reason
from .errors import CodecError
from .hookspecs import hookimpl
from .packetizer import PARTIAL_COST, Packet, Packetizer, PacketLink
from .transport import Address
from .wire.framing import (
    DEFAULT_MAX_MESSAGE,
    EARN_BUFFER,
    FINISHED_REMEMBERED,
    FRAGMENT,
    FRAGMENT_MAGIC,
    FramingError,
)


class CdrCodec(Codec):
    """The ROS wire format itself, passed through untouched (raw subscription, raw publish).
    Frames no cipher authenticated are checked by :func:`rosgate.ros.cdr_checker` first."""

    name = "cdr"
    raw = True

    def encode(self, message: bytes) -> bytes:
        return message

    def decode(self, data: bytes) -> bytes:
        # 4-byte encapsulation header: 0x00 0x00/0x01 (CDR big/little endian) + 2 option bytes
        if len(data) < 4 or data[0] != 0 or data[1] not in (0, 1):
            raise CodecError("not a CDR-encapsulated message")
        return data


class NoCipher(Cipher):
    """No encryption, no authentication: the payload travels as it is."""

    name = "none"
    authenticates = False
    plain = True

    def seal(self, header: bytes, payload: bytes) -> bytes:
        return payload

    def open(self, header: bytes, body: bytes) -> bytes:
        return body


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


#: what a fragment kept aside costs beyond its bytes (a bytes object, a dict entry)
ASIDE_COST = 128


class Reassembler:
    """Puts fragments back together, one buffer per frame, within bounds; each frame given up is
    counted once, ``on_lost(topic_id, reason)``:

    * time: ``timeout`` seconds after its last fragment (``fragment_lost``); partial frames are
      kept in the order last heard of, so expiring never scans them all;
    * per source ``source_partials`` and ``source_bytes``, per link ``max_partials`` and
      ``max_pending_bytes``; the oldest goes first (``reassembly_overflow``).

    Bytes are what a partial frame costs (buffer or fragments aside, plus :data:`PARTIAL_COST`),
    so one-byte fragments are bounded as tightly as large frames. The buffer comes once
    1/:data:`EARN_BUFFER` of the frame has; the completed frame is that buffer, not copied.
    Frame ids are random: a spoofed source cannot slip a fragment into a frame in progress.
    """

    def __init__(self, on_lost: Callable[[int, Reason], None], timeout: float = 2.0,
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
        self.pending_bytes = 0  # what the partial frames are accounted for
        # frames recently completed or given up: a late duplicate fragment of one of them is
        # ignored instead of starting a partial frame that would later count as lost
        self._finished: dict[tuple, None] = {}

    @property
    def pending(self) -> int:
        """Partial frames held now."""
        return len(self._pending)

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
        elif partial.have[index]:
            return None  # a duplicated datagram
        else:
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
            self._give_up(next(iter(owner.partials)), Drop.REASSEMBLY_OVERFLOW)
        if len(self._pending) >= self.max_partials:
            self._give_up(next(iter(self._pending)), Drop.REASSEMBLY_OVERFLOW)
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
        self.pending_bytes += cost
        while owner.cost > self.source_bytes and owner.partials:
            self._give_up(next(iter(owner.partials)), Drop.REASSEMBLY_OVERFLOW)
        while self.pending_bytes > self.max_pending_bytes and self._pending:
            self._give_up(next(iter(self._pending)), Drop.REASSEMBLY_OVERFLOW)

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
        self.pending_bytes -= partial.cost
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
            self._give_up(oldest.key, Drop.FRAGMENT_LOST)

    def _give_up(self, key: tuple, reason: Reason) -> None:
        partial = self._pending[key]
        self._forget(partial)
        self.on_lost(partial.topic_id, reason)


class Fragments(Packetizer):
    """A frame longer than the link's ``max_frame`` as numbered fragments (``RF``, see
    :mod:`rosgate.wire.framing`), reassembled in one buffer per frame; a lost fragment loses the
    frame (counted ``fragment_lost``). What every topic without ``recovery:`` gets."""

    name = "fragments"
    magic = (FRAGMENT_MAGIC,)

    def __init__(self, link: PacketLink):
        super().__init__(link)
        self.reassembler = Reassembler(link.lost, max_message=link.max_message)

    def cut(self, frame: bytes, sender: Any, to: Address, options: Any) -> list[Packet]:
        # frame ids unpredictable: a spoofed source cannot poison a reassembly (see Reassembler)
        frame_id = int.from_bytes(os.urandom(4), "big")
        return list(fragments(frame, self.link.max_frame, sender.topic_id, frame_id))

    def feed(self, packet: bytes | memoryview, source: Address, now: float) -> bytes | None:
        # the buffer it was reassembled in, the handler's to keep: a route hands it to rclpy
        # without a copy (handlers take any bytes-like frame)
        return self.reassembler.add(source, packet)  # type: ignore[return-value]

    def timer(self, now: float) -> float | None:
        if self.reassembler.pending:
            self.reassembler.expire(now)
        return None

    @classmethod
    def cost(cls, frame: int, max_frame: int, options: Any) -> tuple[int, int]:
        packets = max(1, math.ceil(frame / (max_frame - FRAGMENT.size)))
        return frame + packets * FRAGMENT.size, packets


@hookimpl
def rosgate_codecs(register: Any) -> None:
    register(CdrCodec)


@hookimpl
def rosgate_ciphers(register: Any) -> None:
    register(NoCipher)


@hookimpl
def rosgate_packetizers(register: Any) -> None:
    register(Fragments)
