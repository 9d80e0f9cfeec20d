"""The scheduler: in which order, and how fast, frames leave a link.

Every link has one. Frames are queued per topic (by the topic id of their
:class:`~rosgate.links.Sender`), the
topics grouped in priority classes — zenoh's seven, ``real_time`` (1) to ``background`` (7),
and class 0 above them for the control channel (hellos, pings, handshakes) — and a frame leaves
as *packets*: a datagram, a fragment, a chunk of a stream. Then:

* **strict priority** between classes: nothing of a class leaves while a higher class has a
  packet that may go;
* **first come, first served, a packet at a time** between the topics of one class: messages
  leave in the order they came, but a long one's packets take turns with the others' (each
  waits from when the packet before it left), so the fragments of two topics' messages
  interleave and a small message waits at most one packet of every other topic of its class,
  never a whole image;
* **one message at a time per topic**: a message partly sent is finished before the topic's next
  one starts (a topic's fragments never interleave with each other; a stream's chunks must not);
  a topic's packets sent again (retransmissions) go before its other packets;
* **latest only**: a ``latest_only`` topic's message not yet started is replaced by a newer
  one (counted ``superseded``): what waits is never older than one message;
* **too late**: a best-effort topic's message that waited ``max_delay`` seconds without starting is
  dropped (counted ``too_late``) rather than sent stale; a reliable topic's waits, within the
  link's limits (``frames``, ``bytes``: beyond them a new message is refused, ``queue_full``);
  a topic's own ``max_delay`` (its sender's) applies to it whatever its reliability: a camera
  that would rather skip a frame than send one that waited (the link then idles for the next);
* **overload**: a best-effort topic without a ``max_delay`` of its own that stays behind sheds
  its oldest messages (see :class:`Backlog`);
* **budget**: with a ``bandwidth``, a token bucket per destination (per peer: a server's
  clients each have their own) refilled at that many bits per second, counting every packet
  with the transport's ``packet_overhead`` (IP and UDP headers). A packet leaves only when its
  destination has the tokens; another destination's packet may go meanwhile. The bucket holds
  :func:`burst` bytes, enough to keep the rate while the send thread wakes late, small enough
  not to fill the link's own queue.

Nothing here sends or waits: the link's send thread asks :meth:`Scheduler.next` for the next
packet, sends it, and sleeps until the time it is told when there is none yet.
"""

from __future__ import annotations

import time
from collections import OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from .drops import Drop, Reason

CLASSES = 8  # 0: control; 1 (real_time) .. 7 (background)
CONTROL = 0
KEYS_KEPT = 4096  # senders whose queue key is remembered, at most
LAG = 0.02   # seconds: a message that waited longer finds its topic behind
HOLD = 0.2   # seconds behind on end (or caught up, to stop) before a topic sheds (Backlog)


class Backlog:
    """Whether a best-effort topic sheds a message by its age from a link's send queue, where
    it waits only when the link is the bottleneck (a budget, a full kernel send buffer): told
    how long each message waited as it leaves. The subscription's queue and the receive buffer
    never shed: what waits there waits for a thread of the bridge, not for the link, and a
    backlog there is bounded by the topic's QoS depth.

    A message older than :data:`LAG` finds the topic *behind*. Behind for :data:`HOLD` on end,
    the topic sheds every message older than ``LAG`` (counted ``overload``) until none has been
    for ``HOLD``: under a sustained overload what arrives stays fresh. A stall (a process not
    scheduled, a GC pause) leaves a backlog that its thread catches up with in less than
    ``HOLD`` once it runs again, as it sees it, so nothing is shed: the backlog is sent."""

    __slots__ = ("since", "last")

    def __init__(self) -> None:
        self.since: float | None = None  # when this spell behind began
        self.last = -HOLD  # when a message last waited longer than LAG

    def shed(self, waited: float, now: float) -> bool:
        """Whether a message that waited ``waited`` seconds, leaving at ``now``, is shed."""
        if waited <= LAG:
            if self.since is not None and (now - self.since < HOLD or now - self.last >= HOLD):
                self.since = None  # caught up: a stall's backlog is gone, or the overload is
            return False
        if self.since is None or now - self.last >= HOLD:  # (late ones far apart: no spell)
            self.since = now
        self.last = now
        return now - self.since >= HOLD


def backlog(delivery: Any) -> Backlog | None:
    """A sender's :class:`Backlog`; None when it never sheds by age: reliable, or with a
    ``max_delay`` of its own (that age is the one it asked for)."""
    return None if delivery.reliable or delivery.max_delay is not None else Backlog()


def burst(rate_bytes: float, packet: int) -> int:
    """The bucket's size: 10 ms at the rate, and at least four of the link's largest packets."""
    return int(max(rate_bytes * 0.01, 4 * packet))


class Bucket:
    """A token bucket: ``rate`` bytes per second, at most ``capacity`` bytes in it."""

    def __init__(self, rate: float, capacity: int, now: float):
        self.rate = rate
        self.capacity = capacity
        self.tokens = float(capacity)
        self.at = now

    def _fill(self, now: float) -> None:
        if now > self.at:
            self.tokens = min(self.capacity, self.tokens + (now - self.at) * self.rate)
            self.at = now

    def take(self, size: int, now: float) -> float:
        """0 and take ``size`` bytes' tokens when they are there; else the seconds until they
        will be (taking nothing)."""
        self._fill(now)
        need = min(size, self.capacity)  # a packet larger than the bucket waits for a full one
        if self.tokens + 1e-6 >= need:  # (not a rounding error away from it, forever)
            self.tokens -= size
            return 0.0
        return (need - self.tokens) / self.rate

    def charge(self, size: int, now: float) -> None:
        """Count bytes sent outside the queue (acknowledgements): the bucket may go into debt."""
        self._fill(now)
        self.tokens -= size


@dataclass(eq=False)
class Outgoing:
    """One frame on its way: cut into packets when it starts (fragments, repair fragments), and
    told when its last packet left (``done``, e.g. to start a retransmission timer)."""

    sender: Any
    to: Any
    size: int
    cut: Callable[[], list[bytes]]
    queued: float = 0.0
    done: Callable[[float], None] | None = None
    #: a whole frame in one packet, which a datagram link may put in a datagram with others
    batchable: bool = False


@dataclass
class Due:
    """The next packet to send: where, whose, and whether it ends a message or repeats one."""

    packet: bytes
    to: Any
    sender: Any
    ends: Outgoing | None = None
    again: bool = False
    #: frames it ends (a stream's unwritten rest may end several)
    frames: int = 1


@dataclass(eq=False)
class _Topic:
    sender: Any
    priority: int
    waiting: deque[Outgoing] = field(default_factory=deque)
    current: Outgoing | None = None
    packets: deque[bytes] = field(default_factory=deque)
    repairs: deque[tuple[bytes, Any]] = field(default_factory=deque)
    since: float = 0.0     # when its next packet (of the message in progress) became due
    repaired: float = 0.0  # when its repairs were asked for
    backlog: Backlog | None = None


class Scheduler:
    """The send queue of one link (see the module's docstring). Not thread-safe: the link holds
    its lock around every call. ``drop(sender, reason, detail)`` counts a message that will not
    be sent."""

    def __init__(self, *, bandwidth: float | None = None, overhead: int = 0,
                 max_delay: float = 1.0, frames: int = 10_000, bytes: int = 64 * 1024 * 1024,
                 packet: int = 65_536, clock: Callable[[], float] = time.monotonic):
        self.rate = bandwidth / 8 if bandwidth else None  # bytes per second
        self.overhead = overhead
        self.max_delay = max_delay
        self.limit_frames = frames
        self.limit_bytes = bytes
        self.capacity = burst(self.rate, packet + overhead) if self.rate else 0
        self.clock = clock
        self._classes: list[OrderedDict[int, _Topic]] = [OrderedDict() for _ in range(CLASSES)]
        self._topics: dict[tuple[int, int], _Topic] = {}
        self._buckets: dict[Any, Bucket] = {}
        self._frames = 0  # messages waiting (not started)
        self._bytes = 0
        self.dropped: list[tuple[Any, Reason, str]] = []  # for the link to count outside its lock
        #: each sender's queue key, found once (by id; the sender is kept so the id stays its)
        self._keys: dict[int, tuple[Any, tuple[int, int]]] = {}

    # -- in ------------------------------------------------------------------------------------
    def _topic(self, sender: Any) -> _Topic:
        """The queue of the sender's topic (by topic id: what its fragments carry) in the
        sender's class: a route's announcements (the control class) never wait in, or replace
        anything of, the queue of its messages."""
        key = self._key(sender)
        topic = self._topics.get(key)
        if topic is None:
            topic = self._topics[key] = _Topic(sender, key[1], backlog=backlog(sender.delivery))
        return topic

    def _key(self, sender: Any) -> tuple[int, int]:
        """The sender's queue: its topic id and its class, read from it once (they do not
        change)."""
        found = self._keys.get(id(sender))
        if found is not None and found[0] is sender:
            return found[1]
        key = sender.topic_id, min(max(sender.delivery.priority, 0), CLASSES - 1)
        if len(self._keys) >= KEYS_KEPT:  # senders of one message each (service calls)
            self._keys.clear()
        self._keys[id(sender)] = (sender, key)
        return key

    def _activate(self, topic: _Topic) -> None:
        self._classes[topic.priority].setdefault(topic.sender.topic_id, topic)

    def put(self, message: Outgoing) -> bool:
        """Queue a frame; False when the link's limits refuse it (counted ``queue_full``)."""
        topic = self._topic(message.sender)
        if message.sender.delivery.latest_only:
            while topic.waiting:
                old = topic.waiting.popleft()
                self._frames -= 1
                self._bytes -= old.size
                self.dropped.append((old.sender, Drop.SUPERSEDED, "a newer message replaced it"))
        if self._frames >= self.limit_frames or self._bytes + message.size > self.limit_bytes:
            self.dropped.append((message.sender, Drop.QUEUE_FULL,
                                 f"{self._frames} frames, {self._bytes} bytes waiting"))
            return False
        topic.waiting.append(message)
        self._frames += 1
        self._bytes += message.size
        self._activate(topic)
        return True

    def resume(self, message: Outgoing, packets: list[bytes], now: float) -> None:
        """A message whose first packets left from the caller's thread (the link was idle):
        the rest wait here as its topic's message in progress, the next packet due since
        ``now``, so they take turns with what came meanwhile as any message's packets do."""
        topic = self._topic(message.sender)
        assert topic.current is None and not topic.packets, "one message at a time per topic"
        topic.current, topic.since = message, now
        topic.packets.extend(packets)
        self._activate(topic)

    def repair(self, sender: Any, to: Any, packets: list[bytes]) -> None:
        """Packets to send again (what a receiver asked for): first in their topic's turn."""
        topic = self._topic(sender)
        if not topic.repairs:
            topic.repaired = self.clock()
        topic.repairs.extend((p, to) for p in packets)
        self._activate(topic)

    def charge(self, to: Any, size: int) -> None:
        """Count a packet sent without the queue (an acknowledgement) against ``to``'s budget."""
        bucket = self._bucket(to, self.clock())
        if bucket is not None:
            bucket.charge(size + self.overhead, self.clock())

    # -- out -----------------------------------------------------------------------------------
    def _bucket(self, to: Any, now: float) -> Bucket | None:
        if self.rate is None:
            return None
        bucket = self._buckets.get(to)
        if bucket is None:
            bucket = self._buckets[to] = Bucket(self.rate, self.capacity, now)
        return bucket

    def may_send_now(self, to: Any, size: int) -> bool:
        """Whether a packet for ``to`` may leave at once, nothing being queued (then its tokens
        are taken): the caller's fast path."""
        if self._frames or any(self._classes):
            return False
        bucket = self._bucket(to, self.clock())
        return bucket is None or bucket.take(size + self.overhead, self.clock()) == 0.0

    @staticmethod
    def _since(topic: _Topic) -> float | None:
        """Since when the topic's next packet has been waiting (None: it has none)."""
        if topic.repairs:
            return topic.repaired
        if topic.packets:
            return topic.since
        if topic.waiting:
            return topic.waiting[0].queued
        return None

    def _start(self, topic: _Topic, now: float) -> bool:
        """Cut the topic's next message into packets; False when it was dropped instead."""
        message = topic.waiting.popleft()
        self._frames -= 1
        self._bytes -= message.size
        delivery = message.sender.delivery
        limit = delivery.max_delay
        if limit is None and not delivery.reliable:
            limit = self.max_delay
        waited = now - message.queued
        if limit is not None and waited > limit:
            self.dropped.append((message.sender, Drop.TOO_LATE,
                                 f"waited {waited:.3f} s to be sent (max_delay {limit:g} s)"))
            return False
        if topic.backlog is not None and topic.backlog.shed(waited, now):
            self.dropped.append((message.sender, Drop.OVERLOAD,
                                 f"waited {waited * 1e3:.0f} ms to be sent"))
            return False
        try:
            packets = message.cut()
        except Exception as exc:  # a frame that cannot be cut (too large): counted
            self.dropped.append((message.sender, Drop.SEND_ERROR, str(exc)))
            return False
        topic.current, topic.since = message, message.queued
        topic.packets.extend(packets)
        return bool(packets)

    def next(self, now: float | None = None) -> Due | float | None:
        """The packet to send now; or when to ask again (a budget is short); or None when
        nothing waits.

        Within a class, the topic whose next packet has waited longest goes: a message waits
        from when it was queued, the next packet of a message in progress from when the one
        before it left. So whole messages leave in the order they came, and the packets of
        long ones take turns with everything else (round robin when they tie)."""
        now = self.clock() if now is None else now
        soonest: float | None = None
        blocked: set[Any] = set()  # destinations whose budget keeps a packet back
        for topics in self._classes:
            while topics:
                line = []
                for key, topic in list(topics.items()):
                    since = self._since(topic)
                    if since is None:
                        del topics[key]
                    else:
                        line.append((since, key, topic))
                line.sort(key=lambda entry: entry[0])  # stable: ties keep the round robin
                restart = False
                for _, key, topic in line:
                    if not topic.repairs and not topic.packets:
                        if not self._start(topic, now):
                            restart = True  # dropped (late): look at the line again
                            break
                    again = bool(topic.repairs)
                    packet, to = topic.repairs[0] if again else (
                        topic.packets[0], topic.current.to if topic.current else None)
                    if to in blocked:
                        continue
                    bucket = self._bucket(to, now)
                    wait = bucket.take(len(packet) + self.overhead, now) if bucket else 0.0
                    if wait:
                        blocked.add(to)
                        soonest = now + wait if soonest is None else min(soonest, now + wait)
                        continue
                    ends, sender = None, topic.sender
                    if again:
                        topic.repairs.popleft()
                    else:
                        if topic.current is not None:  # the message's own (a service call's)
                            sender = topic.current.sender
                        topic.packets.popleft()
                        topic.since = now
                        if not topic.packets:
                            ends, topic.current = topic.current, None
                    topics.move_to_end(key)  # its turn is over
                    if not (topic.repairs or topic.packets or topic.waiting):
                        del topics[key]
                    return Due(packet, to, sender, ends, again)
                if not restart:
                    break
        return soonest

    def depth(self, sender: Any) -> int:
        """Messages of ``sender`` not fully sent: waiting, plus the one in progress."""
        topic = self._topics.get(self._key(sender))
        if topic is None:
            return 0
        return len(topic.waiting) + (topic.current is not None)

    @property
    def idle(self) -> bool:
        return not any(self._classes)

    @property
    def waiting(self) -> int:
        """Messages waiting to start, all senders."""
        return self._frames

    def forget(self, sender: Any) -> None:
        """A sender that is gone (a removed route): what it queued goes too."""
        topic = self._topics.pop(self._key(sender), None)
        del self._keys[id(sender)]
        if topic is not None:
            self._classes[topic.priority].pop(sender.topic_id, None)
            self._frames -= len(topic.waiting)
            self._bytes -= sum(m.size for m in topic.waiting)

    def clear(self) -> list[Any]:
        """Empty the queue (the link closes): the senders of every message that never left."""
        unsent = [m.sender for t in self._topics.values() for m in t.waiting]
        unsent += [t.sender for t in self._topics.values() if t.current is not None]
        for topics in self._classes:
            topics.clear()
        self._topics.clear()
        self._keys.clear()
        self._frames = self._bytes = 0
        return unsent
