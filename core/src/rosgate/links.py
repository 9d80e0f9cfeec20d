"""Links: the core's side of a transport. Framing, fragmentation and threads live here, so a
transport plugin only opens sockets.

* :class:`DatagramLink` — one bound endpoint; sends whole frames, fragments, FEC fragments or
  fragments it can send again (``recovery``), reassembles, and hands every frame to
  ``on_frame``. A transport with small frames (``max_frame`` below ``framing.COMPACT_BELOW``,
  such as CAN) gets the compact fragment scheme instead. In bare mode (``framing: none``) it
  hands over the datagram untouched.
* :class:`StreamLink` — one connection; frames carry a length prefix, long ones go in chunks.

Both send through a :class:`~rosgate.scheduler.Scheduler` — the one place a link's frames wait:
per-topic queues in priority classes, latest-only replacement, a bandwidth budget per peer
(``bridge.links``) — drained by a send thread of the link's own, so sending never blocks the
caller (a ROS executor). A frame that fits one packet goes out on the caller's thread when
nothing waits and the budget allows: no thread hand-off for a quiet link.
* :class:`LinkSlot` — a place for a stream link that comes and goes (reconnects). While it is
  empty, frames of reliable senders wait in a bounded queue and leave in order when a connection
  is attached; frames of other senders are dropped.
* :class:`Connector` — keeps a :class:`LinkSlot` filled: connects, and reconnects after every loss.
* :class:`Acceptor` — accepts stream connections and hands each to ``on_connection``.

Who sent a frame travels with it: every ``send`` takes the :class:`Sender` (a route, or the
control channel) so a frame dropped later — a queue that overflows, a connection that breaks
with frames still queued — is counted against it, without a lookup. Losses on the receiving
side (a fragment that never came) are reported with the topic id the fragments carried.

Every receive loop catches what a peer's bytes can cause and counts it; a link never dies of
input. :class:`Lifetime` is what a running bridge closes when it stops.
"""

from __future__ import annotations

import itertools
import logging
import random
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any, Callable, Protocol

from .config import LinkConfig
from .errors import LinkError
from .scheduler import Due, Outgoing, Scheduler
from .transport import (Address, DatagramEndpoint, StreamConnection, StreamListener,
                        Transport)
from .wire import envelope, framing, recovery

log = logging.getLogger("rosgate")

FrameHandler = Callable[[bytes, "Link", Address], None]
#: a loss on the receiving side: (topic id when known, reason)
LostHandler = Callable[[int | None, str], None]
#: a frame that arrived whole only thanks to its recovery (FEC repair, retransmission)
RecoveredHandler = Callable[[int], None]

POLL = 0.2  # seconds a receive waits before checking whether the link is closing
CONNECT_TIMEOUT = 5.0


class Sender(Protocol):
    """What sends a frame: a route, or a role's control channel.

    Links read these too, each optional (a sender without it gets the default):
    ``priority`` (0 control .. 7 background, default 5, data), ``latest_only`` (False),
    ``recovery`` ("none", "fec", "retransmit") and ``recovery_overhead`` (0.1), ``bare`` (its
    frames are whole datagrams, never cut: ``framing: none``), and ``on_wire(size, again)``,
    told of every packet put on the link for it (``again``: a retransmission).
    """

    @property
    def topic_id(self) -> int:
        """The id fragments of its frames carry (so a receiver counts a lost one against it)."""

    @property
    def reliable(self) -> bool:
        """Its frames wait in a :class:`LinkSlot` while the link is down (reliable QoS)."""

    def drop(self, reason: str, detail: str = "") -> None:
        """Count one of its frames as dropped on the way out."""


class Link:
    """What a route sends through and what frames are reported from."""

    name: str
    closed: threading.Event
    #: datagram links need a destination for every send; stream links are connected
    datagram: bool = False

    def send(self, frame: bytes, sender: Sender, to: Address | None = None) -> bool:
        """Hand ``frame`` to the link. False when it was dropped at once (counted against
        ``sender``); True when it was sent or queued — a queued frame that is lost later is
        counted against ``sender`` then."""
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError


class Lifetime:
    """What a running bridge closes when it stops, in reverse opening order, and the event that
    says it is stopping. Links that end by themselves (a connection the peer closed) are
    forgotten, so they are not held until the end."""

    def __init__(self) -> None:
        self.stopping = threading.Event()
        self._items: dict[int, Any] = {}
        self._lock = threading.Lock()

    def closing(self, item: Any) -> Any:
        with self._lock:
            self._items[id(item)] = item
        return item

    def forget(self, item: Any) -> None:
        with self._lock:
            self._items.pop(id(item), None)

    def close_all(self) -> None:
        self.stopping.set()
        with self._lock:
            items = list(self._items.values())
            self._items.clear()
        for item in reversed(items):
            item.close()


class _Sending:
    """What both kinds of link share on the way out: the scheduler, its lock, and the send
    thread's bookkeeping. ``_send_due`` is the kind's own."""

    name: str
    closed: threading.Event
    scheduler: Scheduler

    def _init_sending(self, budget: LinkConfig | None, overhead: int, packet: int,
                      frames: int, bytes_: int) -> None:
        self.budget = budget
        self.scheduler = Scheduler(
            bandwidth=budget.bandwidth if budget else None, overhead=overhead,
            max_delay=budget.max_delay if budget else 1.0, frames=frames, bytes=bytes_,
            packet=packet)
        self._lock = threading.Lock()
        self._wake = threading.Condition(self._lock)
        self._busy = False  # a thread is sending (inline or the send thread): one at a time

    def queue_depth(self, sender: Any) -> int:
        """Messages of ``sender`` waiting or being sent."""
        with self._lock:
            return self.scheduler.depth(sender)

    def queued(self) -> int:
        """Messages waiting (not started), all senders."""
        with self._lock:
            return self.scheduler.waiting

    def forget(self, sender: Any) -> None:
        """A sender that is gone: drop what it queued, silently."""
        with self._lock:
            self.scheduler.forget(sender)

    def _put(self, message: Outgoing, inline: bytes | None = None) -> bool:
        """Queue ``message`` — or, when ``inline`` (its one packet) may leave at once, send it
        here. False when it was dropped (counted)."""
        with self._lock:
            if self.closed.is_set():
                queued, go = False, False
            elif (inline is not None and not self._busy
                  and self.scheduler.may_send_now(message.to, len(inline))):
                self._busy, queued, go = True, True, True
            else:
                go = False
                queued = self.scheduler.put(message)
                if queued:
                    self._wake.notify()
        self._count_drops()
        if self.closed.is_set() and not queued:
            message.sender.drop("link_down", f"{self.name} is closed")
            return False
        if not go:
            return queued
        try:
            assert inline is not None
            return self._send_due(Due(inline, message.to, message.sender, message))
        finally:
            with self._lock:
                self._busy = False
                if not self.scheduler.idle:
                    self._wake.notify()

    def _count_drops(self) -> None:
        """Count what the scheduler dropped (outside the lock: counting may log)."""
        dropped = self.scheduler.dropped
        while dropped:
            sender, reason, detail = dropped.pop(0)
            sender.drop(reason, f"{self.name}: {detail}")

    def _next_timer(self) -> float | None:
        """When the send thread must wake with nothing queued (a retransmission probe)."""
        return None

    def _timers(self, now: float) -> None:
        """The kind's timers, under the lock."""

    def _send_loop(self) -> None:
        wake, closed, scheduler = self._wake, self.closed, self.scheduler
        while True:
            with wake:
                while True:
                    if closed.is_set():
                        return
                    now = time.monotonic()
                    self._timers(now)
                    due = None if self._busy else scheduler.next(now)
                    if isinstance(due, Due):
                        self._busy = True
                        break
                    until = [t for t in (due, self._next_timer()) if t is not None]
                    wake.wait(max(0.0, min(until) - now) if until else None)
            self._count_drops()
            try:
                self._send_due(due)
            except Exception:  # a bug; the link must keep sending
                log.exception("%s: error while sending (a bug: please report it)", self.name)
            finally:
                with wake:
                    self._busy = False

    def _send_due(self, due: Due) -> bool:
        raise NotImplementedError


def _on_wire(sender: Any, size: int, again: bool) -> None:
    counted = getattr(sender, "on_wire", None)
    if counted is not None:
        counted(size, again)


class DatagramLink(_Sending, Link):
    """A bound datagram endpoint. Frames out: whole when they fit ``max_frame``, else
    fragments; a topic with ``recovery: fec`` always as FEC fragments (repair included), one
    with ``recovery: retransmit`` always as fragments a receiver can ask for again (kept until
    acknowledged); compact pieces on links of small frames; a bare sender's frames whole,
    whatever their size. Datagrams in: fragments of every kind reassembled, NACKs and ACKs
    answered, each frame to ``on_frame``."""

    datagram = True

    def __init__(self, transport: Transport, endpoint: DatagramEndpoint, name: str,
                 on_frame: FrameHandler, on_lost: LostHandler, bare: bool = False,
                 max_message: int = framing.DEFAULT_MAX_MESSAGE,
                 budget: LinkConfig | None = None,
                 on_recovered: RecoveredHandler | None = None,
                 queue_frames: int = 10_000, queue_bytes: int = 64 * 1024 * 1024):
        self.transport = transport
        self.endpoint = endpoint
        self.name = name
        self.bare = bare
        self.max_frame = transport.max_frame
        self.on_frame = on_frame
        self.on_lost = on_lost
        self.on_recovered = on_recovered or (lambda topic_id: None)
        self.max_message = max_message
        self.closed = threading.Event()
        # small frames cannot spare 14 bytes of fragment header: every frame goes as compact pieces
        self.compact = not bare and self.max_frame < framing.COMPACT_BELOW
        self.reassembler: framing.Reassembler | framing.CompactReassembler
        if self.compact:
            self.reassembler = framing.CompactReassembler(on_lost, envelope.topic_of,
                                                          max_message=max_message)
        else:
            self.reassembler = framing.Reassembler(on_lost, max_message=max_message)
        self._fec: recovery.FecReassembler | None = None        # made with the first of each
        self._repeat: recovery.RepeatReassembler | None = None
        self.store = recovery.RetransmitStore()  # what this side may be asked to send again
        self._frame_ids = itertools.count(1)
        self._counters: dict[Address, int] = {}  # compact: the next piece's counter per destination
        self._init_sending(budget, getattr(transport, "packet_overhead", 0), self.max_frame,
                           queue_frames, queue_bytes)
        self._threads = [
            threading.Thread(target=self._receive_loop, name=f"rx-{name}", daemon=True),
            threading.Thread(target=self._send_loop, name=f"tx-{name}", daemon=True),
        ]
        for thread in self._threads:
            thread.start()

    # -- out -----------------------------------------------------------------------------------
    def send(self, frame: bytes, sender: Sender, to: Address | None = None) -> bool:
        assert to is not None, "a datagram link needs a destination"
        whole = getattr(sender, "bare", False) or self.bare
        if self.bare and len(frame) > self.max_frame:
            sender.drop("too_large_for_bare_framing",
                        f"{len(frame)} bytes, {self.name} carries at most {self.max_frame}")
            return False
        kind = getattr(sender, "recovery", "none")
        one = whole or kind == "none" and not self.compact and len(frame) <= self.max_frame
        message = Outgoing(sender, to, len(frame),
                           lambda: self._cut(frame, sender, to, whole, kind), time.monotonic())
        return self._put(message, frame if one else None)

    def _cut(self, frame: bytes, sender: Any, to: Address, whole: bool, kind: str) -> list[bytes]:
        """A frame's packets, made when it starts (on the send thread, in the order frames
        leave: compact counters and FEC coding happen here, not on the caller's thread)."""
        if whole:
            return [frame]
        if self.compact:
            counter = self._counters.get(to, 0)
            pieces = framing.compact_fragment(frame, self.max_frame, counter)
            self._counters[to] = (counter + len(pieces)) & framing.COMPACT_COUNTER
            return [b"".join(pieces)]  # one packet: a frame's pieces never interleave (no id)
        if kind == "fec":
            return recovery.fec_fragments(frame, self.max_frame, sender.topic_id,
                                          recovery.frame_id(),
                                          getattr(sender, "recovery_overhead", 0.1))
        if kind == "retransmit":
            fid = recovery.frame_id()
            packets = recovery.repeat_fragments(frame, self.max_frame, sender.topic_id, fid)
            self.store.keep(to, fid, packets, sender, time.monotonic())
            self._kept = (to, fid)  # told when its last packet has left (see _send_due)
            return packets
        return framing.fragment(frame, self.max_frame, sender.topic_id, next(self._frame_ids))

    def _send_due(self, due: Due) -> bool:
        packet, to, sender = due.packet, due.to, due.sender
        try:
            if self.compact and not getattr(sender, "bare", False):
                pieces = [packet[i:i + self.max_frame]
                          for i in range(0, len(packet), self.max_frame)]
                for piece in pieces:
                    self.endpoint.send(piece, to)
            else:
                self.endpoint.send(packet, to)
        except OSError as exc:
            sender.drop("send_error", f"to {to} on {self.name}: {exc}")
            return False
        _on_wire(sender, len(packet), due.again)
        if due.ends is not None and packet[:2] == recovery.REPEAT_MAGIC:
            fid = int.from_bytes(packet[10:14], "big")  # RS: magic, index, count, topic, frame
            with self._lock:
                self.store.sent(to, fid, time.monotonic())
        return True

    def _timers(self, now: float) -> None:
        for owner, to, packet in self.store.probes(now):
            self.scheduler.repair(owner, to, [packet])

    def _next_timer(self) -> float | None:
        return self.store.next_probe()
    # -- in ------------------------------------------------------------------------------------
    def _receive_loop(self) -> None:
        while not self.closed.is_set():
            timeout = POLL
            repeat = self._repeat
            if repeat is not None:
                soon = repeat.next_poll()
                if soon is not None:
                    timeout = min(POLL, max(0.001, soon - time.monotonic()))
            try:
                got = self.endpoint.receive(timeout)
            except OSError:
                if self.closed.is_set():
                    return
                continue
            except Exception:  # a transport plugin's bug must not silently end the link
                log.exception("%s: the transport's receive failed (a bug in the plugin)", self.name)
                self.on_lost(None, "transport_error")
                self.closed.wait(POLL)  # do not spin on a receive that fails at once
                continue
            now = time.monotonic()
            if repeat is not None:
                repeat.poll(now)
            if got is None:
                self.reassembler.expire()
                if self._fec is not None:
                    self._fec.expire(now)
                continue
            datagram, source = got
            if self.bare:
                deliver(self, datagram, source)
                continue
            try:
                frame = self._take(datagram, source, now)
            except framing.FramingError:
                self.on_lost(None, "bad_fragment")
                continue
            if frame is not None:
                deliver(self, frame, source)

    def _take(self, datagram: bytes, source: Address, now: float) -> bytes | None:
        """A frame, when this datagram is one or completes one; the link's own datagrams
        (fragments of every kind, NACKs, ACKs) are taken care of here."""
        if self.compact:
            return self.reassembler.add(source, datagram)
        kind = datagram[:2]
        if kind == framing.FRAGMENT_MAGIC:
            return self.reassembler.add(source, datagram)
        if kind == recovery.FEC_MAGIC:
            if self._fec is None:
                self._fec = recovery.FecReassembler(self.on_lost, self.on_recovered,
                                                    max_message=self.max_message)
            return self._fec.add(source, datagram, now)
        if kind == recovery.REPEAT_MAGIC:
            if self._repeat is None:
                self._repeat = recovery.RepeatReassembler(self.on_lost, self.on_recovered,
                                                          self._answer,
                                                          max_message=self.max_message)
            return self._repeat.add(source, datagram, now)
        if kind == recovery.NACK_MAGIC:
            with self._lock:
                again = self.store.on_nack(source, datagram)
                if again is not None:
                    self.scheduler.repair(again[0], source, again[1])
                    self._wake.notify()
            return None
        if kind == recovery.ACK_MAGIC:
            with self._lock:
                self.store.on_ack(source, datagram, now)
            return None
        return datagram

    def _answer(self, datagram: bytes, to: Address) -> None:
        """A NACK or an ACK, sent at once from the receiving thread (a few bytes, counted
        against the budget); one that cannot be sent is asked again later anyway."""
        with self._lock:
            self.scheduler.charge(to, len(datagram))
        try:
            self.endpoint.send(datagram, to)
        except OSError:
            pass

    def close(self) -> None:
        with self._wake:  # once only, whichever thread gets here first
            if self.closed.is_set():
                return
            self.closed.set()
            unsent = self.scheduler.clear()
            self._wake.notify_all()
        for sender in unsent:
            sender.drop("link_down", f"{self.name} closed with the frame still queued")
        self.endpoint.close()
        for thread in self._threads:
            if thread is not threading.current_thread() and thread.ident is not None:
                thread.join(timeout=2)


WRITE = 64 * 1024  # bytes a stream link's writer gathers into one write, at most


class StreamLink(_Sending, Link):
    """One stream connection, framed with length prefixes; frames longer than
    :data:`rosgate.wire.framing.CHUNK` go in chunks, and the writer takes at most
    :data:`WRITE` bytes at a time from the scheduler, so a frame of a higher class (a Twist
    behind a camera's backlog) waits for one write, not for the whole backlog. (The kernel's
    send buffer still holds what was written: a budget below the link's rate keeps it short.)"""

    def __init__(self, connection: StreamConnection, name: str, peer: Address,
                 on_frame: FrameHandler, on_lost: LostHandler,
                 on_close: Callable[[StreamLink], None] | None = None,
                 queue_frames: int = 10_000, queue_bytes: int = 64 * 1024 * 1024,
                 max_message: int = framing.DEFAULT_MAX_MESSAGE,
                 budget: LinkConfig | None = None):
        self.connection = connection
        self.name = name
        self.peer = peer
        self.on_frame = on_frame
        self.on_lost = on_lost
        self.on_close = on_close
        self.closed = threading.Event()
        # for liveness: the main line's roles set it on every control message (a heartbeat), not
        # on bytes, so a stream that lost its frame boundaries does not look alive
        self.last_heard = time.monotonic()
        self.why = ""  # why the connection ended, once it has
        self.queue_frames = queue_frames
        self.queue_bytes = queue_bytes
        self._messages = itertools.count(1)  # numbers of chunked frames
        self._init_sending(budget, 0, framing.CHUNK + framing.CHUNK_HEAD.size, queue_frames,
                           queue_bytes)
        self._reader = framing.StreamReader(max_message)
        self._threads = [
            threading.Thread(target=self._receive_loop, name=f"rx-{name}", daemon=True),
            threading.Thread(target=self._send_loop, name=f"tx-{name}", daemon=True),
        ]
        for thread in self._threads:
            thread.start()

    def send(self, frame: bytes, sender: Sender, to: Address | None = None) -> bool:
        # the limits count a frame with its length prefix, as it is written
        return self._put(Outgoing(sender, None, len(frame) + framing.LENGTH.size,
                                  lambda: framing.stream_records(frame, next(self._messages)),
                                  time.monotonic()))

    def _send_loop(self) -> None:
        """Gather what the scheduler lets go, up to :data:`WRITE` bytes, into one write."""
        wake, closed, scheduler = self._wake, self.closed, self.scheduler
        while True:
            batch: list[Due] = []
            size = 0
            with wake:
                self._busy = False
                wake.notify_all()  # for drain()
                while not batch:
                    if closed.is_set():
                        return
                    due = scheduler.next()
                    while isinstance(due, Due):
                        batch.append(due)
                        size += len(due.packet)
                        if size >= WRITE:
                            break
                        due = scheduler.next()
                    if not batch:
                        wake.wait(max(0.0, due - time.monotonic())
                                  if isinstance(due, float) else None)
                self._busy = True
            self._count_drops()
            try:
                self.connection.send(b"".join(d.packet for d in batch))
            except OSError as exc:
                for due in batch:
                    if due.ends is not None:
                        due.sender.drop("link_down", f"{self.name}: send failed")
                self.fail(f"send failed: {exc}")
                return
            for due in batch:
                _on_wire(due.sender, len(due.packet), False)

    def drain(self, timeout: float) -> bool:
        """Wait until everything sent so far is written (a last word before closing)."""
        with self._wake:
            return self._wake.wait_for(
                lambda: self.scheduler.idle and not self._busy or self.closed.is_set(), timeout)

    def _receive_loop(self) -> None:
        while not self.closed.is_set():
            try:
                data = self.connection.receive(1 << 20, POLL)
            except OSError as exc:
                self.fail(f"receive failed: {exc}")
                return
            except Exception as exc:  # a transport plugin's bug: drop this connection, loudly
                log.exception("%s: the transport's receive failed (a bug in the plugin)", self.name)
                self.on_lost(None, "transport_error")
                self.fail(f"transport error: {type(exc).__name__}: {exc}")
                return
            if data is None:
                continue
            if not data:
                self.fail("closed by peer")
                return
            try:
                for frame in self._reader.feed(data):
                    deliver(self, frame, self.peer)
            except framing.FramingError as exc:
                # a corrupt length means we can no longer find frame boundaries: start afresh
                self.on_lost(None, "bad_length")
                self.fail(f"stream corrupt ({exc})")
                return

    def fail(self, why: str) -> None:
        """End the connection for a reason worth logging (lost, corrupt, silent)."""
        if self.closed.is_set():
            return
        self.why = why
        log.info("%s: connection to %s ended: %s", self.name, self.peer, why)
        self.close()

    def close(self) -> None:
        with self._wake:  # once only, whichever thread gets here first
            if self.closed.is_set():
                return
            self.closed.set()
            self._wake.notify_all()
        try:
            self.connection.close()
        except OSError:
            pass
        for thread in self._threads:
            # the receive thread may fail before the send thread has even started; an unstarted
            # thread sees `closed` when it starts and returns
            if thread is not threading.current_thread() and thread.ident is not None:
                thread.join(timeout=2)
        with self._wake:  # what never reached the connection is a drop, and counted as one
            unsent = self.scheduler.clear()
        for sender in unsent:
            sender.drop("link_down", f"{self.name} closed with the frame still queued")
        if self.on_close:
            self.on_close(self)


@dataclass(frozen=True)
class QueueLimits:
    """How much a :class:`LinkSlot` holds for reliable topics while it has no connection."""

    frames: int
    bytes: int


class LinkSlot(Link):
    """A stream link that comes and goes. A :class:`Connector` (or a server that accepted the
    peer again) :meth:`attach`-es each new connection.

    While there is no live connection, frames of :attr:`Sender.reliable` senders wait, oldest
    dropped first when the limits are reached (counted ``queue_overflow``), and are handed to the
    next connection in order, before anything sent later. Other frames are counted ``link_down``.
    Frames already handed to a connection that then fails are not taken back (there are no
    acknowledgements): a connection's loss can cost what was in flight.
    """

    def __init__(self, name: str, limits: QueueLimits):
        self.name = name
        self.limits = limits
        self.current: StreamLink | None = None
        self.closed = threading.Event()
        self._waiting: deque[tuple[bytes, Sender]] = deque()
        self._waiting_bytes = 0
        self._lock = threading.Lock()  # keeps sends and the flush of the queue in order

    def send(self, frame: bytes, sender: Sender, to: Address | None = None) -> bool:
        overflow: list[Sender] = []
        with self._lock:
            link = self.current
            if link is not None and not link.closed.is_set():
                return link.send(frame, sender)
            if self.closed.is_set() or not sender.reliable:
                refused = True
            else:
                refused = False
                self._waiting.append((frame, sender))
                self._waiting_bytes += len(frame)
                while self._waiting and (len(self._waiting) > self.limits.frames
                                         or self._waiting_bytes > self.limits.bytes):
                    old, old_sender = self._waiting.popleft()
                    self._waiting_bytes -= len(old)
                    overflow.append(old_sender)
        for old_sender in overflow:
            old_sender.drop("queue_overflow", f"{self.name} is down and its queue is full")
        if refused:
            sender.drop("link_down", f"{self.name} is down")
            return False
        return True

    def attach(self, link: StreamLink) -> None:
        """Use ``link`` from now on; what waited goes first."""
        with self._lock:
            while self._waiting:
                frame, sender = self._waiting.popleft()
                link.send(frame, sender)
            self._waiting_bytes = 0
            self.current = link

    def discard(self, reason: str) -> None:
        """Drop what waits (its topic ids mean nothing to a new session), counted by ``reason``."""
        with self._lock:
            senders = [sender for _, sender in self._waiting]
            self._waiting.clear()
            self._waiting_bytes = 0
        for sender in senders:
            sender.drop(reason)

    @property
    def waiting(self) -> int:
        return len(self._waiting)

    def forget(self, sender: Any) -> None:
        link = self.current
        if link is not None:
            link.forget(sender)

    def queue_depth(self, sender: Any) -> int:
        """Messages of ``sender`` waiting here while the link is down, or in its connection."""
        with self._lock:
            held = sum(1 for _, s in self._waiting if s is sender)
            link = self.current
        return held + (link.queue_depth(sender) if link is not None else 0)

    def close(self) -> None:
        self.closed.set()
        self.discard("link_down")
        if self.current is not None:
            self.current.close()


@dataclass(frozen=True)
class Backoff:
    """Seconds between reconnection attempts: from ``min``, doubling up to ``max``, jittered."""

    min: float
    max: float

    def delay(self, failures: int) -> float:
        return min(self.min * 2 ** (failures - 1), self.max) * random.uniform(0.5, 1.0)


class Connector:
    """Keeps a stream connection up: connects, and after every loss reconnects by itself.

    Attempts are spaced by capped exponential backoff with jitter, so a fleet of clients does
    not hammer a server that comes back. After a connection that worked is lost, the next
    attempt is immediate. ``on_connected(link)`` may refuse a connection (a failed handshake),
    which counts as a failed attempt; ``on_lost(link)`` hears of every accepted connection that
    ended.
    """

    def __init__(self, transport: Transport, address: Address, slot: LinkSlot,
                 on_frame: FrameHandler, on_frame_lost: LostHandler, life: Lifetime,
                 backoff: Backoff,
                 on_connected: Callable[[StreamLink], bool] | None = None,
                 on_lost: Callable[[StreamLink], None] | None = None,
                 secure: Callable[[StreamConnection], StreamConnection] | None = None,
                 budget: LinkConfig | None = None):
        self.transport = transport
        self.budget = budget
        self.secure = secure
        self.address = address
        self.slot = slot
        self.on_frame = on_frame
        self.on_frame_lost = on_frame_lost
        self.life = life
        self.backoff = backoff
        self.on_connected = on_connected
        self.on_lost = on_lost
        self.connected = threading.Event()
        self._last_failure = ""
        self._thread = threading.Thread(target=self._loop, name=f"connect-{slot.name}", daemon=True)
        life.closing(self)

    def start(self) -> Connector:
        self._thread.start()
        return self

    def _loop(self) -> None:
        stopping = self.life.stopping
        failures = 0
        while not stopping.is_set() and not self.slot.closed.is_set():
            link = self._connect()
            if link is None:
                failures += 1
                stopping.wait(self.backoff.delay(failures))
                continue
            failures = 0
            self._last_failure = ""
            self.slot.attach(link)
            self.connected.set()
            while not link.closed.wait(0.5):
                if stopping.is_set() or self.slot.closed.is_set():
                    break
            self.connected.clear()
            link.close()
            if self.on_lost is not None and not stopping.is_set():
                self.on_lost(link)

    def _connect(self) -> StreamLink | None:
        """One attempt: a connection its owner accepted, or None."""
        try:
            connection = self.transport.connect(self.address, CONNECT_TIMEOUT)
        except (OSError, LinkError) as exc:
            log.debug("%s: connect failed: %s", self.slot.name, exc)
            return None
        if self.secure is not None:
            try:
                connection = self.secure(connection)
            except LinkError as exc:
                connection.close()
                self.failed(exc)
                return None
        link = StreamLink(connection, self.slot.name, self.address, self.on_frame,
                          self.on_frame_lost, on_close=self.life.forget, budget=self.budget)
        if self.on_connected is not None and not self.on_connected(link):
            link.close()
            return None
        return link

    def failed(self, exc: LinkError) -> None:
        """A connection that opened but was refused (its handshake failed): said once, until a
        connection works again."""
        if str(exc) != self._last_failure:
            self._last_failure = str(exc)
            log.warning("%s: %s", self.slot.name, exc)

    def close(self) -> None:
        self.slot.close()
        if self._thread.is_alive() and threading.current_thread() is not self._thread:
            self._thread.join(timeout=3)


class Acceptor:
    """Accepts connections on a listener until closed."""

    def __init__(self, listener: StreamListener, name: str,
                 on_connection: Callable[[StreamConnection, Address], None]):
        self.listener = listener
        self.name = name
        self.on_connection = on_connection
        self.closed = threading.Event()
        self._thread = threading.Thread(target=self._loop, name=f"accept-{name}", daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        while not self.closed.is_set():
            try:
                got = self.listener.accept(POLL)
            except OSError as exc:
                if self.closed.is_set():
                    return
                log.warning("%s: accept failed: %s", self.name, exc)
                continue
            if got is not None:
                self.on_connection(*got)

    def close(self) -> None:
        if self.closed.is_set():
            return
        self.closed.set()
        self.listener.close()
        self._thread.join(timeout=2)


def deliver(link: DatagramLink | StreamLink, frame: bytes, source: Address) -> None:
    """Hand a frame to the link's handler. A handler that raises has a bug; it is logged with its
    traceback and counted, and the link keeps receiving."""
    try:
        link.on_frame(frame, link, source)
    except Exception:
        log.exception("%s: error while handling a frame from %s (a bug: please report it)",
                      link.name, source)
        link.on_lost(None, "handler_error")
