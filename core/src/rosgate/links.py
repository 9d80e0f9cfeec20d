"""Links: the core's side of a transport. Framing, fragmentation and threads live here, so a
transport plugin only opens sockets.

* :class:`DatagramLink` — one bound endpoint; sends whole frames or fragments, reassembles,
  and hands every frame to ``on_frame``. A transport with small frames (``max_frame`` below
  ``framing.COMPACT_BELOW``, such as CAN) gets the compact fragment scheme instead. In bare
  mode (``framing: none``) it hands over the datagram untouched.
* :class:`StreamLink` — one connection; frames carry a length prefix. Sending never blocks the
  caller: frames wait in a bounded queue for a writer thread.
* :class:`LinkSlot` — a place for a stream link that comes and goes (reconnects). While it is
  empty, frames of reliable topics wait in a bounded queue and leave in order when a connection
  is attached; frames of other topics are dropped.
* :class:`Acceptor` — accepts stream connections and hands each to ``on_connection``.

Every receive loop catches what a peer's bytes can cause and counts it; a link never dies of input.
"""

from __future__ import annotations

import itertools
import logging
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Callable, Collection

from . import envelope, framing
from .transport import Address, DatagramEndpoint, StreamConnection, StreamListener, Transport

log = logging.getLogger("rosgate")

FrameHandler = Callable[[bytes, "Link", Address], None]
DropHandler = Callable[[int | None, str], None]  # topic id (None: unknown), reason

POLL = 0.2  # seconds a receive waits before checking whether the link is closing


class Link:
    """What a route sends through and what frames are reported from."""

    name: str
    closed: threading.Event
    #: datagram links need a destination for every send; stream links are connected
    datagram: bool = False

    def send(self, frame: bytes, topic_id: int, to: Address | None = None) -> bool:
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError


class DatagramLink(Link):
    datagram = True

    def __init__(self, transport: Transport, endpoint: DatagramEndpoint, name: str,
                 on_frame: FrameHandler, on_drop: DropHandler, bare: bool = False,
                 max_message: int = framing.DEFAULT_MAX_MESSAGE):
        self.transport = transport
        self.endpoint = endpoint
        self.name = name
        self.bare = bare
        self.max_frame = transport.max_frame
        self.on_frame = on_frame
        self.on_drop = on_drop
        self.closed = threading.Event()
        # small frames cannot spare 14 bytes of fragment header: every frame goes as compact pieces
        self.compact = not bare and self.max_frame < framing.COMPACT_BELOW
        self.reassembler: framing.Reassembler | framing.CompactReassembler
        if self.compact:
            self.reassembler = framing.CompactReassembler(on_drop, envelope.topic_of,
                                                          max_message=max_message)
        else:
            self.reassembler = framing.Reassembler(on_drop, max_message=max_message)
        self._frame_ids = itertools.count(1)
        self._counters: dict[Address, int] = {}  # compact: the next piece's counter per destination
        # compact pieces carry no frame id: one frame's pieces must not interleave with another's
        self._send_lock = threading.Lock()
        self._thread = threading.Thread(target=self._receive_loop, name=f"rx-{name}", daemon=True)
        self._thread.start()

    def send(self, frame: bytes, topic_id: int, to: Address | None = None) -> bool:
        assert to is not None, "a datagram link needs a destination"
        try:
            if self.compact:
                self._send_compact(frame, to)
            elif len(frame) <= self.max_frame:
                self.endpoint.send(frame, to)
            elif self.bare:
                self.on_drop(topic_id, "too_large_for_bare_framing")
                return False
            else:
                for piece in framing.fragment(frame, self.max_frame, topic_id, next(self._frame_ids)):
                    self.endpoint.send(piece, to)
        except (OSError, framing.FramingError) as exc:
            self.on_drop(topic_id, "send_error")
            log.debug("%s: send to %s failed: %s", self.name, to, exc)
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
        while not self.closed.is_set():
            try:
                got = self.endpoint.receive(POLL)
            except OSError:
                if self.closed.is_set():
                    return
                continue
            except Exception:  # a transport plugin's bug must not silently end the link
                log.exception("%s: the transport's receive failed (a bug in the plugin)", self.name)
                self.on_drop(None, "transport_error")
                self.closed.wait(POLL)  # do not spin on a receive that fails at once
                continue
            if got is None:
                self.reassembler.expire()
                continue
            datagram, source = got
            if self.compact or not self.bare and framing.is_fragment(datagram):
                try:
                    frame = self.reassembler.add(source, datagram)
                except framing.FramingError:
                    self.on_drop(None, "bad_fragment")
                    continue
                if frame is None:
                    continue
                datagram = frame
            deliver(self, datagram, source)

    def close(self) -> None:
        self.closed.set()
        self.endpoint.close()
        if threading.current_thread() is not self._thread:
            self._thread.join(timeout=2)


class StreamLink(Link):
    """One stream connection, framed with length prefixes."""

    def __init__(self, connection: StreamConnection, name: str, peer: Address,
                 on_frame: FrameHandler, on_drop: DropHandler,
                 on_close: Callable[["StreamLink"], None] | None = None,
                 queue_frames: int = 10_000, queue_bytes: int = 64 * 1024 * 1024,
                 max_message: int = framing.DEFAULT_MAX_MESSAGE):
        self.connection = connection
        self.name = name
        self.peer = peer
        self.on_frame = on_frame
        self.on_drop = on_drop
        self.on_close = on_close
        self.closed = threading.Event()
        # for liveness: the main line's roles set it on every control message (a heartbeat), not
        # on bytes, so a stream that lost its frame boundaries does not look alive
        self.last_heard = time.monotonic()
        self.why = ""  # why the connection ended, once it has
        self.queue_frames = queue_frames
        self.queue_bytes = queue_bytes
        self._queue: deque[tuple[bytes, int]] = deque()
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

    def send(self, frame: bytes, topic_id: int, to: Address | None = None) -> bool:
        if self.closed.is_set():
            self.on_drop(topic_id, "link_down")
            return False
        record = framing.length_prefixed(frame)
        with self._wake:
            if (len(self._queue) >= self.queue_frames
                    or self._queued_bytes + len(record) > self.queue_bytes):
                self.on_drop(topic_id, "queue_full")
                return False
            self._queue.append((record, topic_id))
            self._queued_bytes += len(record)
            self._wake.notify()
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
                for _, topic_id in batch:
                    self.on_drop(topic_id, "link_down")
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
                self.on_drop(None, "transport_error")
                self._fail(f"transport error: {type(exc).__name__}: {exc}")
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
                self.on_drop(None, "bad_length")
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
            unsent = [topic_id for _, topic_id in self._queue]
            self._queue.clear()
            self._queued_bytes = 0
        for topic_id in unsent:
            self.on_drop(topic_id, "link_down")
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

    While there is no live connection, frames of the topics in :attr:`reliable` wait, oldest
    dropped first when the limits are reached (counted ``queue_overflow``), and are handed to the
    next connection in order, before anything sent later. Other frames are counted ``link_down``.
    Frames already handed to a connection that then fails are not taken back (there are no
    acknowledgements): a connection's loss can cost what was in flight.
    """

    def __init__(self, name: str, on_drop: DropHandler, limits: QueueLimits):
        self.name = name
        self.on_drop = on_drop
        self.limits = limits
        self.current: StreamLink | None = None
        #: routes whose frames wait for the link (looked up by topic id when the link is down)
        self.reliable: Collection = ()
        self.closed = threading.Event()
        self._waiting: deque[tuple[bytes, int]] = deque()
        self._waiting_bytes = 0
        self._lock = threading.Lock()  # keeps sends and the flush of the queue in order

    def send(self, frame: bytes, topic_id: int, to: Address | None = None) -> bool:
        with self._lock:
            link = self.current
            if link is not None and not link.closed.is_set():
                return link.send(frame, topic_id)
            if self.closed.is_set() or not any(r.topic_id == topic_id for r in self.reliable):
                self.on_drop(topic_id, "link_down")
                return False
            self._waiting.append((frame, topic_id))
            self._waiting_bytes += len(frame)
            while self._waiting and (len(self._waiting) > self.limits.frames
                                     or self._waiting_bytes > self.limits.bytes):
                old, old_topic = self._waiting.popleft()
                self._waiting_bytes -= len(old)
                self.on_drop(old_topic, "queue_overflow")
            return True

    def attach(self, link: StreamLink) -> None:
        """Use ``link`` from now on; what waited goes first."""
        with self._lock:
            while self._waiting:
                frame, topic_id = self._waiting.popleft()
                link.send(frame, topic_id)
            self._waiting_bytes = 0
            self.current = link

    def discard(self, reason: str) -> None:
        """Drop what waits (its topic ids mean nothing to a new session), counted by ``reason``."""
        with self._lock:
            for _, topic_id in self._waiting:
                self.on_drop(topic_id, reason)
            self._waiting.clear()
            self._waiting_bytes = 0

    @property
    def waiting(self) -> int:
        return len(self._waiting)

    def close(self) -> None:
        self.closed.set()
        self.discard("link_down")
        if self.current is not None:
            self.current.close()


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
        link.on_drop(None, "handler_error")
