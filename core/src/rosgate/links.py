"""Links: the core's side of a transport — a queue, threads and dispatch — so a transport
plugin only opens sockets: :class:`DatagramLink` here, :mod:`rosgate.streamlink` for streams,
and the :class:`Lifetime` that closes what a bridge has open when it stops.

Both send through a :class:`~rosgate.scheduler.Scheduler`, drained by a send thread of the
link's own so sending never blocks the caller (a ROS executor); a frame goes out on the
caller's thread when nothing waits and the budget allows (a quiet link has no thread hand-off),
and frames waiting for one destination leave together (one datagram, one stream write). Every
``send`` takes the :class:`Sender`, so a frame dropped later is counted against it. Every
receive loop counts what a peer's bytes cause and never dies of input; an unexpected error's
traceback is logged once per reason per minute (:data:`rosgate.warn.BUGS`). """

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
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
from .transport import Address, DatagramEndpoint, DatagramTransport
from .warn import BUGS
from .wire import envelope, framing

FrameHandler = Callable[[bytes, "Link", Address], None]
#: a loss on the receiving side: (topic id when known, reason)
LostHandler = Callable[[int | None, Reason], None]

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
    #: while a frame is handed to its handler: when its datagram arrived (time.time_ns), 0: unknown
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
    """What a running bridge closes when it stops, in reverse opening order (links that end by
    themselves are forgotten), and the event that says it is stopping."""

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
            return [item for item in self._items.values() if isinstance(item, Link)]

    def close_all(self) -> None:
        self.stopping.set()
        with self._lock:
            items = list(self._items.values())
            self._items.clear()
        for item in reversed(items):
            item.close()


@dataclass
class LinkCounters:
    """What a link carried, per direction: frames, the packets (datagrams, stream writes and
    reads) that carried them, and the frames that shared one with others (coalesced)."""

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


class _Sending:
    """What both kinds of link share: the scheduler, its lock, the send turn, the two threads
    and closing."""

    on_frame: FrameHandler
    on_lost: LostHandler
    # each kind's own: closing its endpoint or connection, its two threads, and sending one
    # packet in this thread's turn (False: dropped, counted)
    _close_io: Callable[[], None]
    _receive_loop: Callable[[], None]
    _send_loop: Callable[[], None]
    _send_due: Callable[[Due], bool]
    #: told once the link has closed (a stream link's owner forgets it)
    on_close: Callable[[Any], None] | None = None
    #: told as soon as it starts closing, before its threads end (a client stops sending)
    on_closing: Callable[[Any], None] | None = None

    def _deliver(self, frame: bytes, source: Address) -> None:
        """Hand a frame to the handler; one that raises has a bug: counted, and the link goes on."""
        try:
            self.on_frame(frame, self, source)  # type: ignore[arg-type]  # a Link subclass's
        except Exception:
            BUGS.bug("handler_error", f"{self.name}: error while handling a frame from {source} "
                                      "(a bug: please report it)")
            self.on_lost(None, Drop.HANDLER_ERROR)

    def _init_sending(self, name: str, budget: LinkConfig | None, overhead: int, packet: int,
                      frames: int, bytes_: int, one_line: bool = False) -> None:
        self.name = name
        self.closed = threading.Event()
        self.counters = LinkCounters()
        self.scheduler = Scheduler(
            bandwidth=budget.bandwidth if budget else None, overhead=overhead,
            max_delay=budget.max_delay if budget else MAX_DELAY_DEFAULT, frames=frames,
            bytes=bytes_, packet=packet, one_line=one_line)
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
        self._threads = [threading.Thread(target=loop, name=f"{kind}-{self.name}", daemon=True)
                         for kind, loop in (("rx", self._receive_loop), ("tx", self._send_loop))]
        for thread in self._threads:
            thread.start()

    def close(self) -> None:
        with self._wake:  # once only, whichever thread gets here first
            if self.closed.is_set():
                return
            self.closed.set()
            self._wake.notify_all()
        if self.on_closing is not None:
            self.on_closing(self)
        self._close_io()
        for thread in self._threads:
            # an unstarted thread (the receive thread failed first) sees `closed` and returns
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

    def queue_depth(self, sender: Any) -> int:
        with self._lock:
            return self.scheduler.depth(sender)

    def queued(self) -> int:
        """Messages waiting (not started), all senders."""
        with self._lock:
            return self.scheduler.waiting

    def forget(self, sender: Any) -> None:
        with self._lock:
            self.scheduler.forget(sender)

    def _claim(self, to: Any, size: int) -> bool:
        """Under the lock: whether the calling thread may send ``size`` bytes to ``to`` itself
        now (nothing sending or queued, the budget's tokens taken); then it is its turn until
        :meth:`_release`."""
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
        """A whole frame sent from the caller's thread if it may leave at once (a quiet link:
        no message object, no hand-off): whether it went; None: queue it."""
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


class _Gather:
    """A packet as its parts (a header, a view of the frame) for scatter-gather sending, no copy
    of the frame; the scheduler takes it for a packet of ``len()`` bytes."""

    __slots__ = ("parts", "size")

    def __init__(self, parts: tuple[bytes | memoryview, ...]):
        self.parts = list(parts)
        self.size = sum(map(len, parts))

    def __len__(self) -> int:
        return self.size


#: what a Due sent from the caller's thread ends: its one frame (see _Sending._send_now)
SENT_INLINE = Outgoing(None, None, 0, list)
#: the longest frame whose fragments leave from the caller's thread (an idle link): a few
#: dozen system calls; a longer one goes to the send thread, so an executor never waits long
INLINE_MAX = 64 * 1024
#: bytes a batch of a topic with recovery leaves its packetizer for its header, so the batch
#: and the header fit one packet (retransmit's takes 14, fec's 21)
REPAIR_HEADROOM = 64
#: how long a caller waits for another thread's packet to leave before it queues its frame
TURN_WAIT = 0.02
#: the most fragments of one frame the send thread hands the kernel in one call
_RUN = 64


def _batchable(due: Due) -> bool:
    """A whole frame in one packet, which may share a datagram with others."""
    return due.ends is not None and due.ends.batchable and not due.again


def batch(frames: list[bytes]) -> list[bytes | memoryview]:
    """The parts of one datagram carrying ``frames``: ``"RB"``, then ``u32 length | frame``."""
    parts: list[bytes | memoryview] = [framing.BATCH_MAGIC]
    pack = framing.LENGTH.pack
    for frame in frames:
        parts += (pack(len(frame)), frame)
    return parts


def batch_size(sizes: int, count: int) -> int:
    """The size of a batch of ``count`` frames of ``sizes`` bytes in all."""
    return len(framing.BATCH_MAGIC) + count * framing.LENGTH.size + sizes


def _groups(frames: list[bytes], limit: int) -> Iterator[tuple[list[bytes], int]]:
    """Consecutive frames in groups whose batch fits ``limit`` bytes (a frame alone when it
    does not), with their bytes in all."""
    start = 0
    while start < len(frames):
        total, end = 0, start
        while end < len(frames) and batch_size(total + len(frames[end]), end - start + 1) <= limit:
            total += len(frames[end])
            end += 1
        if end == start:  # a frame alone: sent as one
            total, end = len(frames[start]), start + 1
        yield frames[start:end], total
        start = end


class DatagramLink(_Sending, Link):
    """A bound datagram endpoint. Frames out: whole when they fit ``max_frame`` (batched with
    others for one destination), else cut by the link's own packetizer, or by the topic's
    ``recovery``; a bare link's whole, never batched. Datagrams in: from ``sources`` only, to the
    packetizer of their magic (``packetizers``: the installed ones by default); a bare link's as
    they came. An own packetizer that ``cuts_every_frame`` (small frames) takes every frame and
    every datagram. It is the :class:`~rosgate.packetizer.PacketLink` of its packetizers (one of
    each, made on first use); the timers of those that implement ``sent`` run on its send
    thread, the others' on its receive thread. An endpoint that says when its line is gone
    (``watch_line``: a serial device unplugged) stops it sending until the line is back:
    reliable frames wait (at most ``hold_frames`` and ``hold_bytes``, the oldest dropped first:
    ``queue_full``), best-effort ones are dropped (``link_down``), and the packetizers' clocks
    stand still (:meth:`~rosgate.packetizer.Packetizer.resumed`)."""

    datagram = True

    def __init__(self, transport: DatagramTransport, endpoint: DatagramEndpoint, name: str,
                 on_frame: FrameHandler, on_lost: LostHandler, bare: bool = False,
                 max_message: int = framing.DEFAULT_MAX_MESSAGE, sources: Sources | None = None,
                 budget: LinkConfig | None = None,
                 on_recovered: Callable[[int], None] | None = None, queue_frames: int = 10_000,
                 queue_bytes: int = 64 * 1024 * 1024, packetizers: Plugins | None = None,
                 hold_frames: int = 1000, hold_bytes: int = 8 * 1024 * 1024):
        self.transport = transport
        self.sources = sources  # None: anyone; others are counted not_allowed
        self.endpoint = endpoint
        self.bare = bare
        self.max_frame = transport.max_frame
        self.on_frame = on_frame
        self.on_lost = self.lost = on_lost  # lost, recovered: what its packetizers report
        self.recovered = on_recovered or (lambda topic_id: None)
        self.max_message = max_message
        self._init_sending(name, budget, transport.packet_overhead, self.max_frame,
                           queue_frames, queue_bytes, transport.one_line)
        self.registry = packetizers or installed()
        #: packetizers made so far, by name and by magic (None: a whole frame, the link's own)
        self._by_name: dict[str, Packetizer] = {}
        self._by_magic: dict[bytes, Packetizer | None] = {envelope.MAGIC: None}
        #: those made so far that implement ``sent`` (their timers run on the send thread)
        self._sending: set[Packetizer] = set()
        self._making = threading.Lock()
        self._tx_timer: float | None = None  # when the send thread runs the timers next
        #: what cuts a frame of a sender without a packetizer of its own when it does not fit
        self.own = self.packetizer("fragments" if bare else own_packetizer(self.max_frame))
        #: every frame is cut by ``own``, and every datagram in is its
        self.cuts = self.own.cuts_every_frame
        # what the endpoint can do beyond send: scatter-gather, several datagrams in one call
        self._gather = hasattr(endpoint, "send_parts")
        self._send_parts: Callable[[Any, Address], None] = getattr(
            endpoint, "send_parts", lambda parts, to: endpoint.send(b"".join(parts), to))
        self._send_datagrams = getattr(endpoint, "send_datagrams", None)
        count_drops = getattr(endpoint, "count_drops", None)  # a CheckingDatagramEndpoint
        if count_drops is not None:
            count_drops(lambda reason, detail: self.on_lost(None, reason))
        #: the line is there (a LineDatagramEndpoint says when it is gone); since when not
        self.line_up, self._gone_at = True, 0.0
        self._hold = (hold_frames, hold_bytes)
        watch_line = getattr(endpoint, "watch_line", None)
        if watch_line is not None:
            watch_line(self._line)
        self._start()

    def send(self, frame: bytes, sender: Sender, to: Address | None = None) -> bool:
        assert to is not None, "a datagram link needs a destination"
        size = len(frame)
        if self.bare and size > self.max_frame:
            sender.drop(Drop.TOO_LARGE_FOR_BARE_FRAMING,
                        f"{size} bytes, {self.name} carries at most {self.max_frame}")
            return False
        delivery = sender.delivery
        up = self.line_up
        if not (up or delivery.reliable):  # it would be stale by the time the line is back
            sender.drop(Drop.LINK_DOWN, f"{self.name}: its line is gone")
            return False
        whole = self.bare or delivery.whole
        plain = delivery.packetizer is None and not self.cuts  # whole or fragments
        one = whole or plain and size <= self.max_frame
        # a frame a topic's recovery cuts (one packet or several) leaves from here too
        cut_here = not self.cuts and size <= INLINE_MAX
        inline = self._send_now if one else self._send_fragments_now if cut_here else None
        if inline is not None and up:
            sent = inline(frame, sender, to)
            if sent is None and self._await_turn() and self._send_waiting():
                sent = inline(frame, sender, to)  # what waited is gone: the link is idle
            if sent is not None:
                return sent
        queued = self._put(Outgoing(sender, to, size,
                                    lambda: self._cut(frame, sender, to, whole),
                                    time.monotonic(), batchable=one and not whole))
        if not up:
            self._held()
        return queued

    def _held(self) -> None:
        """A reliable frame was queued while the line is gone: what waits is kept within the
        hold bounds, the oldest dropped first (counted)."""
        frames, bytes_ = self._hold
        with self._lock:
            self.scheduler.shed(frames, bytes_, f"{self.name}: its line is gone and "
                                f"{frames} messages or {bytes_} bytes wait (bridge.queue)")
        self._count_drops()

    def _line(self, up: bool) -> None:
        """The endpoint says its line is gone (False) or back (True)."""
        now = time.monotonic()
        with self._lock:
            if up == self.line_up:
                return
            if not up:
                self.line_up, self._gone_at = False, now
                return
            down = now - self._gone_at
        # their clocks pushed on before a timer runs again (none runs while the line is gone)
        for packetizer in list(self._by_name.values()):
            try:
                packetizer.resumed(down, now)
            except Exception:
                BUGS.bug("packetizer_error", f"{self.name}: packetizer {packetizer.name} could "
                                             "not resume after the line's outage (a plugin bug)")
        with self._wake:
            self.line_up = True
            self._tx_timer = now
            self._wake.notify_all()

    def send_all(self, frames: list[bytes], sender: Sender, to: Address | None = None) -> int:
        """Frames of one sender: on an idle link those that fit share datagrams sent from here;
        else each is queued (and coalesced again by the send thread)."""
        assert to is not None, "a datagram link needs a destination"
        delivery = sender.delivery
        if len(frames) == 1:  # (most calls: one message taken)
            return int(self.send(frames[0], sender, to))
        if not frames or self.bare or self.cuts or delivery.whole or not self.line_up:
            return sum(self.send(frame, sender, to) for frame in frames)
        if delivery.packetizer is not None:
            return self._send_repaired(frames, sender, to)
        sent = 0
        for group, total in _groups(frames, self.max_frame):
            go = len(group) > 1
            if go:
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

    def _send_repaired(self, frames: list[bytes], sender: Sender, to: Address) -> int:
        """Frames of a topic with recovery: those that fit one packet together go to its
        packetizer as one batch (one packet to repair and acknowledge, not one per message)."""
        sent = 0
        for group, _ in _groups(frames, self.max_frame - REPAIR_HEADROOM):
            if len(group) == 1:
                sent += self.send(group[0], sender, to)
            elif self.send(b"".join(batch(group)), sender, to):
                sent += len(group)
                with self._lock:  # the link's counters count its messages, as for any batch
                    self.counters.frames_out += len(group) - 1
                    self.counters.coalesced_out += len(group)
        return sent

    def _cut(self, frame: bytes, sender: Sender, to: Address, whole: bool) -> list[bytes]:
        """A frame's packets, made when it starts (counters and FEC coding on the send thread)."""
        delivery = sender.delivery
        own = self.cuts or delivery.packetizer is None
        if whole or own and not self.cuts and len(frame) <= self.max_frame:
            return [frame]
        packetizer = self.own if own or delivery.packetizer is None \
            else self._by_name.get(delivery.packetizer.name) or self._make(delivery.packetizer)
        packets = packetizer.cut(frame, sender, to, delivery.packetizer_options)
        return [packet if type(packet) is bytes else self._packet(packet) for packet in packets]

    def _packet(self, packet: Packet) -> bytes:
        if not isinstance(packet, tuple):
            return packet
        # a _Gather stands for its packet: the scheduler only takes its len()
        return cast(bytes, _Gather(packet)) if self._gather else b"".join(packet)

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
                if _sends(found):
                    self._sending.add(found)
                for magic in cls.magic:
                    self._by_magic[magic] = found
                self._by_name[cls.name] = found
            return found

    def _receiver(self, magic: bytes) -> Packetizer | None:
        """The packetizer of ``magic`` (None: a whole frame), looked up once per magic."""
        registration = self.registry.by_wire("packetizer", magic)
        if registration is None:
            self._by_magic[magic] = None  # (a magic is two bytes at most: this stays bounded)
            return None
        return self._make(registration.cls)

    def moved(self, old: Address, new: Address) -> None:
        """The far side at ``old`` is at ``new`` now (a roam): its packetizers send what they
        keep for it there, their timers run at once."""
        for packetizer in list(self._by_name.values()):
            try:
                packetizer.moved(old, new)
            except Exception:
                BUGS.bug("packetizer_error", f"{self.name}: packetizer {packetizer.name} could "
                                             "not follow a far side that moved (a plugin bug)")
        with self._wake:
            self._tx_timer = time.monotonic()
            self._wake.notify_all()

    def repeat(self, sender: Any, to: Address, packets: list[bytes]) -> None:
        with self._lock:
            self.scheduler.repair(sender, to, packets)
            self._wake.notify()

    def answer(self, packet: bytes, to: Address) -> None:
        """Sent at once (counted against the budget); one that fails is asked for again anyway.
        Never to a source read on probation (a stranger, or a client that moved before a genuine
        frame of it moved its address): a replayed datagram must not make this side talk."""
        if self.sources is not None and not self.sources.vouches_for(to):
            return
        with self._lock:
            self.scheduler.charge(to, len(packet))
        try:
            self.endpoint.send(packet, to)
        except OSError:
            pass

    def _run_timers(self, now: float, sending: bool = False) -> float | None:
        """The packetizers' timers: on the send thread those that implement ``sent``, on the
        receive thread the others (so a receive waits in the kernel for its next datagram, not
        for the next few milliseconds' ACKs and probes); when the soonest wants to run again.
        None while the line is gone: their clocks stand still."""
        if not self.line_up:
            return None
        soonest = None
        for packetizer in list(self._by_name.values()):
            if sending != (packetizer in self._sending):
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
        """Wait up to :data:`TURN_WAIT` for another thread's packet to leave; whether the turn
        is free. A longer wait means a thread not scheduled (not a reason to queue where a
        latest-only frame can be replaced) or a full send buffer: after one wait in vain, callers
        queue at once until one gets a turn again."""
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
        """Send what waits (up to :data:`INLINE_MAX` bytes) when nobody is sending: the send
        thread was woken but has not run, and a latest-only frame queued now could be replaced
        before it does. Whether nothing waits any more."""
        scheduler = self.scheduler
        with self._lock:
            if self._busy or self.closed.is_set() or scheduler.idle or not self.line_up:
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
        """A frame longer than ``max_frame``, or one a topic's recovery cuts, cut and sent from
        the caller's thread as :meth:`_send_now` sends a whole one: a hand-off to the send thread
        may take milliseconds on a busy interpreter, long enough for a latest-only frame to be
        superseded, and costs a wake-up per message. The rest goes to the send thread once
        anything else waits or the budget runs short."""
        with self._lock:
            if not self._claim(to, self.max_frame):  # the first fragment's tokens
                return None
        scheduler, lock, counters = self.scheduler, self._lock, self.counters
        try:
            packets = self._cut(frame, sender, to, False)
            # all the packets in one call when the endpoint can and no budget limits; else one at
            # a time, each after a look at what else waits
            turn = len(packets) if scheduler.rate is None and self._send_datagrams else 1
            for start in range(0, len(packets), turn):
                if start:
                    with lock:  # anything else waiting, or a budget short: the send thread's
                        if not scheduler.may_send_now(to, len(packets[start])):
                            rest, now = packets[start:], time.monotonic()
                            scheduler.resume(Outgoing(sender, to, sum(map(len, rest)), list, now),
                                             rest, now)
                            return True
                end = start + turn
                if not self._send_run(packets[start:end], sender, to, end >= len(packets)):
                    return False
            counters.inline_out += 1
            self._ended(packets[-1], to)
            return True
        finally:
            self._release()

    def _send_run(self, packets: list[bytes], sender: Any, to: Address, last: bool) -> bool:
        """Packets of one frame in a row, in one call where the endpoint can; ``last``: they end
        the frame. False when they could not be sent (counted)."""
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
            if self._repairs(packets[0]) and not self.closed.is_set():
                return True  # lost on the way, as far as its packetizer goes: it sends it again
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
            elif self.cuts and not sender.delivery.whole:  # a packet of several datagrams
                pieces = range(0, len(packet), self.max_frame)
                count = len(pieces)
                for i in pieces:
                    self.endpoint.send(packet[i:i + self.max_frame], to)
            else:
                self.endpoint.send(packet, to)
        except OSError as exc:
            if self._repairs(packet) and not self.closed.is_set():
                # no route for now (a host between two addresses): lost on the way, as far as
                # its packetizer goes, which sends it again (the receiver counts what never came)
                self._left(due, packet, to)
                return False
            # a message cut short by close() was counted there, unless this was its last packet
            if due.ends is not None or not self.closed.is_set():
                sender.drop(Drop.SEND_ERROR, f"to {to} on {self.name}: {exc}")
            return False
        counters = self.counters
        counters.packets_out += count
        counters.bytes_out += len(packet)
        if due.ends is not None:
            counters.frames_out += 1
        sender.on_wire(len(packet), due.again)
        self._left(due, packet, to)
        return True

    def _repairs(self, packet: Any) -> bool:
        """Whether ``packet`` is of a packetizer that sends again what is lost (``sent``)."""
        if type(packet) is not bytes:
            return False
        packetizer = self._by_magic.get(packet[:2])
        return packetizer in self._sending

    def _left(self, due: Due, packet: Any, to: Address) -> None:
        """The last packet of a frame has left (or was lost leaving): its packetizer's timer."""
        if due.ends is not None and due.ends is not SENT_INLINE:
            self._ended(packet, to)

    def _ended(self, packet: Any, to: Address) -> None:
        """``packet``, the last of a frame, has left: a packetizer that implements ``sent`` is
        told, and the send thread runs its timer when it asks."""
        if type(packet) is bytes:
            packetizer = self._by_magic.get(packet[:2])
            if packetizer in self._sending:
                now = time.monotonic()
                packetizer.sent(packet, to, now)
                self._arm(packetizer.timer(now))

    def _arm(self, due: float | None) -> None:
        """The send thread runs the timers of the packetizers that implement ``sent`` at
        ``due`` at the latest: woken when that is sooner than the time it waits for. (Read
        first without the lock: a time already set as soon or sooner is run by the send thread,
        which sets the next under the lock, after what every ``sent`` before said.)"""
        if due is None:
            return
        armed = self._tx_timer
        if armed is not None and armed <= due:
            return
        with self._wake:
            if self._tx_timer is None or due < self._tx_timer:
                self._tx_timer = due
                self._wake.notify()

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
        """Send what the scheduler lets go; consecutive whole frames for one destination share a
        datagram, consecutive fragments of one frame one system call."""
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
                    timer = self._tx_timer if self.line_up else None
                    due, carry = carry, None  # None: the timers are due, or drops to count
                    if due is not None or timer is not None and now >= timer:
                        break
                    got = None if self._busy or not self.line_up else scheduler.next(now)
                    if isinstance(got, Due):
                        due = got
                        break
                    if scheduler.dropped:  # counted (outside the lock) before any wait
                        break
                    until = [t for t in (got, timer) if t is not None]
                    wake.wait(max(0.0, min(until) - now) if until else None)
                if due is None:
                    self._tx_timer = None
                else:
                    self._busy = True
                    batch, total = [due], len(due.packet)
                    # whole frames that fit one datagram, or a frame's next fragments (one call)
                    batching = coalesce and _batchable(due)
                    running = run and type(due.packet) is _Gather and due.ends is None
                    while batching or running:
                        more = scheduler.next(now)
                        if not isinstance(more, Due):
                            break
                        total += len(more.packet)
                        if more.to != due.to or not (
                                _batchable(more) and batch_size(total, len(batch) + 1) <= limit
                                if batching else type(more.packet) is _Gather
                                and more.sender is due.sender and not more.again):
                            carry = more
                            break
                        batch.append(more)
                        if running and (more.ends is not None or len(batch) == _RUN):
                            break  # the frame's last, or the most one call takes
            if scheduler.dropped:
                self._count_drops()
            if due is None:  # the packetizers' timers, outside the lock: they may queue repairs
                self._arm(self._run_timers(now, sending=True))
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

    def _receive_loop(self) -> None:
        receive_into = getattr(self.endpoint, "receive_into", None)
        if receive_into is None:
            receive: Callable[[float], tuple[bytes | memoryview, Address] | None] = \
                self.endpoint.receive
        else:
            # one buffer for every datagram, so long that one that fills it is too long
            buffer = memoryview(bytearray(max(self.max_frame, 65_535) + 1))
            endpoint: Any = self.endpoint
            overflowed = [getattr(endpoint, "overflowed", None)]  # (counted so far)

            def receive(timeout: float) -> tuple[bytes | memoryview, Address] | None:
                got = receive_into(buffer, timeout)
                if got is None:
                    return None
                size, source, self.arrived = got
                if overflowed[0] is not None and endpoint.overflowed != overflowed[0]:
                    # the kernel dropped datagrams: the receive buffer was full
                    for _ in range((endpoint.overflowed - overflowed[0]) % 2**32):
                        self.on_lost(None, Drop.RECEIVE_BUFFER_FULL)
                    overflowed[0] = endpoint.overflowed
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
            except OSError:  # passing, or the endpoint closed: the loop's test tells
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
            if got is None:  # idle: the send thread's timers too (a timer that said None)
                self._arm(self._run_timers(now, sending=True))
                continue
            fed = self._datagram(*got, now)
            if fed is not None:  # what it was given may have moved its timer
                due = fed.timer(now)
                if fed in self._sending:  # its timer runs on the send thread
                    self._arm(due)
                elif due is not None and (timer is None or due < timer):
                    timer = due

    def _datagram(self, datagram: bytes | memoryview, source: Address,
                  now: float) -> Packetizer | None:
        """One datagram (a view of the receive buffer); the packetizer it was fed to, if any."""
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
        elif kind == 0x42:  # "RB": a batch
            self._unbatch(datagram, source)
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
        try:
            frame = packetizer.feed(datagram, source, now)
        except framing.FramingError:
            self.on_lost(None, Drop.BAD_FRAGMENT)
            return packetizer
        except Exception:  # a packetizer must raise FramingError; anything else is its bug
            BUGS.bug("packetizer_error", f"{self.name}: packetizer {packetizer.name} failed on a "
                                         "packet (a bug in the plugin)")
            self.on_lost(None, Drop.BAD_FRAGMENT)
            return packetizer
        if frame is None:
            return packetizer
        if frame[:2] == framing.BATCH_MAGIC:  # a topic's batch, repaired as one (_send_repaired)
            self._unbatch(frame, source)
        else:
            counters.frames_in += 1
            self._deliver(frame, source)  # the handler's to keep (rclpy takes it uncopied)
        return packetizer

    def _unbatch(self, datagram: bytes | memoryview, source: Address) -> None:
        """A batch's frames to the handler, read inline (no generator: a cost per message)."""
        counters = self.counters
        end, offset, deliver = len(datagram), _BATCH_START, self._deliver
        while offset < end:
            start = offset + _LENGTH_SIZE
            if start > end or (offset := start + _length(datagram, offset)[0]) > end:
                self.on_lost(None, Drop.BAD_BATCH)
                break
            counters.frames_in += 1
            counters.coalesced_in += 1
            deliver(bytes(datagram[start:offset]), source)

    def _close_io(self) -> None:
        self.endpoint.close()


# reading a batch (see batch)
_BATCH_START, _LENGTH_SIZE, _length = (len(framing.BATCH_MAGIC), framing.LENGTH.size,
                                       framing.LENGTH.unpack_from)

#: a magic the link has not looked up yet
_UNKNOWN: Any = object()


def _sends(packetizer: Packetizer) -> bool:
    """Whether it implements ``sent`` (and has its timer run on the send thread too)."""
    return type(packetizer).sent is not Packetizer.sent
