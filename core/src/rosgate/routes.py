"""Routes: one topic on one side of a link. The data path, top to bottom.

transmit (a ROS subscription callback)::

    message -> codec.encode -> transform (compression, optional) -> framing.frame (envelope
    header, cipher.seal) -> link.send

receive (a link's thread, with a frame whose header names this topic)::

    cipher.open -> replay window -> transform back (when the header says so, by the transform's
    wire id) -> decode (codec, CDR check) -> ROS publish

The cipher of each frame comes from the route's :class:`~rosgate.keyring.Keys` by the
envelope's epoch: one static cipher, or a session's keys, which change with each key
generation and handshake (then a new epoch starts a new sequence).

The framing is a strategy chosen once per route from the entry's ``framing:``
(:class:`EnvelopeFraming`, or :class:`BareFraming` for datagrams without an envelope, whose
receiving topics share a :class:`BarePort`). Every drop is counted by reason in the route's
:class:`Counters`, and warned about at most once per :data:`rosgate.warn.WARN_EVERY` seconds per
reason.
"""

from __future__ import annotations

import itertools
import logging
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from typing import Any, cast

from . import announce
from .announce import Identity, TypeCheck
from .batch import Batches
from .builtin import NoCipher
from .codec import Codec
from .config import ServiceConfig, TopicConfig
from .drops import Drop, Reason
from .errors import CipherError, CodecError
from .keyring import Keys, NoKey, StaticKeys
from .links import Link
from .spec import CONTROL, Delivery
from .transform import Transform, TransformError
from .transport import Address
from .warn import Warner
from .wire import envelope
from .wire.names import LAYOUT_DEFAULT, Layout, NameMissing, pack_name, split_name

log = logging.getLogger("rosgate")

# a transmitting route takes what waits in its subscription up to this much at a time
DRAIN_FRAMES = 32
DRAIN_BYTES = 60_000
# and when a batch window closes (many datagrams' worth: send_all cuts them)
BATCH_FRAMES = 512
BATCH_BYTES = 1_000_000
# a payload at least this long is sealed straight into its frame (a bytearray) by a cipher that
# can: no copy of an image to put the header in front. Shorter frames stay bytes.
SEAL_IN_PLACE = 64 * 1024

# reasons that say something is wrong (a warning); the others are routine and only counted
QUIET_REASONS = {Drop.RATE_LIMIT, Drop.DUPLICATE, Drop.SUPERSEDED}


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
        """Every counter, the drops as a plain mapping."""
        return {**{f.name: getattr(self, f.name) for f in fields(self)}, "drops": dict(self.drops)}


class Route:
    """A topic's (or service's) path through the bridge in one direction; the
    :class:`rosgate.links.Sender` of its frames."""

    #: the sending side of an entry with an envelope: says its type (and QoS) on its link
    announces = False
    #: the entry's ROS class (a message or a service), set with its ROS entity
    interface: Any = None
    #: what :meth:`admit` refuses for skipped sequence numbers is a loss on the way
    counts_lost = False
    link: Link
    destination: Callable[[], Address | None]

    def __init__(self, entry: TopicConfig | ServiceConfig, topic_id: int, codec: Any,
                 keys: Keys, warner: Warner, label: str, delivery: Delivery = Delivery()):
        self.entry = entry
        self.topic_id = topic_id
        self.codec = codec
        self.keys = keys
        self.warner = warner
        self.label = label  # how logs name this route: "/chatter (to robot1)"
        self.delivery = delivery  # what the link reads of each of its frames
        self.counters = Counters()
        self.entity: Any = None  # the ROS subscription, publisher, service or client
        #: the none cipher: a frame's body is its payload (decided once, not per frame)
        self.plain = isinstance(keys, StaticKeys) and type(keys.cipher).open is NoCipher.open
        #: a reassembled frame's bytearray may go on as the payload (see open)
        self.zero_copy = False
        #: see :func:`max_wait_ns` (services have their own deadlines)
        self.max_wait_ns = max_wait_ns(entry) if isinstance(entry, TopicConfig) else 0
        #: the entry's type against the far side's (the router gives this side's hash)
        self.check = TypeCheck(label, Identity(entry.type, None))
        #: a receiving side's sequence numbers: without a cipher that vouches for the header,
        #: one forged frame may not move it
        self.replay = envelope.ReplayWindow(authenticated=keys.authenticates)
        self._lock = threading.Lock()  # frames may come from several links (reconnects)
        self._announced = itertools.count(1)
        # an announcement the link drops is not data (not among the drops): the next one comes
        self.announcer = SideSender(self, CONTROL, lambda reason, detail="": None)
        self.born = time.monotonic()

    def announcement(self, qos: dict[str, Any] | None) -> bytes:
        """An announcement frame of this entry (:mod:`rosgate.announce`): its type and hash,
        and ``qos`` when it was found from publishers. NoKey before a session has keys."""
        body = announce.encode(self.check.mine, qos)
        epoch = self.keys.epoch()
        return self.seal(envelope.FLAG_ANNOUNCE, epoch, next(self._announced), body)

    def admit(self, header: envelope.Header, frame: bytes) -> bytes | None:
        """A received frame's payload, once its cipher and the replay window accept it; None
        (counted) when either does not. A topic's skipped sequence numbers count as lost (a
        late frame that fills a gap takes one back)."""
        payload = self.open(frame, header.epoch)
        if payload is None:
            return None
        replay = self.replay
        with self._lock:
            refused = replay.accept(header.epoch, header.seq)
            if self.counts_lost:
                self.counters.lost = replay.lost
        if refused:
            self.drop(refused)
            return None
        return payload

    def heard(self, header: envelope.Header,
              frame: bytes) -> tuple[Identity | None, dict[str, Any] | None] | None:
        """The far side's announcement frame of this entry: see :meth:`told`."""
        body = self.open(frame, header.epoch)
        return None if body is None else self.told(bytes(body))

    def told(self, said: Any) -> tuple[Identity | None, dict[str, Any] | None] | None:
        """What the far side says of this entry (an announcement's opened body, or a hello's or
        a welcome's item; None: nothing, an older rosgate): read, its type checked. None
        (counted) when it cannot be read."""
        try:
            identity, qos = (announce.parse_body(said) if isinstance(said, bytes)
                             else announce.read(said))
        except ValueError as exc:
            self.drop(Drop.BAD_ANNOUNCEMENT, str(exc))
            return None
        self.check.far(identity)
        return identity, qos

    def refuse_type(self) -> None:
        """A frame dropped because the far side's type is not this side's."""
        self.counters.drops[Drop.TYPE_MISMATCH] += 1
        self.check.say()

    def on_wire(self, size: int, again: bool) -> None:
        """A packet of ``size`` bytes left on the link for this route (``again``: re-sent)."""
        self.counters.bytes_on_wire += size
        if again:
            self.counters.retransmitted += 1

    def close(self) -> None:
        """The route is removed (its ROS entity is gone already)."""

    def drop(self, reason: Reason, detail: str = "") -> None:
        self.counters.drops[reason] += 1
        if reason not in QUIET_REASONS:
            self.warner.warn(self.label, reason, detail or reason.replace("_", " "))

    def seal(self, flags: int, epoch: int, seq: int, payload: bytes,
             stamp: int | None = None) -> bytes:
        """An envelope frame of this route: the header, then the payload sealed with it."""
        header = envelope.pack(flags, self.topic_id, epoch, seq,
                               time.time_ns() if stamp is None else stamp)
        sealer = self.keys.sealer(epoch)
        if sealer.in_place and len(payload) >= SEAL_IN_PLACE:
            frame = bytearray(envelope.SIZE + len(payload) + sealer.overhead)
            frame[:envelope.SIZE] = header
            with memoryview(frame) as view:
                sealer.seal_into(header, payload, view[envelope.SIZE:])
            return cast(bytes, frame)  # bytes-like: links send views of a frame this long
        return header + sealer.seal(header, payload)

    def open(self, frame: bytes, epoch: int) -> bytes | None:
        """An envelope frame's payload if the cipher of its epoch accepts it; None (counted)
        when it does not.
        A reassembled frame comes as the bytearray it was reassembled in, the route's to keep:
        on a receiving route of a raw codec (cdr: the core's own decode, CDR check and publisher
        take a bytearray) with the ``none`` cipher, or one that opens in place
        (:attr:`Cipher.in_place`), its header is cut off in place and the rest goes to rclpy
        without a copy.
        Other ciphers and codecs get bytes, as their contracts say."""
        if self.plain:
            if type(frame) is bytearray and self.zero_copy:
                del frame[:envelope.SIZE]  # O(1): CPython moves the start, copies nothing
                return cast(bytes, frame)
            return bytes(frame[envelope.SIZE:])
        cipher = self.keys.opener(epoch)
        if cipher is None:
            self.drop(Drop.UNKNOWN_KEY, "sealed under a key this side does not hold (an earlier "
                                        "session, a restart, or an expired key generation)")
            return None
        try:
            if type(frame) is bytearray and self.zero_copy and cipher.in_place:
                # a reassembled frame, opened where it lies; header and tag cut off in place
                with memoryview(frame) as view:
                    start, end = cipher.open_into(view[:envelope.SIZE], view[envelope.SIZE:])
                del frame[envelope.SIZE + end:]
                del frame[:envelope.SIZE + start]  # O(1), as above
                return cast(bytes, frame)
            header, body = bytes(frame[:envelope.SIZE]), bytes(frame[envelope.SIZE:])
            return cipher.open(header, body)
        except CipherError as exc:
            self.drop(Drop.AUTH_FAILED, f"{exc} (wrong key, tampered, or not from the peer)")
            return None


class SideSender:
    """Frames of a route that are not its messages, as the link's sender: an announcement (in
    the control class, never waiting out a link loss: the next one comes soon) or a service
    call (whose drop fails the call). Their bytes are not the route's data."""

    __slots__ = ("route", "delivery", "drop")

    def __init__(self, route: Route, delivery: Delivery, drop: Callable[..., None]):
        self.route = route
        self.delivery = delivery
        self.drop = drop  # (reason, detail="")

    @property
    def topic_id(self) -> int:
        return self.route.topic_id

    def on_wire(self, size: int, again: bool) -> None:
        pass


class TopicFraming:
    """How a topic's payloads become frames, chosen once per route (the spec's
    ``Delivery.whole`` says the link must not cut them: ``framing: none``)."""

    def frame(self, route: TransmitRoute, payload: bytes, stamp: int, flags: int = 0) -> bytes:
        """``flags``: the envelope's (FLAG_COMPRESSED); a bare frame has none."""
        raise NotImplementedError


class EnvelopeFraming(TopicFraming):
    """``framing: rosgate``: the 28-byte envelope (topic id, the sender's epoch and sequence
    number, the send time), then the payload sealed by the topic's cipher, which authenticates
    the header too. Receivers are found by topic id (the router) and keep a replay window."""

    def frame(self, route: TransmitRoute, payload: bytes, stamp: int, flags: int = 0) -> bytes:
        # no lock: a route's messages come from the one executor thread (RosNode)
        epoch = route.keys.epoch()
        if epoch != route.epoch:  # a new key: a new sequence under it
            route.epoch, route.seqs = epoch, itertools.count(1)
        return route.seal(flags, epoch, next(route.seqs), payload, stamp)


class BareFraming(TopicFraming):
    """``framing: none``: one datagram per message, the codec's bytes alone — laid out with the
    topic's ``remote`` name (:mod:`rosgate.wire.names`) when the codec writes MessagePack (the
    microcontroller format), so several topics can share a port."""

    def __init__(self, name: str | None, layout: Layout = LAYOUT_DEFAULT):
        self.prefix = pack_name(name, layout) if name is not None else b""

    def frame(self, route: TransmitRoute, payload: bytes, stamp: int, flags: int = 0) -> bytes:
        return self.prefix + payload


def max_wait_ns(topic: TopicConfig) -> int:
    """How long (ns) a message may wait in the bridge's own buffers — the subscription's
    queue, the receive buffer — before it is dropped (``too_late``) rather than delivered late:
    the topic's ``max_delay`` (a camera that would rather skip a frame); 0, never, without one.

    Why not a default for best effort: what waits there waits for a thread of the bridge, not
    for the link. A process that is not scheduled for a while (a busy machine) finds a backlog
    when it runs again and sends it at once; the link was idle meanwhile, so dropping it would
    lose messages the link could carry. Where the link is the bottleneck (a budget, a full
    kernel send buffer) frames wait in the link's queue instead, and there latest-only
    replaces them (``superseded``) and the link's ``max_delay`` drops them (``too_late``). A
    backlog in front of the bridge is bounded by the topic's own QoS depth; one in the link's
    queue that stays longer than a stall lasts is shed (:class:`~rosgate.scheduler.Backlog`)."""
    return int(1e9 * topic.max_delay) if topic.max_delay is not None else 0


class TransmitRoute(Route):
    """ROS subscription -> link."""

    def __init__(self, topic: TopicConfig, topic_id: int, codec: Codec, keys: Keys,
                 warner: Warner, label: str, delivery: Delivery, *, framing: TopicFraming,
                 link: Link, destination: Callable[[], Address | None],
                 compression: Transform | None = None):
        super().__init__(topic, topic_id, codec, keys, warner, label, delivery)
        self.topic = topic
        self.framing = framing
        self.link = link
        self.destination = destination  # where to send, looked up per message (a server learns it)
        self.epoch: int | None = None  # of the key in use, set by the first frame
        self.seqs = itertools.count(1)  # its sequence numbers
        self._size = 1  # of a frame, lately: how many messages a datagram's worth is
        rate = topic.max_rate
        self.min_interval_ns = int(1e9 / rate) if rate else 0
        self.last_sent_ns = 0
        #: takes the next message already waiting, or None (set with the subscription)
        self.take: Callable[[], Any] | None = None
        self.transform = compression
        self.transform_id = bytes([compression.wire_id]) if compression is not None else b""
        #: the QoS found from the publishers here (entries without qos; None: none found yet)
        self.qos_found: dict[str, Any] | None = None
        #: and the one its subscription has (None: the entry's own)
        self.qos_in_use: dict[str, Any] | None = None
        #: the batch window (seconds, 0: none), its node's open windows, and what came in it
        self.window = topic.batch or 0.0
        self.batches = Batches()
        self.pending: list[Any] = []

    def encode(self, message: Any) -> tuple[bytes, int]:
        """The message's payload, transformed (compressed) when that makes it smaller: then after
        the transform's wire id, with the envelope flag that says so."""
        payload = self.codec.encode(message)
        if self.transform is None:
            return payload, 0
        packed = self.transform.encode(payload)
        counters = self.counters
        counters.bytes_before_compression += len(payload)
        if packed is None:
            counters.bytes_after_compression += len(payload)
            counters.not_compressed += 1
            return payload, 0
        counters.bytes_after_compression += len(packed)
        return self.transform_id + packed, envelope.FLAG_COMPRESSED

    def on_message(self, message: Any) -> None:
        """A message from the subscription, and every other one already waiting in it (up to a
        datagram's worth): framed, then handed to the link together, so a backlog leaves in
        few datagrams (one executor wake-up, one system call) instead of one per message.
        With a batch window, the message opens the window instead (or joins the open one)."""
        if self.window:
            self.pending.append(message)
            if len(self.pending) == 1:
                self.batches.open(time.monotonic() + self.window, self.flush)
            return
        self._send(self._drain([message], DRAIN_FRAMES, DRAIN_BYTES))

    def flush(self) -> None:
        """The batch window closed: what came in it, and everything waiting now, leaves
        together."""
        messages, self.pending = self.pending, []
        if self.take is not None and self.entity is not None:
            messages = self._drain(messages, BATCH_FRAMES, BATCH_BYTES)
        self._send(messages)

    def _drain(self, messages: list[Any], frames: int, size: int) -> list[Any]:
        """``messages`` and those waiting in the subscription after them, up to ``frames``
        messages or about ``size`` bytes of frames."""
        take = self.take
        if take is None:
            return messages
        max_wait, now = self.max_wait_ns, time.time_ns()
        while len(messages) < frames:
            got = take()
            if got is None:
                break
            more, received = got
            late = None
            if max_wait and now - received > max_wait:
                late = Drop.TOO_LATE, f"waited over {max_wait / 1e6:.0f} ms to be taken"
            if late:  # too long in the subscription's queue, and so was every message
                # before it: drop them all
                for _ in range(len(messages) + 1):
                    self.drop(*late)
                messages.clear()
                continue
            messages.append(more)
            if len(messages) * self._size >= size:
                break
        return messages

    def _send(self, messages: list[Any]) -> None:
        """Messages framed and handed to the link in one call."""
        if not messages:
            return
        to = self.destination()
        if to is None and self.link.datagram:
            for _ in messages:
                self.drop(Drop.NO_PEER_YET, "the far side's address is not known yet")
            return
        frames: list[bytes] = []
        size = 0
        for one in messages:
            frame = self._frame(one)
            if frame is not None:
                frames.append(frame)
                size += len(frame)
        if size:
            self._size = size // len(frames)
        if frames:
            sent = self.link.send_all(frames, self, to)
            counters = self.counters
            counters.sent += sent
            counters.bytes_sent += size if sent == len(frames) else sum(map(len, frames[:sent]))

    def _frame(self, message: Any) -> bytes | None:
        """One message framed, or None when it was dropped (counted)."""
        now = time.time_ns()
        if self.min_interval_ns:
            if now - self.last_sent_ns < self.min_interval_ns:
                self.drop(Drop.RATE_LIMIT)
                return None
            self.last_sent_ns = now
        try:
            payload, flags = self.encode(message)
            return self.framing.frame(self, payload, now, flags)
        except NoKey:
            self.drop(Drop.NO_SESSION_KEY, "the session's handshake has not happened yet")
            return None
        except Exception as exc:  # a codec or cipher bug must not stop the executor
            self.drop(Drop.ENCODE_ERROR, f"{type(exc).__name__}: {exc}")
            return None

    @property
    def queue_depth(self) -> int:
        """Its messages waiting in the link, or being sent, now."""
        return self.link.queue_depth(self)

    def close(self) -> None:
        """The route is removed: what it queued goes (a message half sent is not finished)."""
        self.pending.clear()  # an open window closes with nothing to send
        self.link.forget(self)


class ReceiveRoute(Route):
    """Link -> ROS publisher."""

    counts_lost = True

    def __init__(self, topic: TopicConfig, topic_id: int, codec: Codec, keys: Keys,
                 warner: Warner, label: str, delivery: Delivery, *,
                 decode: Callable[[bytes], Any],
                 transforms: Callable[[int], Transform | None] = lambda wire_id: None):
        super().__init__(topic, topic_id, codec, keys, warner, label, delivery)
        self.topic = topic
        self.decode = decode  # the codec's, with a CDR check where no cipher authenticates
        #: publishes what decode returned (set with the publisher: raw CDR as bytes or bytearray)
        self.publish: Callable[[Any], None] = lambda message: self.entity.publish(message)
        self.zero_copy = codec.raw  # the core's raw decode, CDR check and publisher take one
        self.last_received = time.monotonic()
        self.stale_warnings_given = 0
        #: whatever this side's file says: the sender's envelope says what it transformed, and
        #: the payload's first byte with which transform
        self.transforms = transforms
        #: the QoS its publisher has from the far side's publishers (None: the entry's own)
        self.qos_in_use: dict[str, Any] | None = None

    def on_frame(self, header: envelope.Header, frame: bytes, arrived: int = 0) -> None:
        """An envelope frame (framing rosgate), found by its topic id; ``arrived``: when the
        datagram that carried it reached this machine (time.time_ns(); 0: unknown)."""
        size = len(frame)
        payload = self.admit(header, frame)
        if payload is None:
            return
        if self.check.mismatch is not None:
            self.refuse_type()
            return
        if self.check.awaiting and self.check.hold(size, lambda agreed: self.accept(
                header, payload, size) if agreed else self.refuse_type()):
            return  # until the far side says its type (rosgate.announce)
        self.accept(header, payload, size, arrived)

    def accept(self, header: envelope.Header, payload: bytes, size: int,
               arrived: int = 0) -> None:
        """A frame past its checks: published, unless it waited too long here."""
        if arrived and self.max_wait_ns:  # the topic's max_delay
            waited = time.time_ns() - arrived
            if waited > self.max_wait_ns:
                self.drop(Drop.TOO_LATE, f"waited {waited / 1e6:.0f} ms in the receive buffer")
                return
        if header.flags & envelope.FLAG_COMPRESSED:
            restored = self.transform_back(payload)
            if restored is None:
                return
            payload = restored
        self.deliver(payload, size)

    def transform_back(self, payload: bytes) -> bytes | None:
        """A transformed payload as the codec wrote it; None when it cannot be (counted)."""
        transform = self.transforms(payload[0]) if payload else None
        if transform is None:
            self.drop(Drop.DECOMPRESSION_ERROR, "transformed by a transform this side does not "
                      f"have (wire id {payload[0] if payload else 'missing'})")
            return None
        try:
            return transform.decode(bytes(payload[1:]))
        except TransformError as exc:
            self.drop(Drop.DECOMPRESSION_ERROR, f"{transform.name}: {exc}")
        except Exception as exc:  # a transform must raise TransformError; anything else: its bug
            self.drop(Drop.DECOMPRESSION_ERROR, f"{transform.name} failed: {type(exc).__name__}: "
                      f"{exc}")
        return None

    def deliver(self, payload: bytes, size: int) -> None:
        """Decode and publish; ``size`` is what arrived on the link, for the counters."""
        try:
            message = self.decode(payload)
        except CodecError as exc:
            self.drop(Drop.DECODE_ERROR, str(exc))
            return
        except Exception as exc:  # a codec must raise CodecError; anything else is its bug
            self.drop(Drop.DECODE_ERROR,
                      f"codec {self.codec.name} failed: {type(exc).__name__}: {exc}")
            return
        try:
            self.publish(message)
        except Exception as exc:
            self.drop(Drop.PUBLISH_ERROR, f"{type(exc).__name__}: {exc}")
            return
        self.counters.received += 1
        self.counters.bytes_received += size
        self.last_received = time.monotonic()
        self.stale_warnings_given = 0


class BarePort:
    """The receiving topics of one port with ``framing: none``: told apart by the name in front
    of each datagram when their codec writes MessagePack, else the port's only topic.
    ``link_drop(link, reason, detail)`` counts a datagram that belongs to none of them."""

    def __init__(self, named: bool, link_drop: Callable[[Link, Reason, str], None]):
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

    def on_frame(self, datagram: bytes, link: Link, source: Address) -> None:
        if not self.named:
            if self.only is not None:
                self.only.deliver(datagram, len(datagram))
            return
        try:
            name, rest = split_name(datagram)
        except NameMissing as exc:
            self.link_drop(link, Drop.UNNAMED_FRAME, f"{len(datagram)} bytes from {source}: {exc}")
            return
        route = self.routes.get(name)
        if route is None:
            self.link_drop(link, Drop.UNKNOWN_TOPIC, f"name {name!r} from {source}")
            return
        route.deliver(rest, len(datagram))
