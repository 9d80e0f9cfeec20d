"""Links that come and go: a :class:`LinkSlot` is the place a route sends through, a
:class:`Connector` keeps it filled (connects, and reconnects after every loss), and a bridge's
:class:`Lifetime` closes whatever is still open when it stops.

While a slot is empty, frames of reliable senders wait in a bounded queue and leave in order
when a connection is attached; frames of other senders are dropped.
"""

from __future__ import annotations

import logging
import random
import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from .config import LinkConfig
from .drops import Drop, Reason
from .errors import LinkError
from .links import FrameHandler, Link, LinkCounters, LostHandler, Sender
from .streamlink import StreamLink
from .transport import Address, StreamConnection, StreamTransport, Transport

log = logging.getLogger("rosgate")

CONNECT_TIMEOUT = 5.0


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


@dataclass(frozen=True)
class QueueLimits:
    """How much a :class:`LinkSlot` holds for reliable topics while it has no connection."""

    frames: int
    bytes: int


class LinkSlot(Link):
    """A stream link that comes and goes. A :class:`Connector` (or a server that accepted the
    peer again) :meth:`attach`-es each new connection.

    While there is no live connection, frames of reliable senders wait, oldest
    dropped first when the limits are reached (counted ``queue_full``), and are handed to the
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

    def send_all(self, frames: list[bytes], sender: Sender, to: Address | None = None) -> int:
        overflow: list[Sender] = []
        with self._lock:
            link = self.current
            if link is not None and not link.closed.is_set():
                return link.send_all(frames, sender)
            if self.closed.is_set() or not sender.delivery.reliable:
                refused = True
            else:
                refused = False
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

    def attach(self, link: StreamLink) -> None:
        """Use ``link`` from now on; what waited goes first."""
        with self._lock:
            while self._waiting:
                frame, sender = self._waiting.popleft()
                link.send(frame, sender)
            self._waiting_bytes = 0
            self.current = link

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
        assert isinstance(transport, StreamTransport)
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
            if stopping.is_set() and not self.slot.closed.is_set():
                return  # the bridge is stopping: its role may have a last word (bye), then
                # closing the slot closes the link
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
        link = self.life.closing(StreamLink(connection, self.slot.name, self.address,
                                            self.on_frame, self.on_frame_lost,
                                            on_close=self.life.forget, budget=self.budget))
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
