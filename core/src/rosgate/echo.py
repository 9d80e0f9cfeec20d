"""No echo between two peers that both send and receive one name: each bridge's publisher of the
name (what the far side sent) and its subscription of it (what this side's own publishers send)
meet in one DDS domain, and rclpy cannot make a subscription ignore its own participant's
publishers. So each message the receiving route publishes is remembered (a digest of its CDR)
for :data:`ECHO_WAIT` seconds, and the transmitting route of the name drops the one copy of it
that comes back (``echo``, counted): what a bridge brings in never goes back out."""

from __future__ import annotations

import hashlib
import threading
import time
from collections import Counter, deque
from typing import Any

ECHO_WAIT = 5.0  # seconds a published message's echo is waited for (then forgotten)
MAX_WAITING = 10_000  # echoes waited for at once (the oldest is forgotten first)


def _digest(message: Any) -> bytes:
    """A message's digest, by its CDR (raw routes carry the CDR itself)."""
    if not isinstance(message, bytes | bytearray | memoryview):
        from rclpy.serialization import serialize_message

        message = serialize_message(message)
    return hashlib.blake2b(message, digest_size=16).digest()


class EchoGuard:
    """The messages one name's receiving route published, until its transmitting route takes
    each back once."""

    def __init__(self, wait: float = ECHO_WAIT, clock: Any = time.monotonic):
        self.wait, self.clock = wait, clock
        self._waiting: Counter[bytes] = Counter()  # published, not yet taken back
        self._taken: Counter[bytes] = Counter()  # taken back, still in the order (the oldest)
        self._order: deque[tuple[float, bytes]] = deque()
        self._lock = threading.Lock()

    def publishing(self, message: Any) -> None:
        """The receiving route publishes ``message`` (called before it does: the echo may come
        back at once)."""
        digest, now = _digest(message), self.clock()
        with self._lock:
            self._forget(now)
            self._waiting[digest] += 1
            self._order.append((now, digest))

    def returned(self, message: Any) -> bool:
        """Whether ``message``, taken by the transmitting route, is one the bridge published."""
        digest = _digest(message)
        with self._lock:
            self._forget(self.clock())
            if not self._waiting.get(digest):
                return False
            self._waiting[digest] -= 1
            self._taken[digest] += 1
            return True

    def _forget(self, now: float) -> None:
        """Publications older than the wait go, the oldest of a digest first (taken back or
        not)."""
        order = self._order
        while order and (now - order[0][0] > self.wait or len(order) > MAX_WAITING):
            _, digest = order.popleft()
            counts = self._taken if self._taken[digest] else self._waiting
            counts[digest] -= 1
            if counts[digest] <= 0:
                del counts[digest]
