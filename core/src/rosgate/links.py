"""Links: the core's side of a transport — a queue, threads and dispatch — so a transport
plugin only opens sockets: :class:`DatagramLink` here (with the batches it makes and splits),
:mod:`rosgate.streamlink` for stream links, and the :class:`Lifetime` that closes what a bridge
has open when it stops.

Both send through a :class:`~rosgate.scheduler.Scheduler` — the one place a link's frames wait:
per-topic queues in priority classes, latest-only replacement, late best-effort frames dropped,
a bandwidth budget per peer (``bridge.links``) — drained by a send thread of the link's own, so
sending never blocks the caller (a ROS executor). A frame goes out on the caller's thread when
nothing waits and the budget allows — whole, or its fragments until something else waits — so a
quiet link has no thread hand-off (a late send thread must not cost a latest-only message).
Frames that wait for the same destination leave together (one datagram up to ``max_frame``,
one stream write), so a backlog costs few system calls.

Who sent a frame travels with it: every ``send`` takes the :class:`Sender` (a route, or the
control channel) so a frame dropped later — a queue that overflows, a connection that breaks
with frames still queued — is counted against it, without a lookup; how to carry it is the
sender's :class:`~rosgate.spec.Delivery`, read, never guessed. What a transport can do beyond
``send`` (scatter-gather, several datagrams per call, receiving in place) is looked up once,
when the link is made. Losses on the receiving side (a fragment that never came) are reported
with the topic id the fragments carried. Who a link takes frames from is
:mod:`rosgate.admission`'s (:class:`~rosgate.admission.Sources`).

Every receive loop catches what a peer's bytes can cause and counts it; a link never dies of
input, and an unexpected error's traceback is logged once per reason per minute
(:data:`rosgate.warn.BUGS`). """

from __future__ import annotations

import logging
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol, cast

from .admission import Sources
from .config import MAX_DELAY_DEFAULT, LinkConfig
from .drops import Drop, Reason
from .errors import LinkError
from .packetizer import Packet, Packetizer, own_packetizer
from .plugins import Plugins, distribution_hint, installed
from .scheduler import Due, Outgoing, Scheduler
from .spec import Delivery
from .transport import (
    Address,
    DatagramEndpoint,
    DatagramTransport,
)
from .warn import BUGS
from .wire import envelope, framing

log = logging.getLogger("rosgate")

FrameHandler = Callable[[bytes, "Link", Address], None]
#: a loss on the receiving side: (topic id when known, reason)
LostHandler = Callable[[int | None, Reason], None]
#: a frame that arrived whole only thanks to its recovery (FEC repair, retransmission)
RecoveredHandler = Callable[[int], None]

POLL = 0.2  # seconds a receive waits before checking whether the link is closing


class Sender(Protocol):
    """What sends a frame: a route, a call, or a role's control channel."""

    @property
    def delivery(self) -> Delivery:
        """How the link carries its frames (read on every send: set once, never changed)."""

    @property
    def topic_id(self) -> int:
        """The id fragments of its frames carry (so a receiver counts a lost one against it)."""

    def drop(self, reason: Reason, detail: str = "") -> None:
        """Count one of its frames as dropped on the way out."""

    def on_wire(self, size: int, again: bool) -> None:
        """A packet of ``size`` bytes left on the link for it (``again``: a retransmission)."""


class Link:
    """What a route sends through and what frames are reported from."""

    name: str
    closed: threading.Event
    counters: LinkCounters
    #: datagram links need a destination for every send; stream links are connected
    datagram: bool = False
    #: while a frame is handed to its handler: when the datagram that carried it arrived (ns,
    #: the clock of time.time_ns, as the transport's receive_into says), or 0: unknown
    arrived: int = 0

    # a link implements send or send_all (or both): each defaults to the other

    def send(self, frame: bytes, sender: Sender, to: Address | None = None) -> bool:
        """Hand ``frame`` to the link. False when it was dropped at once (counted against
        ``sender``); True when it was sent or queued — a queued frame that is lost later is
        counted against ``sender`` then."""
        return self.send_all([frame], sender, to) == 1

    def send_all(self, frames: list[bytes], sender: Sender, to: Address | None = None) -> int:
        """Hand several frames of one sender to the link at once (they may share a datagram or a
        write); how many were sent or queued, as :meth:`send` says for one."""
        return sum(self.send(frame, sender, to) for frame in frames)

    def queue_depth(self, sender: Sender) -> int:
        """Messages of ``sender`` waiting or being sent (a link without a queue: none)."""
        return 0

    def forget(self, sender: Sender) -> None:
        """A sender that is gone: drop what it queued, silently."""

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

    def links(self) -> list[Link]:
        """The links open now that count what they carry."""
        with self._lock:
            return [item for item in self._items.values()
                    if isinstance(item, Link)]

    def close_all(self) -> None:
        self.stopping.set()
        with self._lock:
            items = list(self._items.values())
            self._items.clear()
        for item in reversed(items):
            item.close()


@dataclass
class LinkCounters:
    """What a link carried, per direction: frames, the datagrams (or stream writes and reads)
    that carried them, and how many frames shared one with others (coalesced)."""

    frames_out: int = 0
    #: of frames_out, those sent from the caller's thread (the link was idle: no hand-off)
    inline_out: int = 0
    packets_out: int = 0
    coalesced_out: int = 0
    bytes_out: int = 0
    frames_in: int = 0
    packets_in: int = 0
    coalesced_in: int = 0
    bytes_in: int = 0

    def snapshot(self) -> dict[str, int]:
        return dict(vars(self))

    def line(self) -> str:
        return (f"out {self.frames_out} frames in {self.packets_out} packets "
                f"({self.coalesced_out} coalesced, {self.inline_out} inline, {self.bytes_out} B), "
                f"in {self.frames_in} frames in {self.packets_in} packets "
                f"({self.coalesced_in} coalesced, {self.bytes_in} B)")


class _Sending(ABC):
    """What both kinds of link share: the scheduler, its lock, the send thread's bookkeeping,
    the two threads and closing. ``_send_due`` and the loops are the kind's own."""

    on_frame: FrameHandler
    on_lost: LostHandler
    #: told once the link has closed (a stream link's owner forgets it)
    on_close: Callable[[Any], None] | None = None

    def _deliver(self, frame: bytes, source: Address) -> None:
        """Hand a frame to the handler. A handler that raises has a bug; it is counted, its
        traceback logged once per minute, and the link keeps receiving."""
        try:
            self.on_frame(frame, self, source)  # type: ignore[arg-type]  # a Link subclass's
        except Exception:
            BUGS.bug("handler_error", f"{self.name}: error while handling a frame from {source} "
                                      "(a bug: please report it)")
            self.on_lost(None, Drop.HANDLER_ERROR)

    def _init_sending(self, name: str, budget: LinkConfig | None, overhead: int, packet: int,
                      frames: int, bytes_: int) -> None:
        self.name = name
        self.closed = threading.Event()
        self.counters = LinkCounters()
        self.scheduler = Scheduler(
            bandwidth=budget.bandwidth if budget else None, overhead=overhead,
            max_delay=budget.max_delay if budget else MAX_DELAY_DEFAULT, frames=frames,
            bytes=bytes_, packet=packet)
        # entered as the plain lock on the way out (a Condition's own with-statement costs a
        # Python call each way, ~0.3 us); the send thread waits on the condition
        self._lock = threading.Lock()
        self._wake = threading.Condition(self._lock)
        self._busy = False  # a thread is sending (inline or the send thread): one at a time
        #: callers waiting for the turn (see DatagramLink._await_turn), told when it is free
        self._turn = threading.Condition(self._lock)
        self._turn_waiters = 0
        self._stuck = False  # the last wait for the turn timed out: the link is the bottleneck
        #: what a stream's inline write left unwritten: it goes before anything else
        self._rest: Due | None = None

    def _start(self) -> None:
        """Start the receive and the send thread: the last step of making a link."""
        self._threads = [
            threading.Thread(target=self._receive_loop, name=f"rx-{self.name}", daemon=True),
            threading.Thread(target=self._send_loop, name=f"tx-{self.name}", daemon=True),
        ]
        for thread in self._threads:
            thread.start()

    def close(self) -> None:
        with self._wake:  # once only, whichever thread gets here first
            if self.closed.is_set():
                return
            self.closed.set()
            self._wake.notify_all()
        self._close_io()
        for thread in self._threads:
            # the receive thread may fail before the send thread has even started; an unstarted
            # thread sees `closed` when it starts and returns
            if thread is not threading.current_thread() and thread.ident is not None:
                thread.join(timeout=2)
        with self._wake:  # what never reached the transport is a drop, and counted as one
            unsent = self.scheduler.clear()
            if self._rest is not None:
                unsent.append(self._rest.sender)
                self._rest = None
        for sender in unsent:
            sender.drop(Drop.LINK_DOWN, f"{self.name} closed with the frame still queued")
        if self.on_close is not None:
            self.on_close(self)

    @abstractmethod
    def _close_io(self) -> None:
        """Close the endpoint or the connection (the threads see ``closed`` and end)."""

    @abstractmethod
    def _receive_loop(self) -> None: ...

    @abstractmethod
    def _send_loop(self) -> None: ...

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

    def _claim(self, to: Any, size: int) -> bool:
        """Under the lock: whether the calling thread may send ``size`` bytes to ``to`` itself,
        now — open, nobody sending, nothing left over from a write, nothing queued, the budget
        has the tokens. When True it is this thread's turn until :meth:`_release`."""
        if (self.closed.is_set() or self._busy or self._rest is not None
                or not self.scheduler.may_send_now(to, size)):
            return False
        self._busy = True
        self._stuck = False
        return True

    def _release(self) -> None:
        """The caller's turn is over: the send thread takes what waits."""
        with self._lock:
            self._busy = False
            if not self.scheduler.idle or self._rest is not None:
                self._wake.notify()
            if self._turn_waiters:
                self._turn.notify_all()

    def _send_now(self, packet: bytes, sender: Any, to: Any) -> bool | None:
        """Send ``packet`` (a whole frame) from the caller's thread when it may leave at once
        (see :meth:`_claim`): whether it went (False: dropped, counted); None when it must be
        queued instead. The common case of a quiet link: no message object, no hand-off."""
        with self._lock:
            if not self._claim(to, len(packet)):
                return None
        try:
            sent = self._send_due(Due(packet, to, sender, SENT_INLINE))
            self.counters.inline_out += sent
            return sent
        finally:
            self._release()

    def _put(self, message: Outgoing) -> bool:
        """Queue ``message`` for the send thread. False when it was dropped (counted)."""
        with self._lock:
            queued = not self.closed.is_set() and self.scheduler.put(message)
            if queued and not self._busy:
                self._wake.notify()
        if self.scheduler.dropped:
            self._count_drops()
        if not queued and self.closed.is_set():
            message.sender.drop(Drop.LINK_DOWN, f"{self.name} is closed")
        return queued

    def _count_drops(self) -> None:
        """Count what the scheduler dropped (outside the lock: counting may log)."""
        dropped = self.scheduler.dropped
        while dropped:
            sender, reason, detail = dropped.pop(0)
            sender.drop(reason, f"{self.name}: {detail}")

    @abstractmethod
    def _send_due(self, due: Due) -> bool:
        """Send one packet from the caller's thread (its turn, see :meth:`_claim`); False when
        it was dropped (counted). Each kind of link has its own."""


class _Gather:
    """A packet as its parts — a fragment's header and a view of the frame — for scatter-gather
    sending (``send_parts``: no copy of the frame); the scheduler takes it for a packet of
    ``len()`` bytes."""

    __slots__ = ("parts", "size")

    def __init__(self, parts: tuple[bytes | memoryview, ...]):
        self.parts = list(parts)
        self.size = sum(map(len, parts))

    def __len__(self) -> int:
        return self.size


#: what a Due sent from the caller's thread ends: its one frame (see _Sending._send_now)
SENT_INLINE = Outgoing(None, None, 0, list)
#: the longest frame whose fragments leave from the caller's thread (an idle link): one
#: loopback datagram's worth, a few dozen system calls (one with segmentation offload). A
#: longer one (an image) goes to the send thread, so a ROS executor never waits on a long one.
INLINE_MAX = 64 * 1024
#: how long a caller waits for another thread's packet to leave before it queues its frame
TURN_WAIT = 0.02
#: the most fragments of one frame the send thread hands the kernel in one call
_RUN = 64


def _batchable(due: Due) -> bool:
    """A whole frame in one packet, which may share a datagram with others."""
    return due.ends is not None and due.ends.batchable and not due.again


def batch(frames: list[bytes]) -> list[bytes | memoryview]:
    """The parts of one datagram carrying ``frames``: ``"RB"``, then ``u32 length | frame`` for
    each (the records of a stream link). Its size is :func:`batch_size`."""
    parts: list[bytes | memoryview] = [framing.BATCH_MAGIC]
    pack = framing.LENGTH.pack
    for frame in frames:
        parts += (pack(len(frame)), frame)
    return parts


def batch_size(sizes: int, count: int) -> int:
    """The size of a batch of ``count`` frames of ``sizes`` bytes in all."""
    return len(framing.BATCH_MAGIC) + count * framing.LENGTH.size + sizes


class DatagramLink(_Sending, Link):
    """A bound datagram endpoint. Frames out: whole when they fit ``max_frame`` (several in one
    datagram, a batch, when they leave one after the other for one destination), else cut by
    the link's own packetizer (:func:`~rosgate.packetizer.own_packetizer`); every frame of a
    topic with ``recovery: NAME`` by that packetizer; a bare sender's (``framing: none``) whole,
    whatever its size, never batched. Datagrams in: from admitted ``sources`` only, batches
    split, every other packet to the packetizer of its magic (found in ``packetizers``, by
    default the installed plugins), each frame to ``on_frame``; on a bare link, each datagram as
    it came. When its own packetizer ``cuts_every_frame`` (on links of small frames), every frame
    out and every datagram in is that packetizer's.

    It is the :class:`~rosgate.packetizer.PacketLink` of its packetizers: one of each kind it
    meets, made on first use and kept for its life; their timers run on both of its threads."""

    datagram = True

    def __init__(self, transport: DatagramTransport, endpoint: DatagramEndpoint, name: str,
                 on_frame: FrameHandler, on_lost: LostHandler, bare: bool = False,
                 max_message: int = framing.DEFAULT_MAX_MESSAGE, sources: Sources | None = None,
                 budget: LinkConfig | None = None,
                 on_recovered: RecoveredHandler | None = None,
                 queue_frames: int = 10_000, queue_bytes: int = 64 * 1024 * 1024,
                 packetizers: Plugins | None = None):
        self.transport = transport
        #: who frames are taken from (None: anyone); others are counted ``not_allowed``
        self.sources = sources
        self.endpoint = endpoint
        self.bare = bare
        self.max_frame = transport.max_frame
        self.on_frame = on_frame
        self.on_lost = on_lost
        self.on_recovered = on_recovered or (lambda topic_id: None)
        self.max_message = max_message
        self._init_sending(name, budget, transport.packet_overhead, self.max_frame,
                           queue_frames, queue_bytes)
        self.registry = packetizers or installed()
        #: packetizers made so far, by name and by magic (None: a whole frame, the link's own)
        self._by_name: dict[str, Packetizer] = {}
        self._by_magic: dict[bytes, Packetizer | None] = {envelope.MAGIC: None}
        self._making = threading.Lock()
        self._tx_timer: float | None = None  # when the send thread runs the timers next
        #: what cuts a frame of a sender without a packetizer of its own when it does not fit
        self.own = self.packetizer("fragments" if bare else own_packetizer(self.max_frame))
        #: every frame is cut by ``own``, and every datagram in is its
        self.cuts = self.own.cuts_every_frame
        # what the endpoint can do beyond send, looked up once: scatter-gather (a packet's parts
        # without joining them; else joined here), several datagrams in one call (UDP:
        # segmentation offload)
        self._gather = hasattr(endpoint, "send_parts")
        self._send_parts: Callable[[Any, Address], None] = getattr(
            endpoint, "send_parts", lambda parts, to: endpoint.send(b"".join(parts), to))
        self._send_datagrams = getattr(endpoint, "send_datagrams", None)
        self._start()

    # -- out -----------------------------------------------------------------------------------
    def send(self, frame: bytes, sender: Sender, to: Address | None = None) -> bool:
        assert to is not None, "a datagram link needs a destination"
        size = len(frame)
        if self.bare and size > self.max_frame:
            sender.drop(Drop.TOO_LARGE_FOR_BARE_FRAMING,
                        f"{size} bytes, {self.name} carries at most {self.max_frame}")
            return False
        delivery = sender.delivery
        whole = self.bare or delivery.whole
        plain = delivery.packetizer is None and not self.cuts  # whole or fragments
        one = whole or plain and size <= self.max_frame
        inline: Callable[[bytes, Any, Address], bool | None] | None = None
        if one:
            inline = self._send_now
        elif plain and size <= INLINE_MAX:
            inline = self._send_fragments_now
        if inline is not None:
            sent = inline(frame, sender, to)
            if sent is None and self._await_turn() and self._send_waiting():
                sent = inline(frame, sender, to)  # what waited is gone: the link is idle
            if sent is not None:
                return sent
        return self._put(Outgoing(sender, to, size,
                                  lambda: self._cut(frame, sender, to, whole),
                                  time.monotonic(), batchable=one and not whole))

    def send_all(self, frames: list[bytes], sender: Sender, to: Address | None = None) -> int:
        """Frames of one sender together (a route's backlog): when the link is idle, those that
        fit share datagrams sent from here; otherwise each is queued (and coalesced again by
        the send thread)."""
        assert to is not None, "a datagram link needs a destination"
        delivery = sender.delivery
        if len(frames) < 2 or self.bare or self.cuts or delivery.whole \
                or delivery.packetizer is not None:
            return sum(self.send(frame, sender, to) for frame in frames)
        limit, sent, start = self.max_frame, 0, 0
        while start < len(frames):  # groups of consecutive frames that fit one datagram
            total, end = 0, start
            while end < len(frames) and len(frames[end]) <= limit \
                    and batch_size(total + len(frames[end]), end - start + 1) <= limit:
                total += len(frames[end])
                end += 1
            if end - start < 2:
                sent += self.send(frames[start], sender, to)
                start += 1
                continue
            group, start = frames[start:end], end
            with self._lock:
                go = self._claim(to, batch_size(total, len(group)))
            if not go:
                sent += sum(self.send(frame, sender, to) for frame in group)
                continue
            try:
                batched = self._send_batch([Due(frame, to, sender) for frame in group], to)
                self.counters.inline_out += batched
                sent += batched
            finally:
                self._release()
        return sent

    def _cut(self, frame: bytes, sender: Sender, to: Address, whole: bool) -> list[bytes]:
        """A frame's packets, made when it starts (on the send thread, in the order frames
        leave: counters and FEC coding happen here, not on the caller's thread)."""
        delivery = sender.delivery
        own = self.cuts or delivery.packetizer is None
        if whole or own and not self.cuts and len(frame) <= self.max_frame:
            return [frame]
        packetizer = self.own if own or delivery.packetizer is None \
            else self._make(delivery.packetizer)
        packets = packetizer.cut(frame, sender, to, delivery.packetizer_options)
        return [self._packet(packet) for packet in packets]

    def _packet(self, packet: Packet) -> bytes:
        if not isinstance(packet, tuple):
            return packet
        if not self._gather:
            return b"".join(packet)
        # a _Gather stands for its packet: the scheduler only takes its len()
        return cast(bytes, _Gather(packet))

    # -- packetizers ---------------------------------------------------------------------------
    def packetizer(self, name: str) -> Packetizer:
        """The link's packetizer of that name, made on first use."""
        found = self._by_name.get(name)
        if found is None:
            registration = self.registry.get("packetizer", name)
            if registration is None:
                raise LinkError(f"{self.name}: no packetizer {name!r} is installed, which a link "
                                f"of {self.max_frame}-byte packets needs",
                                f"pip install {distribution_hint('packetizer', name)}")
            found = self._make(registration.cls)
        return found

    def _make(self, cls: type[Packetizer]) -> Packetizer:
        with self._making:  # the send thread and the receive thread may both meet it first
            found = self._by_name.get(cls.name)
            if found is None:
                found = cls(self)
                for magic in cls.magic:
                    self._by_magic[magic] = found
                self._by_name[cls.name] = found
            return found

    def _receiver(self, magic: bytes) -> Packetizer | None:
        """The packetizer of packets with ``magic``; None: a whole frame. Looked up once per
        magic (the first unknown one loads every plugin, see Plugins.by_wire)."""
        registration = self.registry.by_wire("packetizer", magic)
        if registration is None:
            if len(self._by_magic) < 0x10000:  # the two bytes bound it
                self._by_magic[magic] = None
            return None
        return self._make(registration.cls)

    def lost(self, topic_id: int | None, reason: Reason) -> None:
        self.on_lost(topic_id, reason)

    def recovered(self, topic_id: int) -> None:
        self.on_recovered(topic_id)

    def repeat(self, sender: Any, to: Address, packets: list[bytes]) -> None:
        with self._lock:
            self.scheduler.repair(sender, to, packets)
            self._wake.notify()

    def answer(self, packet: bytes, to: Address) -> None:
        """A packet sent at once from the calling thread (a few bytes, counted against the
        budget); one that cannot be sent is asked again later anyway."""
        with self._lock:
            self.scheduler.charge(to, len(packet))
        try:
            self.endpoint.send(packet, to)
        except OSError:
            pass

    def _run_timers(self, now: float, sending: bool = False) -> float | None:
        """Every packetizer's timer (on the send thread: of those told of frames ``sent``); when
        the soonest wants to run again. A packetizer's bug is logged, and the link keeps
        going."""
        soonest = None
        for packetizer in list(self._by_name.values()):
            if sending and not _sends(packetizer):
                continue
            try:
                due = packetizer.timer(now)
            except Exception:
                BUGS.bug("packetizer_error", f"{self.name}: packetizer {packetizer.name}'s timer "
                                             "failed (a bug in the plugin)")
                continue
            if due is not None and (soonest is None or due < soonest):
                soonest = due
        return soonest

    def _await_turn(self) -> bool:
        """Wait up to :data:`TURN_WAIT` while another thread sends a packet; whether the turn
        is free. A packet takes microseconds; a thread that holds the turn longer was not
        scheduled (a busy machine) — not a reason to queue a frame where a latest-only one can
        be replaced — or is held by the kernel (a full send buffer: the link is the
        bottleneck). After one wait in vain the link counts as the bottleneck, and callers
        queue at once until they get a turn again."""
        with self._lock:
            if not self._busy:
                return True
            if self._stuck or self.closed.is_set():
                return False
            self._turn_waiters += 1
            try:
                free = self._turn.wait_for(lambda: not self._busy, TURN_WAIT)
            finally:
                self._turn_waiters -= 1
            self._stuck = not free
            return free

    def _send_waiting(self) -> bool:
        """Send what waits from the caller's thread (up to :data:`INLINE_MAX` bytes) when
        nobody is sending: the send thread was woken for it but has not run yet, and a frame
        queued behind it now could be replaced (latest-only) before it does. Whether nothing
        waits any more. What the budget holds back stays for the send thread."""
        scheduler = self.scheduler
        with self._lock:
            if self._busy or self.closed.is_set() or scheduler.idle:
                return False
            self._busy = True
        try:
            left = INLINE_MAX
            while left > 0:
                with self._lock:
                    due = scheduler.next()
                if scheduler.dropped:
                    self._count_drops()
                if not isinstance(due, Due):
                    break
                self._send_due(due)
                left -= len(due.packet)
            with self._lock:
                return scheduler.idle
        finally:
            self._release()

    def _send_fragments_now(self, frame: bytes, sender: Any, to: Address) -> bool | None:
        """A frame longer than ``max_frame``, cut and sent from the caller's thread when the link
        is idle, as :meth:`_send_now` sends a whole one; None when it must be queued instead.

        Why not hand it to the send thread: waking it costs a thread switch that a busy
        interpreter may put off for milliseconds, long enough for the topic's next message to
        replace a latest-only one (``superseded``) on an idle link. The send thread still gets
        the rest of the frame as soon as anything else waits or the budget runs short
        (:meth:`Scheduler.resume`), so a long frame takes turns with others as before."""
        with self._lock:
            if not self._claim(to, self.max_frame):  # the first fragment's tokens
                return None
        scheduler, lock, counters = self.scheduler, self._lock, self.counters
        try:
            packets = self._cut(frame, sender, to, False)
            # a turn: the packets handed to the kernel at once, all in one call when the
            # endpoint can; else one, then a look at what else waits (and at the budget, whose
            # bucket is a few packets deep)
            turn = len(packets) if scheduler.rate is None and self._send_datagrams else 1
            start = 0
            while start < len(packets):
                if start:
                    with lock:  # anything else waiting, or a budget short: the send thread's
                        go = scheduler.may_send_now(to, len(packets[start]))
                        if not go:
                            scheduler.resume(Outgoing(sender, to, sum(map(len, packets[start:])),
                                                      list, time.monotonic()),
                                             packets[start:], time.monotonic())
                    if not go:
                        return True
                end = min(start + turn, len(packets))
                if not self._send_run(packets[start:end], sender, to, end == len(packets)):
                    return False
                start = end
            counters.inline_out += 1
            return True
        finally:
            self._release()

    def _send_run(self, packets: list[bytes], sender: Any, to: Address, last: bool) -> bool:
        """Packets of one frame in a row (from the caller's thread, or the send thread's run),
        in one call where the endpoint takes several datagrams; ``last``: they end the frame.
        False when they could not be sent (counted: the frame is lost)."""
        try:
            if len(packets) > 1 and self._send_datagrams is not None:
                self._send_datagrams([cast(_Gather, p).parts if type(p) is _Gather else [p]
                                      for p in packets], to)
            else:
                for packet in packets:
                    if type(packet) is _Gather:
                        self._send_parts(cast(_Gather, packet).parts, to)
                    else:
                        self.endpoint.send(packet, to)
        except OSError as exc:
            sender.drop(Drop.LINK_DOWN if self.closed.is_set() else Drop.SEND_ERROR,
                        f"to {to} on {self.name}: {exc}")
            return False
        counters = self.counters
        counters.packets_out += len(packets)
        counters.frames_out += last
        for packet in packets:
            counters.bytes_out += len(packet)
            sender.on_wire(len(packet), False)
        return True

    def _send_due(self, due: Due) -> bool:
        packet, to, sender = due.packet, due.to, due.sender
        count = 1
        try:
            if type(packet) is _Gather:
                self._send_parts(cast(_Gather, packet).parts, to)
            elif self.cuts and not sender.delivery.whole:
                step = self.max_frame
                count = 0
                for i in range(0, len(packet), step):
                    self.endpoint.send(packet[i:i + step], to)
                    count += 1
            else:
                self.endpoint.send(packet, to)
        except OSError as exc:
            # a message cut short by close() was counted there (link_down), unless this was
            # its last packet
            if due.ends is not None or not self.closed.is_set():
                sender.drop(Drop.SEND_ERROR, f"to {to} on {self.name}: {exc}")
            return False
        counters = self.counters
        counters.packets_out += count
        counters.bytes_out += len(packet)
        if due.ends is not None:
            counters.frames_out += 1
        sender.on_wire(len(packet), due.again)
        if due.ends is not None and due.ends is not SENT_INLINE and type(packet) is bytes:
            packetizer = self._by_magic.get(packet[:2])
            if packetizer is not None and _sends(packetizer):  # the last packet of a frame
                now = time.monotonic()
                packetizer.sent(packet, to, now)
                due_at = packetizer.timer(now)
                if due_at is not None and (self._tx_timer is None or due_at < self._tx_timer):
                    self._tx_timer = due_at
        return True

    def _send_batch(self, dues: list[Due], to: Address) -> int:
        """Whole frames in one datagram; how many were sent (a failure is counted for each)."""
        frames = [due.packet for due in dues]
        try:
            self._send_parts(batch(frames), to)
        except OSError as exc:
            for due in dues:
                due.sender.drop(Drop.SEND_ERROR, f"to {to} on {self.name}: {exc}")
            return 0
        counters = self.counters
        counters.frames_out += len(frames)
        counters.packets_out += 1
        counters.coalesced_out += len(frames)
        counters.bytes_out += batch_size(sum(map(len, frames)), len(frames))
        for due in dues:
            due.sender.on_wire(len(due.packet) + framing.LENGTH.size, False)
        return len(frames)

    def _send_loop(self) -> None:
        """Send what the scheduler lets go; whole frames that come one after the other for the
        same destination share a datagram (the one that does not fit is sent next)."""
        wake, closed, scheduler = self._wake, self.closed, self.scheduler
        limit, coalesce = self.max_frame, not self.bare
        run = self._send_datagrams is not None  # fragments in runs (see _send_run)
        carry: Due | None = None  # taken from the scheduler, not sent yet: it goes next
        while True:
            with wake:
                while True:
                    if closed.is_set():
                        return
                    now = time.monotonic()
                    timer = self._tx_timer
                    if timer is not None and now >= timer:
                        due = None
                        break
                    if carry is not None:
                        due, carry = carry, None
                        break
                    got = None if self._busy else scheduler.next(now)
                    if isinstance(got, Due):
                        due = got
                        break
                    if scheduler.dropped:  # counted (outside the lock) before any wait
                        due = None
                        break
                    until = [t for t in (got, timer) if t is not None]
                    wake.wait(max(0.0, min(until) - now) if until else None)
                if due is None:
                    self._tx_timer = None
                else:
                    self._busy = True
                    batch = [due]
                    if coalesce and _batchable(due):
                        total = len(due.packet)
                        while True:
                            more = scheduler.next(now)
                            if not isinstance(more, Due):
                                break
                            if (_batchable(more) and more.to == due.to and batch_size(
                                    total + len(more.packet), len(batch) + 1) <= limit):
                                batch.append(more)
                                total += len(more.packet)
                            else:
                                carry = more
                                break
                    elif run and type(due.packet) is _Gather and due.ends is None:
                        # the next fragments of the same frame, while the scheduler lets them go
                        # one after the other: one system call (segmentation offload)
                        while len(batch) < _RUN:
                            more = scheduler.next(now)
                            if not isinstance(more, Due):
                                break
                            if (type(more.packet) is _Gather and more.sender is due.sender
                                    and more.to == due.to and not more.again):
                                batch.append(more)
                                if more.ends is not None:
                                    break  # the frame's last
                            else:
                                carry = more
                                break
            if scheduler.dropped:
                self._count_drops()
            if due is None:  # the packetizers' timers, outside the lock: they may queue repairs
                self._tx_timer = self._run_timers(now, sending=True)
                continue
            try:
                if len(batch) == 1:
                    self._send_due(due)
                elif type(due.packet) is _Gather:
                    self._send_run([d.packet for d in batch], due.sender, due.to,
                                   batch[-1].ends is not None)
                else:
                    self._send_batch(batch, due.to)
            except Exception:  # a bug; the link must keep sending
                BUGS.bug("send_error", f"{self.name}: error while sending (a bug: please "
                                       "report it)")
            finally:
                with wake:
                    self._busy = carry is not None  # a carried frame keeps its turn
                    if self._turn_waiters and not self._busy:
                        self._turn.notify_all()

    # -- in ------------------------------------------------------------------------------------
    def _receive_loop(self) -> None:
        receive_into = getattr(self.endpoint, "receive_into", None)
        if receive_into is None:
            receive: Callable[[float], tuple[bytes | memoryview, Address] | None] = \
                lambda timeout: self.endpoint.receive(timeout)
        else:
            # one buffer for every datagram: longer than any frame this link accepts, so a
            # datagram that fills it is one too long
            buffer = memoryview(bytearray(max(self.max_frame, 65_535) + 1))

            def receive(timeout: float) -> tuple[bytes | memoryview, Address] | None:
                got = receive_into(buffer, timeout)
                if got is None:
                    return None
                size, source, self.arrived = got
                if size >= len(buffer):
                    self.on_lost(None, Drop.OVERSIZED_DATAGRAM)
                    return None
                return buffer[:size], source

        closed = self.closed
        timer: float | None = None  # when the packetizers' timers run next on this thread
        while not closed.is_set():
            timeout = POLL if timer is None else min(POLL, max(0.001, timer - time.monotonic()))
            try:
                got = receive(timeout)
            except OSError:
                if closed.is_set():
                    return
                continue
            except Exception:  # a transport plugin's bug must not silently end the link
                BUGS.bug("transport_error", f"{self.name}: the transport's receive failed "
                                            "(a bug in the plugin)")
                self.on_lost(None, Drop.TRANSPORT_ERROR)
                closed.wait(POLL)  # do not spin on a receive that fails at once
                continue
            now = time.monotonic()
            if got is None or timer is not None and now >= timer:
                timer = self._run_timers(now)
            if got is None:
                continue
            fed = self._datagram(*got, now)
            if fed is not None:  # what it was given may have moved its timer
                due = fed.timer(now)
                if due is not None and (timer is None or due < timer):
                    timer = due

    def _datagram(self, datagram: bytes | memoryview, source: Address,
                  now: float = 0.0) -> Packetizer | None:
        """One datagram as it came (a view of the receive buffer, valid until the next one); the
        packetizer it was fed to, if any."""
        if self.sources is not None and not self.sources.admits(source, datagram):
            self.on_lost(None, Drop.NOT_ALLOWED)
            return None
        counters = self.counters
        counters.packets_in += 1
        counters.bytes_in += len(datagram)
        kind = datagram[1] if len(datagram) > 1 and datagram[0] == 0x52 else 0  # "R?"
        if self.bare or kind == 0x47 and not self.cuts:  # "RG": an envelope, the most common
            packetizer = None
        elif self.cuts:  # every datagram is its own packetizer's
            packetizer = self.own
        elif kind == 0x42:  # "RB": several frames (see batch), read here, not by a generator
            # (the receive thread's cost per message); a length past the end ends it, counted
            end, offset, deliver = len(datagram), _BATCH_START, self._deliver
            while offset < end:
                start = offset + _LENGTH_SIZE
                if start > end or (offset := start + _length(datagram, offset)[0]) > end:
                    self.on_lost(None, Drop.BAD_BATCH)
                    break
                counters.frames_in += 1
                counters.coalesced_in += 1
                deliver(bytes(datagram[start:offset]), source)
            return None
        else:
            magic = bytes(datagram[:2])
            packetizer = self._by_magic.get(magic, _UNKNOWN)
            if packetizer is _UNKNOWN:
                packetizer = self._receiver(magic)
        if packetizer is None:  # a whole frame
            counters.frames_in += 1
            self._deliver(datagram if type(datagram) is bytes else bytes(datagram), source)
            return None
        assert isinstance(packetizer, Packetizer)
        try:
            frame = packetizer.feed(datagram, source, now or time.monotonic())
        except framing.FramingError:
            self.on_lost(None, Drop.BAD_FRAGMENT)
            return packetizer
        except Exception:  # a packetizer must raise FramingError; anything else is its bug
            BUGS.bug("packetizer_error", f"{self.name}: packetizer {packetizer.name} failed on a "
                                         "packet (a bug in the plugin)")
            self.on_lost(None, Drop.BAD_FRAGMENT)
            return packetizer
        if frame is not None:
            counters.frames_in += 1
            # the buffer it was put together in, the handler's to keep: a route hands it to
            # rclpy without a copy (typed bytes: handlers take any bytes-like frame)
            self._deliver(frame, source)
        return packetizer

    def _close_io(self) -> None:
        self.endpoint.close()


# reading a batch (see batch)
_BATCH_START, _LENGTH_SIZE, _length = (len(framing.BATCH_MAGIC), framing.LENGTH.size,
                                       framing.LENGTH.unpack_from)

#: a magic the link has not looked up yet
_UNKNOWN: Any = object()


def _sends(packetizer: Packetizer) -> bool:
    """Whether it wants to know when its frames left (and has its timer run on the send thread
    too): it implements ``sent``."""
    return type(packetizer).sent is not Packetizer.sent
