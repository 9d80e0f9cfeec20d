"""The conformance suite of packetizers (:mod:`rosgate.packetizer`)::

    from rosgate_testing import PacketizerConformance

    class TestFecConformance(PacketizerConformance):
        packetizer = Fec
        options = {"overhead": 0.3}      # the topic's options for it (default {})
        recovers = True                  # it brings frames through losses

Two instances, a sender and a receiver, each with a link of its own (:class:`SimulatedLink`):
packets, acknowledgements and packets sent again cross a simulated path with a delay, seeded
losses, and a simulated clock that drives the timers (nothing waits). It checks: the class is
found through its entry point; frames from one byte (or, with ``cuts_every_frame = False``, from
``max_frame + 1``; or the sizes its ``frame_sizes`` says) to 100 kB cross byte for byte and
exactly once, in packets no longer than
``max_frame`` that start with one of its magics (a packetizer that ``cuts_every_frame`` may have
none, and its packets are sent as the link sends them: cut in datagrams of ``max_frame``);
:meth:`~rosgate.Packetizer.cost` is what ``cut`` makes; reordered (unless it needs them
``ordered``) and duplicated packets still give each frame once; with losses, a
packetizer that ``recovers`` brings every frame through (and reports it recovered), any other
counts every frame it lost, once; garbage, and damaged packets, are a frame, nothing or
``FramingError``, never another exception.
"""

from __future__ import annotations

import itertools
import random
import time
from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar

import pytest

from rosgate import FramingError, Packetizer, Reason
from rosgate.options import parse

from .helpers import assert_registered, mutations

DELAY = 0.005  # seconds a packet takes on the simulated path
#: the two sides' addresses
ADDRESSES = {"a": ("192.0.2.1", 1), "b": ("192.0.2.2", 2)}


@dataclass(eq=False)
class Topic:
    """A sender as the packetizer sees it."""

    topic_id: int = 7


@dataclass
class SimulatedLink:
    """The :class:`~rosgate.PacketLink` of one side: what it is told is recorded, what it sends
    goes to ``outbox`` for the path to carry."""

    name: str
    max_frame: int
    max_message: int = 64 * 1024 * 1024
    lost_frames: list[tuple[int | None, str]] = field(default_factory=list)
    recovered_frames: list[int] = field(default_factory=list)
    outbox: list[bytes] = field(default_factory=list)

    def lost(self, topic_id: int | None, reason: Reason) -> None:
        self.lost_frames.append((topic_id, reason))

    def recovered(self, topic_id: int) -> None:
        self.recovered_frames.append(topic_id)

    def answer(self, packet: bytes, to: Any) -> None:
        self.outbox.append(packet)

    def repeat(self, sender: Any, to: Any, packets: list[bytes]) -> None:
        self.outbox.extend(packets)


def as_bytes(packet: Any) -> bytes:
    """A packet as ``cut`` gives it (bytes, or a tuple of parts), joined."""
    return b"".join(packet) if isinstance(packet, tuple) else bytes(packet)


def datagrams(cls: type[Packetizer], packets: list[Any], max_frame: int) -> list[bytes]:
    """What a link sends of the packets ``cut`` gave: each one, or, for a packetizer that
    ``cuts_every_frame``, each cut in datagrams of ``max_frame`` bytes."""
    out = [as_bytes(p) for p in packets]
    if not cls.cuts_every_frame:
        return out
    return [p[i:i + max_frame] for p in out for i in range(0, len(p), max_frame)]


class Path:
    """Two packetizers, ``a`` sending to ``b``, on a simulated path that loses ``loss`` of the
    packets each way (seeded) and delays each by :data:`DELAY`."""

    def __init__(self, cls: type[Packetizer], max_frame: int, loss: float, seed: int,
                 duplicate: bool = False, reorder: bool = False):
        self.cls, self.max_frame = cls, max_frame
        self.links = {"a": SimulatedLink("a", max_frame), "b": SimulatedLink("b", max_frame)}
        self.sides = {name: cls(link) for name, link in self.links.items()}
        self.loss, self.duplicate, self.reorder = loss, duplicate, reorder
        self.rng = random.Random(seed)
        self.now = time.monotonic()
        self.flying: list[tuple[float, int, str, bytes]] = []  # (arrives, order, to, packet)
        self.order = itertools.count()
        self.frames: list[bytes] = []

    def put(self, to: str, packets: list[bytes]) -> None:
        for packet in packets:
            for _ in range(2 if self.duplicate else 1):
                if self.rng.random() >= self.loss:
                    late = self.rng.random() * 4 * DELAY if self.reorder else 0.0
                    self.flying.append((self.now + DELAY + late, next(self.order), to, packet))

    def send(self, frames: list[bytes], options: Any) -> None:
        """``a`` cuts and sends every frame (its last packet then reported ``sent``)."""
        a = self.sides["a"]
        for frame in frames:
            packets = datagrams(self.cls, a.cut(frame, Topic(), ADDRESSES["b"], options),
                                self.max_frame)
            self.put("b", packets)
            a.sent(packets[-1], ADDRESSES["b"], self.now)

    def run(self, seconds: float) -> None:
        """Time passes in steps of :data:`DELAY`: packets arrive, timers run, what they send
        goes on the path."""
        end = self.now + seconds
        while self.now < end:
            self.now += DELAY
            due = sorted(f for f in self.flying if f[0] <= self.now)
            self.flying = [f for f in self.flying if f[0] > self.now]
            for _, _, to, packet in due:
                frame = self.sides[to].feed(memoryview(packet),
                                            ADDRESSES["a" if to == "b" else "b"], self.now)
                if frame is not None:
                    assert to == "b", "a frame came back to the sender"
                    self.frames.append(bytes(frame))
            for name, side in self.sides.items():
                side.timer(self.now)
                outbox = self.links[name].outbox
                self.put("b" if name == "a" else "a", outbox[:])
                outbox.clear()


class PacketizerConformance:
    """Subclass it as ``Test...`` and set :attr:`packetizer`."""

    packetizer: ClassVar[type[Packetizer]]
    options: ClassVar[Mapping[str, Any]] = {}
    #: False for a packetizer the link asks only for frames longer than ``max_frame``
    cuts_every_frame: ClassVar[bool] = True
    #: it brings frames through losses (else it counts each frame lost)
    recovers: ClassVar[bool] = False
    #: it needs its packets in the order they were sent (as a CAN bus keeps them)
    ordered: ClassVar[bool] = False
    #: the share of packets the loss test loses, each way
    loss: ClassVar[float] = 0.03
    #: seconds of simulated time the loss test gives the frames to arrive
    patience: ClassVar[float] = 5.0
    max_frame: ClassVar[int] = 1200
    fuzz_inputs: ClassVar[int] = 400

    def topic_options(self) -> Any:
        return parse(self.packetizer, self.options)

    def frame_sizes(self, max_frame: int) -> list[int]:
        """The sizes of the frames the tests send; override it for a packetizer that carries
        only some (one that refuses frames longer than a packet)."""
        sizes = [1, 100, max_frame - 30, max_frame, max_frame + 1, 3 * max_frame + 7, 100_000]
        return sizes if self.cuts_every_frame else [s for s in sizes if s > max_frame]

    def frame(self, rng: random.Random, size: int) -> bytes:
        """A frame of ``size`` bytes; override it for a packetizer that reads the frame (the
        topic from the envelope: see :func:`rosgate.wire.envelope.topic_of`)."""
        return rng.randbytes(size)

    def frames(self, max_frame: int) -> list[bytes]:
        rng = random.Random(max_frame)
        return [self.frame(rng, size) for size in self.frame_sizes(max_frame)]

    def test_found_through_its_entry_point(self) -> None:
        assert_registered("packetizer", self.packetizer)

    @pytest.mark.parametrize("max_frame", [1200, 300])
    def test_frames_cross_whole_and_once_in_packets_of_its_magic(self, max_frame: int) -> None:
        path = Path(self.packetizer, max_frame, loss=0.0, seed=1)
        frames = self.frames(max_frame)
        sender = self.packetizer(SimulatedLink("a", max_frame))
        for frame in frames:
            packets = sender.cut(frame, Topic(), ADDRESSES["b"], self.topic_options())
            for data in datagrams(self.packetizer, packets, max_frame):
                assert len(data) <= max_frame
                assert data[:2] in self.packetizer.magic or not self.packetizer.magic
        path.send(frames, self.topic_options())
        path.run(1.0)
        assert sorted(path.frames) == sorted(frames)
        assert path.links["b"].lost_frames == []

    def test_cost_is_what_cut_makes(self) -> None:
        link = SimulatedLink("a", self.max_frame)
        packetizer = self.packetizer(link)
        for frame in self.frames(self.max_frame):
            packets = datagrams(self.packetizer, packetizer.cut(
                frame, Topic(), ADDRESSES["b"], self.topic_options()), self.max_frame)
            assert self.packetizer.cost(len(frame), self.max_frame, self.topic_options()) == (
                sum(map(len, packets)), len(packets)), len(frame)

    def test_reordered_and_duplicated_packets_give_each_frame_once(self) -> None:
        path = Path(self.packetizer, self.max_frame, loss=0.0, seed=2, duplicate=True,
                    reorder=not self.ordered)
        frames = self.frames(self.max_frame)
        path.send(frames, self.topic_options())
        path.run(1.0)
        assert sorted(path.frames) == sorted(frames)

    def test_losses(self) -> None:
        path = Path(self.packetizer, self.max_frame, loss=self.loss, seed=3)
        rng = random.Random(4)
        sizes = self.frame_sizes(self.max_frame)
        frames = [self.frame(rng, rng.choice(sizes)) for _ in range(20)]
        path.send(frames, self.topic_options())
        path.run(self.patience)
        lost = path.links["b"].lost_frames
        if self.recovers:
            assert sorted(path.frames) == sorted(frames), lost
            assert path.links["b"].recovered_frames  # and it says which needed it
            assert lost == []
        else:
            assert not Counter(path.frames) - Counter(frames)  # none more often than sent
            assert len(path.frames) + len(lost) == len(frames)
            assert {topic for topic, _ in lost} <= {Topic().topic_id}

    def test_garbage_is_a_framing_error_and_nothing_else(self) -> None:
        rng = random.Random(20240601)
        link = SimulatedLink("b", self.max_frame)
        receiver = self.packetizer(link)
        sender = self.packetizer(SimulatedLink("a", self.max_frame))
        valid = [p for frame in self.frames(self.max_frame)[-2:]
                 for p in datagrams(self.packetizer, sender.cut(
                     frame, Topic(), ADDRESSES["b"], self.topic_options()), self.max_frame)]
        magic = self.packetizer.magic or (b"",)
        inputs = itertools.chain(
            (rng.choice(magic) + rng.randbytes(rng.randrange(40))
             for _ in range(self.fuzz_inputs // 2)),
            mutations(rng.choice(valid), rng, self.fuzz_inputs // 2))
        now = time.monotonic()
        for data in inputs:
            try:
                frame = receiver.feed(memoryview(data), ADDRESSES["a"], now)
                receiver.timer(now)
            except FramingError:
                continue
            except Exception as exc:  # the point of the test: report, do not propagate
                pytest.fail(f"feed({data[:40]!r}) raised {type(exc).__name__}: {exc}")
            assert frame is None or len(frame) <= link.max_message
