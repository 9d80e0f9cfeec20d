"""The scheduler alone, on a simulated clock: the order packets leave in (strict priority,
round robin, one message at a time per topic, repairs first), latest-only replacement, late
best-effort messages, the link's limits, and budgets per destination within 10 % over a few
seconds."""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import pytest

from rosgate.scheduler import (
    FRESH,
    FRESH_HOLD,
    HOLD,
    LAG,
    Backlog,
    Bucket,
    Due,
    Outgoing,
    Scheduler,
    burst,
)
from rosgate.spec import Delivery

IDS = itertools.count(1)


@dataclass(eq=False)
class Topic:
    name: str
    priority: int = 5
    topic_id: int = field(default_factory=lambda: next(IDS))
    latest_only: bool = False
    reliable: bool = True
    max_delay: float | None = None
    drops: list[str] = field(default_factory=list)

    @property
    def delivery(self) -> Delivery:
        return Delivery(reliable=self.reliable, priority=self.priority,
                        latest_only=self.latest_only, max_delay=self.max_delay)


class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def message(topic: Topic, name: str, packets: int = 1, size: int = 100, to="b",
            queued: float = 0.0) -> Outgoing:
    return Outgoing(topic, to, packets * size,
                    lambda: [f"{name}.{i}".encode().ljust(size, b".") for i in range(packets)],
                    queued)


def drain(scheduler: Scheduler, clock: Clock | None = None, limit: int = 10_000) -> list[str]:
    """Every packet in the order it leaves (advancing the clock when a budget says wait)."""
    out = []
    for _ in range(limit):
        due = scheduler.next(clock() if clock else 0.0)
        if due is None:
            break
        if isinstance(due, float):
            assert clock is not None
            clock.now = due
            continue
        out.append(due.packet.decode().rstrip("."))
    for sender, reason, _ in scheduler.dropped:
        sender.drops.append(reason)
    scheduler.dropped.clear()
    return out


def test_strict_priority_between_classes():
    s = Scheduler()
    image, twist, status = Topic("image", 6), Topic("twist", 2), Topic("status", 5)
    s.put(message(image, "img", packets=3))
    s.put(message(status, "st"))
    s.put(message(twist, "tw"))
    s.put(message(Topic("hello", 0), "ctl"))  # the control channel's class
    assert drain(s) == ["ctl.0", "tw.0", "st.0", "img.0", "img.1", "img.2"]


def test_round_robin_between_the_topics_of_a_class_packet_by_packet():
    s = Scheduler()
    a, b, c = Topic("a"), Topic("b"), Topic("c")
    s.put(message(a, "a1", packets=4))
    s.put(message(b, "b1", packets=2))
    s.put(message(c, "c1"))
    s.put(message(c, "c2"))
    assert drain(s) == ["a1.0", "b1.0", "c1.0", "a1.1", "b1.1", "c2.0", "a1.2", "a1.3"]


def test_a_control_topic_waits_at_most_one_packet_of_a_large_message():
    s = Scheduler()
    image, twist = Topic("image", 5), Topic("twist", 2)
    s.put(message(image, "img", packets=700))
    out = []
    for i in range(50):  # a Twist arrives after every ten image fragments
        out += [s.next(0.0).packet.decode().rstrip(".") for _ in range(10)]
        s.put(message(twist, f"tw{i}"))
        out.append(s.next(0.0).packet.decode().rstrip("."))
    assert out[10::11] == [f"tw{i}.0" for i in range(50)]


def test_a_topic_s_messages_never_interleave_and_repairs_go_first():
    s = Scheduler()
    t = Topic("t")
    s.put(message(t, "m1", packets=3))
    s.put(message(t, "m2", packets=2))
    first = s.next(0.0)
    assert first.packet.startswith(b"m1.0")
    s.repair(t, "b", [b"m0.5"])  # a receiver asked for a fragment of an earlier message
    out = [first.packet.decode().rstrip(".")] + drain(s)
    assert out == ["m1.0", "m0.5", "m1.1", "m1.2", "m2.0", "m2.1"]


def test_the_last_packet_of_a_message_says_so():
    s = Scheduler()
    t = Topic("t")
    m = message(t, "m", packets=2)
    s.put(m)
    dues = [s.next(0.0), s.next(0.0)]
    assert [d.ends for d in dues] == [None, m]


def test_latest_only_replaces_the_message_not_yet_started():
    s = Scheduler()
    cam = Topic("cam", latest_only=True)
    s.put(message(cam, "f1", packets=3))
    assert s.next(0.0).packet.startswith(b"f1.0")   # f1 started: it is finished
    for n in range(2, 6):
        s.put(message(cam, f"f{n}", packets=3))      # f2..f4 replaced in turn by f5
    assert s.depth(cam) == 2  # f1 in progress, f5 waiting
    assert drain(s) == ["f1.1", "f1.2", "f5.0", "f5.1", "f5.2"]
    assert cam.drops == ["superseded"] * 3
    assert s.depth(cam) == 0


def test_latest_only_on_an_idle_link_keeps_what_waits_for_the_send_thread():
    """A 20 Hz camera on an idle link hands over two images 1 ms apart (its executor was busy)
    before the send thread woke: both go. One that waited longer than LAG, with nothing of the
    link's on its way, is still replaced by the next."""
    s = Scheduler()
    cam = Topic("cam", latest_only=True, reliable=False)
    for n in range(10):  # its pace: one every 50 ms, each sent before the next
        s.put(message(cam, f"f{n}", queued=n * 0.05))
        assert drain(s) == [f"f{n}.0"]
    s.put(message(cam, "f10", queued=0.5))
    s.put(message(cam, "f11", queued=0.501))
    assert s.depth(cam) == 2
    s.put(message(cam, "f12", queued=0.55))  # the send thread slept through 50 ms: behind
    assert s.depth(cam) == 1
    assert drain(s) == ["f12.0"] and cam.drops == ["superseded"] * 2


def test_reliable_topics_queue_everything():
    s = Scheduler()
    t = Topic("t")
    for n in range(5):
        s.put(message(t, f"m{n}"))
    assert s.depth(t) == 5
    assert drain(s) == [f"m{n}.0" for n in range(5)]


def test_a_best_effort_message_that_waited_too_long_is_dropped_as_late():
    clock = Clock()
    s = Scheduler(max_delay=0.5, clock=clock)
    be, rel = Topic("be", reliable=False), Topic("rel")
    s.put(message(be, "old", queued=0.0))
    s.put(message(rel, "old-reliable", queued=0.0))
    s.put(message(be, "new", queued=0.4))
    clock.now = 0.6
    assert drain(s, clock) == ["old-reliable.0", "new.0"]  # first come, first served
    assert be.drops == ["too_late"] and rel.drops == []


def test_a_topic_s_own_max_delay_applies_to_reliable_topics_too():
    """A camera that would rather skip a frame than send one that waited: its max_delay."""
    clock = Clock()
    s = Scheduler(max_delay=5.0, clock=clock)
    cam = Topic("cam")
    cam.max_delay = 0.05  # type: ignore[attr-defined]
    s.put(message(cam, "waited", queued=0.0))
    s.put(message(cam, "fresh", queued=0.08))
    clock.now = 0.1
    assert drain(s, clock) == ["fresh.0"]
    assert cam.drops == ["too_late"]


def test_the_link_s_limits_refuse_new_messages():
    s = Scheduler(frames=3, bytes=250)
    t = Topic("t")
    assert [s.put(message(t, f"m{n}")) for n in range(3)] == [True, True, False]  # bytes
    assert t.drops == [] and [r for _, r, _ in s.dropped] == ["queue_full"]
    s2 = Scheduler(frames=2)
    assert [s2.put(message(t, f"m{n}")) for n in range(3)] == [True, True, False]  # frames


def test_clear_names_what_never_left():
    s = Scheduler()
    a, b = Topic("a"), Topic("b")
    s.put(message(a, "a1", packets=2))
    s.put(message(b, "b1"))
    s.next(0.0)
    assert sorted(t.name for t in s.clear()) == ["a", "b"]
    assert s.idle and s.next(0.0) is None


# -- budgets -----------------------------------------------------------------------------------
def test_bucket():
    b = Bucket(rate=1000.0, capacity=500, now=0.0)
    assert b.take(400, 0.0) == 0.0
    assert b.take(400, 0.0) == pytest.approx(0.3)   # 100 left, 300 to come at 1000 B/s
    assert b.take(400, 0.3) == 0.0
    b.charge(1000, 0.3)                             # an acknowledgement: into debt
    assert b.take(100, 0.3) == pytest.approx(1.1)


@pytest.mark.parametrize("bandwidth, packet", [(20e6, 1200), (2e6, 1200), (500e3, 300)])
def test_a_budget_holds_within_10_percent_over_a_few_seconds(bandwidth, packet):
    clock = Clock()
    s = Scheduler(bandwidth=bandwidth, overhead=28, clock=clock, packet=packet)
    image, twist = Topic("image"), Topic("twist", 2)
    sent = 0
    t = 0.0
    while clock.now < 3.0:
        # offered: far more than the budget (an image every 0.1 s, twists at 50 Hz)
        while t <= clock.now:
            s.put(message(image, f"i{t:.2f}", packets=int(bandwidth / 8 / packet / 2),
                          size=packet, queued=t))
            s.put(message(twist, f"t{t:.2f}", size=60, queued=t))
            t += 0.02
        due = s.next()
        if isinstance(due, float):
            clock.now = due
        elif isinstance(due, Due):
            if clock.now >= 0.5:  # after the first burst
                sent += len(due.packet) + 28
    rate = sent * 8 / 2.5
    assert bandwidth * 0.9 <= rate <= bandwidth * 1.1, rate / bandwidth


def test_every_destination_has_a_budget_of_its_own():
    clock = Clock()
    s = Scheduler(bandwidth=80_000, clock=clock, packet=1000)  # 10 kB/s per destination
    a, b = Topic("a"), Topic("b")
    s.put(message(a, "to-x", packets=30, size=1000, to="x"))
    s.put(message(b, "to-y", packets=30, size=1000, to="y"))
    out = drain(s, clock)
    assert len(out) == 60
    assert clock.now == pytest.approx((30_000 - burst(10_000, 1000)) / 10_000, rel=0.01)


def test_a_budget_keeps_strict_priority_for_its_destination():
    """A large high-priority packet waiting for tokens is not overtaken by a small lower one."""
    clock = Clock()
    s = Scheduler(bandwidth=8000, clock=clock, packet=1000)  # 1 kB/s, a 4 kB bucket
    high, low = Topic("high", 1), Topic("low", 7)
    s.put(message(high, "h", packets=6, size=1000))
    s.put(message(low, "l", size=10))
    assert drain(s, clock) == [f"h.{i}" for i in range(6)] + ["l.0"]


# -- shedding by age: only while a best-effort topic stays behind --------------------------------
def run(topic: Topic, seconds: float = 3.0, packet_time: float = 0.002,
        stalls: tuple[tuple[float, float], ...] = ()) -> tuple[list[tuple[float, float]], int]:
    """2,500-byte messages offered one a millisecond on a budget of one per ``packet_time``,
    the send thread held during each (start, length) of ``stalls``: (when, how long it waited)
    of every message that left, and how many were offered."""
    clock = Clock()
    s = Scheduler(bandwidth=2_500 * 8 / packet_time, clock=clock, packet=2_500)
    left: list[tuple[float, float]] = []
    offered = 0
    while clock.now < seconds:
        while offered * 0.001 <= clock.now:
            s.put(message(topic, f"m{offered}", size=2_500, queued=offered * 0.001))
            offered += 1
        held = next((start + length for start, length in stalls
                     if start <= clock.now < start + length), None)
        due = None if held else s.next()
        if isinstance(due, Due):
            assert due.ends is not None  # one packet each
            left.append((clock.now, clock.now - due.ends.queued))
            continue
        clock.now = min(due or math.inf, held or math.inf, offered * 0.001)
    for sender, reason, _ in s.dropped:
        sender.drops.append(reason)
    return left, offered


def test_a_best_effort_topic_that_stays_behind_sheds_its_oldest_and_what_leaves_is_fresh():
    be = Topic("scan", reliable=False)
    left, offered = run(be)  # twice what the link carries
    # behind from the start: what leaves ages as the queue grows, until the topic has been
    # behind for HOLD on end; from then on nothing older than LAG leaves
    early = [age for at, age in left if at < HOLD]
    late = [age for at, age in left if at > 2 * HOLD]
    assert max(early) > 2 * LAG
    assert late and max(late) <= LAG + 0.002 + 1e-9  # LAG, and one packet's time on the link
    assert set(be.drops) == {"overload"}  # never too_late: the link's max_delay is not reached
    waiting = offered - len(left) - len(be.drops)
    assert 0 <= waiting <= LAG / 0.001 + 2  # the rest is what waits at the end: LAG's worth
    assert len(left) == pytest.approx(3.0 / 0.002, rel=0.02)  # the link stayed busy


def test_a_reliable_topic_never_sheds_by_age():
    rel = Topic("scan")
    left, _ = run(rel)
    assert rel.drops == []
    assert max(age for _, age in left) > 1.0  # it waits, however long: the queue bounds it


def test_a_topic_with_a_max_delay_of_its_own_is_dropped_at_that_age_only():
    cam = Topic("cam", reliable=False, max_delay=0.1)
    left, _ = run(cam)
    assert set(cam.drops) == {"too_late"}
    late = [age for at, age in left if at > 2 * HOLD]
    assert LAG < max(late) <= 0.1 + 0.002 + 1e-9  # its own limit, not the shedding's


def test_stalls_shorter_than_the_hold_shed_nothing():
    """The send thread held for 120 ms, five times: what waited leaves late, catching up
    within 120 ms more (the link carries twice what is offered), and nothing is dropped."""
    be = Topic("scan", reliable=False)
    stalls = tuple((0.1 + n * 0.5, 0.12) for n in range(5))
    left, offered = run(be, packet_time=0.0005, stalls=stalls)
    assert be.drops == []
    assert len(left) == offered
    assert max(age for _, age in left) >= 0.119  # the stalls were real
    assert max(age for at, age in left if at > 2.7) < 0.001  # caught up long since


def test_backlog_sheds_only_after_hold_on_end_and_stops_after_hold_caught_up():
    b = Backlog()
    shed = [(n * 0.001, b.shed(2 * LAG, n * 0.001)) for n in range(int(3 * HOLD / 0.001))]
    assert not any(s for at, s in shed if at < HOLD - 0.0015)
    assert all(s for at, s in shed if at >= HOLD + 0.0015)
    end = shed[-1][0]
    # caught up, with a late one now and then: the late ones are still shed
    assert not b.shed(LAG / 2, end)
    assert b.shed(2 * LAG, end + HOLD / 2)
    # then caught up for HOLD: the next late one starts a new spell, and goes through
    assert not b.shed(LAG / 2, end + HOLD / 2 + HOLD)
    assert not b.shed(2 * LAG, end + HOLD / 2 + HOLD + 0.001)


def test_backlog_of_stalls_never_sheds():
    """Backlogs that take just under HOLD to catch up with, each ended by a fresh message,
    again and again."""
    b = Backlog()
    t = 0.0
    for _ in range(50):
        for _ in range(int(HOLD / 0.001) - 5):
            assert not b.shed(0.1 + LAG, t)
            t += 0.001
        assert not b.shed(0.0, t)
        t += 0.001


def test_backlog_a_late_message_long_after_the_last_one_starts_a_new_spell():
    """Observations further apart than HOLD are not a topic that stays behind (one that went
    quiet, then stalled once more)."""
    b = Backlog()
    for n in range(10):
        assert not b.shed(2 * LAG, n * (HOLD + 0.01))


def test_backlog_never_sheds_a_message_that_waited_less_than_its_topics_period():
    """A 20 Hz camera's images, each 40 ms late (over FRESH, under the 50 ms between them), in
    a bridge that stays that busy: each is the newest there is, and goes. Once they wait 60 ms,
    the next image is behind each: after FRESH_HOLD on end, they are shed."""
    b = Backlog(FRESH, FRESH_HOLD)
    at = [n * 0.05 for n in range(40)]
    assert not any(b.shed(0.04, t + 0.04) for t in at)
    later = [b.shed(0.06, t + 2 + 0.06) for t in at]
    assert not any(later[:2]) and all(later[3:])
