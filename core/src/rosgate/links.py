"""Links: the core's side of a transport. Framing, fragmentation and threads live here, so a
transport plugin only opens sockets.

* :class:`DatagramLink` — one bound endpoint; sends whole frames or fragments, reassembles,
  and hands every frame to ``on_frame``. A transport with small frames (``max_frame`` below
  ``framing.COMPACT_BELOW``, such as CAN) gets the compact fragment scheme instead. In bare
  mode (``framing: none``) it hands over the datagram untouched.
* :class:`StreamLink` — one connection; frames carry a length prefix. Sending never blocks the
  caller: frames wait in a bounded queue for a writer thread.
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

from .errors import LinkError
from .transport import (Address, DatagramEndpoint, StreamConnection, StreamListener,
                        Transport)
from .wire import envelope, framing

log = logging.getLogger("rosgate")

FrameHandler = Callable[[bytes, "Link", Address], None]
#: a loss on the receiving side: (topic id when known, reason)
LostHandler = Callable[[int | None, str], None]

POLL = 0.2  # seconds a receive waits before checking whether the link is closing
CONNECT_TIMEOUT = 5.0


class Sender(Protocol):
    """What sends a frame: a route, or a role's control channel."""

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


class DatagramLink(Link):
    datagram = True

    def __init__(self, transport: Transport, endpoint: DatagramEndpoint, name: str,
                 on_frame: FrameHandler, on_lost: LostHandler, bare: bool = False,
                 max_message: int = framing.DEFAULT_MAX_MESSAGE):
        self.transport = transport
        self.endpoint = endpoint
        self.name = name
        self.bare = bare
        self.max_frame = transport.max_frame
        self.on_frame = on_frame
        self.on_lost = on_lost
        self.closed = threading.Event()
        # small frames cannot spare 14 bytes of fragment header: every frame goes as compact pieces
        self.compact = not bare and self.max_frame < framing.COMPACT_BELOW
        self.reassembler: framing.Reassembler | framing.CompactReassembler
        if self.compact:
            self.reassembler = framing.CompactReassembler(on_lost, envelope.topic_of,
                                                          max_message=max_message)
        else:
            self.reassembler = framing.Reassembler(on_lost, max_message=max_message)
        self._frame_ids = itertools.count(1)
        self._counters: dict[Address, int] = {}  # compact: the next piece's counter per destination
        # compact pieces carry no frame id: one frame's pieces must not interleave with another's
        self._send_lock = threading.Lock()
        self._thread = threading.Thread(target=self._receive_loop, name=f"rx-{name}", daemon=True)
        self._thread.start()

    def send(self, frame: bytes, sender: Sender, to: Address | None = None) -> bool:
        assert to is not None, "a datagram link needs a destination"
        try:
            if self.compact:
                self._send_compact(frame, to)
            elif len(frame) <= self.max_frame:
                self.endpoint.send(frame, to)
            elif self.bare:
                sender.drop("too_large_for_bare_framing",
                            f"{len(frame)} bytes, {self.name} carries at most {self.max_frame}")
                return False
            else:
                for piece in framing.fragment(frame, self.max_frame, sender.topic_id,
                                              next(self._frame_ids)):
                    self.endpoint.send(piece, to)
        except (OSError, framing.FramingError) as exc:
            sender.drop("send_error", f"to {to} on {self.name}: {exc}")
            return False
        return True

    def _send_compact(self, frame: bytes, to: Address) -> None:
        with self._send_lock:
            counter = self._counters.get(to, 0)
            pieces = framing.compact_fragment(frame, self.max_frame, counter)
            self._counters[to] = (counter + len(pieces)) & framing.COMPACT_COUNTER
            for piece in pieces:
                self.endpoint.send(piece, to)

    def _receive_loop(self) -> None:
        receive_into = getattr(self.endpoint, "receive_into", None)
        if receive_into is None:
            receive: Callable[[], tuple[bytes | memoryview, Address] | None] = \
                lambda: self.endpoint.receive(POLL)
        else:
            # one buffer for every datagram: longer than any frame this link accepts, so a
            # datagram that fills it is one too long
            buffer = memoryview(bytearray(max(self.max_frame, 65_535) + 1))

            def receive() -> tuple[bytes | memoryview, Address] | None:
                got = receive_into(buffer, POLL)
                if got is None:
                    return None
                size, source = got
                if size >= len(buffer):
                    self.on_lost(None, "oversized_datagram")
                    return None
                return buffer[:size], source

        closed = self.closed
        while not closed.is_set():
            try:
                got = receive()
            except OSError:
                if closed.is_set():
                    return
                continue
            except Exception:  # a transport plugin's bug must not silently end the link
                log.exception("%s: the transport's receive failed (a bug in the plugin)", self.name)
                self.on_lost(None, "transport_error")
                closed.wait(POLL)  # do not spin on a receive that fails at once
                continue
            if got is None:
                self.reassembler.expire()
                continue
            self._datagram(*got)

    def _datagram(self, datagram: bytes | memoryview, source: Address) -> None:
        """One datagram as it came (a view of the receive buffer, valid until the next one)."""
        if self.compact or not self.bare and datagram[:2] == framing.FRAGMENT_MAGIC:
            try:
                frame = self.reassembler.add(source, datagram)
            except framing.FramingError:
                self.on_lost(None, "bad_fragment")
                return
            if frame is not None:
                deliver(self, frame, source)
            return
        deliver(self, datagram if type(datagram) is bytes else bytes(datagram), source)

    def close(self) -> None:
        self.closed.set()
        self.endpoint.close()
        if threading.current_thread() is not self._thread:
            self._thread.join(timeout=2)


class StreamLink(Link):
    """One stream connection, framed with length prefixes."""

    def __init__(self, connection: StreamConnection, name: str, peer: Address,
                 on_frame: FrameHandler, on_lost: LostHandler,
                 on_close: Callable[[StreamLink], None] | None = None,
                 queue_frames: int = 10_000, queue_bytes: int = 64 * 1024 * 1024,
                 max_message: int = framing.DEFAULT_MAX_MESSAGE):
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
        self._queue: deque[tuple[bytes, Sender]] = deque()
        self._queued_bytes = 0
        self._writing = False  # the writer holds a batch not yet written
        self._wake = threading.Condition()
        self._reader = framing.StreamReader(max_message)
        self._threads = [
            threading.Thread(target=self._receive_loop, name=f"rx-{name}", daemon=True),
            threading.Thread(target=self._send_loop, name=f"tx-{name}", daemon=True),
        ]
        for thread in self._threads:
            thread.start()

    def send(self, frame: bytes, sender: Sender, to: Address | None = None) -> bool:
        if self.closed.is_set():
            sender.drop("link_down", f"{self.name} is closed")
            return False
        record = framing.length_prefixed(frame)
        with self._wake:
            if (len(self._queue) >= self.queue_frames
                    or self._queued_bytes + len(record) > self.queue_bytes):
                full = True
            else:
                full = False
                self._queue.append((record, sender))
                self._queued_bytes += len(record)
                self._wake.notify()
        if full:
            sender.drop("queue_full", f"{self.name} has {self.queue_frames} frames or "
                                      f"{self.queue_bytes} bytes waiting")
            return False
        return True

    def _send_loop(self) -> None:
        while True:
            with self._wake:
                self._writing = False
                self._wake.notify_all()  # for drain()
                while not self._queue and not self.closed.is_set():
                    self._wake.wait()
                if self.closed.is_set():
                    return
                # one write for everything queued: fewer system calls under load
                batch = list(self._queue)
                self._queue.clear()
                self._queued_bytes = 0
                self._writing = True
            try:
                self.connection.send(b"".join(record for record, _ in batch))
            except OSError as exc:
                for _, sender in batch:
                    sender.drop("link_down", f"{self.name}: send failed")
                self.fail(f"send failed: {exc}")
                return

    def drain(self, timeout: float) -> bool:
        """Wait until everything sent so far is written (a last word before closing)."""
        with self._wake:
            return self._wake.wait_for(
                lambda: not self._queue and not self._writing or self.closed.is_set(), timeout)

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
            unsent = [sender for _, sender in self._queue]
            self._queue.clear()
            self._queued_bytes = 0
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
                 on_lost: Callable[[StreamLink], None] | None = None):
        self.transport = transport
        self.address = address
        self.slot = slot
        self.on_frame = on_frame
        self.on_frame_lost = on_frame_lost
        self.life = life
        self.backoff = backoff
        self.on_connected = on_connected
        self.on_lost = on_lost
        self.connected = threading.Event()
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
        link = StreamLink(connection, self.slot.name, self.address, self.on_frame,
                          self.on_frame_lost, on_close=self.life.forget)
        if self.on_connected is not None and not self.on_connected(link):
            link.close()
            return None
        return link

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
