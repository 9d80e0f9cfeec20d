"""The place a route sends through while stream connections come and go: frames of reliable
senders wait in it while there is none, and a main line's are written again on the next
connection when the far side says it never got them.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any

from ..drops import Drop, Reason
from ..links.base import Link, LinkCounters, Sender
from ..transport import Address
from ..wire import envelope
from .link import StreamLink

log = logging.getLogger("rosgate")

#: seconds a slot keeps a reliable frame it wrote, to write it again on the next connection when
#: the far side says it never got it (a connection dies with what its buffers held)
RESEND_WITHIN = 10.0

#: what the far side of a slot took: topic id -> epoch -> the newest sequence number
Taken = dict[int, dict[int, int]]


@dataclass(frozen=True)
class QueueLimits:
    """How much a :class:`LinkSlot` holds for reliable topics while it has no connection."""

    frames: int
    bytes: int


class LinkSlot(Link):
    """A stream link that comes and goes: a :class:`~.connector.Connector` (or a server that
    accepted the peer again) :meth:`attach`-es each new connection. While there is none, frames
    of reliable senders wait, oldest dropped first past the limits (``queue_full``), and go to
    the next connection first; other frames are counted ``link_down``. Frames handed to a
    connection that then fails are lost, unless the slot ``resends`` (a main line, whose
    handshake says what each side took): then they are kept a while (:data:`RESEND_WITHIN`,
    within the same limits), and the next connection of the same session writes again those the
    far side says it did not take (:meth:`attach`), before what waited."""

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

