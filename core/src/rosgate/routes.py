"""Routes: one topic on one side of a link. The data path, top to bottom.

transmit (a ROS subscription callback)::

    message -> codec.encode -> compress (optional) -> framing.frame (envelope header,
    cipher.seal) -> link.send

receive (a link's thread, with a frame whose header names this topic)::

    cipher.open -> replay window -> decompress (when the header says so) -> decode (codec, CDR
    check) -> ROS publish

The cipher of each frame comes from the route's :class:`~rosgate.keyring.Keys` by the
envelope's epoch: one static cipher, or a session's keys, which change with each key
generation and handshake (then a new epoch starts a new sequence).

The framing is a strategy chosen once per route from the entry's ``framing:``
(:class:`EnvelopeFraming`, or :class:`BareFraming` for datagrams without an envelope, whose
receiving topics share a :class:`BarePort`). Every drop is counted by reason in the route's
:class:`Counters`, and warned about at most once per :data:`WARN_EVERY` seconds per reason.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Any, Callable, ClassVar

from .codec import Codec
from .config import (PRIORITIES, RECOVERY_OVERHEAD_DEFAULT, Compression, Recovery,
                     ServiceConfig, TopicConfig)
from .errors import CipherError, CodecError
from .keyring import Keys, NoKey
from .links import Link
from .transport import Address
from .wire import envelope
from .wire.compression import CompressionError, Compressor, Decompressor
from .wire.framing import DEFAULT_MAX_MESSAGE
from .wire.names import NameMissing, pack_name, split_name

log = logging.getLogger("rosgate")

WARN_EVERY = 5.0  # seconds between two warnings of one kind for one topic

# reasons that say something is wrong (a warning); the others are routine and only counted
QUIET_REASONS = {"rate_limit", "duplicate", "superseded"}


@dataclass
class Counters:
    sent: int = 0
    received: int = 0
    bytes_sent: int = 0
    bytes_received: int = 0
    lost: int = 0  # sequence numbers skipped by the sender's frames and never filled in
    drops: Counter = field(default_factory=Counter)
    # the link's view (sender): every byte of every packet put on it for this topic — after
    # compression, with fragment headers, repair fragments and retransmissions; and how many
    # packets were sent again because a receiver asked (recovery: retransmit)
    bytes_on_wire: int = 0
    retransmitted: int = 0
    # receiver: frames that arrived whole only thanks to their recovery (fec, retransmit)
    recovered: int = 0
    # compression (sender): payload bytes before and after, and payloads sent as they were
    # because compressing did not make them smaller
    bytes_before_compression: int = 0
    bytes_after_compression: int = 0
    not_compressed: int = 0

    def snapshot(self) -> dict[str, Any]:
        return {"sent": self.sent, "received": self.received, "bytes_sent": self.bytes_sent,
                "bytes_received": self.bytes_received, "lost": self.lost,
                "drops": dict(self.drops),
                "bytes_before_compression": self.bytes_before_compression,
                "bytes_after_compression": self.bytes_after_compression,
                "not_compressed": self.not_compressed, "bytes_on_wire": self.bytes_on_wire,
                "retransmitted": self.retransmitted, "recovered": self.recovered}


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
    """A topic's (or service's) path through the bridge in one direction; the
    :class:`rosgate.links.Sender` of its frames."""

    #: what the link's scheduler and fragmentation read (a transmitting topic sets its own)
    priority: int = PRIORITIES["data"]
    latest_only = False
    max_delay: float | None = None  # None: the link's, for best effort
    recovery = Recovery.NONE.value
    recovery_overhead = RECOVERY_OVERHEAD_DEFAULT
    bare = False

    def __init__(self, entry: TopicConfig | ServiceConfig, topic_id: int, codec: Any,
                 keys: Keys, warner: Warner, label: str, reliable: bool = False):
        self.entry = entry
        self.topic_id = topic_id
        self.codec = codec
        self.keys = keys
        self.warner = warner
        self.label = label  # how logs name this route: "/chatter (to robot1)"
        self.reliable = reliable  # frames wait out a stream link's loss (reliable QoS)
        self.counters = Counters()
        self.entity: Any = None  # the ROS subscription, publisher, service or client

    def on_wire(self, size: int, again: bool) -> None:
        """A packet of ``size`` bytes left on the link for this route (``again``: re-sent)."""
        self.counters.bytes_on_wire += size
        if again:
            self.counters.retransmitted += 1

    def drop(self, reason: str, detail: str = "") -> None:
        self.counters.drops[reason] += 1
        if reason not in QUIET_REASONS:
            self.warner.warn(self.label, reason, detail or reason.replace("_", " "))

    def seal(self, flags: int, epoch: int, seq: int, payload: bytes,
             stamp: int | None = None) -> bytes:
        """An envelope frame of this route: the header, then the payload sealed with it."""
        header = envelope.pack(flags, self.topic_id, epoch, seq,
                               time.time_ns() if stamp is None else stamp)
        return header + self.keys.sealer(epoch).seal(header, payload)

    def open(self, frame: bytes, epoch: int) -> bytes | None:
        """An envelope frame's payload if the cipher of its epoch accepts it; None (counted)
        when it does not."""
        cipher = self.keys.opener(epoch)
        if cipher is None:
            self.drop("unknown_key", "sealed under a key this side does not hold (an earlier "
                                     "session, a restart, or an expired key generation)")
            return None
        try:
            return cipher.open(frame[:envelope.SIZE], frame[envelope.SIZE:])
        except CipherError as exc:
            self.drop("auth_failed", f"{exc} (wrong key, tampered, or not from the peer)")
            return None


class TopicFraming:
    """How a topic's payloads become frames, chosen once per route."""

    #: True: datagrams carry the payload alone (no envelope, no fragments, no cipher)
    bare: ClassVar[bool]

    def frame(self, route: TransmitRoute, payload: bytes, stamp: int, flags: int = 0) -> bytes:
        """``flags``: the envelope's (FLAG_COMPRESSED); a bare frame has none."""
        raise NotImplementedError


class EnvelopeFraming(TopicFraming):
    """``framing: rosgate``: the 28-byte envelope (topic id, the sender's epoch and sequence
    number, the send time), then the payload sealed by the topic's cipher, which authenticates
    the header too. Receivers are found by topic id (the router) and keep a replay window."""

    bare = False

    def frame(self, route: TransmitRoute, payload: bytes, stamp: int, flags: int = 0) -> bytes:
        with route.lock:
            epoch = route.keys.epoch()
            if epoch != route.epoch:  # a new key: a new sequence under it
                route.epoch, route.seq = epoch, 0
            route.seq += 1
            seq = route.seq
        return route.seal(flags, epoch, seq, payload, stamp)


class BareFraming(TopicFraming):
    """``framing: none``: one datagram per message, the codec's bytes alone — after the topic's
    ``remote`` name as a MessagePack str when the codec writes MessagePack (the CVRA format), so
    several topics can share a port."""

    bare = True

    def __init__(self, name: str | None):
        self.prefix = pack_name(name) if name is not None else b""

    def frame(self, route: TransmitRoute, payload: bytes, stamp: int, flags: int = 0) -> bytes:
        return self.prefix + payload


class TransmitRoute(Route):
    """ROS subscription -> link."""

    def __init__(self, topic: TopicConfig, topic_id: int, codec: Codec, keys: Keys,
                 warner: Warner, label: str, reliable: bool, *, framing: TopicFraming,
                 link: Link, destination: Callable[[], Address | None],
                 priority: int = PRIORITIES["data"], latest_only: bool = False):
        super().__init__(topic, topic_id, codec, keys, warner, label, reliable)
        self.topic = topic
        self.framing = framing
        self.link = link
        self.priority = priority
        self.latest_only = latest_only
        self.max_delay = topic.max_delay
        self.recovery = topic.recovery.value
        self.recovery_overhead = topic.recovery_overhead
        self.bare = framing.bare
        self.destination = destination  # where to send, looked up per message (a server learns it)
        self.epoch: int | None = None  # of the key in use, set by the first frame
        self.seq = 0
        rate = topic.max_rate
        self.min_interval_ns = int(1e9 / rate) if rate else 0
        self.last_sent_ns = 0
        self.lock = threading.Lock()  # a ROS callback group may call from several threads
        self.compressor = (Compressor(topic.compression_level)
                           if topic.compression is Compression.ZSTD else None)

    def encode(self, message: Any) -> tuple[bytes, int]:
        """The message's payload, compressed when that makes it smaller; and the envelope flags
        that say so."""
        payload = self.codec.encode(message)
        if self.compressor is None:
            return payload, 0
        packed = self.compressor.compress(payload)
        counters = self.counters
        counters.bytes_before_compression += len(payload)
        if packed is None:
            counters.bytes_after_compression += len(payload)
            counters.not_compressed += 1
            return payload, 0
        counters.bytes_after_compression += len(packed)
        return packed, envelope.FLAG_COMPRESSED

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
            payload, flags = self.encode(message)
            frame = self.framing.frame(self, payload, now, flags)
        except NoKey:
            self.drop("no_session_key", "the session's handshake has not happened yet")
            return
        except Exception as exc:  # a codec or cipher bug must not stop the executor
            self.drop("encode_error", f"{type(exc).__name__}: {exc}")
            return
        if self.link.send(frame, self, to):
            self.last_sent_ns = now
            self.counters.sent += 1
            self.counters.bytes_sent += len(frame)

    @property
    def queue_depth(self) -> int:
        """Its messages waiting in the link, or being sent, now."""
        depth = getattr(self.link, "queue_depth", None)
        return depth(self) if depth is not None else 0

    def close(self) -> None:
        """The route is removed: what it queued goes (a message half sent is not finished)."""
        forget = getattr(self.link, "forget", None)
        if forget is not None:
            forget(self)


class ReceiveRoute(Route):
    """Link -> ROS publisher."""

    def __init__(self, topic: TopicConfig, topic_id: int, codec: Codec, keys: Keys,
                 warner: Warner, label: str, reliable: bool, *,
                 decode: Callable[[bytes], Any]):
        super().__init__(topic, topic_id, codec, keys, warner, label, reliable)
        self.topic = topic
        self.decode = decode  # the codec's, with a CDR check where no cipher authenticates
        self.window = envelope.ReplayWindow()
        self.last_received = time.monotonic()
        self.stale_warnings_given = 0
        self._lock = threading.Lock()  # frames may come from several links (reconnects)
        #: whatever this side's file says: the sender's envelope says what it compressed
        self.decompressor = Decompressor(DEFAULT_MAX_MESSAGE)

    def on_frame(self, header: envelope.Header, frame: bytes) -> None:
        """An envelope frame (framing rosgate), found by its topic id."""
        payload = self.open(frame, header.epoch)
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
        if header.flags & envelope.FLAG_COMPRESSED:
            try:
                payload = self.decompressor.decompress(payload)
            except CompressionError as exc:
                self.drop("decompression_error", str(exc))
                return
        self.deliver(payload, len(frame))

    def deliver(self, payload: bytes, size: int) -> None:
        """Decode and publish; ``size`` is what arrived on the link, for the counters."""
        try:
            message = self.decode(payload)
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


class BarePort:
    """The receiving topics of one port with ``framing: none``: told apart by the name in front
    of each datagram when their codec writes MessagePack, else the port's only topic.
    ``link_drop(link, reason, detail)`` counts a datagram that belongs to none of them."""

    def __init__(self, named: bool, link_drop: Callable[[Link, str, str], None]):
        self.named = named
        self.link_drop = link_drop
        self.routes: dict[str, ReceiveRoute] = {}
        self.only: ReceiveRoute | None = None

    def add(self, route: ReceiveRoute, names: set[str]) -> None:
        if self.named:
            for name in names:
                self.routes[name] = route
        else:
            self.only = route

    @property
    def receivers(self) -> list[ReceiveRoute]:
        return list({id(r): r for r in self.routes.values()}.values()) if self.named \
            else [self.only] if self.only is not None else []

    def on_frame(self, datagram: bytes, link: Link, source: Address) -> None:
        if not self.named:
            if self.only is not None:
                self.only.deliver(datagram, len(datagram))
            return
        try:
            name, rest = split_name(datagram)
        except NameMissing as exc:
            self.link_drop(link, "unnamed_frame", f"{len(datagram)} bytes from {source}: {exc}")
            return
        route = self.routes.get(name)
        if route is None:
            self.link_drop(link, "unknown_topic", f"name {name!r} from {source}")
            return
        route.deliver(rest, len(datagram))
