"""The data path of a route, top to bottom:

* transmit (a ROS subscription callback): message -> codec.encode -> transform (optional) ->
  framing.frame (envelope header, cipher.seal) -> link.send
* receive (a link's thread): cipher.open -> (in order) -> replay window -> transform back ->
  decode (codec, CDR check) -> ROS publish

Each frame's cipher comes from the route's :class:`~rosgate.keyring.Keys` by the envelope's
epoch (a new key generation starts a new sequence). Every drop is counted by reason in the
route's :class:`~.counters.Counters`, warned about at most once per
:data:`rosgate.warn.WARN_EVERY` s.
"""

from __future__ import annotations

import itertools
import threading
import time
from collections.abc import Callable
from typing import Any, cast

from ..announce import Identity, TypeCheck
from ..batch import Batches
from ..cipher import Cipher
from ..codec import Codec
from ..config import ServiceConfig, TopicConfig
from ..drops import Drop, Reason
from ..echo import EchoGuard
from ..errors import CipherError, CodecError
from ..holdback import Holdback
from ..inorder import Ordered
from ..keyring import Keys, NoKey
from ..links.base import Link
from ..matching import PublishGate
from ..scheduler import FRESH, FRESH_HOLD, Backlog
from ..spec import CONTROL, Delivery
from ..transform import Transform, TransformError
from ..transport import Address
from ..warn import Warner
from ..wire import envelope
from .bare import BareFraming
from .counters import QUIET_REASONS, Counters, SideSender
from .held import Holding, max_wait_ns
from .said import Said

# a transmitting route takes what waits in its subscription up to this much at a time
DRAIN_FRAMES = 32
DRAIN_BYTES = 60_000
# a payload at least this long is sealed straight into its frame (a bytearray) by a cipher that
# can: no copy of an image to put the header in front. Shorter frames stay bytes.
SEAL_IN_PLACE = 64 * 1024


class Route(Said):
    """A topic's (or service's) path through the bridge in one direction; the
    :class:`rosgate.links.base.Sender` of its frames."""

    #: the sending side of an entry with an envelope: says its type (and QoS) on its link
    announces = False
    interface: Any = None  # the entry's ROS class (message or service), set with its entity
    #: what :meth:`admit` refuses for skipped sequence numbers is a loss on the way
    counts_lost = False
    #: the QoS found from the publishers here (a transmitting entry without qos; None: none
    #: yet), and the one its subscription or publisher has (None: the entry's own)
    qos_found: dict[str, Any] | None = None
    qos_in_use: dict[str, Any] | None = None
    #: whether the far side says a real ROS server of this service runs there (None: it has
    #: said nothing yet; what a calling side's proxy follows, :mod:`rosgate.announce`)
    far_served: bool | None = None
    link: Link
    destination: Callable[[], Address | None]
    #: the wall clock (ns) the bridge's own queues measure waits by (the kernel's and the
    #: middleware's stamps are of it)
    clock: Callable[[], int] = staticmethod(time.time_ns)
    #: a name this bridge both sends and receives (peers' patterns): what it published itself
    echo: EchoGuard | None = None

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
        self.plain = keys.plain
        #: the ciphers it holds (the keys' version then, epoch, cipher, until): Keys.sealing
        self._sealing = self._opening = cast(tuple[int, int, Cipher, float] | None, None)
        self.zero_copy = False  # a reassembled frame's bytearray may become the payload (open)
        self.max_wait_ns = max_wait_ns(entry) if isinstance(entry, TopicConfig) else 0
        #: a best-effort topic without a max_delay: what sheds its messages that stand in the
        #: bridge's own queue (the subscription's, or the receive buffer) by their age
        self.backlog = Backlog(FRESH, FRESH_HOLD) if isinstance(entry, TopicConfig) and not (
            self.max_wait_ns or delivery.reliable) else None
        #: the entry's type against the far side's (the router gives this side's hash)
        self.check = TypeCheck(label, Identity(entry.type, None))
        #: without a cipher that vouches for the header, one forged frame may not move it
        self.replay = envelope.ReplayWindow(authenticated=keys.authenticates)
        self._lock = threading.Lock()  # frames may come from several links (reconnects)
        self._announced = itertools.count(1)
        # an announcement the link drops is not data (not among the drops): the next one comes
        self.announcer = SideSender(self, CONTROL, lambda reason, detail="": None)
        self.born = time.monotonic()

    def admit(self, header: envelope.Header, frame: bytes) -> bytes | None:
        """A received frame's payload once its cipher, keys and replay window accept it; None
        (counted) when one does not. Skipped sequence numbers of a topic count as lost (a late
        frame that fills a gap takes one back)."""
        payload = self.open(frame, header.epoch)
        return None if payload is None else self.replayed(header, payload)

    def replayed(self, header: envelope.Header, payload: bytes) -> bytes | None:
        """An opened frame's payload unless the replay window refuses it (counted)."""
        replay = self.replay
        with self._lock:
            refused = replay.accept(header.epoch, header.seq) if not self.keys.dated \
                or self.keys.fresh(header.epoch, header.stamp) else Drop.REPLAYED
            if self.counts_lost:
                self.counters.lost = replay.lost
        if refused:
            self.drop(refused)
            return None
        return payload

    @property
    def shedding(self) -> bool:
        """Whether its queue in this bridge stands behind now, and sheds its oldest."""
        return self.backlog is not None and self.backlog.shedding(self.clock() / 1e9)

    def stale(self, waited_ns: int, now_ns: int, where: str) -> bool:
        """Whether a best-effort message that waited ``waited_ns`` in the bridge's own queue
        (``where``) is dropped for it (counted ``too_late``): only while the queue stands
        behind (:class:`~rosgate.scheduler.Backlog`), and only when the QoS in use is best
        effort (a reliable one found from the publishers never is)."""
        backlog = self.backlog
        if backlog is None or not backlog.shed(waited_ns / 1e9, now_ns / 1e9):
            return False
        found = self.qos_in_use
        if found is not None and found.get("reliability") != "best_effort":
            return False
        self.drop(Drop.TOO_LATE, f"waited {waited_ns / 1e6:.0f} ms {where}, behind for "
                                 f"{FRESH_HOLD * 1e3:.0f} ms on end (oldest first)")
        return True

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

    def sealing(self) -> tuple[int, Cipher]:
        """The epoch a frame sealed now carries and its cipher, held while the keys' version
        stays and their time lasts (:meth:`~rosgate.keyring.Keys.sealing`); NoKey: none yet."""
        keys, held = self.keys, self._sealing
        if held is None or held[0] != keys.changes.version or keys.clock() >= held[3]:
            version = keys.changes.version
            epoch, cipher, until = keys.sealing()
            held = self._sealing = (version, epoch, cipher, until)
        return held[1], held[2]

    def seal(self, flags: int, epoch: int, seq: int, payload: bytes,
             stamp: int | None = None, sealer: Cipher | None = None) -> bytes:
        """An envelope frame of this route: the header, then the payload sealed with it (by
        ``sealer``, the cipher of ``epoch``, when the caller holds it)."""
        keys = self.keys
        if stamp is None:
            stamp = time.time_ns()
        header = envelope.pack(flags, self.topic_id, epoch, seq,
                               keys.stamp(stamp) if keys.dated else stamp)
        if sealer is None:
            sealer = keys.sealer(epoch)
        if sealer.in_place and len(payload) >= SEAL_IN_PLACE:
            frame = bytearray(envelope.SIZE + len(payload) + sealer.overhead)
            frame[:envelope.SIZE] = header
            with memoryview(frame) as view:
                sealer.seal_into(header, payload, view[envelope.SIZE:])
            return cast(bytes, frame)  # bytes-like: links send views of a frame this long
        return header + sealer.seal(header, payload)

    def open(self, frame: bytes, epoch: int) -> bytes | None:
        """An envelope frame's payload if the cipher of its epoch accepts it; None (counted)
        when it does not. A reassembled frame (a bytearray, the route's to keep) of a zero-copy
        route with the none cipher or one that opens in place loses its header in place and
        goes to rclpy without a copy; other ciphers and codecs get bytes, as their contracts
        say."""
        if self.plain:
            if type(frame) is bytearray and self.zero_copy:
                del frame[:envelope.SIZE]  # O(1): CPython moves the start, copies nothing
                return cast(bytes, frame)
            return bytes(frame[envelope.SIZE:])
        keys, held = self.keys, self._opening
        if held is not None and held[1] == epoch and held[0] == keys.changes.version \
                and keys.clock() < held[3]:
            cipher = held[2]
        else:
            version = keys.changes.version
            found = keys.opening(epoch)
            if found is None:
                self.drop(Drop.UNKNOWN_KEY, "sealed under a key this side does not hold (an "
                          "earlier session, a restart, or an expired key generation)")
                return None
            cipher = found[0]
            self._opening = (version, epoch, cipher, found[1])
        try:
            if type(frame) is bytearray and self.zero_copy and cipher.in_place:
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


class EnvelopeFraming:
    """``framing: rosgate``: the 28-byte envelope (topic id, the sender's epoch and sequence
    number, the send time), then the payload sealed by the topic's cipher, which authenticates
    the header too. Receivers are found by topic id (the router) and keep a replay window."""

    def frame(self, route: TransmitRoute, payload: bytes, stamp: int, flags: int = 0) -> bytes:
        # no lock: a route's messages come from the one executor thread (RosNode)
        epoch, sealer = route.sealing()
        if epoch != route.epoch:  # a new key: a new sequence under it
            route.epoch, route.seqs = epoch, itertools.count(1)
        return route.seal(flags, epoch, next(route.seqs), payload, stamp, sealer)




class TransmitRoute(Holding, Route):
    """ROS subscription -> link."""

    def __init__(self, topic: TopicConfig, topic_id: int, codec: Codec, keys: Keys,
                 warner: Warner, label: str, delivery: Delivery, *,
                 framing: EnvelopeFraming | BareFraming, link: Link,
                 destination: Callable[[], Address | None], compression: Transform | None = None,
                 select: Callable[[Any], Any] | None = None, hold: Holdback | None = None):
        super().__init__(topic, topic_id, codec, keys, warner, label, delivery)
        self.topic = topic
        #: what of each message the far side may see (None: nothing, ``foreign_goal``): an
        #: action's feedback and status for one client (rosgate.actions.ClientGoals)
        self.select = select
        #: where its messages wait while the far side is out of reach (a client's), else None
        self.hold = hold
        self.framing = framing
        self.link = link
        self.destination = destination  # where to send, looked up per message (a server learns it)
        self.epoch: int | None = None  # of the key in use, set by the first frame
        self.seqs = itertools.count(1)  # its sequence numbers
        self._size = 1  # of a frame, lately: how many messages a datagram's worth is
        self.min_interval_ns = int(1e9 / topic.max_rate) if topic.max_rate else 0
        self.last_sent_ns = 0
        #: takes the next message waiting in the subscription, or None (set with it)
        self.take: Callable[[], Any] | None = None
        self.transform = compression
        self.transform_id = bytes([compression.wire_id]) if compression is not None else b""
        #: the batch window (seconds, 0: none), its node's open windows, and what came in it
        self.window = topic.batch or 0.0
        self.batches = Batches()
        self.pending: list[Any] = []

    def encode(self, message: Any) -> tuple[bytes, int]:
        """The message's payload and envelope flags: compressed when that makes it smaller (then
        after the transform's wire id, with FLAG_COMPRESSED)."""
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
        """A message, and every other one already waiting in the subscription (up to a
        datagram's worth), handed to the link together: a backlog leaves in few datagrams
        (one wake-up, one system call). With a batch window, it opens or joins the window."""
        if self.window:
            self.pending.append(message)
            if len(self.pending) == 1:
                self.batches.open(time.monotonic() + self.window, self.flush)
            return
        self._send(self._drain([message], DRAIN_FRAMES, DRAIN_BYTES))

    def _drain(self, messages: list[Any], frames: int, size: int) -> list[Any]:
        """``messages`` and those waiting in the subscription after them, up to ``frames``
        messages or about ``size`` bytes of frames."""
        take = self.take
        if take is None:
            return messages
        max_wait, now = self.max_wait_ns, self.clock()
        while len(messages) < frames and (got := take()) is not None:
            more, received = got
            if max_wait and now - received > max_wait:
                # too long in the subscription's queue, and so was every message before it
                for _ in range(len(messages) + 1):
                    self.drop(Drop.TOO_LATE, f"waited over {max_wait / 1e6:.0f} ms to be taken")
                messages.clear()
                continue
            if self.backlog is not None and self.stale(now - received, now, "to be taken"):
                continue
            messages.append(more)
            if len(messages) * self._size >= size:
                break
        return messages

    def _send(self, messages: list[Any]) -> None:
        """Messages framed and handed to the link in one call (or held while the far side is
        out of reach: :mod:`rosgate.holdback`)."""
        hold = self.hold
        if hold is not None and hold.down:
            self._hold(hold, messages)
            return
        to = self.destination()
        if to is None and self.link.datagram:
            for _ in messages:
                self.drop(Drop.NO_PEER_YET, "the far side's address is not known yet")
            return
        frames = [frame for frame in map(self._frame, messages) if frame is not None]
        self._hand(frames, to)

    def _hand(self, frames: list[bytes], to: Address | None, again: bool = False) -> None:
        """Frames handed to the link in one call, and counted (``again``: sent before, counted
        then)."""
        size = sum(map(len, frames))
        if size:
            self._size = size // len(frames)
        if frames:
            sent = self.link.send_all(frames, self, to)
            if again:
                return
            counters = self.counters
            counters.sent += sent
            counters.bytes_sent += size if sent == len(frames) else sum(map(len, frames[:sent]))

    def _encode(self, message: Any) -> tuple[bytes, int, int] | None:
        """One message's payload, envelope flags and the time it was taken (ns), or None when
        it was dropped (counted)."""
        if self.echo is not None and self.echo.returned(message):
            self.drop(Drop.ECHO)  # before the rate limit: an echo takes no message's turn
            return None
        now = time.time_ns()
        if self.min_interval_ns:
            if now - self.last_sent_ns < self.min_interval_ns:
                self.drop(Drop.RATE_LIMIT)
                return None
            self.last_sent_ns = now
        try:
            if self.select is not None and (message := self.select(message)) is None:
                self.drop(Drop.FOREIGN_GOAL, "about a goal another client sent")
                return None
            payload, flags = self.encode(message)
        except Exception as exc:  # a codec bug must not stop the executor
            self.drop(Drop.ENCODE_ERROR, f"{type(exc).__name__}: {exc}")
            return None
        return payload, flags, now

    def _seal(self, payload: bytes, flags: int, stamp: int) -> bytes | None:
        """An encoded message framed (sealed), or None when it was dropped (counted)."""
        try:
            return self.framing.frame(self, payload, stamp, flags)
        except NoKey:
            self.drop(Drop.NO_SESSION_KEY, "the session's handshake has not happened yet")
            return None
        except Exception as exc:  # a cipher bug must not stop the executor
            self.drop(Drop.ENCODE_ERROR, f"{type(exc).__name__}: {exc}")
            return None

    def _frame(self, message: Any) -> bytes | None:
        """One message framed, or None when it was dropped (counted)."""
        encoded = self._encode(message)
        return None if encoded is None else self._seal(*encoded)


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
        #: the hold in front of its publisher while that matches its subscribers
        self.gate: PublishGate | None = None
        self.check.pace = self._pace_release
        self._pace_until = 0.0
        self.zero_copy = codec.raw  # the core's raw decode, CDR check and publisher take one
        self.last_received = time.monotonic()
        self.stale_warnings_given = 0
        #: the transform of a wire id, whatever this side's file says (the sender's frame says)
        self.transforms = transforms
        resends = delivery.packetizer.resends_within if delivery.packetizer else None
        self.order = Ordered(self, resends) if delivery.reliable and resends else None

    def on_frame(self, header: envelope.Header, frame: bytes, arrived: int = 0) -> bool:
        """An envelope frame (framing rosgate), found by its topic id; ``arrived``: when the
        datagram that carried it reached this machine (time.time_ns(); 0: unknown). A reliable
        topic whose link repairs is published in its sender's order (:mod:`rosgate.inorder`).
        Whether its cipher and the replay window took it (a genuine, new frame of the far side;
        one held in order for a gap is not yet one)."""
        found = self.qos_in_use  # what the far side found (None: the entry's own qos)
        if self.order is not None and (found is None or found["reliability"] != "best_effort"):
            return self.order.on_frame(header, frame, arrived)
        size = len(frame)  # before it is opened: a cipher may open it where it lies
        return self.admitted(header, self.admit(header, frame), size, arrived)

    def admitted(self, header: envelope.Header, payload: bytes | None, size: int,
                 arrived: int) -> bool:
        """A frame's payload past its cipher and the replay window (None: refused, counted);
        whether it was."""
        if payload is None:
            return False
        if self.check.mismatch is not None:
            self.refuse_type()
        elif not (self.check.awaiting and self.check.hold(size, lambda agreed: self.accept(
                header, payload, size) if agreed else self.refuse_type())):
            self.accept(header, payload, size, arrived)  # else: until the far side says its type
        return True

    def accept(self, header: envelope.Header, payload: bytes, size: int,
               arrived: int = 0) -> None:
        """A frame past its checks: published, unless it waited too long here."""
        if arrived and self.max_wait_ns:  # the topic's max_delay
            waited = self.clock() - arrived
            if waited > self.max_wait_ns:
                self.drop(Drop.TOO_LATE, f"waited {waited / 1e6:.0f} ms in the receive buffer")
                return
        elif arrived and self.backlog is not None:
            now = self.clock()
            if self.stale(now - arrived, now, "in the receive buffer"):
                return
        if header.flags & envelope.FLAG_COMPRESSED:
            self.transform_back(payload, size)
        else:
            self.deliver(payload, size)

    def transform_back(self, payload: bytes, size: int) -> None:
        """A transformed payload delivered as the codec wrote it, or dropped (counted)."""
        transform = self.transforms(payload[0]) if payload else None
        if transform is None:
            self.drop(Drop.DECOMPRESSION_ERROR, "transformed by a transform this side does not "
                      f"have (wire id {payload[0] if payload else 'missing'})")
            return
        try:
            restored = transform.decode(bytes(payload[1:]))
        except Exception as exc:  # a transform must raise TransformError; anything else: its bug
            failed = "" if isinstance(exc, TransformError) else f" failed: {type(exc).__name__}"
            self.drop(Drop.DECOMPRESSION_ERROR, f"{transform.name}{failed}: {exc}")
        else:
            self.deliver(restored, size)

    def close(self) -> None:
        if self.order is not None:
            self.order.close()

    def deliver(self, payload: bytes, size: int) -> None:
        """Decode and publish; ``size`` is what arrived on the link, for the counters."""
        try:
            message = self.decode(payload)
        except Exception as exc:  # a codec must raise CodecError; anything else is its bug
            self.drop(Drop.DECODE_ERROR, str(exc) if isinstance(exc, CodecError)
                      else f"codec {self.codec.name} failed: {type(exc).__name__}: {exc}")
            return
        try:
            if self.echo is not None:
                self.echo.publishing(message)
            self.publish(message)
        except Exception as exc:
            self.drop(Drop.PUBLISH_ERROR, f"{type(exc).__name__}: {exc}")
            return
        self.counters.received += 1
        self.counters.bytes_received += size
        self.last_received = time.monotonic()
        self.stale_warnings_given = 0

