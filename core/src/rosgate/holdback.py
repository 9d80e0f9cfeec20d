"""What a client's reliable topics take while its server is out of reach (the main line down):
kept encoded but not sealed, in order, within the ``bridge.queue`` bounds, and sealed under the
session's keys once a main line is up again — the same session's, or a restarted server's new
one, so nothing waits under a key the far side no longer holds.

A stream link's messages wait here instead of going out. A datagram link's go out as ever (the
server may be up, only the main line lost) and a copy waits: when the server answers with the
same session the copies are forgotten; when it restarted (a new session), the old one died
with them, so they are sent again, sealed anew. A server that stops says ``bye`` first: from
then on nothing reliable goes out until the next session. Best-effort messages never wait: a
stream link counts them ``link_down``, and so does a datagram link those it sent to a server
that turned out to restart. What overflows the bounds, or outlives a topic's ``max_delay``, is
counted; what still waits when the bridge stops is counted ``link_down``.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Protocol

from .drops import Drop, Reason
from .warn import WARN_EVERY

log = logging.getLogger("rosgate")


class Holder(Protocol):
    """A transmitting route, as the holdback sees it."""

    max_wait_ns: int

    def drop(self, reason: Reason, detail: str = "") -> None:
        """Count one of its messages as dropped."""

    def send_again(self, held: list[Held], again: bool) -> None:
        """Seal ``held`` (its own, in order) under the keys of now and send them (``again``:
        copies of them went out before)."""


@dataclass(slots=True)
class Held:
    """One message taken while the far side was down: its payload, envelope flags and the time
    it was taken (ns), and whether a copy went out already (a datagram link's)."""

    route: Holder
    payload: bytes
    flags: int
    stamp: int
    sent: bool


@dataclass
class Holdback:
    """The held messages of one client, shared by its routes. ``down`` is read on every message
    without the lock (a route that read it True holds under the lock, and finds it False if
    :meth:`resume` ran meanwhile: it then sends after what was held)."""

    max_frames: int
    max_bytes: int
    down: bool = False
    _held: deque[Held] = field(default_factory=deque)
    _bytes: int = 0
    #: messages sent on datagram links while down that will not be sent again (best-effort
    #: ones, copies past the bounds), per route: lost if the server restarted
    _unconfirmed: dict[int, tuple[Holder, int]] = field(default_factory=dict)
    #: while down, a datagram link's reliable messages go out as well as waiting
    _copies: bool = False
    #: main lines lost so far (one may be lost while :meth:`resume` sends, on its thread)
    _failures: int = 0
    _lock: threading.RLock = field(default_factory=threading.RLock)
    _overflow_said: float = float("-inf")

    def fail(self) -> None:
        """The main line is down: reliable messages wait from now on (a datagram link's go out
        too, unless the server said it leaves or a handshake began)."""
        with self._lock:
            self._failures += 1
            if not self.down:
                self.down, self._copies = True, True

    def leave(self) -> None:
        """The server said it stops: nothing reliable goes out until the next session."""
        with self._lock:
            self.down, self._copies = True, False

    def handshake(self) -> None:
        """A main line is making its handshake: nothing reliable goes out until :meth:`resume`
        (the keys it brings may be a new session's), nor after, if it fails."""
        self.leave()

    def take(self, route: Holder, encoded: list[tuple[bytes, int, int]], reliable: bool,
             datagram: bool) -> bool:
        """Messages of ``route`` (payload, flags, time taken, in order) while :attr:`down`:
        kept when reliable. Whether they go out now as well: a datagram link's, unless the
        server said it leaves or a handshake began (then a best-effort one is counted
        ``link_down``); a stream link's best-effort ones (the link counts them); and any, once
        the far side is back."""
        overflow: list[Held] = []
        refused = 0
        with self._lock:
            if not self.down:
                return True
            now = datagram and self._copies
            if reliable:
                overflow = self._keep(route, encoded, now)
            elif now:
                self._unconfirm(route, len(encoded))
            elif datagram:  # the server left, or is answering: nobody would take them
                refused = len(encoded)
        for _ in range(refused):
            route.drop(Drop.LINK_DOWN, "the server is out of reach")
        if overflow:
            self._overflowed(overflow)
        return now or not (reliable or datagram)

    def _keep(self, route: Holder, encoded: list[tuple[bytes, int, int]],
              sent: bool) -> list[Held]:
        """Under the lock: ``encoded`` kept, and the oldest gone past the bounds; those that
        never went out, to be counted."""
        overflow = []
        for payload, flags, stamp in encoded:
            self._held.append(Held(route, payload, flags, stamp, sent))
            self._bytes += len(payload)
        while self._held and (len(self._held) > self.max_frames or self._bytes > self.max_bytes):
            gone = self._held.popleft()
            self._bytes -= len(gone.payload)
            if gone.sent:  # its copy went out: lost only if the server restarted
                self._unconfirm(gone.route, 1)
            else:
                overflow.append(gone)
        return overflow

    def _unconfirm(self, route: Holder, count: int) -> None:
        """Under the lock: ``count`` messages of ``route`` went out on a datagram link while the
        main line was down and wait for no resend: lost if the server restarted."""
        if count:
            _, before = self._unconfirmed.get(id(route), (route, 0))
            self._unconfirmed[id(route)] = (route, before + count)

    def _overflowed(self, gone: list[Held]) -> None:
        """The oldest messages went to make room: counted, and said once per burst."""
        for item in gone:
            item.route.drop(Drop.QUEUE_FULL, "the server is out of reach and the queue is full")
        now = time.monotonic()
        if now - self._overflow_said >= WARN_EVERY:
            self._overflow_said = now
            log.warning("the server is out of reach: reliable messages past bridge.queue "
                        "(%d frames, %d bytes) are dropped, the oldest first (queue_full)",
                        self.max_frames, self.max_bytes)

    def resume(self, new_session: bool) -> None:
        """A main line is up again: what waits is sealed under the keys of now and sent, in the
        order it was taken, before anything newer. ``new_session``: the server restarted, so
        what went out on datagram links meanwhile is sent again; else only what waited."""
        with self._lock:
            failures = self._failures
            held, self._held, self._bytes = list(self._held), deque(), 0
            unconfirmed, self._unconfirmed = list(self._unconfirmed.values()), {}
            if new_session:
                for route, count in unconfirmed:
                    for _ in range(count):
                        route.drop(Drop.LINK_DOWN, "sent while the main line was down, to a "
                                                   "server that restarted meanwhile")
            now, out = time.time_ns(), 0
            run: list[Held] = []
            for item in held:
                if item.sent and not new_session:
                    continue  # the server kept its session: the copy that went out arrived
                route = item.route
                if route.max_wait_ns and now - item.stamp > route.max_wait_ns:
                    route.drop(Drop.TOO_LATE, "waited longer than its max_delay for the "
                                              "server to come back")
                    continue
                if run and (run[-1].route is not route or run[-1].sent != item.sent):
                    run[0].route.send_again(run, run[0].sent)
                    run = []
                run.append(item)
                out += 1
            if run:
                run[0].route.send_again(run, run[0].sent)
            if out:
                log.info("%d reliable message(s) that waited for the server went out, sealed "
                         "under %s", out, "its new session's keys (it restarted)"
                         if new_session else "the session's keys")
            # a main line lost while these went out (fail, on this thread) keeps it down
            self.down = self._failures != failures

    @property
    def waiting(self) -> int:
        """Messages held now (copies that went out included)."""
        return len(self._held)

    def depth(self, route: Holder) -> int:
        """Messages of ``route`` held now."""
        with self._lock:
            return sum(1 for item in self._held if item.route is route)

    def forget(self, route: Holder) -> None:
        """A route that is gone: what it held goes, silently (as a link forgets it)."""
        with self._lock:
            kept = [item for item in self._held if item.route is not route]
            self._held = deque(kept)
            self._bytes = sum(len(item.payload) for item in kept)
            self._unconfirmed.pop(id(route), None)

    def close(self) -> None:
        """The bridge stops: what never went out is counted ``link_down``."""
        with self._lock:
            held, self._held, self._bytes = list(self._held), deque(), 0
        for item in held:
            if not item.sent:
                item.route.drop(Drop.LINK_DOWN, "the server was out of reach until the bridge "
                                                "stopped")
