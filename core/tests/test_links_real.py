"""Datagram and stream links on a bad link: two real links on loopback with the link
emulator's relay between them (seeded losses, a rate, a delay). Loss recovery (fec,
retransmit) brings every frame through losses that lose most of them without it; a budget
holds within 10 % over a few seconds; priorities and latest-only order what waits.

Nothing is timed but the budget (bytes counted over seconds, within 10 %); everything else
waits on arrivals with timeouts and asserts what arrived."""

from __future__ import annotations

import random
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import pytest
from polling import settles
from rosgate_emulator import Profile, TcpRelay, UdpRelay
from rosgate_recovery import Fec
from rosgate_transport_tcp import TcpTransport
from rosgate_transport_udp import UdpTransport

from rosgate.config import LinkConfig
from rosgate.links.datagram import DatagramLink
from rosgate.plugins import installed
from rosgate.spec import Delivery
from rosgate.streamlink.link import StreamLink
from rosgate.wire import envelope

TIMEOUT = 20.0


@dataclass(eq=False)
class Topic:
    """A route as a link sees it."""

    topic_id: int
    priority: int = 5
    recovery: str = "none"
    recovery_options: Any = None
    latest_only: bool = False
    reliable: bool = True
    drops: list[str] = field(default_factory=list)
    wire: int = 0
    again: int = 0

    @property
    def delivery(self) -> Delivery:
        packetizer = None if self.recovery == "none" else installed().get("packetizer",
                                                                          self.recovery).cls
        return Delivery(reliable=self.reliable, priority=self.priority,
                        latest_only=self.latest_only, packetizer=packetizer,
                        packetizer_options=self.recovery_options)

    def drop(self, reason: str, detail: str = "") -> None:
        self.drops.append(reason)

    def on_wire(self, size: int, again: bool) -> None:
        self.wire += size
        self.again += again


class Receiver:
    def __init__(self) -> None:
        self.frames: list[bytes] = []
        self.lost: list[tuple[int | None, str]] = []
        self.recovered: list[int] = []
        self._changed = threading.Condition()

    def on_frame(self, frame: bytes, link, source) -> None:
        with self._changed:
            self.frames.append(bytes(frame))
            self._changed.notify_all()

    def on_lost(self, topic_id, reason) -> None:
        with self._changed:
            self.lost.append((topic_id, reason))
            self._changed.notify_all()

    def on_recovered(self, topic_id) -> None:
        self.recovered.append(topic_id)

    def wait(self, predicate, timeout: float = TIMEOUT) -> bool:
        with self._changed:
            return self._changed.wait_for(predicate, timeout)


@pytest.fixture
def closing():
    things = []
    yield lambda thing: things.append(thing) or thing
    for thing in reversed(things):
        thing.close()


def frame(topic: int, seq: int, size: int) -> bytes:
    header = envelope.pack(0, topic, 1, seq, 0)
    return header + random.Random(seq * 1000 + topic).randbytes(size - len(header))


def lossy_pair(closing, profile: Profile, budget: LinkConfig | None = None,
               max_frame: int = 1200):
    """Link a sends to the relay, which passes datagrams on to link b through ``profile``
    (both ways: b's NACKs and ACKs come back through it)."""
    transport = UdpTransport({"max_frame": max_frame})
    rx = Receiver()
    b_end = transport.bind(("127.0.0.1", 0))
    closing(DatagramLink(transport, b_end, "b", rx.on_frame, rx.on_lost,
                         on_recovered=rx.on_recovered))
    relay = closing(UdpRelay(profile, target=b_end.sock.getsockname()))
    a = closing(DatagramLink(transport, transport.bind(("127.0.0.1", 0)), "a",
                             Receiver().on_frame, Receiver().on_lost, budget=budget))
    return a, relay, rx


LOSSY = Profile(delay=0.005, loss=0.03, seed=11)


@pytest.mark.parametrize("kind", ["fec", "retransmit"])
def test_recovery_brings_every_frame_through_3_percent_loss(closing, kind):
    """20 frames of 100 kB (84 datagrams each): without recovery 92 % of them are lost
    (1 - 0.97^84); with either recovery, none."""
    a, relay, rx = lossy_pair(closing, LOSSY)
    topic = Topic(9, recovery=kind, recovery_options=Fec.Options(overhead=0.25))
    frames = [frame(9, i, 100_000) for i in range(20)]
    for f in frames:
        assert a.send(f, topic, relay.address)
    assert rx.wait(lambda: len(rx.frames) >= 20), (len(rx.frames), rx.lost, topic.drops)
    assert sorted(rx.frames) == sorted(frames)
    assert rx.lost == [] and topic.drops == []
    assert relay.up.dropped["loss"] > 20            # the link lost plenty
    assert len(rx.recovered) >= 15                  # and recovery brought those frames back
    if kind == "retransmit":
        assert topic.again >= relay.up.dropped["loss"] * 0.8  # about what was lost, sent again
        store = a.packetizer("retransmit").store
        assert settles(lambda: len(store) == 0)   # every frame acknowledged
    else:
        assert topic.again == 0
        assert topic.wire > 1.2 * sum(map(len, frames))  # the repair fragments


def test_without_recovery_most_large_frames_are_lost_and_counted(closing):
    a, relay, rx = lossy_pair(closing, LOSSY)
    topic = Topic(9)
    frames = [frame(9, i, 100_000) for i in range(20)]
    for f in frames:
        a.send(f, topic, relay.address)
    assert rx.wait(lambda: len(rx.frames) + len(rx.lost) >= 20, 10)
    assert len(rx.frames) <= 6
    assert rx.lost.count((9, "fragment_lost")) == 20 - len(rx.frames)


def test_retransmit_recovers_frames_lost_whole_and_small_frames_too(closing):
    """A 1-fragment frame lost whole leaves the receiver nothing to ask about: the sender's
    probe (its last fragment again) does."""
    a, relay, rx = lossy_pair(closing, Profile(delay=0.002, loss=0.2, seed=5))
    topic = Topic(4, recovery="retransmit")
    frames = [frame(4, i, 200) for i in range(40)]
    for f in frames:
        a.send(f, topic, relay.address)
    assert rx.wait(lambda: len(rx.frames) >= 40), (len(rx.frames), rx.lost)
    assert sorted(rx.frames) == sorted(frames)
    assert relay.up.dropped["loss"] >= 5 and topic.again >= 5


def test_a_backlog_of_small_frames_with_retransmit_shares_packets_and_arrives_whole(closing):
    """Frames handed over together (a topic's backlog) are repaired as batches, one packet
    each as far as they fit: 60 frames of 200 bytes in 12 packets, not 60, through 20 % loss."""
    a, relay, rx = lossy_pair(closing, Profile(delay=0.002, loss=0.2, seed=9))
    topic = Topic(6, recovery="retransmit")
    frames = [frame(6, i, 200) for i in range(60)]
    for start in range(0, 60, 5):
        assert a.send_all(frames[start:start + 5], topic, relay.address) == 5
    assert rx.wait(lambda: len(rx.frames) >= 60), (len(rx.frames), rx.lost)
    assert sorted(rx.frames) == sorted(frames) and rx.lost == []
    counters = a.counters  # 12 batches of five, some of them sent again
    assert (counters.frames_out, counters.coalesced_out) == (60, 60)
    assert counters.packets_out < 12 + 3 * relay.up.dropped["loss"] + 10, counters
    assert relay.up.dropped["loss"] >= 2 and topic.again >= 2


def test_fec_needs_no_way_back(closing):
    """FEC rebuilds without a word from the receiver: with the return path cut (the relay
    loses everything b sends), frames still arrive."""
    transport = UdpTransport({})
    rx = Receiver()
    b_end = transport.bind(("127.0.0.1", 0))
    closing(DatagramLink(transport, b_end, "b", rx.on_frame, rx.on_lost,
                         on_recovered=rx.on_recovered))
    relay = closing(UdpRelay(Profile(loss=0.05, seed=3), target=b_end.sock.getsockname()))
    a = closing(DatagramLink(transport, transport.bind(("127.0.0.1", 0)), "a",
                             Receiver().on_frame, Receiver().on_lost))
    topic = Topic(2, recovery="fec", recovery_options=Fec.Options(overhead=0.3))
    frames = [frame(2, i, 30_000) for i in range(10)]
    for f in frames:
        a.send(f, topic, relay.address)
    assert rx.wait(lambda: len(rx.frames) >= 10), rx.lost
    assert sorted(rx.frames) == sorted(frames)
    assert relay.down.datagrams_in == 0  # nothing came back


@pytest.mark.parametrize("bandwidth", [2e6, 8e6])
def test_a_budget_holds_within_10_percent_over_a_few_seconds(closing, bandwidth):
    """Offered: three times the budget. Counted: the bytes the relay got (plus 28 bytes of IP
    and UDP headers a datagram), between 1 s and 4 s after the start."""
    a, relay, rx = lossy_pair(closing, Profile(), LinkConfig("udp", bandwidth=bandwidth))
    topic = Topic(3)
    stop = threading.Event()

    def offer() -> None:
        seq = 0
        while not stop.is_set():
            seq += 1
            a.send(frame(3, seq, 60_000), topic, relay.address)  # 3 x budget, best effort
            stop.wait(60_000 * 8 / (3 * bandwidth))

    thread = threading.Thread(target=offer, daemon=True)
    thread.start()
    samples = []
    try:
        start = time.monotonic()
        for at in (1.0, 4.0):
            time.sleep(max(0.0, start + at - time.monotonic()))
            up = relay.up
            samples.append((time.monotonic(), up.bytes_in + 28 * up.datagrams_in))
    finally:
        stop.set()
        thread.join()
    (t0, b0), (t1, b1) = samples
    rate = (b1 - b0) * 8 / (t1 - t0)
    assert 0.9 * bandwidth <= rate <= 1.1 * bandwidth, f"{rate / bandwidth:.3f} of the budget"


def test_a_small_frame_of_a_higher_class_overtakes_a_large_frame_in_progress(closing):
    """On a 1 Mbit/s budget a 300 kB frame takes 2.4 s; a control frame sent after it starts
    arrives long before it (the receiver sees the small one first)."""
    a, relay, rx = lossy_pair(closing, Profile(), LinkConfig("udp", bandwidth=1e6))
    image, twist = Topic(1, priority=6), Topic(2, priority=2)
    big = frame(1, 1, 300_000)
    a.send(big, image, relay.address)
    assert relay.wait_until(lambda up, _: up.datagrams_in >= 5, TIMEOUT)  # the image started
    small = [frame(2, i, 60) for i in range(5)]
    for f in small:
        assert a.send(f, twist, relay.address)
    assert rx.wait(lambda: big in rx.frames)
    assert rx.frames == small + [big]


def test_latest_only_keeps_one_waiting_message_and_counts_the_rest(closing):
    a, relay, rx = lossy_pair(closing, Profile(), LinkConfig("udp", bandwidth=2e6))
    camera = Topic(5, latest_only=True, reliable=False)
    frames = [frame(5, i, 50_000) for i in range(10)]  # 200 ms each on the link
    a.send(frames[0], camera, relay.address)
    assert relay.wait_until(lambda up, _: up.datagrams_in >= 1, TIMEOUT)  # the first started
    for f in frames[1:]:
        a.send(f, camera, relay.address)  # at once: they wait behind it
    assert rx.wait(lambda: frames[-1] in rx.frames)
    # the first (already started) and the last arrive; everything between was replaced
    assert rx.frames == [frames[0], frames[-1]]
    assert camera.drops == ["superseded"] * 8


def test_streams_interleave_large_frames_with_small_ones_of_a_higher_class(closing):
    """TCP through a 4 Mbit/s relay: a 2 MB frame in chunks, a control frame sent after it
    starts arrives first."""
    transport = TcpTransport({})
    listener = closing(transport.listen(("127.0.0.1", 0)))
    relay = closing(TcpRelay(Profile(rate=4e6, queue=64_000), listener.sock.getsockname()))
    client = transport.connect(relay.address, 2.0)
    accepted = listener.accept(5.0)
    assert accepted is not None
    rx = Receiver()
    closing(StreamLink(accepted[0], "b", accepted[1], rx.on_frame, rx.on_lost))
    a = closing(StreamLink(client, "a", relay.address, Receiver().on_frame, Receiver().on_lost,
                           budget=LinkConfig("tcp", bandwidth=3.5e6)))
    image, twist = Topic(1, priority=6), Topic(2, priority=2)
    big = frame(1, 1, 2_000_000)
    a.send(big, image)
    assert relay.wait_until(lambda up, _: up.bytes_in > 100_000, TIMEOUT)
    small = [frame(2, i, 60) for i in range(3)]
    for f in small:
        a.send(f, twist)
    assert rx.wait(lambda: big in rx.frames, 30)
    assert rx.frames == small + [big]

