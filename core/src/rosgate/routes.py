"""Routes: one topic on one side of a link. The data path, top to bottom.

transmit (a ROS subscription callback):
    message -> codec.encode -> envelope header -> cipher.seal -> link.send (frames, fragments)
receive (called by the link's receive thread with a frame whose header names this topic):
    cipher.open -> replay window -> codec.decode -> ROS publish

Every drop is counted by reason in the route's :class:`Counters`, and warned about at most once
per :data:`WARN_EVERY` seconds per reason.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Any, Callable

from . import envelope
from .cipher import Cipher
from .codec import Codec
from .config import TopicConfig
from .errors import CipherError, CodecError
from .links import Link
from .transport import Address

log = logging.getLogger("rosgate")

WARN_EVERY = 5.0  # seconds between two warnings of one kind for one topic

# reasons that say something is wrong (a warning); the others are routine and only counted
QUIET_REASONS = {"rate_limit", "duplicate"}


@dataclass
class Counters:
    sent: int = 0
    received: int = 0
    bytes_sent: int = 0
    bytes_received: int = 0
    lost: int = 0  # sequence numbers skipped by the sender's frames and never filled in
    drops: Counter = field(default_factory=Counter)

    def snapshot(self) -> dict[str, Any]:
        return {"sent": self.sent, "received": self.received, "bytes_sent": self.bytes_sent,
                "bytes_received": self.bytes_received, "lost": self.lost,
                "drops": dict(self.drops)}


class Warner:
    """Rate-limited warnings: the first at once, then at most one per ``every`` seconds, saying
    how many were held back."""

    def __init__(self, every: float = WARN_EVERY):
        self.every = every
        self._last: dict[tuple[str, str], float] = {}
        self._held: Counter = Counter()
        self._lock = threading.Lock()

    def warn(self, subject: str, reason: str, detail: str) -> None:
        key = (subject, reason)
        now = time.monotonic()
        with self._lock:
            if now - self._last.get(key, -self.every) < self.every:
                self._held[key] += 1
                return
            self._last[key] = now
            held = self._held.pop(key, 0)
        more = f" ({held} more since the last warning)" if held else ""
        log.warning("%s: dropped (%s): %s%s", subject, reason, detail, more)


class Route:
    """A topic's path through the bridge in one direction."""

    def __init__(self, topic: TopicConfig, topic_id: int, codec: Codec, cipher: Cipher,
                 warner: Warner, label: str):
        self.topic = topic
        self.topic_id = topic_id
        self.codec = codec
        self.cipher = cipher
        self.warner = warner
        self.label = label  # how logs name this route: "/chatter (to robot1)"
        self.counters = Counters()
        self.entity: Any = None  # the ROS subscription or publisher

    def drop(self, reason: str, detail: str = "") -> None:
        self.counters.drops[reason] += 1
        if reason not in QUIET_REASONS:
            self.warner.warn(self.label, reason, detail or reason.replace("_", " "))

    def open(self, frame: bytes) -> bytes | None:
        """The frame's payload if the cipher accepts it; None (counted) when it does not."""
        try:
            return self.cipher.open(frame[:envelope.SIZE], frame[envelope.SIZE:])
        except CipherError as exc:
            self.drop("auth_failed", f"{exc} (wrong key, tampered, or not from the peer)")
            return None


class TransmitRoute(Route):
    """ROS subscription -> link."""

    def __init__(self, *args: Any, link: Link, destination: Callable[[], Address | None],
                 bare: bool = False, **kwargs: Any):
        super().__init__(*args, **kwargs)
        self.link = link
        self.destination = destination  # where to send, looked up per message (a server learns it)
        self.bare = bare
        self.epoch = int.from_bytes(os.urandom(4), "big")
        self.seq = 0
        rate = self.topic.max_rate
        self.min_interval_ns = int(1e9 / rate) if rate else 0
        self.last_sent_ns = 0
        self._lock = threading.Lock()  # a ROS callback group may call from several threads

    def on_message(self, message: Any) -> None:
        now = time.time_ns()
        if self.min_interval_ns and now - self.last_sent_ns < self.min_interval_ns:
            self.drop("rate_limit")
            return
        to = self.destination()
        if to is None and self.link.datagram:
            self.drop("no_peer_yet", "the far side's address is not known yet")
            return
        try:
            if self.bare:
                frame = self.codec.encode_bare(self.topic.remote, message)
            else:
                payload = self.codec.encode(message)
                with self._lock:
                    self.seq += 1
                    header = envelope.pack(0, self.topic_id, self.epoch, self.seq, now)
                frame = header + self.cipher.seal(header, payload)
        except Exception as exc:  # a codec or cipher bug must not stop the executor
            self.drop("encode_error", f"{type(exc).__name__}: {exc}")
            return
        if self.link.send(frame, self.topic_id, to):
            self.last_sent_ns = now
            self.counters.sent += 1
            self.counters.bytes_sent += len(frame)


class ReceiveRoute(Route):
    """Link -> ROS publisher."""

    def __init__(self, *args: Any, **kwargs: Any):
        super().__init__(*args, **kwargs)
        self.window = envelope.ReplayWindow()
        self.last_received = time.monotonic()
        self.stale_warnings_given = 0
        self._lock = threading.Lock()  # frames may come from several links (reconnects)

    def on_frame(self, header: envelope.Header, frame: bytes) -> None:
        payload = self.open(frame)
        if payload is None:
            return
        with self._lock:
            top = self.window.top(header.epoch)
            refused = self.window.accept(header.epoch, header.seq)
            if not refused and top is not None:
                # losses on the way: a jump over sequence numbers counts them, and a late frame
                # (reordered) that fills a gap takes one back
                self.counters.lost += header.seq - top - 1 if header.seq > top else -1
        if refused:
            self.drop(refused)
            return
        self.deliver(payload, len(frame), self.codec.decode)

    def on_bare(self, rest: bytes, size: int) -> None:
        self.deliver(rest, size, self.codec.decode_bare)

    def deliver(self, payload: bytes, size: int, decode: Callable[[bytes], Any]) -> None:
        try:
            message = decode(payload)
        except CodecError as exc:
            self.drop("decode_error", str(exc))
            return
        except Exception as exc:  # a codec must raise CodecError; anything else is its bug
            self.drop("decode_error", f"codec {self.codec.name} failed: {type(exc).__name__}: {exc}")
            return
        try:
            self.entity.publish(message)
        except Exception as exc:
            self.drop("publish_error", f"{type(exc).__name__}: {exc}")
            return
        self.counters.received += 1
        self.counters.bytes_received += size
        self.last_received = time.monotonic()
        self.stale_warnings_given = 0
