"""The hold in front of a publisher the bridge makes, until that publisher has matched the
subscriptions waiting for it (why: :mod:`rosgate.endpoints`). It holds at most :data:`HOLD_FOR`
seconds after the publisher was made and at most :data:`HOLD_COUNT` messages (the oldest make
room, each counted); then it publishes what it holds, in order."""

from __future__ import annotations

import itertools
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

#: seconds a new publisher holds at most before it publishes what it holds, matched or not (a
#: subscription the graph shows may never match: its node went, or a policy besides reliability
#: and durability differs)
HOLD_FOR = 5.0
#: messages a new publisher holds at most
HOLD_COUNT = 1000
#: seconds after the publisher was made before it publishes, matched: for the subscriptions
#: that were there before it to learn of it
SETTLE = 0.1
#: seconds between two looks at the publisher's matches while it holds
LOOK_EVERY = 0.01
#: seconds a release may spend waiting for its subscribers to acknowledge, in all
PACE_FOR = 2.0
#: seconds a released hold waits at most for one history's worth to be acknowledged
PACE_EACH = 0.5


class PublishGate:
    """``publish`` behind a hold until ``matched()`` (and :data:`SETTLE` seconds have passed),
    or :data:`HOLD_FOR` passed, or ``matched()`` says None: nobody to wait for.
    ``lost(reason, count)`` counts what the hold could not keep: ``"full"`` (the oldest pushed
    out), ``"closed"`` (the route ended while it held);
    ``failed(exc)`` a publish that raised on the releasing thread; ``opened(publish)`` is told
    when the hold is over, so the route publishes straight through ``publish`` from then on
    (the gate stays off the data path).

    A reliable publisher keeps only its history's depth of messages its subscribers have not
    acknowledged: a release of more in one go overwrites what a subscriber missed in the burst
    before it can ask for it again (measured: of a 137-message release through a depth-10
    publisher, a subscriber got 24). So the release publishes ``every`` messages at a time and
    calls ``pace()`` (wait until the subscribers acknowledged) in between, for at most
    :data:`PACE_FOR` seconds in all; ``every=0``: in one go (best effort: nothing to wait for)."""

    def __init__(self, publish: Callable[[Any], None], matched: Callable[[], bool | None],
                 lost: Callable[[str, int], None], failed: Callable[[Exception], None],
                 opened: Callable[[Callable[[Any], None]], None],
                 pace: Callable[[], Any] = lambda: None, every: int = 0):
        self._publish = publish
        self._opened = opened
        self._pace = pace
        self._every = every
        self._matched = matched
        self._lost = lost
        self._failed = failed
        self._held: deque[Any] = deque()
        self._lock = threading.Lock()
        self._closed = threading.Event()
        #: set once the hold is over: publish goes straight to ``publish``
        self.open = False
        self._thread = threading.Thread(target=self._wait, name="publisher-match", daemon=True)
        self._thread.start()

    def __call__(self, message: Any) -> None:
        if self.open:
            self._publish(message)
            return
        with self._lock:
            if not self.open:
                self._hold(message)
                return
        self._publish(message)  # the hold ended while this one waited for the lock

    def _hold(self, message: Any) -> None:
        if len(self._held) >= HOLD_COUNT:
            self._held.popleft()
            self._lost("full", 1)
        self._held.append(message)

    def _wait(self) -> None:
        clock = time.monotonic
        made = clock()
        while not self._closed.wait(LOOK_EVERY):
            now = clock()
            if now - made >= HOLD_FOR:
                break
            try:
                matched = self._matched()
            except Exception:  # the publisher was destroyed meanwhile: the close follows
                matched = False
            # SETTLE from the publisher's making: a subscription there before it learns of it
            # from its announcement; one that comes later knows it already
            if matched is None or matched and now - made >= SETTLE:
                break
        self._release()

    def _release(self) -> None:
        deadline = time.monotonic() + PACE_FOR
        with self._lock:  # what arrives meanwhile waits: it goes after the backlog
            if self._closed.is_set():
                return
            for sent in itertools.count():
                if not self._held:
                    break
                if self._every and sent and sent % self._every == 0 \
                        and time.monotonic() < deadline:
                    self._pace()
                try:
                    self._publish(self._held.popleft())
                except Exception as exc:
                    self._failed(exc)
            self.open = True
            publish = self._publish
        self._opened(publish)  # outside the lock: the router takes its own

    def hand_over(self, successor: PublishGate) -> None:
        """A new publisher replaces this one: what this one holds goes first in the successor's
        hold (or out through it, if it holds no longer), and so does whatever comes here after."""
        with self._lock:
            held, self._held = list(self._held), deque()
            self._closed.set()
            self._publish = successor
            self.open = True
        successor.take_first(held)

    def take_first(self, messages: list[Any]) -> None:
        with self._lock:
            if not self.open:
                self._held.extendleft(reversed(messages))
                while len(self._held) > HOLD_COUNT:
                    self._held.popleft()
                    self._lost("full", 1)
                return
        for message in messages:
            try:
                self._publish(message)
            except Exception as exc:
                self._failed(exc)

    def close(self) -> None:
        """The route ends: what is held is lost (counted)."""
        with self._lock:
            if self._closed.is_set():
                return
            self._closed.set()
            held, self._held = len(self._held), deque()
            self.open = True
            self._publish = _nowhere
        if held:
            self._lost("closed", held)


def _nowhere(message: Any) -> None:
    """Where a closed gate sends what still reaches it: ROS has no publisher for it any more."""
    raise RuntimeError("the route's publisher is gone")
