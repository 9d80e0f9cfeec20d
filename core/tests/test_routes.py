"""A transmitting route takes what waits in its subscription and hands it to the link at once,
within a datagram's worth; every frame keeps its own envelope and sequence number."""

from __future__ import annotations

import inspect
import time
from collections import deque

from rosgate.builtin import CdrCodec, NoCipher
from rosgate.config import TopicConfig
from rosgate.keyring import StaticKeys
from rosgate.routes import (
    DRAIN_BYTES,
    DRAIN_FRAMES,
    EnvelopeFraming,
    ReceiveRoute,
    TransmitRoute,
    Warner,
)
from rosgate.spec import Delivery
from rosgate.wire import envelope


class Link:
    datagram = True

    def __init__(self) -> None:
        self.calls: list[list[bytes]] = []

    def send_all(self, frames, sender, to=None) -> int:
        self.calls.append(list(frames))
        return len(frames)

    def forget(self, sender) -> None:
        """What the link queued for a removed route goes (nothing is queued here)."""


def route(waiting: deque, max_rate: float | None = None, reliable: bool = False,
          max_delay: float | None = None) -> tuple[TransmitRoute, Link]:
    """A transmitting route; ``waiting`` holds what its subscription has waiting: messages, or
    (message, when it arrived) pairs (else: just now)."""
    fields = inspect.signature(TopicConfig).parameters
    topic = TopicConfig(**{name: None for name, p in fields.items() if p.default is p.empty})
    topic.max_rate, topic.max_delay = max_rate, max_delay
    link = Link()
    r = TransmitRoute(topic, 7, CdrCodec(None, {}), StaticKeys(NoCipher({}, ".")), Warner(), "/t",
                      Delivery(reliable=reliable),
                      framing=EnvelopeFraming(), link=link,  # type: ignore[arg-type]
                      destination=lambda: ("127.0.0.1", 9))

    def take():
        if not waiting:
            return None
        item = waiting.popleft()
        return item if isinstance(item, tuple) else (item, time.time_ns())

    r.take = take
    return r, link


def test_a_message_alone_is_one_frame():
    r, link = route(deque())
    r.on_message(b"\x00\x01\x00\x00alone")
    assert len(link.calls) == 1 and len(link.calls[0]) == 1
    header = envelope.unpack(link.calls[0][0])
    assert (header.topic_id, header.seq) == (7, 1)
    assert r.counters.sent == 1 and r.counters.bytes_sent == envelope.SIZE + 9


def test_what_waits_goes_with_it_in_order():
    waiting = deque(b"\x00\x01\x00\x00%d" % i for i in range(1, 10))
    r, link = route(waiting)
    r.on_message(b"\x00\x01\x00\x000")
    assert [len(call) for call in link.calls] == [10]
    assert [envelope.unpack(f).seq for f in link.calls[0]] == list(range(1, 11))
    assert [f[envelope.SIZE:] for f in link.calls[0]] == [b"\x00\x01\x00\x00%d" % i
                                                          for i in range(10)]
    assert not waiting and r.counters.sent == 10


def test_taking_stops_at_a_datagrams_worth():
    waiting = deque(bytes(1000) for _ in range(500))
    r, link = route(waiting)
    r.on_message(bytes(1000))
    assert len(link.calls[0]) == min(DRAIN_FRAMES, -(-DRAIN_BYTES // 1028))
    left = len(waiting)
    r.on_message(bytes(1000))  # the executor calls again for the next one: the rest follow
    assert len(waiting) < left


def test_what_waited_too_long_is_dropped_with_all_before_it():
    now = time.time_ns()
    old, fresh = now - 50_000_000, now  # older than the topic's max_delay (20 ms)
    waiting = deque([(b"1", old), (b"2", old), (b"3", fresh), (b"4", old), (b"5", fresh)])
    r, link = route(waiting, max_delay=0.02)
    r.on_message(b"0")
    assert [[f[envelope.SIZE:] for f in call] for call in link.calls] == [[b"5"]]
    assert r.counters.drops == {"too_late": 5} and r.counters.sent == 1
    # the sequence numbers stay without gaps: what was dropped never got one
    assert envelope.unpack(link.calls[0][0]).seq == 1


def test_a_reliable_topic_never_drops_for_age():
    old = time.time_ns() - 10_000_000_000
    waiting = deque([(b"1", old), (b"2", old)])
    r, link = route(waiting, reliable=True)
    r.on_message(b"0")
    assert [len(call) for call in link.calls] == [3] and not r.counters.drops


def test_the_rate_limit_applies_to_what_is_taken():
    waiting = deque(bytes(10) for _ in range(5))
    r, link = route(waiting, max_rate=1)
    r.on_message(bytes(10))
    assert [len(call) for call in link.calls] == [1]
    assert r.counters.drops == {"rate_limit": 5} and not waiting


# --- receiving: a reassembled frame reaches the publisher without a copy ---------------------

class RecordingCipher(NoCipher):
    """A cipher (it is not the none cipher) that records the types it is given."""

    name = "recording"
    got: list[type] = []

    def open(self, header, body):
        self.got += [type(header), type(body)]
        return body


def receiver(codec, cipher, max_delay: float | None = None) -> ReceiveRoute:
    fields = inspect.signature(TopicConfig).parameters
    topic = TopicConfig(**{name: None for name, p in fields.items() if p.default is p.empty})
    topic.max_delay = max_delay
    return ReceiveRoute(topic, 7, codec, StaticKeys(cipher), Warner(), "/t", Delivery(),
                        decode=codec.decode)


def test_a_reassembled_frame_is_the_payload_it_carries():
    route = receiver(CdrCodec(None, {}), NoCipher({}, "."))
    published = []
    route.publish = published.append
    frame = bytearray(envelope.pack(0, 7, 1, 1, 0) + b"\x00\x01\x00\x00cdr")
    route.on_frame(envelope.unpack(frame), frame)  # type: ignore[arg-type]
    assert published == [b"\x00\x01\x00\x00cdr"] and published[0] is frame
    assert route.counters.bytes_received == envelope.SIZE + 7


def test_ciphers_get_bytes_whatever_the_frame():
    cipher = RecordingCipher({}, ".")
    route = receiver(CdrCodec(None, {}), cipher)
    published = []
    route.publish = published.append
    frame = bytearray(envelope.pack(0, 7, 1, 1, 0) + b"\x00\x01\x00\x00cdr")
    route.on_frame(envelope.unpack(frame), frame)  # type: ignore[arg-type]
    assert cipher.got == [bytes, bytes] and published == [b"\x00\x01\x00\x00cdr"]


def test_a_frame_that_waited_too_long_in_the_receive_buffer_is_dropped():
    route = receiver(CdrCodec(None, {}), NoCipher({}, "."), max_delay=0.02)
    published = []
    route.publish = published.append
    now = time.time_ns()
    for seq, arrived in ((1, now - 50_000_000), (2, now), (3, 0)):  # 0: the link cannot tell
        frame = envelope.pack(0, 7, 1, seq, 0) + b"\x00\x01\x00\x00%d" % seq
        route.on_frame(envelope.unpack(frame), frame, arrived)
    assert published == [b"\x00\x01\x00\x002", b"\x00\x01\x00\x003"]
    assert route.counters.drops == {"too_late": 1} and route.counters.lost == 0
