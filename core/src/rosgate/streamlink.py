"""Stream links: a :class:`StreamLink` is one connection (TCP, RFCOMM, a Noise channel over
either), its frames length-prefixed, long ones in chunks, sent through the link's scheduler as a
datagram link's are (:mod:`rosgate.links`); a :class:`LinkSlot` is the place a route sends
through while connections come and go, and a :class:`Connector` keeps it filled.
"""

from __future__ import annotations

import itertools
import logging
import random
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from contextlib import suppress
from dataclasses import dataclass
from typing import Any, cast

from .admission import proven
from .config import LinkConfig
from .drops import Drop, Reason
from .errors import LinkError
from .links import (
    POLL,
    SENT_INLINE,
    FrameHandler,
    Lifetime,
    Link,
    LinkCounters,
    LostHandler,
    Sender,
    _Sending,
)
from .scheduler import Due, Outgoing
from .transport import Address, StreamConnection, StreamTransport, Transport
from .warn import BUGS
from .wire import envelope
from .wire.framing import (
    CHUNK,
    CHUNK_HEAD,
    CHUNK_LENGTH,
    CHUNKED,
    DEFAULT_MAX_MESSAGE,
    DIRECT_ABOVE,
    EARN_BUFFER,
    LAST,
    LENGTH,
    MAX_OPEN_MESSAGES,
    FramingError,
)

log = logging.getLogger("rosgate")

WRITE = 64 * 1024  # bytes a stream link's writer gathers into one write, at most
CONNECT_TIMEOUT = 5.0
#: seconds between two checks that a connection's local address is still this host's (a roam)
ADDRESS_CHECK = 0.25
#: seconds a slot keeps a reliable frame it wrote, to write it again on the next connection when
#: the far side says it never got it (a connection dies with what its buffers held)
RESEND_WITHIN = 10.0

#: what the far side of a slot took: topic id -> epoch -> the newest sequence number
Taken = dict[int, dict[int, int]]


def length_prefixed(frame: bytes) -> bytes:
    return LENGTH.pack(len(frame)) + frame


def stream_records(frame: bytes, message: int, chunk: int = CHUNK) -> list[bytes]:
    """``frame`` as the records of a stream: one, or chunks of ``message`` when it is longer
    than ``chunk``."""
    if len(frame) <= chunk:
        return [length_prefixed(frame)]
    view = memoryview(frame)
    starts = range(0, len(frame), chunk)
    last = starts[-1]
    return [CHUNK_HEAD.pack(CHUNKED | (LAST if start == last else 0)
                            | (min(chunk, len(frame) - start) + 4), message & 0xFFFFFFFF)
            + view[start:start + chunk] for start in starts]


class StreamReader:
    """Cuts a byte stream into frames, chunked ones put back together: :meth:`feed` it what the
    connection gives. With ``direct``, a frame longer than :data:`DIRECT_ABOVE` is read straight
    into a buffer of its own once 1/:data:`EARN_BUFFER` of it has come (a length prefix alone
    does not make the reader zero 64 MiB): while :meth:`target` is not None, the caller reads
    into it and says how many bytes came (:meth:`filled`), saving a copy of large frames."""

    def __init__(self, max_frame: int = DEFAULT_MAX_MESSAGE, direct: bool = False):
        self.max_frame = max_frame
        self.direct = direct
        self._buffer = bytearray()
        self._open: dict[int, bytearray] = {}  # message -> what came of it
        self._open_bytes = 0
        self._frame: bytearray | None = None  # a large frame being read into place
        self._filled = 0

    def target(self) -> memoryview | None:
        """Where the next bytes go when a large frame is being read in place, else None."""
        return None if self._frame is None else memoryview(self._frame)[self._filled:]

    def filled(self, count: int) -> bytearray | None:
        """``count`` bytes were read into :meth:`target`; the frame once it is whole."""
        self._filled += count
        frame = self._frame
        if frame is None or self._filled < len(frame):
            return None
        self._frame = None
        return frame

    def feed(self, data: bytes | memoryview) -> Iterator[bytes]:
        """Yield every complete frame; raise FramingError when a length is impossible."""
        buffer = self._buffer
        buffer += data
        start = 0
        try:
            while len(buffer) - start >= 4:
                (length,) = LENGTH.unpack_from(buffer, start)
                chunked = length & CHUNKED
                size = length & CHUNK_LENGTH if chunked else length
                if size > self.max_frame or chunked and size < 4:
                    raise FramingError(f"frame length {size} over the limit {self.max_frame}"
                                       if size > self.max_frame else "a chunk without its head")
                end = start + 4 + size
                if end > len(buffer):
                    have = len(buffer) - start - 4
                    if (self.direct and not chunked and size > DIRECT_ABOVE
                            and have * EARN_BUFFER >= size):
                        # the rest is read straight into the frame's own buffer
                        self._frame = frame = bytearray(size)
                        frame[:have] = memoryview(buffer)[start + 4:]
                        self._filled = have
                        start = len(buffer)
                    break
                if not chunked:
                    yield bytes(buffer[start + 4:end])
                else:
                    whole = self._chunk(buffer, start + 4, end, bool(length & LAST))
                    if whole is not None:
                        yield cast(bytes, whole)  # bytes-like: handlers take either
                start = end
        finally:
            del buffer[:start]

    def _chunk(self, buffer: bytearray, start: int, end: int, last: bool) -> bytearray | None:
        (message,) = LENGTH.unpack_from(buffer, start)
        part = self._open.get(message)
        if part is None:
            if len(self._open) >= MAX_OPEN_MESSAGES:
                raise FramingError(f"more than {MAX_OPEN_MESSAGES} chunked frames open at once")
            part = self._open[message] = bytearray()
        part += buffer[start + 4:end]
        self._open_bytes += end - start - 4
        if len(part) > self.max_frame or self._open_bytes > 2 * self.max_frame:
            raise FramingError(f"chunked frames over the limit {self.max_frame}")
        if not last:
            return None
        del self._open[message]
        self._open_bytes -= len(part)
        return part  # its own buffer, the handler's to keep (and cut: routes do)


@dataclass(frozen=True)
class Untrusted:
    """What a connection may do before its owner trusts it (``bridge.limits``): frames of at most
    ``max_frame`` bytes, and ``deadline`` seconds to earn trust before it is closed."""

    max_frame: int
    deadline: float


class StreamLink(_Sending, Link):
    """One stream connection. The writer takes at most :data:`WRITE` bytes at a time from the
    scheduler, so a frame of a higher class (a Twist behind a camera's backlog) waits for one
    write, not for the whole backlog. When nothing waits, frames are written from the caller's
    thread as far as the connection takes them without waiting (``send_nowait``: no hand-off).

    With ``untrusted``, the connection is held to those limits until :meth:`trust` (a frame too
    long is a corrupt stream; the deadline passing ends it, counted ``handshake_timeout``)."""

    def __init__(self, connection: StreamConnection, name: str, peer: Address,
                 on_frame: FrameHandler, on_lost: LostHandler,
                 on_close: Callable[[StreamLink], None] | None = None,
                 on_closing: Callable[[StreamLink], None] | None = None,
                 queue_frames: int = 10_000, queue_bytes: int = 64 * 1024 * 1024,
                 max_message: int = DEFAULT_MAX_MESSAGE,
                 untrusted: Untrusted | None = None, budget: LinkConfig | None = None):
        self.connection = connection
        self.peer = peer
        self.on_frame = on_frame
        self.on_lost = on_lost
        self.on_close = on_close
        self.on_closing = on_closing
        # for liveness: the main line's roles set it on every control message (a heartbeat), not
        # on bytes, so a stream that lost its frame boundaries does not look alive
        self.last_heard = time.monotonic()
        self.why = ""  # why the connection ended, once it has
        self._send_nowait = getattr(connection, "send_nowait", None)
        self._messages = itertools.count(1)  # numbers of chunked frames
        self._init_sending(name, budget, 0, CHUNK + CHUNK_HEAD.size, queue_frames,
                           queue_bytes)
        self._reader = StreamReader(untrusted.max_frame if untrusted else max_message,
                                            direct=hasattr(connection, "receive_into"))
        self.max_message = max_message
        self._trust_by = time.monotonic() + untrusted.deadline if untrusted else None
        self._start()

    def send(self, frame: bytes, sender: Sender, to: Address | None = None) -> bool:
        # the limits count a frame with its length prefix, as it is written
        if len(frame) <= CHUNK:
            record = length_prefixed(frame)
            if self._send_nowait is not None:
                sent = self._send_now(record, sender, None)
                if sent is not None:
                    return sent
            return self._put(Outgoing(sender, None, len(record), _one(record), time.monotonic()))
        return self._put(Outgoing(sender, None, len(frame) + LENGTH.size,
                                  lambda: stream_records(frame, next(self._messages)),
                                  time.monotonic()))

    def send_all(self, frames: list[bytes], sender: Sender, to: Address | None = None) -> int:
        """Frames of one sender together (a route's backlog): one write from the caller's
        thread when nothing waits; otherwise each is queued."""
        if len(frames) < 2 or self._send_nowait is None or max(map(len, frames)) > CHUNK:
            return sum(self.send(frame, sender) for frame in frames)
        records = [length_prefixed(frame) for frame in frames]
        data = b"".join(records)
        with self._lock:
            go = self._claim(None, len(data))
        if not go:
            now = time.monotonic()
            return sum(self._put(Outgoing(sender, None, len(record), _one(record), now))
                       for record in records)
        try:
            self._send_due(Due(data, None, sender, SENT_INLINE, frames=len(records)))
        finally:
            self._release()
        return len(records)

    def _send_due(self, due: Due) -> bool:
        """Write ``due``'s records as far as the connection takes them now; the rest goes first
        when the writer next writes (nothing comes between: this thread has the turn), and its
        frames are counted out with it."""
        assert self._send_nowait is not None
        try:
            written = self._send_nowait(due.packet)
        except OSError as exc:
            for _ in range(due.frames):
                due.sender.drop(Drop.LINK_DOWN, f"{self.name}: send failed")
            self.fail(f"send failed: {exc}")
            return False
        counters = self.counters
        if written:
            counters.packets_out += 1
            counters.bytes_out += written
        if written == len(due.packet):
            counters.frames_out += due.frames
            if due.frames > 1:
                counters.coalesced_out += due.frames
        else:
            rest = Due(due.packet[written:], None, due.sender, SENT_INLINE, frames=due.frames)
            with self._lock:
                self._rest = rest
        due.sender.on_wire(written, False)
        return True

    def _send_loop(self) -> None:
        """Gather what the scheduler lets go, up to :data:`WRITE` bytes, into one write."""
        wake, closed, scheduler, counters = self._wake, self.closed, self.scheduler, self.counters
        while True:
            batch: list[Due] = []
            size = 0
            with wake:
                while not batch:
                    if closed.is_set():
                        return
                    if self._busy:  # a caller is writing: its rest, if any, comes first
                        wake.wait()
                        continue
                    if self._rest is not None:
                        batch.append(self._rest)
                        size, self._rest = len(self._rest.packet), None
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
            if scheduler.dropped:
                self._count_drops()
            try:
                self.connection.send(b"".join([d.packet for d in batch]))
            except OSError as exc:
                for due in batch:
                    if due.ends is not None:
                        due.sender.drop(Drop.LINK_DOWN, f"{self.name}: send failed")
                self.fail(f"send failed: {exc}")
                return
            counters.packets_out += 1
            counters.bytes_out += size
            frames = 0
            for due in batch:
                if due.ends is not None:
                    frames += due.frames
                due.sender.on_wire(len(due.packet), False)
            counters.frames_out += frames
            if frames > 1:
                counters.coalesced_out += frames
            with wake:
                self._busy = False
                wake.notify_all()  # for drain()

    def drain(self, timeout: float) -> bool:
        """Wait until everything sent so far is written (a last word before closing)."""
        with self._wake:
            return self._wake.wait_for(
                lambda: (self.scheduler.idle and not self._busy and self._rest is None
                         or self.closed.is_set()), timeout)

    def trust(self) -> None:
        """The connection proved itself: the full frame size, no deadline, and its place in
        the connection limits is never given up to a newer connection."""
        self._reader.max_frame = self.max_message
        self._trust_by = None
        proven(self.connection)

    @property
    def trusted(self) -> bool:
        return self._trust_by is None

    def _receive_loop(self) -> None:
        receive_into = getattr(self.connection, "receive_into", None)
        buffer = memoryview(bytearray(256 * 1024))
        reader, closed, counters = self._reader, self.closed, self.counters
        while not closed.is_set():
            target = reader.target() if receive_into is not None else None
            try:
                if receive_into is None:
                    got: int | bytes | None = self.connection.receive(len(buffer), POLL)
                else:  # a large frame in place
                    got = receive_into(buffer if target is None else target, POLL)
            except OSError as exc:
                self.fail(f"receive failed: {exc}")
                return
            except Exception as exc:  # a transport plugin's bug: drop this connection, loudly
                BUGS.bug("transport_error", f"{self.name}: the transport's receive failed "
                                            "(a bug in the plugin)")
                self.on_lost(None, Drop.TRANSPORT_ERROR)
                self.fail(f"transport error: {type(exc).__name__}: {exc}")
                return
            trust_by = self._trust_by
            if trust_by is not None and time.monotonic() > trust_by:
                self.on_lost(None, Drop.HANDSHAKE_TIMEOUT)
                self.fail("no handshake in time")
                return
            if got is None:
                continue
            if not got:
                self.fail("closed by peer")
                return
            counters.packets_in += 1
            if target is not None:
                assert isinstance(got, int)
                target.release()  # the frame is the handler's: it may cut it (routes do)
                counters.bytes_in += got
                whole = reader.filled(got)
                if whole is not None:
                    counters.frames_in += 1
                    # its own buffer, the handler's to keep (typed bytes: see DatagramLink)
                    self._deliver(cast(bytes, whole), self.peer)
                continue
            data = buffer[:got] if isinstance(got, int) else got
            counters.bytes_in += len(data)
            count = 0
            try:
                for frame in reader.feed(data):
                    count += 1
                    self._deliver(frame, self.peer)
            except FramingError as exc:
                # a corrupt length means we can no longer find frame boundaries: start afresh
                self.on_lost(None, Drop.BAD_LENGTH)
                self.fail(f"stream corrupt ({exc})")
                return
            finally:
                counters.frames_in += count
                if count > 1:
                    counters.coalesced_in += count

    def fail(self, why: str) -> None:
        """End the connection for a reason worth logging (lost, corrupt, silent)."""
        if self.closed.is_set():
            return
        self.why = why
        # a stranger's connection (never trusted) is counted by its reason, not logged: a
        # flood of them must not flood the log
        log.log(logging.INFO if self.trusted else logging.DEBUG,
                "%s: connection to %s ended: %s", self.name, self.peer, why)
        self.close()

    def _close_io(self) -> None:
        with suppress(OSError):
            self.connection.close()


@dataclass(frozen=True)
class QueueLimits:
    """How much a :class:`LinkSlot` holds for reliable topics while it has no connection."""

    frames: int
    bytes: int


class LinkSlot(Link):
    """A stream link that comes and goes: a :class:`Connector` (or a server that accepted the
    peer again) :meth:`attach`-es each new connection. While there is none, frames of reliable
    senders wait, oldest dropped first past the limits (``queue_full``), and go to the next
    connection first; other frames are counted ``link_down``. Frames handed to a connection
    that then fails are lost, unless the slot ``resends`` (a main line, whose handshake says
    what each side took): then they are kept a while (:data:`RESEND_WITHIN`, within the same
    limits), and the next connection of the same session writes again those the far side says
    it did not take (:meth:`attach`), before what waited."""

    def __init__(self, name: str, limits: QueueLimits, resends: bool = False):
        self.name = name
        self.limits = limits
        self.resends = resends
        self.current: StreamLink | None = None
        self.closed = threading.Event()
        self._waiting: deque[tuple[bytes, Sender]] = deque()
        self._waiting_bytes = 0
        self._written: deque[tuple[bytes, Sender, float]] = deque()  # reliable, maybe in flight
        self._written_bytes = 0
        self._lock = threading.Lock()  # keeps sends and the flush of the queue in order

    def send_all(self, frames: list[bytes], sender: Sender, to: Address | None = None) -> int:
        overflow: list[Sender] = []
        with self._lock:
            link = self.current
            if link is not None and not link.closed.is_set():
                if self.resends and sender.delivery.reliable:
                    self._wrote(frames, sender)
                return link.send_all(frames, sender)
            refused = self.closed.is_set() or not sender.delivery.reliable
            if not refused:
                for frame in frames:
                    self._waiting.append((frame, sender))
                    self._waiting_bytes += len(frame)
                while self._waiting and (len(self._waiting) > self.limits.frames
                                         or self._waiting_bytes > self.limits.bytes):
                    old, old_sender = self._waiting.popleft()
                    self._waiting_bytes -= len(old)
                    overflow.append(old_sender)
        for old_sender in overflow:
            old_sender.drop(Drop.QUEUE_FULL, f"{self.name} is down and its queue is full")
        if refused:
            for _ in frames:
                sender.drop(Drop.LINK_DOWN, f"{self.name} is down")
            return 0
        return len(frames)

    def _wrote(self, frames: list[bytes], sender: Sender) -> None:
        """Keep reliable frames handed to a connection (under the lock), the oldest forgotten
        past the limits and :data:`RESEND_WITHIN`."""
        now, written = time.monotonic(), self._written
        for frame in frames:
            written.append((frame, sender, now))
            self._written_bytes += len(frame)
        limits, since = self.limits, now - RESEND_WITHIN
        while written and (len(written) > limits.frames or self._written_bytes > limits.bytes
                           or written[0][2] < since):
            self._written_bytes -= len(written.popleft()[0])

    def attach(self, link: StreamLink, taken: Taken | None = None) -> None:
        """Use ``link`` from now on; what waited goes first. ``taken``: what the far side
        says it took of this session's topics (a connection of the same session, again):
        frames written to the connections before that it did not take go before them."""
        with self._lock:
            again: list[tuple[bytes, Sender]] = []
            if taken is not None:  # else nothing is known of what the far side took
                again = [(frame, sender) for frame, sender, _ in self._written
                         if _untaken(frame, taken)]
                self._written.clear()
                self._written_bytes = 0
            for frame, sender in [*again, *self._waiting]:
                if self.resends:
                    self._wrote([frame], sender)
                link.send(frame, sender)
            self._waiting.clear()
            self._waiting_bytes = 0
            self.current = link
        if again:
            log.info("%s: %d frame(s) the far side did not get written again", self.name,
                     len(again))

    def forget_written(self) -> None:
        """A new session: what the last one wrote means nothing to it."""
        with self._lock:
            self._written.clear()
            self._written_bytes = 0

    def discard(self, reason: Reason) -> None:
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

    @property
    def counters(self) -> LinkCounters:  # type: ignore[override]  # the connection's, read-only
        link = self.current
        return link.counters if link is not None else LinkCounters()

    def close(self) -> None:
        self.closed.set()
        self.discard(Drop.LINK_DOWN)
        if self.current is not None:
            self.current.close()


def _untaken(frame: bytes, taken: Taken) -> bool:
    """Whether ``frame`` is a topic's message its far side has not taken (a topic it says
    nothing of, and anything else, is never written again)."""
    try:
        header = envelope.unpack(frame)
    except envelope.EnvelopeError:
        return False
    newest = taken.get(header.topic_id)
    if newest is None or header.flags & _NOT_MESSAGE:
        return False
    top = newest.get(header.epoch)
    return top is None or header.seq > top


_NOT_MESSAGE = (envelope.FLAG_CONTROL | envelope.FLAG_HELLO | envelope.FLAG_REQUEST
                | envelope.FLAG_REPLY | envelope.FLAG_ANNOUNCE)


@dataclass(frozen=True)
class Backoff:
    """Seconds between reconnection attempts: from ``min``, doubling up to ``max``, jittered."""

    min: float
    max: float

    def delay(self, failures: int) -> float:
        return min(self.min * 2 ** (failures - 1), self.max) * random.uniform(0.5, 1.0)


@dataclass(eq=False)
class Connector:
    """Keeps a stream connection up: connects, and after every loss reconnects by itself, with
    capped exponential backoff and jitter (a fleet of clients does not hammer a server that
    comes back); after a connection that worked is lost, at once. ``on_connected(link)`` may
    refuse a connection (a failed handshake: a failed attempt); ``on_lost(link)`` hears of
    every accepted connection that ended; ``on_closing(link)`` hears of every connection that
    starts closing (accepted or refused) at once, on the thread that closes it."""

    transport: Transport
    address: Address
    slot: LinkSlot
    on_frame: FrameHandler
    on_frame_lost: LostHandler
    life: Lifetime
    backoff: Backoff
    on_connected: Callable[[StreamLink], bool] | None = None
    on_lost: Callable[[StreamLink], None] | None = None
    secure: Callable[[StreamConnection], StreamConnection] | None = None
    budget: LinkConfig | None = None
    on_closing: Callable[[StreamLink], None] | None = None

    def __post_init__(self) -> None:
        self._last_failure = ""
        self._thread = threading.Thread(target=self._loop, name=f"connect-{self.slot.name}",
                                        daemon=True)
        self.life.closing(self)

    def start(self) -> None:
        self._thread.start()

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
            gone = getattr(link.connection, "address_gone", None)
            while not link.closed.wait(ADDRESS_CHECK):
                if stopping.is_set() or self.slot.closed.is_set():
                    break
                if gone is not None and gone():  # it roamed: the connection is dead already
                    link.fail("this host no longer has the address it connected from")
            if stopping.is_set() and not self.slot.closed.is_set():
                return  # the role may have a last word (bye); closing the slot closes the link
            link.close()
            if self.on_lost is not None and not stopping.is_set():
                self.on_lost(link)

    def _connect(self) -> StreamLink | None:
        """One attempt: a connection its owner accepted, or None."""
        assert isinstance(self.transport, StreamTransport)
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
        link = self.life.closing(StreamLink(connection, self.slot.name, self.address,
                                            self.on_frame, self.on_frame_lost,
                                            on_close=self.life.forget,
                                            on_closing=self.on_closing, budget=self.budget))
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


def _one(packet: bytes) -> Callable[[], list[bytes]]:
    return lambda: [packet]
