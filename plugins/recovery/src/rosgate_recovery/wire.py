"""The formats and the state of loss recovery on datagram links: forward error correction and
selective repeat (the packetizers of :mod:`rosgate_recovery` put them on a link).

A message cut into fragments is lost when any fragment is: at 1 % packet loss a 921,600-byte
image in 1,200-byte datagrams (778 fragments) arrives whole 0.04 % of the time. A topic chooses
how to ride that out (``recovery:`` in bringup.yaml); the sender's fragments say which, so the
receiver needs no setting. All integers are big-endian.

``fec``: forward error correction, Reed-Solomon over GF(2^8) (zfec). The frame is cut into K
chunks of equal size (the last padded with zeros), the chunks into blocks of at most
:func:`block_limit` ``k``, and each block gets ``m = ceil(k * overhead)`` repair chunks: any
``k`` of a block's ``k + m`` rebuild it. Blocks are sent interleaved (the first fragment of
every block, then the second...) so that a burst of losses is shared among them::

    offset size field
    0      2    magic     b"RE"
    2      4    frame_id  random per frame
    6      4    topic_id  for counting a lost message against its topic
    10     4    length    of the frame (the padding is cut off)
    14     2    block     0-based
    16     2    blocks    how many
    18     1    index     in the block: 0..k-1 data, k..k+m-1 repair
    19     1    k
    20     1    m
    21          chunk     the same size in every fragment of a frame

``retransmit``: selective repeat. Every frame of such a topic — whole or not — travels as
numbered fragments (the layout of plain fragments, ``b"RF"``, with the magic ``b"RS"``, so the
receiver knows it may ask again; a frame that fits is one fragment of one). The sender keeps
each frame's fragments until it is acknowledged or :data:`DEADLINE` passes after its last
fragment left; the receiver asks
for what is missing (NACK) — a fragment three places behind one that came, or everything
still missing once a frame's fragments have stopped coming for a while — and acknowledges each
frame it completes (ACK), again for every fragment of it that comes after. An ACK names every
frame completed since the last one to that sender: it goes at once when the last went
:data:`ACK_EVERY` ago or more, else with the first frame completed once that time is up, or
:data:`ACK_LATE` after it when none comes (so a busy topic costs an ACK per 10 ms, not one per
message, and a quiet one is acknowledged at once). A frame whose last
fragments are lost leaves the receiver nothing to ask about: the sender re-sends its last
fragment when no ACK came within a probe timeout (as QUIC's PTO does), and the receiver then
asks for the rest. ::

    NACK: b"RN", frame_id u32, ranges u16, then ranges x (first u16, count u16)
    ACK:  b"RA", frames u16, then frames x frame_id u32

A NACK or ACK is taken only from the address the frame was sent to; frame ids are random, so
someone off the path cannot make a sender repeat itself, and every fragment is re-sent a
bounded number of times (:data:`MAX_SENDS`) within the sender's bandwidth budget.

The receivers here keep what they hold within bounds on time (``timeout``, the deadline) and
memory, and count every frame they give up once, as :class:`rosgate.builtin.Reassembler`
does. Nothing here opens a socket or reads a clock of its own: times are passed in.
"""

from __future__ import annotations

import itertools
import math
import os
import struct
from array import array
from collections import OrderedDict
from collections.abc import Callable, Hashable, Iterator
from dataclasses import dataclass, field
from typing import Any

from rosgate import (
    DEFAULT_MAX_MESSAGE,
    FINISHED_REMEMBERED,
    FRAGMENT,
    Drop,
    FramingError,
    Reason,
    declare,
)

FEC = struct.Struct(">2sIIIHHBBB")
FEC_MAGIC = b"RE"
REPEAT_MAGIC = b"RS"
NACK = struct.Struct(">2sIH")
NACK_MAGIC = b"RN"
ACK = struct.Struct(">2sH")
ACK_MAGIC = b"RA"
RANGE = struct.Struct(">HH")
FRAME_ID = struct.Struct(">I")

DEADLINE = 2.0          # seconds a sender keeps a sent frame for re-sending, and a receiver waits
MAX_SENDS = 8           # times one fragment is sent at most (the first time included)
REORDER = 3             # a fragment this many places behind one that came is taken as lost
NACK_AFTER = 0.02       # seconds without a new fragment before the rest is asked for (at least)
RTT_INITIAL = 0.1       # seconds, until a round trip is measured
MAX_RANGES = 128        # ranges in one NACK (more wait for the next one)
OVERTAKEN_SCAN = 64     # kept frames an ACK looks at for ones sent before and still unanswered
# probes of a frame to where no one has ever answered: one, for a first message lost on a live
# link (then the ACKs of later frames bring it again); more would bring a receiver started later
# what was sent before it was there, scattered, with gaps that were never its to fill
VOID_PROBES = 1
MAX_ANSWERED = 10_000
# an ACK to one sender at most this often (seconds): what completes meanwhile waits, and goes
# in one ACK with the next frame completed after that time, or ACK_LATE later when none comes
# (the timer's run, on a link's send thread: one wake-up per ACK_EVERY on a busy link). An ACK
# is at most ACK_EVERY + ACK_LATE late: below a probe timeout's smallest (30 ms)
ACK_EVERY = 0.01
ACK_LATE = 0.01
ACK_MOST = 64  # frame ids in one ACK at most (more go at once)

#: a sent frame forgotten before it was acknowledged, to keep the store within its bytes
REPAIR_OVERFLOW = declare("repair_overflow", "a sent frame not yet acknowledged, forgotten by "
                          "`retransmit` to keep what it holds for re-sending within its bound "
                          "(32 MiB per link): if it was lost on the way, it stays lost")

Lost = Callable[[int | None, Reason], None]
Recovered = Callable[[int], None]
Send = Callable[[bytes, Any], None]


_IDS_AT_ONCE = 1024
_ids: Iterator[int] = iter(())


def frame_id() -> int:
    """A random frame id: unpredictable, so no one off the path can name a frame. Read from
    the system's random source 1,024 at a time (one system call each, not one per frame)."""
    global _ids
    try:
        return next(_ids)  # (an array's iterator: one step is atomic under the GIL)
    except StopIteration:
        _ids = iter(array("I", os.urandom(4 * _IDS_AT_ONCE)))
        return next(_ids)


def magic(datagram: bytes | memoryview) -> bytes:
    return bytes(datagram[:2])


# -- forward error correction ----------------------------------------------------------------
def _zfec() -> Any:
    import zfec  # type: ignore[import-untyped]  # a C extension, imported when first used

    return zfec


def block_limit(overhead: float) -> int:
    """The most data chunks in one block: k + ceil(k * overhead) <= 256 (GF(2^8))."""
    k = 255
    while k + math.ceil(k * overhead) > 256:
        k -= 1
    return k


def fec_fragments(frame: bytes, max_frame: int, topic_id: int, frame_id: int,
                  overhead: float) -> list[bytes]:
    """``frame`` as FEC fragments of at most ``max_frame`` bytes, data and repair, interleaved."""
    room = max_frame - FEC.size
    if room <= 0:
        raise FramingError(f"a datagram of {max_frame} bytes cannot carry an FEC fragment header")
    length = len(frame)
    total = max(1, -(-length // room))        # data chunks
    per_block = block_limit(overhead)
    blocks = -(-total // per_block)
    if blocks > 0xFFFF or length > 0xFFFFFFFF:
        raise FramingError(f"a frame of {length} bytes is too large for FEC")
    size = max(1, -(-length // total))          # chunk size: no more padding than needed
    padded = frame + bytes(total * size - length)
    zfec = _zfec()
    out: list[list[bytes]] = []
    start = 0
    for block in range(blocks):
        k = total // blocks + (block < total % blocks)
        m = math.ceil(k * overhead)
        data = tuple(padded[(start + i) * size:(start + i + 1) * size] for i in range(k))
        start += k
        repair = zfec.Encoder(k, k + m).encode(data, tuple(range(k, k + m))) if m else []
        out.append([FEC.pack(FEC_MAGIC, frame_id, topic_id, length, block, blocks, index, k, m)
                     + chunk for index, chunk in enumerate((*data, *repair))])
    return [fragments[i] for i in range(max(map(len, out))) for fragments in out
            if i < len(fragments)]


@dataclass
class _Block:
    k: int
    m: int
    chunks: dict[int, bytes] = field(default_factory=dict)
    data: list[bytes] | None = None  # once rebuilt


@dataclass
class _FecFrame:
    topic_id: int
    length: int
    size: int  # chunk size
    last: float  # when a fragment of it last came
    blocks: list[_Block | None]
    done: int = 0
    held: int = 0  # bytes
    recovered: bool = False


class _Pending:
    """What both receivers of loss recovery keep: frames in progress in the order they were last
    heard of (a frame is given up ``timeout`` seconds after its newest fragment, so a large one
    on a slow link is waited for while it comes; expiry looks at the longest silent only), within
    ``max_pending_bytes``, and the frames lately finished (their late fragments are ignored).
    A frame has ``topic_id``, ``last`` and ``held`` (bytes)."""

    def __init__(self, on_lost: Lost, on_recovered: Recovered, timeout: float,
                 max_pending_bytes: int, max_message: int):
        self.on_lost = on_lost
        self.on_recovered = on_recovered
        self.timeout = timeout
        self.max_pending_bytes = max_pending_bytes
        self.max_message = max_message
        self._pending: OrderedDict[Any, Any] = OrderedDict()  # longest silent first
        self.pending_bytes = 0
        self._finished: OrderedDict[Hashable, None] = OrderedDict()

    def _heard(self, key: Hashable, frame: Any, now: float) -> None:
        frame.last = now
        self._pending.move_to_end(key)

    def _remember(self, key: Hashable) -> None:
        self._finished[key] = None
        if len(self._finished) > FINISHED_REMEMBERED:
            self._finished.popitem(last=False)

    def expire(self, now: float) -> None:
        """Give up frames whose fragments stopped coming for the timeout, longest silent first."""
        while self._pending:
            key, frame = next(iter(self._pending.items()))
            if now - frame.last <= self.timeout:
                return
            self._give_up(key, Drop.FRAGMENT_LOST)

    def _shed(self) -> None:
        while self.pending_bytes > self.max_pending_bytes and self._pending:
            self._give_up(next(iter(self._pending)), Drop.REASSEMBLY_OVERFLOW)

    def _give_up(self, key: Hashable, reason: Reason) -> None:
        frame = self._pending.pop(key)
        self.pending_bytes -= frame.held
        self._remember(key)
        self.on_lost(frame.topic_id, reason)


class FecReassembler(_Pending):
    """Rebuilds FEC frames from any ``k`` fragments of each block. ``on_lost(topic_id, reason)``
    once per frame given up; ``on_recovered(topic_id)`` once per frame that needed its repair
    fragments."""

    def __init__(self, on_lost: Lost, on_recovered: Recovered, timeout: float = DEADLINE,
                 max_pending_bytes: int = 4 * DEFAULT_MAX_MESSAGE,
                 max_message: int = DEFAULT_MAX_MESSAGE):
        super().__init__(on_lost, on_recovered, timeout, max_pending_bytes, max_message)

    def add(self, source: Hashable, datagram: bytes | memoryview, now: float) -> bytes | None:
        """Take one fragment; the frame when it completes one."""
        if len(datagram) <= FEC.size:
            raise FramingError("FEC fragment too short")
        _, fid, topic_id, length, block, blocks, index, k, m = FEC.unpack_from(datagram)
        chunk = bytes(datagram[FEC.size:])
        size = len(chunk)
        # every block holds at least one chunk of real data, and at most 255
        if (not 0 < k <= 255 or k + m > 256 or index >= k + m or block >= blocks
                or length > self.max_message
                or not (blocks - 1) * size <= length <= blocks * 255 * size):
            raise FramingError("FEC fragment header out of range")
        key = (source, topic_id, fid)
        frame = self._pending.get(key)
        if frame is None:
            if key in self._finished:
                return None
            self.expire(now)
            frame = self._pending[key] = _FecFrame(topic_id, length, size, now, [None] * blocks)
        elif (frame.length, frame.size, len(frame.blocks)) != (length, size, blocks):
            raise FramingError("FEC fragment header changed within a frame")
        state = frame.blocks[block]
        if state is None:
            state = frame.blocks[block] = _Block(k, m)
        elif (state.k, state.m) != (k, m):
            raise FramingError("FEC block header changed within a frame")
        if state.data is not None or index in state.chunks:
            return None  # a block already rebuilt, or a duplicate
        self._heard(key, frame, now)
        state.chunks[index] = chunk
        frame.held += size
        self.pending_bytes += size
        if len(state.chunks) < k:
            self._shed()
            return None
        indexes = sorted(state.chunks)[:k]
        if indexes[-1] < k:  # every data chunk came
            state.data = [state.chunks[i] for i in range(k)]
        else:
            zfec = _zfec()
            rebuilt = zfec.Decoder(k, k + m).decode(tuple(state.chunks[i] for i in indexes),
                                                    tuple(indexes))
            state.data = [bytes(c) for c in rebuilt]
            frame.recovered = True
        self.pending_bytes -= sum(len(c) for c in state.chunks.values())
        frame.held -= sum(len(c) for c in state.chunks.values())
        state.chunks.clear()
        frame.done += 1
        if frame.done < blocks:
            return None
        del self._pending[key]
        self._remember(key)
        whole = b"".join(c for b in frame.blocks if b is not None and b.data for c in b.data)
        if len(whole) < length:
            raise FramingError("FEC blocks shorter than the frame's length")
        if frame.recovered:
            self.on_recovered(topic_id)
        return whole[:length]


# -- selective repeat ------------------------------------------------------------------------
def repeat_fragments(frame: bytes, max_frame: int, topic_id: int,
                     frame_id: int) -> list[bytes]:
    """``frame`` as numbered fragments (one, when it fits) a receiver can ask for again."""
    room = max_frame - FRAGMENT.size
    if room <= 0:
        raise FramingError(f"a datagram of {max_frame} bytes cannot carry a fragment header")
    count = max(1, -(-len(frame) // room))
    if count > 0xFFFF:
        raise FramingError(f"a frame of {len(frame)} bytes needs more than 65535 fragments")
    view = memoryview(frame)
    return [FRAGMENT.pack(REPEAT_MAGIC, i, count, topic_id, frame_id)
            + view[i * room:(i + 1) * room] for i in range(count)]


def nack(frame_id: int, missing: list[int]) -> bytes:
    """A NACK for ``missing`` (sorted fragment indexes), as ranges."""
    ranges: list[tuple[int, int]] = []
    for index in missing:
        if ranges and ranges[-1][0] + ranges[-1][1] == index:
            ranges[-1] = (ranges[-1][0], ranges[-1][1] + 1)
        elif len(ranges) < MAX_RANGES:
            ranges.append((index, 1))
    return NACK.pack(NACK_MAGIC, frame_id, len(ranges)) + b"".join(
        RANGE.pack(*r) for r in ranges)


def parse_nack(datagram: bytes | memoryview) -> tuple[int, list[int]]:
    if len(datagram) < NACK.size:
        raise FramingError("NACK too short")
    _, fid, count = NACK.unpack_from(datagram)
    if len(datagram) != NACK.size + count * RANGE.size:
        raise FramingError("NACK of the wrong length")
    missing: list[int] = []
    for i in range(count):
        first, n = RANGE.unpack_from(datagram, NACK.size + i * RANGE.size)
        missing.extend(range(first, min(first + n, 0x10000)))
    return fid, missing


def ack(frame_ids: list[int]) -> bytes:
    return ACK.pack(ACK_MAGIC, len(frame_ids)) + b"".join(FRAME_ID.pack(f) for f in frame_ids)


def parse_ack(datagram: bytes | memoryview) -> list[int]:
    if len(datagram) < ACK.size:
        raise FramingError("ACK too short")
    _, count = ACK.unpack_from(datagram)
    if len(datagram) != ACK.size + count * FRAME_ID.size:
        raise FramingError("ACK of the wrong length")
    return [FRAME_ID.unpack_from(datagram, ACK.size + i * FRAME_ID.size)[0]
            for i in range(count)]


@dataclass
class _RepeatFrame:
    topic_id: int
    count: int
    last: float                       # when a new fragment last came
    parts: dict[int, bytes] = field(default_factory=dict)
    held: int = 0                     # bytes
    highest: int = -1
    gap: float = NACK_AFTER           # mean time between its fragments (smoothed)
    asked: dict[int, float] = field(default_factory=dict)  # index -> when it was last asked for
    recovered: bool = False
    check_at: float = 0.0             # when poll looks at it next


class RepeatReassembler(_Pending):
    """The receiving side of selective repeat: reassembles ``b"RS"`` fragments, asks for the
    missing ones and acknowledges whole frames through ``send(datagram, source)``.

    Call :meth:`poll` when :meth:`next_poll` says: it asks again for what stopped coming, and
    gives up frames past the deadline (``on_lost``, once each).
    """

    def __init__(self, on_lost: Lost, on_recovered: Recovered, send: Send,
                 timeout: float = DEADLINE, max_pending_bytes: int = 4 * DEFAULT_MAX_MESSAGE,
                 max_message: int = DEFAULT_MAX_MESSAGE):
        super().__init__(on_lost, on_recovered, timeout, max_pending_bytes, max_message)
        self.send = send  # pending: (source, topic id, frame id) -> the frame
        self._rtt: dict[Hashable, float] = {}  # per source: NACK to the first fragment it brought
        self._acks: dict[Hashable, list[int]] = {}  # per source: frame ids not acknowledged yet
        self._acked: dict[Hashable, float] = {}  # per source: when an ACK last went there
        self.ack_due: float | None = None  # when the frame ids in _acks go

    def add(self, source: Hashable, datagram: bytes | memoryview, now: float) -> bytes | None:
        if len(datagram) <= FRAGMENT.size:
            raise FramingError("fragment too short")
        _, index, count, topic_id, fid = FRAGMENT.unpack_from(datagram)
        key = (source, topic_id, fid)
        if count == 1 and index == 0 and key not in self._pending:
            # a frame of one fragment (most messages): whole at once, nothing to keep
            if key not in self._finished:
                self._remember(key)
                self._ack(source, fid, now)
                return bytes(datagram[FRAGMENT.size:])
            self._ack(source, fid, now)  # our ACK was lost: the sender is still asking
            return None
        chunk = bytes(datagram[FRAGMENT.size:])
        if index >= count or count * len(chunk) > self.max_message + len(chunk):
            raise FramingError("fragment header out of range")
        frame = self._pending.get(key)
        if frame is None:
            if key in self._finished:
                self._ack(source, fid, now)  # our ACK was lost: the sender is still asking
                return None
            self.expire(now)
            frame = self._pending[key] = _RepeatFrame(topic_id, count, now)
        elif frame.count != count:
            raise FramingError("fragment count changed within a frame")
        if index in frame.parts:
            return None
        asked = frame.asked.pop(index, None)
        if asked is not None:
            frame.recovered = True
            rtt = self._rtt.get(source, RTT_INITIAL)
            self._rtt[source] = 0.8 * rtt + 0.2 * (now - asked)
        else:
            frame.gap = 0.8 * frame.gap + 0.2 * (now - frame.last)
        frame.parts[index] = chunk
        frame.held += len(chunk)
        self.pending_bytes += len(chunk)
        self._heard(key, frame, now)
        frame.check_at = now + max(NACK_AFTER, 4 * frame.gap)
        if len(frame.parts) == count:
            del self._pending[key]
            self.pending_bytes -= frame.held
            self._remember(key)
            self._ack(source, fid, now)
            if frame.recovered:
                self.on_recovered(topic_id)
            return b"".join(frame.parts[i] for i in range(count))
        if index > frame.highest:
            frame.highest = index
            # fragments of a frame come in order: one this far behind the newest is lost
            behind = [i for i in range(max(0, index - 64), index - REORDER + 1)
                      if i not in frame.parts and i not in frame.asked]
            if behind:
                self._ask(source, fid, frame, behind, now)
        self._shed()
        return None

    def moved(self, old: Hashable, new: Hashable) -> None:
        """Frames in progress from ``old`` go on from ``new`` (it roamed): asked for there."""
        for key in [key for key in self._pending if key[0] == old]:
            moved = (new, *key[1:])
            if moved not in self._pending:
                self._pending[moved] = self._pending.pop(key)
        if old in self._rtt:
            self._rtt[new] = self._rtt.pop(old)
        if old in self._acks:
            self._acks.setdefault(new, []).extend(self._acks.pop(old))

    def _ack(self, source: Hashable, fid: int, now: float) -> None:
        """Acknowledge frame ``fid`` of ``source``: at once if the last ACK there went
        :data:`ACK_EVERY` ago or more, else with the others when that time is up."""
        waiting = self._acks.get(source)
        if waiting is None:
            last = self._acked.get(source)
            if last is None or now - last >= ACK_EVERY:
                if last is None and len(self._acked) >= MAX_ANSWERED:  # sources: the network's
                    self._acked.clear()
                self._acked[source] = now
                self.send(ack([fid]), source)
                return
            waiting = self._acks[source] = []
            due = last + ACK_EVERY
            if self.ack_due is None or due < self.ack_due:
                self.ack_due = due
        waiting.append(fid)
        if self.ack_due is not None and now >= self.ack_due:
            self._send_acks(now)
        elif len(waiting) >= ACK_MOST:
            del self._acks[source]
            self._acked[source] = now
            self.send(ack(waiting), source)

    def _send_acks(self, now: float) -> None:
        """Every frame id waiting, in one ACK per source (their time is up)."""
        self.ack_due = None
        for source, fids in self._acks.items():
            self._acked[source] = now
            self.send(ack(fids), source)
        self._acks.clear()

    def resumed(self, down: float, now: float) -> None:
        """The line was gone for ``down`` seconds: frames in progress wait that much longer,
        and what they miss is asked for now."""
        for frame in self._pending.values():
            frame.last += down
            frame.check_at = now

    def _interval(self, source: Hashable) -> float:
        """How long to wait before asking for the same fragment again."""
        return max(1.5 * self._rtt.get(source, RTT_INITIAL), NACK_AFTER)

    def _ask(self, source: Hashable, fid: int, frame: _RepeatFrame, missing: list[int],
             now: float) -> None:
        missing = missing[:MAX_RANGES]
        for i in missing:
            frame.asked[i] = now
        self.send(nack(fid, missing), source)

    def poll(self, now: float) -> None:
        """Send the ACKs that are due, ask again for what stopped coming, give up what is past
        the deadline."""
        if self.ack_due is not None and now >= self.ack_due:
            self._send_acks(now)
        self.expire(now)
        for (source, _, fid), frame in list(self._pending.items()):
            if now < frame.check_at:
                continue
            interval = self._interval(source)
            frame.check_at = now + interval
            again = now - interval
            missing = [i for i in range(frame.count)
                       if i not in frame.parts and frame.asked.get(i, -1.0) <= again]
            if missing:
                self._ask(source, fid, frame, missing, now)

    def next_poll(self) -> float | None:
        """When :meth:`poll` has something to do next (None: nothing pending)."""
        acks = None if self.ack_due is None else self.ack_due + ACK_LATE
        if not self._pending:
            return acks
        soonest = min(frame.check_at for frame in self._pending.values())
        oldest = next(iter(self._pending.values())).last + self.timeout
        return min(soonest, oldest) if acks is None else min(soonest, oldest, acks)



@dataclass
class _Kept:
    owner: Any
    packets: list[bytes]
    kept: float
    sends: list[int]
    last_sent: float | None = None   # when its last fragment left (the probe timer starts)
    probe_at: float | None = None
    probes: int = 0
    overtaken: int = 0  # frames to the same place sent after it and acknowledged before it


class RetransmitStore:
    """The sending side of selective repeat: the fragments of each frame until it is
    acknowledged or :data:`DEADLINE` passes after its last fragment left, within ``max_bytes``
    (oldest forgotten first).
    Keyed by destination and frame id; ``owner`` is whoever re-sends (the route)."""

    def __init__(self, deadline: float = DEADLINE, max_bytes: int = 32 * 1024 * 1024):
        self.deadline = deadline
        self.max_bytes = max_bytes
        self._kept: OrderedDict[tuple[Any, int], _Kept] = OrderedDict()
        self._bytes = 0
        #: per destination: the smoothed round trip and its mean deviation (RFC 6298's SRTT
        #: and RTTVAR), from frames acknowledged without a probe
        self._rtt: dict[Any, float] = {}
        self._rttvar: dict[Any, float] = {}
        self._answered: set[Any] = set()  # destinations that ever acknowledged a frame
        #: no probe or deadline is due before this (a bound, not exact: an acknowledged frame
        #: leaves it as it was); None: nothing sent is kept
        self.soonest: float | None = None

    def _soon(self, at: float) -> None:
        if self.soonest is None or at < self.soonest:
            self.soonest = at

    def __len__(self) -> int:
        return len(self._kept)

    def keep(self, to: Any, fid: int, packets: list[bytes], owner: Any, now: float) -> list[Any]:
        """Keep a frame's fragments; the owners of the frames forgotten for room (oldest first),
        once each, for the caller to count."""
        self._kept[(to, fid)] = _Kept(owner, packets, now, [1] * len(packets))
        self._bytes += sum(map(len, packets))
        forgotten = []
        while self._bytes > self.max_bytes and self._kept:
            forgotten.append(self._forget(next(iter(self._kept))).owner)
        return forgotten

    def sent(self, to: Any, fid: int, now: float) -> None:
        """Its last fragment has left: start the probe timer."""
        kept = self._kept.get((to, fid))
        if kept is not None:
            kept.last_sent = now
            kept.probe_at = now + self._pto(to)
            self._soon(kept.probe_at)

    def _pto(self, to: Any) -> float:
        """The probe timeout: the smoothed round trip, four deviations of it (a line whose
        queue comes and goes, as a slow serial line's does, is not probed at each slow
        acknowledgement) and the most an ACK is held back (:data:`ACK_EVERY` + ACK_LATE);
        30 ms at least."""
        rtt = self._rtt.get(to)
        if rtt is None:
            return 2 * RTT_INITIAL + 0.01
        return max(rtt + 4 * self._rttvar.get(to, rtt / 2) + ACK_EVERY + ACK_LATE, 0.03)

    def on_nack(self, to: Any, datagram: bytes | memoryview) -> tuple[Any, list[bytes]] | None:
        """(owner, fragments to send again) for a NACK from ``to``; None when the frame is not
        (or no longer) kept for ``to``."""
        fid, missing = parse_nack(datagram)
        kept = self._kept.get((to, fid))
        if kept is None:
            return None
        again = []
        for index in missing:
            if index < len(kept.packets) and kept.sends[index] < MAX_SENDS:
                kept.sends[index] += 1
                again.append(kept.packets[index])
        if kept.probe_at is not None and kept.last_sent is not None:
            kept.probe_at = max(kept.probe_at, kept.last_sent + self._pto(to))
        return (kept.owner, again) if again else None

    def on_ack(self, to: Any, datagram: bytes | memoryview, now: float) -> None:
        if to not in self._answered:
            if len(self._answered) > MAX_ANSWERED:  # addresses come from the network
                self._answered.clear()
            self._answered.add(to)
        for fid in parse_ack(datagram):
            kept = self._kept.get((to, fid))
            if kept is None:
                continue
            if kept.last_sent is not None and not kept.probes:
                rtt, sample = self._rtt.get(to), now - kept.last_sent
                if rtt is None:
                    self._rtt[to], self._rttvar[to] = sample, sample / 2
                else:
                    self._rttvar[to] = 0.75 * self._rttvar[to] + 0.25 * abs(rtt - sample)
                    self._rtt[to] = 0.875 * rtt + 0.125 * sample
            self._forget((to, fid))
            if kept.last_sent is not None:
                self._overtaken(to, kept.last_sent, now)

    def _overtaken(self, to: Any, sent: float, now: float) -> None:
        """A frame to ``to`` whose last fragment left at ``sent`` is acknowledged: a frame sent
        before it and acknowledged by :data:`REORDER` such later frames is lost whole, most
        likely (as QUIC's packet threshold says), and probed now, once, not a probe timeout
        later (a small message, one fragment, is lost whole every time). The oldest
        :data:`OVERTAKEN_SCAN` kept frames are looked at."""
        for (dest, _), kept in itertools.islice(self._kept.items(), OVERTAKEN_SCAN):
            if dest != to or kept.last_sent is None:
                continue
            if kept.last_sent >= sent:
                return
            kept.overtaken += 1
            if kept.overtaken == REORDER:
                kept.probe_at = now
                self._soon(now)

    def moved(self, old: Any, new: Any, now: float) -> None:
        """Frames kept for ``old`` are ``new``'s now (it roamed): probed there at once, their
        deadline and sends counted afresh (those to ``old`` were lost with it)."""
        for (to, fid) in [key for key in self._kept if key[0] == old]:
            kept = self._kept.pop((to, fid))
            kept.sends = [1] * len(kept.packets)
            kept.probes = 0
            if kept.last_sent is not None:
                kept.last_sent = kept.probe_at = now
                self._soon(now)
            self._kept[(new, fid)] = kept
        if old in self._rtt:
            self._rtt[new] = self._rtt.pop(old)
            self._rttvar[new] = self._rttvar.pop(old)

    def resumed(self, down: float, now: float) -> None:
        """The line was gone for ``down`` seconds: every frame kept waits that much longer for
        its acknowledgement, and is probed now (what was on the way when the line went is lost)."""
        for kept in self._kept.values():
            if kept.last_sent is not None:
                kept.last_sent += down
                kept.probe_at = now
                kept.probes = 0

    def probes(self, now: float) -> list[tuple[Any, Any, bytes]]:
        """(owner, destination, fragment) for each frame whose ACK is overdue: its last
        fragment again, so the receiver learns what it lacks. Frames past the deadline go.
        Looks at every frame kept only when :attr:`soonest` is due."""
        if self.soonest is None or now < self.soonest:
            return []
        out = []
        soonest = None
        for key, kept in list(self._kept.items()):
            if kept.last_sent is None:
                continue  # still going out: sent() starts its timers
            # the deadline runs from when its last fragment left: a frame still going out (a
            # large one on a slow link) is kept
            ends = kept.last_sent + self.deadline
            if now >= ends:
                self._forget(key)
                continue
            if kept.probe_at is not None and now >= kept.probe_at:
                last = len(kept.packets) - 1
                if kept.sends[last] >= MAX_SENDS or (kept.probes >= VOID_PROBES
                                                     and key[0] not in self._answered):
                    kept.probe_at = None  # (no one there has ever answered: not into the void)
                else:
                    kept.sends[last] += 1
                    kept.probes += 1
                    kept.probe_at = now + self._pto(key[0]) * 2 ** kept.probes
                    out.append((kept.owner, key[0], kept.packets[last]))
            at = ends if kept.probe_at is None else min(kept.probe_at, ends)
            soonest = at if soonest is None else min(soonest, at)
        self.soonest = soonest
        return out

    def next_probe(self) -> float | None:
        """When :meth:`probes` may have something to do next (None: nothing kept is sent)."""
        return self.soonest

    def _forget(self, key: tuple[Any, int]) -> _Kept:
        kept = self._kept.pop(key)
        self._bytes -= sum(map(len, kept.packets))
        return kept
