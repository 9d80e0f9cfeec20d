"""Bus links: rosgate's side of a bus session (:mod:`rosgate_fleet.session`), one each.

A bus carries whole frames by key, so there is no framing here: no length prefix, no fragments,
no reconnection (the bus does those). What a link does:

* **One queue in, one thread.** Everything the session reports — frames, queries, answers to
  queries, liveliness — is queued by the bus library's thread and handled by the link's own
  thread, in arrival order. The bus library's callbacks must return at once (a slow one stalls
  the whole session), and the handlers above (cipher, codec, ROS publish) take their time.
  The queue is bounded: what arrives while it is full is dropped and counted
  (``queue_full``, against the topic when the subscription has one).
* **Outlets.** A route sends through a :class:`BusOutlet` (publish on its key), a
  :class:`BusCaller` (one query per service call) or the link's :class:`BusAnswerer` (the
  answer to a query that came in, found by the ``(key, number)`` it was handed over with as
  its source).

Every drop is counted: by the route that sent a frame, by the route a subscription belongs to,
or per bridge (``link_drop``) when a frame belongs to none.
"""

from __future__ import annotations

import itertools
import logging
import queue
import threading
import time
from collections.abc import Callable
from typing import Any

from rosgate import (
    BUGS,
    FLAG_ANNOUNCE,
    Address,
    Drop,
    EnvelopeError,
    FrameHandler,
    Link,
    LinkDrop,
    Reason,
    Sender,
    unpack_envelope,
)

from .session import BusPublisher, BusQuery, BusSession, FleetTransport, Handle

log = logging.getLogger("rosgate")

QUEUE_DEFAULT = 10_000  # items waiting for the link's thread before arrivals are dropped
POLL = 0.2  # seconds the thread waits for an item before looking after unanswered queries
QUERY_MARGIN = 1.0  # seconds a query outlives its call's timeout: the call's deadline goes first

#: a frame from a subscription: (its concrete key, the frame)
KeyedFrameHandler = Callable[[str, bytes], None]
#: a subscription's drops before its handler saw the frame: (concrete key, reason)
KeyedDrop = Callable[[str, Reason], None]


class BusLink:
    """A session on a bus, its inbound queue and the thread that drains it."""

    def __init__(self, transport: FleetTransport, session: BusSession, name: str,
                 link_drop: LinkDrop, queue_limit: int = QUEUE_DEFAULT):
        self.transport = transport
        self.session = session
        self.name = name
        self.link_drop = link_drop
        self.queue_limit = queue_limit
        self.closed = threading.Event()
        self.answerer = BusAnswerer(self)
        # (action, arguments), or None: stop
        self._inbox: queue.SimpleQueue[tuple[Callable[..., None], tuple] | None] = \
            queue.SimpleQueue()
        self._handles: list[Handle] = []
        self._pending: dict[int, tuple[BusQuery, float]] = {}  # queries served: number -> hold
        self._numbers = itertools.count(1)
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._loop, name=f"rx-{name}", daemon=True)
        self._thread.start()

    # -- what routes send through ---------------------------------------------------------------
    def outlet(self, key: str, reliable: bool, priority: int) -> BusOutlet:
        return BusOutlet(self, key, self.session.publisher(key, reliable=reliable,
                                                           priority=priority))

    def caller(self, key: str, timeout: float) -> BusCaller:
        return BusCaller(self, key, timeout + QUERY_MARGIN)

    # -- what comes in ----------------------------------------------------------------------------
    def subscribe(self, key_expr: str, on_frame: KeyedFrameHandler, drop: KeyedDrop) -> Handle:
        """Frames on keys matching ``key_expr`` go to ``on_frame(key, frame)`` on the link's thread;
        ``drop(key, reason)`` counts one the queue had no room for."""
        return self.keep(self.session.subscribe(key_expr, self.queued(on_frame, drop)))

    def queued(self, on_frame: KeyedFrameHandler, drop: KeyedDrop) -> KeyedFrameHandler:
        """A callback for the bus library's thread that queues each frame for ``on_frame`` on
        the link's thread (what :meth:`subscribe` declares; a bus's own kinds of subscription
        use it too, with :meth:`keep`)."""
        def arrived(key: str, frame: bytes) -> None:
            if not self._put(on_frame, (key, frame)):
                drop(key, Drop.QUEUE_FULL)

        return arrived

    def serve(self, key: str, on_frame: FrameHandler, hold: float) -> Handle:
        """Queries on ``key`` go to ``on_frame(frame, answerer, (key, number))``; the answer is
        sent through :attr:`answerer` to that source. A query nobody answers within ``hold``
        seconds is closed without an answer (its caller has given up by then)."""
        def arrived(concrete: str, payload: bytes, query: BusQuery) -> None:
            number = next(self._numbers)
            with self._lock:
                self._pending[number] = (query, time.monotonic() + hold)
            if not self._put(on_frame, (payload, self.answerer, (concrete, number))):
                self._finish(number)
                self.link_drop(self, Drop.QUEUE_FULL, f"a query on {concrete}")

        return self.keep(self.session.serve(key, arrived))

    def token(self, key: str) -> Handle:
        return self.keep(self.session.token(key))

    def watch(self, key_expr: str, on_change: Callable[[str, bool], None]) -> Handle:
        """Liveliness, in order with the frames: ``on_change(key, alive)`` on the link's thread.
        Never dropped for want of room: a missed departure would leave a robot forever."""
        return self.keep(self.session.watch(
            key_expr, lambda key, alive: self._inbox.put((on_change, (key, alive)))))

    def keep(self, handle: Handle) -> Handle:
        """Withdraw ``handle`` when the link closes."""
        with self._lock:
            self._handles.append(handle)
        return handle

    def declared_by(self, make: Callable[[], None]) -> list[Handle]:
        """What ``make()`` declared through this link (called on the link's thread, where
        routes are made): what to release when what it made goes."""
        with self._lock:
            mark = len(self._handles)
        make()
        with self._lock:
            return self._handles[mark:]

    def release(self, handle: Handle) -> None:
        """Withdraw a declaration made through this link."""
        with self._lock:
            if handle in self._handles:
                self._handles.remove(handle)
        handle.close()

    def call_later(self, action: Callable[..., None], *args: Any) -> None:
        """Run ``action(*args)`` on the link's thread, after what is queued (never dropped)."""
        self._inbox.put((action, args))

    def _put(self, action: Callable[..., None], args: tuple) -> bool:
        if self.closed.is_set() or self._inbox.qsize() >= self.queue_limit:
            return False
        self._inbox.put((action, args))
        return True

    # -- the link's thread ------------------------------------------------------------------------
    def _loop(self) -> None:
        next_sweep = time.monotonic() + POLL
        while True:
            try:
                item = self._inbox.get(timeout=POLL)
            except queue.Empty:
                pass  # nothing came: look after the queries
            else:
                if item is None:
                    return
                action, args = item
                try:
                    action(*args)
                except Exception:
                    BUGS.bug("handler_error", f"{self.name}: error while handling what the bus "
                                              "delivered (a bug: please report it)")
                    self.link_drop(self, Drop.HANDLER_ERROR, "see the traceback logged each minute")
            now = time.monotonic()
            if now >= next_sweep:  # under load too: a held query must not wait for a quiet moment
                next_sweep = now + POLL
                self._expire(now)

    def _expire(self, now: float) -> None:
        with self._lock:
            over = [n for n, (_, hold) in self._pending.items() if hold <= now]
        for number in over:
            self._finish(number)

    def take(self, number: int) -> BusQuery | None:
        """The query handed over as ``number``, if it is still open; it is then the caller's."""
        with self._lock:
            return self._pending.pop(number, (None, 0.0))[0]

    def _finish(self, number: int) -> BusQuery | None:
        query = self.take(number)
        if query is not None:
            try:
                query.close()
            except OSError:
                pass
        return query

    def close(self) -> None:
        if self.closed.is_set():
            return
        self.closed.set()
        with self._lock:
            handles, self._handles = self._handles, []
            numbers = list(self._pending)
        for number in numbers:
            self._finish(number)
        for handle in handles:
            try:
                handle.close()
            except Exception:  # the session is closed below in any case
                log.debug("%s: closing a declaration failed", self.name, exc_info=True)
        self.session.close()
        self._inbox.put(None)
        if threading.current_thread() is not self._thread:
            self._thread.join(timeout=2)


class BusOutlet(Link):
    """A route's publisher on its key."""

    def __init__(self, link: BusLink, key: str, publisher: BusPublisher):
        self.bus = link
        self.key = key
        self.publisher = publisher
        self.name = f"{link.name}:{key}"
        self.closed = link.closed

    def send(self, frame: bytes, sender: Sender, to: Address | None = None) -> bool:
        if self.closed.is_set():
            sender.drop(Drop.LINK_DOWN, f"{self.bus.name} is closed")
            return False
        try:
            self.publisher.put(frame)
        except OSError as exc:
            sender.drop(Drop.SEND_ERROR, f"on {self.key}: {exc}")
            return False
        return True

    def close(self) -> None:
        try:
            self.publisher.close()
        except OSError:
            pass


class BusCaller(Link):
    """A service's calls: each request frame is one query on the key; answers come back through
    the link's thread to ``on_frame`` (the router, which finds the call). A query no server
    answers fails its call at once (``no_server``). The caller's announcement of the entry
    (:mod:`rosgate.announce`) is a query too, which servers hear and close unanswered."""

    def __init__(self, link: BusLink, key: str, timeout: float):
        self.bus = link
        self.key = key
        self.timeout = timeout
        self.name = f"{link.name}:{key}"
        self.closed = link.closed
        self.on_answer: FrameHandler | None = None  # set by the role: the router's on_frame

    def send(self, frame: bytes, sender: Sender, to: Address | None = None) -> bool:
        if self.closed.is_set():
            sender.drop(Drop.LINK_DOWN, f"{self.bus.name} is closed")
            return False
        on_answer = self.on_answer
        assert on_answer is not None, "a caller's answers need a handler"
        bus = self.bus

        def answered(payload: bytes) -> None:
            bus.call_later(on_answer, payload, self, (self.key, 0))

        def done(answers: int) -> None:
            if not answers and not announcement:
                bus.call_later(sender.drop, Drop.NO_SERVER,
                               f"nothing on {bus.name} answered on {self.key} (no bridge serves "
                               "it, or it refused the call)")

        try:
            announcement = bool(unpack_envelope(frame).flags & FLAG_ANNOUNCE)
        except EnvelopeError:  # a call in another framing
            announcement = False

        try:
            bus.session.query(self.key, frame, self.timeout, answered, done)
        except OSError as exc:
            sender.drop(Drop.SEND_ERROR, f"query on {self.key}: {exc}")
            return False
        return True

    def close(self) -> None:
        pass


class BusAnswerer(Link):
    """Answers to queries that came in: ``to`` is the ``(key, number)`` a query was handed over
    with. An answer to a query that was closed meanwhile is counted ``late_answer``."""

    def __init__(self, link: BusLink):
        self.bus = link
        self.name = link.name
        self.closed = link.closed

    def send(self, frame: bytes, sender: Sender, to: Address | None = None) -> bool:
        assert to is not None
        query = self.bus.take(to[1]) if not self.closed.is_set() else None
        if query is None:
            sender.drop(Drop.LATE_ANSWER, f"the query on {to[0]} was closed before the answer")
            return False
        try:
            body = self.body(frame)
            if body is None:
                return False
            query.reply(body)
        except OSError as exc:
            sender.drop(Drop.SEND_ERROR, f"answer on {to[0]}: {exc}")
            return False
        finally:
            try:
                query.close()
            except OSError:
                pass
        return True

    def body(self, frame: bytes) -> bytes | None:
        """What answers the query: the frame itself. A bus plugin that speaks another
        convention may unwrap it (None: the query gets no answer)."""
        return frame

    def close(self) -> None:
        pass
