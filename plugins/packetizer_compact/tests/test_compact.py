"""The compact packetizer: its pieces byte for byte, reassembly within bounds on order, time,
memory and sources, its cost for ``rosgate check``, and the plugin kit's packetizer suite."""

from __future__ import annotations

import random
import time

import pytest
from rosgate_compact import Compact, CompactReassembler, compact_fragment
from rosgate_testing import PacketizerConformance

from rosgate import PARTIAL_COST, FramingError
from rosgate.wire import envelope


class Lost:
    """An on_lost callback that records its calls."""

    def __init__(self) -> None:
        self.calls: list[tuple[int | None, str]] = []

    def __call__(self, topic_id: int | None, reason: str) -> None:
        self.calls.append((topic_id, reason))


class Clock:
    """time.monotonic for the reassembler, moved by hand."""

    def __init__(self, monkeypatch, now: float = 1000.0):
        self.now = now
        monkeypatch.setattr("rosgate_compact.time.monotonic", lambda: self.now)


def frame_on(topic_id: int, size: int, rng: random.Random) -> bytes:
    """A frame as routes make them: an envelope header naming the topic, then the body."""
    header = envelope.pack(0, topic_id, 1, 1, 0)
    return header + rng.randbytes(max(0, size - len(header)))


def assemble(reassembler: CompactReassembler, pieces, source="s") -> list[bytes]:
    return [f for f in (reassembler.add(source, p) for p in pieces) if f is not None]


def test_compact_layout_byte_exact():
    # 8-byte pieces: head, length 20 (one LEB128 byte), 6 bytes; then head + 7 bytes; the
    # counter starts where the caller's stood and wraps at 128
    pieces = compact_fragment(bytes(range(20)), 8, counter=126)
    assert pieces == [b"\xfe\x14" + bytes(range(0, 6)),
                      b"\x7f" + bytes(range(6, 13)),
                      b"\x00" + bytes(range(13, 20))]
    assert compact_fragment(b"", 8, 5) == [b"\x85\x00"]
    assert compact_fragment(b"abc", 64, 0) == [b"\x80\x03abc"]  # every frame is pieces, even small


def test_compact_length_is_leb128():
    assert compact_fragment(bytes(300), 64, 0)[0][:3] == b"\x80\xac\x02"
    assert compact_fragment(bytes(100_000), 64, 0)[0][:4] == b"\x80\xa0\x8d\x06"


def test_compact_overhead_of_a_100_kB_frame():
    # what the module docstring promises for classic CAN and CAN FD
    assert len(compact_fragment(bytes(100_000), 8, 0)) == 14_287
    assert len(compact_fragment(bytes(100_000), 64, 0)) == 1_588
    assert all(len(p) <= 8 for p in compact_fragment(bytes(100_000), 8, 0))


def test_compact_frames_of_every_size_round_trip_in_order():
    rng = random.Random(8)
    for max_frame in (3, 8, 64, 255):
        frames = [b"", b"x", *(rng.randbytes(rng.randint(0, 3000)) for _ in range(40))]
        counter, pieces = 0, []
        for frame in frames:
            mine = compact_fragment(frame, max_frame, counter)
            counter = (counter + len(mine)) & 0x7F
            assert all(len(p) <= max_frame for p in mine)
            pieces += mine
        lost = Lost()
        assert assemble(CompactReassembler(lost, envelope.topic_of), pieces) == frames, max_frame
        assert lost.calls == []


def test_compact_header_too_large_for_the_frame():
    assert compact_fragment(bytes(100), 2, 0)[0] == b"\x80\x64"  # a first piece with no chunk
    with pytest.raises(FramingError, match="cannot carry"):
        compact_fragment(bytes(200), 2, 0)  # 1 + 2 bytes of header
    with pytest.raises(FramingError, match="cannot carry"):
        compact_fragment(b"", 1, 0)


def test_compact_padding_after_the_length_is_ignored():
    # a CAN FD driver pads 50 data bytes to 64: the length says where the frame ends
    frame = bytes(range(100))
    pieces = compact_fragment(frame, 64, 0)
    padded = [p.ljust(64, b"\x00") for p in pieces]
    assert assemble(CompactReassembler(Lost()), padded) == [frame]


def test_compact_lost_piece_drops_that_frame_only_and_counts_it_against_its_topic():
    rng = random.Random(9)
    frames = [frame_on(7, 500, rng) for _ in range(3)]
    counter, pieces = 0, []
    for frame in frames:
        mine = compact_fragment(frame, 8, counter)
        counter += len(mine)
        pieces.append(mine)
    del pieces[1][40]  # in the middle of the second frame
    lost = Lost()
    assert assemble(CompactReassembler(lost, envelope.topic_of),
                    [p for mine in pieces for p in mine]) == [frames[0], frames[2]]
    assert lost.calls == [(7, "fragment_lost")]


def test_compact_lost_first_piece_counts_against_the_sources_last_topic():
    rng = random.Random(10)
    first, second, third = frame_on(3, 100, rng), frame_on(3, 100, rng), frame_on(3, 100, rng)
    a = compact_fragment(first, 8, 0)
    b = compact_fragment(second, 8, len(a))
    c = compact_fragment(third, 8, len(a) + len(b))
    lost = Lost()
    # the second frame's first piece is lost: its other pieces are ignored, counted once
    assert assemble(CompactReassembler(lost, envelope.topic_of), a + b[1:] + c) == [first, third]
    assert lost.calls == [(3, "fragment_lost")]


def test_compact_a_frame_vanished_whole_is_counted():
    rng = random.Random(11)
    frames = [frame_on(4, 50, rng) for _ in range(3)]
    pieces = compact_fragment(frames[0], 64, 0) + compact_fragment(frames[2], 64, 2)
    lost = Lost()
    assert assemble(CompactReassembler(lost, envelope.topic_of), pieces) == [frames[0], frames[2]]
    assert lost.calls == [(4, "fragment_lost")]


def test_compact_loss_before_any_topic_is_known_counts_against_none():
    rng = random.Random(12)
    pieces = compact_fragment(frame_on(4, 50, rng), 8, 0)
    lost = Lost()
    assert assemble(CompactReassembler(lost, envelope.topic_of), pieces[:1] + pieces[2:]) == []
    assert lost.calls == [(None, "fragment_lost")]


def test_compact_a_duplicated_piece_is_ignored():
    frame = frame_on(2, 200, random.Random(13))
    pieces = compact_fragment(frame, 8, 0)
    doubled = [p for piece in pieces for p in (piece, piece)]
    lost = Lost()
    assert assemble(CompactReassembler(lost, envelope.topic_of), doubled) == [frame]
    assert lost.calls == []


def test_compact_a_new_first_piece_abandons_the_frame_in_progress():
    rng = random.Random(14)
    half = compact_fragment(frame_on(6, 100, rng), 8, 0)[:5]
    whole = frame_on(6, 100, rng)
    lost = Lost()
    # the counter runs on (no gap), yet a first piece arrives: the sender gave up the frame
    assert assemble(CompactReassembler(lost, envelope.topic_of),
                    half + compact_fragment(whole, 8, 5)) == [whole]
    assert lost.calls == [(6, "fragment_lost")]


def test_compact_stalled_frame_expires_once_and_late_pieces_are_ignored():
    pieces = compact_fragment(frame_on(5, 100, random.Random(15)), 8, 0)
    lost = Lost()
    reassembler = CompactReassembler(lost, envelope.topic_of, timeout=1.0)
    assert assemble(reassembler, pieces[:4]) == []
    reassembler.expire(now=time.monotonic() + 0.5)
    assert lost.calls == []
    reassembler.expire(now=time.monotonic() + 1.5)
    assert lost.calls == [(5, "fragment_lost")]
    assert assemble(reassembler, pieces[4:]) == []
    reassembler.expire(now=time.monotonic() + 10)
    assert lost.calls == [(5, "fragment_lost")]


def test_compact_sources_reassemble_independently():
    rng = random.Random(16)
    frames = {source: frame_on(1, 400, rng) for source in ("a", "b", "c")}
    tagged = {source: compact_fragment(frame, 8, 0) for source, frame in frames.items()}
    reassembler = CompactReassembler(Lost())
    done = {}
    for i in range(max(map(len, tagged.values()))):  # round robin, as ids share a bus
        for source, pieces in tagged.items():
            if i < len(pieces):
                frame = reassembler.add(source, pieces[i])
                if frame is not None:
                    done[source] = frame
    assert done == frames


def test_compact_memory_bound_sheds_a_frame_in_progress():
    rng = random.Random(17)
    lost = Lost()
    # each frame in progress: its bytes and its bookkeeping
    reassembler = CompactReassembler(lost, envelope.topic_of,
                                     max_pending_bytes=2 * PARTIAL_COST + 600)
    frames = {topic: frame_on(topic, 500, rng) for topic in (1, 2)}
    pieces = {topic: compact_fragment(frame, 64, 0) for topic, frame in frames.items()}
    assemble(reassembler, pieces[1][:4], source=1)   # 60 + 3 * 63 = 249 bytes pending
    assert lost.calls == []
    assemble(reassembler, pieces[2][:6], source=2)   # 249 + 375 = 624: the older frame goes
    assert lost.calls == [(1, "reassembly_overflow")]
    assert assemble(reassembler, pieces[2][6:], source=2) == [frames[2]]


@pytest.mark.parametrize("piece, message", [
    (b"", "empty"),
    (b"\x80", "without a complete length"),
    (b"\x80\xff\xff", "without a complete length"),
    (b"\x80\xff\xff\xff\xff\xff\x01", "without a complete length"),
    (b"\x80\xe9\x07", "over the limit 1000"),  # 1001
], ids=["empty", "no-length", "cut-length", "six-byte-length", "over-max-message"])
def test_compact_malformed_first_pieces(piece, message):
    lost = Lost()
    with pytest.raises(FramingError, match=message):
        CompactReassembler(lost, max_message=1000).add("s", piece)
    assert lost.calls == []


def test_compact_frames_expire_in_the_order_their_sources_went_quiet(monkeypatch):
    clock = Clock(monkeypatch)
    lost = Lost()
    reassembler = CompactReassembler(lost, envelope.topic_of, timeout=2.0)
    rng = random.Random(18)
    pieces = {source: compact_fragment(frame_on(topic, 200, rng), 8, 0)
              for topic, source in ((1, "a"), (2, "b"), (3, "c"))}
    start = clock.now
    for source, at in (("a", 0.0), ("b", 0.5), ("c", 1.0)):
        clock.now = start + at
        assemble(reassembler, pieces[source][:2], source=source)
    clock.now = start + 1.5
    assemble(reassembler, pieces["a"][2:3], source="a")  # a keeps sending
    reassembler.expire(now=start + 2.8)
    assert lost.calls == [(2, "fragment_lost")]
    reassembler.expire(now=start + 3.2)
    assert lost.calls == [(2, "fragment_lost"), (3, "fragment_lost")]
    clock.now = start + 3.3
    assert assemble(reassembler, pieces["a"][3:], source="a") != []


@pytest.mark.parametrize("size", [1, 6, 7, 8, 100, 1000, 70_000])
@pytest.mark.parametrize("max_frame", [8, 64])
def test_the_compact_packetizer_s_cost_is_what_it_cuts(size, max_frame):
    pieces = compact_fragment(bytes(size), max_frame, 0)
    assert Compact.cost(size, max_frame, None) == (sum(map(len, pieces)), len(pieces))
    assert all(len(piece) <= max_frame for piece in pieces)


def test_compact_claims_no_magic_and_cuts_every_frame():
    assert Compact.magic == () and Compact.cuts_every_frame


class TestCompactConformance(PacketizerConformance):
    packetizer = Compact
    ordered = True  # pieces carry no index: a CAN bus keeps them in order
    max_frame = 64  # CAN FD

    def frame(self, rng: random.Random, size: int) -> bytes:
        # its losses are counted against the topic of the envelope the frame starts with
        header = envelope.pack(0, 7, 1, 1, 0)[:size]
        return header + rng.randbytes(size - len(header))


def test_compact_several_gaps_in_one_frame_count_it_once():
    rng = random.Random(19)
    first, second = frame_on(7, 500, rng), frame_on(8, 500, rng)
    a = compact_fragment(first, 8, 0)
    b = compact_fragment(second, 8, len(a))
    torn = a[:20] + a[21:40] + a[41:60] + a[61:]  # three pieces of the first frame lost
    lost = Lost()
    assert assemble(CompactReassembler(lost, envelope.topic_of), torn + b) == [second]
    assert lost.calls == [(7, "fragment_lost")]
