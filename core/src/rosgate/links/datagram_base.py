"""What a datagram link does beside each frame's way out and in (:mod:`.datagram`): it is made,
makes its packetizers and runs their timers, holds reliable frames while its line is gone, and
drains its queue on a send thread of its own (frames that wait for one destination leave
together, in one ``"RB"`` datagram)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

from ..admission import Sources
from ..config import LinkConfig
from ..drops import Drop
from ..errors import LinkError
from ..packetizer import Packetizer, own_packetizer
from ..plugins import Plugins, distribution_hint, installed
from ..scheduler import Due
from ..transport import Address, DatagramEndpoint, DatagramTransport
from ..warn import BUGS
from ..wire import envelope, framing
from .base import FrameHandler, LostHandler
from .sending import _SendingBase

#: the longest frame whose fragments leave from the caller's thread (an idle link): a few
#: dozen system calls; a longer one goes to the send thread, so an executor never waits long
INLINE_MAX = 64 * 1024
#: how long a caller waits for another thread's packet to leave before it queues its frame
TURN_WAIT = 0.02
#: the most fragments of one frame the send thread hands the kernel in one call
_RUN = 64


def _batchable(due: Due) -> bool:
    """A whole frame in one packet, which may share a datagram with others."""
    return due.ends is not None and due.ends.batchable and not due.again


def batch_size(sizes: int, count: int) -> int:
    """The size of a batch of ``count`` frames of ``sizes`` bytes in all."""
    return len(framing.BATCH_MAGIC) + count * framing.LENGTH.size + sizes



def batch(frames: list[bytes]) -> list[bytes | memoryview]:
    """The parts of one datagram carrying ``frames``: ``"RB"``, then ``u32 length | frame``."""
    parts: list[bytes | memoryview] = [framing.BATCH_MAGIC]
    pack = framing.LENGTH.pack
    for frame in frames:
        parts += (pack(len(frame)), frame)
    return parts


class DatagramBase(_SendingBase):
    """A :class:`~.datagram.DatagramLink` but for each frame's way (see there)."""

    # the datagram link's own (rosgate.links.datagram): each frame's way out
    _claim: Callable[[Any, int], bool]
    _release: Callable[[], None]
    _send_run: Callable[[list[bytes], Any, Address, bool], bool]
    _arm: Callable[[float | None], None]
    answer: Callable[[bytes, Address], None]
    #: the type of a packet sent as its parts (scatter-gather)
    _parts: type

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
        self._tell_packetizers(lambda p: p.resumed(down, now), "resume after the line's outage")
        with self._wake:
            self.line_up = True
            self._tx_timer = now
            self._wake.notify_all()

    def _tell_packetizers(self, tell: Callable[[Packetizer], None], failed: str) -> None:
        """``tell`` each of its packetizers what happened; one that raises is a plugin's bug
        (logged once a minute), and the others are still told."""
        for packetizer in list(self._by_name.values()):
            try:
                tell(packetizer)
            except Exception:
                BUGS.bug("packetizer_error", f"{self.name}: packetizer {packetizer.name} could "
                                             f"not {failed} (a plugin bug)")

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
        self._tell_packetizers(lambda p: p.moved(old, new), "follow a far side that moved")
        with self._wake:
            self._tx_timer = time.monotonic()
            self._wake.notify_all()

    def repeat(self, sender: Any, to: Address, packets: list[bytes]) -> None:
        with self._lock:
            self.scheduler.repair(sender, to, packets)
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

    def _repairs(self, packet: Any) -> bool:
        """Whether ``packet`` is of a packetizer that sends again what is lost (``sent``)."""
        if type(packet) is not bytes:
            return False
        packetizer = self._by_magic.get(packet[:2])
        return packetizer in self._sending

    def _send_loop(self) -> None:
        """Send what the scheduler lets go; consecutive whole frames for one destination share a
        datagram, consecutive fragments of one frame one system call."""
        wake, closed, scheduler = self._wake, self.closed, self.scheduler
        limit, coalesce = self.max_frame, not self.bare
        gather = self._parts  # (a packet sent as its parts)
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
                    running = run and type(due.packet) is gather and due.ends is None
                    while batching or running:
                        more = scheduler.next(now)
                        if not isinstance(more, Due):
                            break
                        total += len(more.packet)
                        if more.to != due.to or not (
                                _batchable(more) and batch_size(total, len(batch) + 1) <= limit
                                if batching else type(more.packet) is gather
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
                elif type(due.packet) is gather:
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


def _sends(packetizer: Packetizer) -> bool:
    """Whether it implements ``sent`` (and has its timer run on the send thread too)."""
    return type(packetizer).sent is not Packetizer.sent
