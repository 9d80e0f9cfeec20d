"""The twice packetizer: the plugin kit's packetizer suite (frames of one packet), and what it
refuses."""

from __future__ import annotations

import pytest
from rosgate_packetizer_twice import HEADER, Twice
from rosgate_testing import PacketizerConformance
from rosgate_testing.packetizers import SimulatedLink, Topic

from rosgate.wire.framing import FramingError


class TestTwiceConformance(PacketizerConformance):
    packetizer = Twice
    recovers = True

    def frame_sizes(self, max_frame: int) -> list[int]:
        return [0, 1, 100, max_frame - HEADER.size]


def test_a_frame_goes_twice_and_arrives_once():
    sender, receiver = Twice(SimulatedLink("a", 1200)), Twice(SimulatedLink("b", 1200))
    first, second = sender.cut(b"cmd", Topic(), ("b", 1), None)
    assert (first[:2], first[-3:], second[-3:]) == (b"T2", b"cmd", b"cmd")
    assert first[:10] == second[:10] and (first[10], second[10]) == (0, 1)
    assert receiver.feed(first, ("a", 1), 0.0) == b"cmd"
    assert receiver.feed(second, ("a", 1), 0.0) is None
    assert receiver.link.recovered_frames == []


def test_a_second_copy_alone_says_it_recovered_the_frame():
    link = SimulatedLink("b", 1200)
    _, second = Twice(SimulatedLink("a", 1200)).cut(b"cmd", Topic(9), ("b", 1), None)
    assert Twice(link).feed(second, ("a", 1), 0.0) == b"cmd"
    assert link.recovered_frames == [9]


@pytest.mark.parametrize("action, message", [
    (lambda t: t.cut(bytes(1200 - HEADER.size + 1), Topic(), ("b", 1), None),
     "twice carries frames of one packet, not of 1190 bytes"),
    (lambda t: t.feed(b"T2\x00", ("a", 1), 0.0), "a packet shorter than its header"),
    (lambda t: t.feed(HEADER.pack(b"T2", 1, 2, 2), ("a", 1), 0.0), "copy 2 of two"),
])
def test_what_it_refuses(action, message):
    with pytest.raises(FramingError, match=message):
        action(Twice(SimulatedLink("a", 1200)))
