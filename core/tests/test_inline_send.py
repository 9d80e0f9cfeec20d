"""Frames leave from the caller's thread when the link is idle, fragmented ones too: a
best-effort, latest-only topic loses nothing on an idle link however late its send thread is
scheduled. Real UDP sockets on loopback, udp's default 1,200-byte frames (a 2.5 kB message is
three fragments).

The send thread is made as late as it can be: the interpreter switches threads only once a
second here (``sys.setswitchinterval``), so a frame handed to it waits while the caller offers
the next one. Nothing is timed: the tests count what arrived and what was dropped."""

from __future__ import annotations

import math
import random
import sys
import threading
from dataclasses import dataclass, field

import pytest
from polling import settles
from rosgate_transport_udp import UdpEndpoint, UdpTransport

from rosgate.config import LinkConfig
from rosgate.links.datagram import DatagramLink
from rosgate.links.datagram_base import INLINE_MAX
from rosgate.spec import Delivery
from rosgate.wire import envelope, framing

TIMEOUT = 20.0


@dataclass(eq=False)
class Camera:
    """A best-effort, latest-only route as a link sees it."""

    topic_id: int = 7
    latest_only: bool = True
    reliable: bool = False
    drops: list[str] = field(default_factory=list)

    @property
    def delivery(self) -> Delivery:
        return Delivery(reliable=self.reliable, latest_only=self.latest_only)

    def drop(self, reason: str, detail: str = "") -> None:
        self.drops.append(reason)

    def on_wire(self, size: int, again: bool) -> None:
        pass


class Receiver:
    def __init__(self) -> None:
        self.frames: list[bytes] = []
        self.lost: list[str] = []
        self._changed = threading.Condition()

    def on_frame(self, frame: bytes, link, source) -> None:
        with self._changed:
            self.frames.append(bytes(frame))
            self._changed.notify_all()

    def on_lost(self, topic_id, reason) -> None:
        self.lost.append(reason)

    def wait_for(self, count: int) -> bool:
        with self._changed:
            return self._changed.wait_for(lambda: len(self.frames) >= count, TIMEOUT)


class SendOnly:
    """A udp endpoint with only the plain ``send`` (no scatter-gather, no several datagrams at
    once): the link's fallback for transports that offer nothing more."""

    def __init__(self, inner: UdpEndpoint):
        self.inner = inner
        self.sock = inner.sock
        self.receive = inner.receive
        self.close = inner.close

    def send(self, frame: bytes, to) -> None:
        self.inner.send(frame, to)


class OneAtATime(SendOnly):
    """A udp endpoint with scatter-gather but not several datagrams in one call."""

    def send_parts(self, parts, to) -> None:
        self.inner.send_parts(parts, to)


@pytest.fixture
def late_send_thread():
    before = sys.getswitchinterval()
    sys.setswitchinterval(1.0)
    yield
    sys.setswitchinterval(before)


@pytest.fixture
def closing():
    things = []
    yield lambda thing: things.append(thing) or thing
    for thing in reversed(things):
        thing.close()


def message(seq: int, size: int = 2_500) -> bytes:
    header = envelope.pack(0, 7, 1, seq, 0)
    return header + random.Random(seq).randbytes(size - len(header))


def pair(closing, wrap=None, budget: LinkConfig | None = None):
    transport = UdpTransport({"max_frame": 1_200})
    rx = Receiver()
    b_end = transport.bind(("127.0.0.1", 0))
    closing(DatagramLink(transport, b_end, "b", rx.on_frame, rx.on_lost))
    a_end = transport.bind(("127.0.0.1", 0))
    a = closing(DatagramLink(transport, wrap(a_end) if wrap else a_end, "a",
                             Receiver().on_frame, Receiver().on_lost, budget=budget))
    return a, b_end.sock.getsockname()[:2], rx


@pytest.mark.parametrize("wrap", [None, OneAtATime, SendOnly],
                         ids=["several-datagrams-at-once", "scatter-gather", "plain-send"])
def test_fragmented_best_effort_messages_on_an_idle_link_are_never_superseded(
        closing, late_send_thread, wrap):
    a, to, rx = pair(closing, wrap)
    camera = Camera()
    sent = [message(seq) for seq in range(300)]
    for frame in sent:
        assert a.send(frame, camera, to)
    assert rx.wait_for(len(sent))
    assert camera.drops == []
    assert rx.frames == sent  # every one, byte for byte, in order
    assert rx.lost == []
    counters = a.counters
    assert counters.inline_out == counters.frames_out == 300
    assert counters.packets_out == 3 * 300  # 2,500 bytes in 1,200-byte fragments
    assert a.queued() == 0


def test_a_whole_frame_counts_as_inline_too(closing, late_send_thread):
    a, to, rx = pair(closing)
    camera = Camera()
    small = [message(seq, 800) for seq in range(50)]
    for frame in small:
        assert a.send(frame, camera, to)
    assert rx.wait_for(len(small))
    assert rx.frames == small and camera.drops == []
    assert a.counters.inline_out == a.counters.frames_out == a.counters.packets_out == 50


def test_on_a_budget_the_send_thread_finishes_what_the_bucket_cannot_hold(closing):
    """A 60 kB frame on a 2 Mbit/s budget: the bucket holds a few fragments, the first leave
    from the caller, the rest wait their turn in the scheduler (and the link is not idle for
    the next frame, which waits behind it: latest-only replaces nothing that started)."""
    a, to, rx = pair(closing, budget=LinkConfig("udp", bandwidth=2e6))
    camera = Camera()
    first, second = message(1, 60_000), message(2, 60_000)
    assert a.send(first, camera, to)
    assert a.counters.packets_out >= 1  # the first fragment left from this thread
    assert a.queue_depth(camera) == 1  # the rest: the message in progress
    assert a.send(second, camera, to)  # waits behind the first
    assert rx.wait_for(2)
    assert rx.frames == [first, second]
    assert camera.drops == []
    assert settles(lambda: a.counters.frames_out >= 2)
    assert a.counters.frames_out == 2
    assert a.counters.inline_out == 0  # neither left whole from the caller
    per_frame = math.ceil(60_000 / (1_200 - framing.FRAGMENT.size))
    assert a.counters.packets_out == 2 * per_frame


def test_a_frame_that_cannot_go_at_once_is_queued_and_counted_once_superseded(
        closing, late_send_thread):
    """While a frame of another topic is in progress on the send thread, a latest-only topic's
    messages wait; all but the newest are replaced, each counted once. (The link is the
    bottleneck here: a budget.)"""
    a, to, rx = pair(closing, budget=LinkConfig("udp", bandwidth=2e6))
    other = Camera(topic_id=8, latest_only=False, reliable=True)
    big = message(1, 60_000)
    assert a.send(big, other, to)  # its rest is in progress: the link is busy
    camera = Camera()
    frames = [message(seq) for seq in range(10, 15)]
    for frame in frames:
        assert a.send(frame, camera, to)
    with rx._changed:
        assert rx._changed.wait_for(lambda: big in rx.frames and frames[-1] in rx.frames,
                                    TIMEOUT)
    # the newest arrives; one more may have started before the others came (a message that
    # started is never replaced); every other one was replaced, and counted once
    camera_got = [f for f in rx.frames if f in frames]
    assert camera_got[-1] == frames[-1] and len(camera_got) <= 2
    assert camera_got == [f for f in frames if f in camera_got]  # in order
    assert camera.drops == ["superseded"] * (len(frames) - len(camera_got))
    assert a.counters.inline_out == 0


class CountingRuns(OneAtATime):
    """A udp endpoint that counts what it is handed: several datagrams at once, or one."""

    def __init__(self, inner: UdpEndpoint):
        super().__init__(inner)
        self.runs: list[int] = []
        self.threads: set[str] = set()

    def send_datagrams(self, datagrams, to) -> None:
        self.runs.append(len(datagrams))
        self.threads.add(threading.current_thread().name)
        self.inner.send_datagrams(datagrams, to)


def test_a_frame_longer_than_what_leaves_inline_goes_from_the_send_thread_in_runs(closing):
    """A 300 kB frame (longer than INLINE_MAX) is the send thread's; it hands the kernel the
    frame's fragments 64 at a time (one system call each with segmentation offload), and the
    counters still count every packet and one frame."""
    a, to, rx = pair(closing, CountingRuns)
    camera = Camera()
    image = message(1, 300_000)
    assert len(image) > INLINE_MAX
    assert a.send(image, camera, to)
    assert rx.wait_for(1)
    assert rx.frames == [image] and camera.drops == [] and rx.lost == []
    packets = math.ceil(300_000 / (1_200 - framing.FRAGMENT.size))
    wire = a.endpoint
    assert wire.threads == {"tx-a"}
    assert settles(lambda: a.counters.packets_out >= packets and a.counters.frames_out >= 1)
    assert a.counters.packets_out == packets
    assert max(wire.runs) == 64 and sum(wire.runs) >= packets - 1  # the first may go alone
    assert a.counters.frames_out == 1 and a.counters.inline_out == 0
