"""The scheduler: in which order, and how fast, frames leave a link (the rules are
docs/real-links.md's "Priorities", "Latest only", "Late messages" and "Budgets").

Frames queue per topic (the :class:`~rosgate.links.base.Sender`'s topic id) in priority classes —
zenoh's seven, and class 0 above them for the control channel — and leave as *packets* (a
datagram, a fragment, a chunk of a stream): strict priority between classes; within one, the
packet that has waited longest (so a long message's packets take turns with the others'); one
message at a time per topic, its retransmissions first; ``latest_only`` replacement
(``superseded``); a message dropped when it waited past ``max_delay`` before starting
(``too_late``) or by its :class:`Backlog` (``overload``); a token bucket per destination.

Nothing here sends or waits: the link's send thread asks :meth:`Scheduler.next` for the next
packet, sends it, and sleeps until the time it is told when there is none yet.
"""

from __future__ import annotations

import time
from collections import OrderedDict, deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

from .drops import Drop, Reason

CLASSES = 8  # 0: control; 1 (real_time) .. 7 (background)
CONTROL = 0
KEYS_KEPT = 4096  # senders whose queue key is remembered, at most
LAG = 0.02   # seconds: a message that waited longer finds its topic behind
HOLD = 0.2   # seconds behind on end (or caught up, to stop) before a topic sheds (Backlog)
#: seconds a best-effort message without a ``max_delay`` of its own may wait in the bridge's own
#: queues (its subscription's, the receive buffer) once its topic has stood behind there for
#: FRESH_HOLD on end: what waited longer is dropped, oldest first (``too_late``). Longer than
#: LAG (a bridge near the limit of its CPU waits for its threads some milliseconds without
#: being overloaded); FRESH_HOLD is CoDel's interval: a 50 ms stall's backlog is caught up with
#: well within it, while a queue that stands this long is one that will not drain by itself.
FRESH = 0.025
FRESH_HOLD = 0.1
#: seconds: the longest time between two messages a topic's period is taken from
PERIOD_MAX = 1.0


class Period:
    """A topic's time between messages, smoothed (1/8 of each new gap, as TCP's SRTT) from when
    each came in; a quiet spell counts for PERIOD_MAX at most. None until a second came."""

    __slots__ = ("at", "value")

    def __init__(self) -> None:
        self.at: float | None = None  # when the latest message came in
        self.value: float | None = None

    def note(self, at: float) -> float | None:
        """A message came in at ``at``: the period now."""
        last = self.at
        if last is None or at > last:
            if last is not None:
                gap = min(at - last, PERIOD_MAX)
                value = self.value
                self.value = gap if value is None else value + (gap - value) / 8
            self.at = at
        return self.value


class Backlog:
    """Whether a best-effort topic sheds a message from a queue by its age, the way CoDel does:
    only a queue that stands, not one that comes and goes. Behind (a message older than
    ``lag``, and older than the topic's period: a newer one of it is due behind it) for
    ``hold`` on end, it sheds what is older than that until nothing has been for ``hold``; a
    stall's backlog is caught up with in less than ``hold``: sent, not shed. A message that
    waited less than its topic's period is its topic's newest: dropping it makes nothing
    fresher (a 20 Hz camera's image 40 ms late in a busy bridge is still the latest one). The
    send queue's are :data:`LAG` and :data:`HOLD`; the bridge's own queues' (the
    subscription's, the receive buffer) :data:`FRESH` and :data:`FRESH_HOLD`."""

    __slots__ = ("since", "last", "lag", "hold", "period")

    def __init__(self, lag: float = LAG, hold: float = HOLD) -> None:
        self.since: float | None = None  # when this spell behind began
        self.last = -hold  # when a message last waited longer than lag
        self.lag = lag
        self.hold = hold
        self.period = Period()  # of the messages it judges

    def shedding(self, now: float) -> bool:
        """Whether, at ``now``, the queue stands behind and sheds (what ``rosgate top`` shows)."""
        return (self.since is not None and self.last - self.since >= self.hold
                and now - self.last < self.hold)

    def shed(self, waited: float, now: float) -> bool:
        """Whether a message that waited ``waited`` seconds, leaving at ``now``, is shed."""
        period = self.period.note(now - waited)  # (every message: its gaps are the period)
        if waited <= self.lag or period is not None and waited <= period:
            if self.since is not None and (now - self.since < self.hold
                                           or now - self.last >= self.hold):
                self.since = None  # caught up: a stall's backlog is gone, or the overload is
            return False
        if self.since is None or now - self.last >= self.hold:  # (late ones far apart: no spell)
            self.since = now
        self.last = now
        return now - self.since >= self.hold


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

    def take(self, size: int, now: float) -> float:
        """0 and take ``size`` bytes' tokens when they are there; else the seconds until they
        will be (taking nothing)."""
        if now > self.at:
            self.tokens = min(self.capacity, self.tokens + (now - self.at) * self.rate)
            self.at = now
        need = min(size, self.capacity)  # a packet larger than the bucket waits for a full one
        if self.tokens + 1e-6 >= need:  # (not a rounding error away from it, forever)
            self.tokens -= size
            return 0.0
        return (need - self.tokens) / self.rate

    def charge(self, size: int, now: float) -> None:
        """Count bytes sent outside the queue (acknowledgements): the bucket may go into debt."""
        self.take(0, now)  # (takes nothing: fills the bucket up to now)
        self.tokens -= size


@dataclass(eq=False)
class Outgoing:
    """One frame on its way, cut into its packets when it starts."""

    sender: Any
    to: Any
    size: int
    cut: Callable[[], list[bytes]]
    queued: float = 0.0
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
    period: Period = field(default_factory=Period)  # of its messages, from their queue times

    def supersedes(self, message: Outgoing, busy: bool) -> Iterator[Outgoing]:
        """What ``message`` replaces of a latest-only topic's waiting messages: all of them
        while the link is ``busy`` with another topic's or one of this topic's is on its way
        (they wait for the link); else those that waited longer than LAG, or than the topic's
        period (a newer one is due after each). One that waited less waits for the send thread
        to wake, not for the link: two images a 20 Hz camera handed over together both go on
        an idle link."""
        now = message.queued
        period = self.period.note(now)
        stale = 0.0 if busy or self.current is not None or self.packets else \
            LAG if period is None else min(LAG, period)
        waiting = self.waiting
        while waiting and now - waiting[0].queued >= stale:
            yield waiting.popleft()


class Scheduler:
    """The send queue of one link. Not thread-safe: the link holds its lock around every call,
    and counts what ``dropped`` holds outside it."""

    def __init__(self, *, bandwidth: float | None = None, overhead: int = 0,
                 max_delay: float = 1.0, frames: int = 10_000, bytes: int = 64 * 1024 * 1024,
                 packet: int = 65_536, clock: Callable[[], float] = time.monotonic,
                 one_line: bool = False):
        self.rate = bandwidth / 8 if bandwidth else None  # bytes per second
        self.one_line = one_line  # one budget for every destination (a serial line)
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

    def _topic(self, sender: Any) -> _Topic:
        """The queue of the sender's topic in its class: a route's announcements (the control
        class) never wait in, or replace anything of, the queue of its messages. Reliable
        topics and those with a ``max_delay`` of their own never shed by age."""
        key = self._key(sender)
        topic = self._topics.get(key)
        if topic is None:
            delivery = sender.delivery
            sheds = not delivery.reliable and delivery.max_delay is None
            topic = self._topics[key] = _Topic(sender, key[1], backlog=Backlog() if sheds else None)
        return topic

    def _key(self, sender: Any) -> tuple[int, int]:
        """The sender's topic id and class, read once (they do not change)."""
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
            active = sum(map(len, self._classes))  # topics with something to send
            busy = active > (topic.sender.topic_id in self._classes[topic.priority])
            for old in topic.supersedes(message, busy):
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

    def shed(self, frames: int, bytes_: int, detail: str) -> None:
        """Drop the oldest messages waiting to start until at most ``frames`` of them, and
        ``bytes_``, wait (counted ``queue_full``): a link whose line is gone keeps the newest."""
        while self._frames > frames or self._bytes > bytes_:
            topic = min((t for t in self._topics.values() if t.waiting),
                        key=lambda t: t.waiting[0].queued)
            old = topic.waiting.popleft()
            self._frames -= 1
            self._bytes -= old.size
            self.dropped.append((old.sender, Drop.QUEUE_FULL, detail))

    def resume(self, message: Outgoing, packets: list[bytes], now: float) -> None:
        """The rest of a message whose first packets left from the caller's thread: its topic's
        message in progress, due since ``now``."""
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

    def _bucket(self, to: Any, now: float) -> Bucket | None:
        if self.rate is None:
            return None
        key = None if self.one_line else to
        bucket = self._buckets.get(key)
        if bucket is None:
            bucket = self._buckets[key] = Bucket(self.rate, self.capacity, now)
        return bucket

    def may_send_now(self, to: Any, size: int) -> bool:
        """Whether a packet for ``to`` may leave at once (nothing queued; its tokens taken)."""
        if self._frames or any(self._classes):
            return False
        if self.rate is None:  # no budget (no clock to read)
            return True
        bucket = self._bucket(to, self.clock())
        return bucket is None or bucket.take(size + self.overhead, self.clock()) == 0.0

    def _start(self, topic: _Topic, now: float) -> bool:
        """Cut the topic's next message into packets; False when it was dropped instead."""
        message = topic.waiting.popleft()
        self._frames -= 1
        self._bytes -= message.size
        delivery = message.sender.delivery  # best effort waits the link's max_delay at most
        limit = delivery.max_delay if delivery.max_delay is not None or delivery.reliable \
            else self.max_delay
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
        """The packet to send now; or when to ask again (a budget is short); or None.

        Within a class the packet that has waited longest goes: a message waits from when it
        was queued, a message's next packet from when the one before it left."""
        now = self.clock() if now is None else now
        soonest: float | None = None
        blocked: set[Any] = set()  # destinations whose budget keeps a packet back
        for topics in self._classes:
            while topics:
                line = []
                for key, topic in list(topics.items()):  # since when its next packet waits
                    since = topic.repaired if topic.repairs else topic.since if topic.packets \
                        else topic.waiting[0].queued if topic.waiting else None
                    if since is None:
                        del topics[key]
                    else:
                        line.append((since, key, topic))
                line.sort(key=lambda entry: entry[0])  # stable: ties keep the round robin
                for _, key, topic in line:
                    if not topic.repairs and not topic.packets and not self._start(topic, now):
                        break  # dropped (late): look at the line again
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
                else:  # nothing of this class may go now: the next class
                    break
        return soonest

    def depth(self, sender: Any) -> int:
        """Messages of ``sender`` not fully sent: waiting, plus the one in progress."""
        topic = self._topics.get(self._key(sender))
        return 0 if topic is None else len(topic.waiting) + (topic.current is not None)

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
