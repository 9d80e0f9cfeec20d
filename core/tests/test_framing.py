"""Framing: length prefixes cut back into the same frames however the stream is chunked, and
fragments reassembled exactly once within bounds on time, memory and header sanity."""

from __future__ import annotations

import random
import time

import pytest

from rosgate.builtin import (
    PARTIAL_COST,
    Fragments,
    Reassembler,
    fragment,
)
from rosgate.packetizer import RESERVED_MAGIC
from rosgate.streamlink.link import StreamReader, length_prefixed, stream_records
from rosgate.wire.framing import (
    CHUNK,
    CHUNK_HEAD,
    CHUNKED,
    DEFAULT_MAX_MESSAGE,
    FRAGMENT,
    FRAGMENT_MAGIC,
    LAST,
    LENGTH,
    MAX_OPEN_MESSAGES,
    FramingError,
)


def frames_of(rng: random.Random) -> list[bytes]:
    return [b"", b"a", bytes(range(256)), b"\x00\x00\x00\x00", rng.randbytes(5000), b"",
            b"\xff\xff\xff\xff", rng.randbytes(70_000), b"z"]


def read_all(reader: StreamReader, chunks) -> list[bytes]:
    out: list[bytes] = []
    for chunk in chunks:
        out += reader.feed(chunk)
    return out


class Lost:
    """An on_lost callback that records its calls."""

    def __init__(self) -> None:
        self.calls: list[tuple[int | None, str]] = []

    def __call__(self, topic_id: int | None, reason: str) -> None:
        self.calls.append((topic_id, reason))


# --- streams -------------------------------------------------------------------------------------

def test_length_prefix_is_a_big_endian_u32():
    assert length_prefixed(b"abc") == b"\x00\x00\x00\x03abc"
    assert length_prefixed(b"") == b"\x00\x00\x00\x00"
    assert length_prefixed(b"x" * 0x010203) == b"\x00\x01\x02\x03" + b"x" * 0x010203


def test_everything_at_once():
    frames = frames_of(random.Random(1))
    stream = b"".join(map(length_prefixed, frames))
    assert read_all(StreamReader(), [stream]) == frames


def test_one_byte_at_a_time():
    frames = frames_of(random.Random(2))
    stream = b"".join(map(length_prefixed, frames))
    reader = StreamReader()
    got = read_all(reader, (stream[i:i + 1] for i in range(len(stream))))
    assert got == frames
    # nothing was left over in the reader
    assert read_all(reader, [length_prefixed(b"next")]) == [b"next"]


def test_every_single_cut_point():
    frames = [b"", b"hello", bytes(range(40)), b"", b"RG\x01"]
    stream = b"".join(map(length_prefixed, frames))
    for cut in range(len(stream) + 1):
        assert read_all(StreamReader(), [stream[:cut], stream[cut:]]) == frames, cut


def test_every_pair_of_cut_points():
    frames = [b"ab", b"", b"cdef"]
    stream = b"".join(map(length_prefixed, frames))
    for i in range(len(stream) + 1):
        for j in range(i, len(stream) + 1):
            assert read_all(StreamReader(), [stream[:i], stream[i:j], stream[j:]]) == frames, (i, j)


def test_random_chunkings():
    rng = random.Random(3)
    frames = frames_of(rng) + [rng.randbytes(rng.randint(0, 3000)) for _ in range(50)]
    stream = b"".join(map(length_prefixed, frames))
    for _ in range(40):
        cuts = sorted(rng.sample(range(1, len(stream)), rng.randint(1, 200)))
        bounds = [0, *cuts, len(stream)]
        chunks = [stream[a:b] for a, b in zip(bounds, bounds[1:], strict=False)]
        assert read_all(StreamReader(), chunks) == frames


def test_frames_are_yielded_as_soon_as_complete():
    reader = StreamReader()
    record = length_prefixed(b"12345")
    assert read_all(reader, [record[:-1]]) == []
    assert read_all(reader, [record[-1:] + length_prefixed(b"6")[:3]]) == [b"12345"]
    assert read_all(reader, [b"\x01", b"6"]) == [b"6"]


def test_empty_frames():
    assert read_all(StreamReader(), [b"\x00\x00\x00\x00" * 3]) == [b"", b"", b""]
    assert read_all(StreamReader(), [b"\x00", b"\x00\x00", b"\x00"]) == [b""]


def test_length_at_the_limit_is_accepted():
    assert read_all(StreamReader(max_frame=100), [length_prefixed(b"x" * 100)]) == [b"x" * 100]


def test_length_over_the_limit_is_refused_before_the_body_arrives():
    reader = StreamReader(max_frame=100)
    with pytest.raises(FramingError, match="101 over the limit 100"):
        read_all(reader, [LENGTH.pack(101)])


def test_huge_length_refused_with_the_default_limit():
    with pytest.raises(FramingError):
        read_all(StreamReader(), [b"\xff\xff\xff\xff"])
    with pytest.raises(FramingError):
        read_all(StreamReader(), [LENGTH.pack(DEFAULT_MAX_MESSAGE + 1)])


def test_frames_before_a_bad_length_are_still_delivered():
    feed = StreamReader(max_frame=10).feed(length_prefixed(b"ok") + LENGTH.pack(11) + b"x" * 11)
    assert next(feed) == b"ok"
    with pytest.raises(FramingError):
        next(feed)


def read_in_place(reader: StreamReader, stream: bytes, chunk: int) -> list[bytes]:
    """Read ``stream`` as a link with receive_into does: into the reader's target while it has
    one, else ``chunk`` bytes at a time through feed."""
    out: list[bytes] = []
    position = 0
    while position < len(stream):
        target = reader.target()
        if target is not None:
            n = min(len(target), chunk, len(stream) - position)
            target[:n] = stream[position:position + n]
            position += n
            frame = reader.filled(n)
            if frame is not None:
                out.append(frame)
        else:
            out += reader.feed(stream[position:position + chunk])
            position += chunk
    return out


def test_large_frames_are_read_into_place():
    rng = random.Random(50)
    frames = [b"small", rng.randbytes(200_000), b"", rng.randbytes(1_000_000), b"after"]
    stream = b"".join(map(length_prefixed, frames))
    reader = StreamReader(direct=True)
    got = read_in_place(reader, stream, 65_536)
    assert got == frames
    assert [type(f) for f in got] == [bytes, bytearray, bytes, bytearray, bytes]
    assert reader.target() is None


def test_a_length_alone_earns_no_buffer():
    reader = StreamReader(direct=True)
    assert list(reader.feed(LENGTH.pack(60_000_000) + b"x" * 100)) == []
    assert reader.target() is None  # 100 bytes of 60 MB: kept, not a 60 MB buffer
    assert list(StreamReader().feed(LENGTH.pack(200_000) + bytes(100_000))) == []


# --- fragment ------------------------------------------------------------------------------------

def test_a_frame_that_fits_is_returned_as_is():
    frame = b"x" * 100
    pieces = fragment(frame, 100, topic_id=1, frame_id=1)
    assert pieces == [frame] and pieces[0] is frame
    assert fragment(b"", 100, 1, 1) == [b""]


def test_fragment_layout_byte_exact():
    frame = bytes(range(25))
    # 24-byte datagrams: 14 bytes of header, 10 of chunk -> 3 fragments (10, 10, 5)
    pieces = fragment(frame, 24, topic_id=7, frame_id=0x01020304)
    assert pieces == [
        b"RF\x00\x00\x00\x03\x00\x00\x00\x07\x01\x02\x03\x04" + bytes(range(0, 10)),
        b"RF\x00\x01\x00\x03\x00\x00\x00\x07\x01\x02\x03\x04" + bytes(range(10, 20)),
        b"RF\x00\x02\x00\x03\x00\x00\x00\x07\x01\x02\x03\x04" + bytes(range(20, 25)),
    ]
    assert all(p[:2] == FRAGMENT_MAGIC for p in pieces)
    # the link hands them to the fragments packetizer by that magic, never as whole frames
    assert Fragments.magic == (FRAGMENT_MAGIC,) and FRAGMENT_MAGIC not in RESERVED_MAGIC


def test_one_byte_over_makes_two_fragments():
    pieces = fragment(b"y" * 101, 100, 1, 1)
    # 86 bytes of frame in the first, the other 15 in the second
    assert [len(p) for p in pieces] == [100, FRAGMENT.size + 15]


def test_one_megabyte_splits_and_reassembles_once_from_shuffled_duplicates():
    rng = random.Random(4)
    frame = rng.randbytes(1_000_000)
    pieces = fragment(frame, 65_000, topic_id=9, frame_id=77)
    assert len(pieces) == -(-len(frame) // (65_000 - FRAGMENT.size)) == 16
    assert all(len(p) <= 65_000 for p in pieces)
    assert b"".join(p[FRAGMENT.size:] for p in pieces) == frame

    datagrams = pieces + rng.sample(pieces, 8)
    rng.shuffle(datagrams)
    lost = Lost()
    reassembler = Reassembler(lost)
    results = [reassembler.add(("10.0.0.1", 5000), d) for d in datagrams]
    done = [r for r in results if r is not None]
    assert len(done) == 1 and done[0] == frame
    assert lost.calls == []


def test_the_completing_fragment_returns_the_frame():
    rng = random.Random(5)
    frame = rng.randbytes(1000)
    pieces = fragment(frame, 114, topic_id=1, frame_id=1)  # chunks of 100: 10 fragments
    reassembler = Reassembler(Lost())
    order = list(reversed(pieces))
    assert [reassembler.add("s", p) for p in order[:-1]] == [None] * 9
    assert reassembler.add("s", order[-1]) == frame


def test_a_lost_fragment_is_counted_once_after_the_timeout():
    rng = random.Random(6)
    frame = rng.randbytes(500)
    pieces = fragment(frame, 114, topic_id=42, frame_id=3)
    lost = Lost()
    reassembler = Reassembler(lost, timeout=1.0)
    t0 = time.monotonic()
    for piece in pieces[:2] + pieces[3:]:  # piece 2 never comes
        assert reassembler.add("s", piece) is None
    reassembler.expire(now=t0 + 0.5)  # still within the timeout
    assert lost.calls == []
    reassembler.expire(now=time.monotonic() + 1.5)
    assert lost.calls == [(42, "fragment_lost")]
    reassembler.expire(now=time.monotonic() + 100)
    assert lost.calls == [(42, "fragment_lost")]


def test_expire_gives_up_a_frame_older_than_the_timeout():
    lost = Lost()
    reassembler = Reassembler(lost, timeout=0.001)
    old = fragment(b"o" * 300, 114, topic_id=1, frame_id=1)
    reassembler.add("s", old[0])
    reassembler.expire(now=time.monotonic() + 1)
    assert lost.calls == [(1, "fragment_lost")]
    # the frame's remaining fragments start it afresh: it can never complete from them alone
    assert [reassembler.add("s", p) for p in old[1:]] == [None, None]


def test_interleaved_frames_from_two_sources_and_topics_reassemble_independently():
    rng = random.Random(7)
    # same frame_id everywhere: only (source, topic, frame_id) tells them apart
    streams = {
        ("a", 1): rng.randbytes(2000),
        ("b", 1): rng.randbytes(2000),
        ("a", 2): rng.randbytes(1500),
        ("b", 2): rng.randbytes(2100),
    }
    datagrams = [(source, piece) for (source, topic), frame in streams.items()
                 for piece in fragment(frame, 214, topic_id=topic, frame_id=5)]
    rng.shuffle(datagrams)
    reassembler = Reassembler(Lost())
    done: list[tuple[str, bytes]] = []
    for source, piece in datagrams:
        frame = reassembler.add(source, piece)
        if frame is not None:
            done.append((source, frame))
    assert sorted(done) == sorted((source, frame) for (source, _), frame in streams.items())


def cost(count: int, frame: int) -> int:
    """What a partial frame of ``count`` fragments and ``frame`` bytes is accounted for once it
    has its buffer (fragments of 100 bytes earn it at once)."""
    return PARTIAL_COST + count + frame


def test_memory_bound_sheds_the_oldest_partial_frame():
    lost = Lost()
    # room for two partial 300-byte frames, not three
    reassembler = Reassembler(lost, max_pending_bytes=2 * cost(3, 300) + 100)
    frames = {topic: bytes([topic]) * 300 for topic in (1, 2, 3)}
    pieces = {topic: fragment(frame, 114, topic_id=topic, frame_id=topic)
              for topic, frame in frames.items()}
    for topic in (1, 2):
        for piece in pieces[topic][:2]:
            assert reassembler.add("s", piece) is None
    assert lost.calls == [] and reassembler.pending_bytes == 2 * cost(3, 300)
    assert reassembler.add("s", pieces[3][0]) is None     # a third: frame 1 goes
    assert lost.calls == [(1, "reassembly_overflow")]
    assert reassembler.add("s", pieces[2][2]) == frames[2]
    assert [reassembler.add("s", p) for p in pieces[3][1:]] == [None, frames[3]]
    assert lost.calls == [(1, "reassembly_overflow")]
    assert reassembler.pending == reassembler.pending_bytes == 0


def test_shedding_keeps_going_until_under_the_bound():
    lost = Lost()
    reassembler = Reassembler(lost, max_pending_bytes=cost(2, 400) + 10)
    for topic in (1, 2):
        reassembler.add("s", fragment(b"x" * 300, 114, topic_id=topic, frame_id=1)[0])
    # the two older frames go, the one that pushed past the bound stays
    big = fragment(b"y" * 400, 214, topic_id=3, frame_id=1)
    reassembler.add("s", big[0])
    assert lost.calls == [(1, "reassembly_overflow"), (2, "reassembly_overflow")]
    assert reassembler.add("s", big[1]) == b"y" * 400


@pytest.mark.parametrize("datagram, message", [
    (b"RF", "too short"),
    (FRAGMENT.pack(b"RF", 0, 2, 1, 1), "too short"),                        # a header, no chunk
    (FRAGMENT.pack(b"RF", 3, 3, 1, 1) + b"x", "out of range"),              # index == count
    (FRAGMENT.pack(b"RF", 9, 3, 1, 1) + b"x", "out of range"),              # index > count
    (FRAGMENT.pack(b"RF", 0, 1, 1, 1) + b"x", "out of range"),              # count 1
    (FRAGMENT.pack(b"RF", 0, 0, 1, 1) + b"x", "out of range"),              # count 0
    (FRAGMENT.pack(b"RF", 0, 100, 1, 1) + b"x" * 100, "out of range"),      # 10 kB claimed > 1000
    (FRAGMENT.pack(b"RF", 0, 0xFFFF, 1, 1) + b"x" * 50, "out of range"),
], ids=["magic-only", "no-chunk", "index=count", "index>count", "count1", "count0",
        "claim-10k", "claim-65535"])
def test_malformed_fragment_headers(datagram, message):
    lost = Lost()
    reassembler = Reassembler(lost, max_message=1000)
    with pytest.raises(FramingError, match=message):
        reassembler.add("s", datagram)
    assert lost.calls == []


def test_a_claim_within_max_message_is_accepted():
    reassembler = Reassembler(Lost(), max_message=1000)
    assert reassembler.add("s", FRAGMENT.pack(b"RF", 0, 10, 1, 1) + b"x" * 100) is None


def test_count_changed_mid_frame():
    reassembler = Reassembler(Lost())
    assert reassembler.add("s", FRAGMENT.pack(b"RF", 0, 3, 1, 1) + b"a") is None
    with pytest.raises(FramingError, match="count changed"):
        reassembler.add("s", FRAGMENT.pack(b"RF", 1, 4, 1, 1) + b"b")
    # the frame itself can still complete with the original count
    assert reassembler.add("s", FRAGMENT.pack(b"RF", 1, 3, 1, 1) + b"b") is None
    assert reassembler.add("s", FRAGMENT.pack(b"RF", 2, 3, 1, 1) + b"c") == b"abc"


def test_a_frame_needing_more_than_65535_fragments_is_refused():
    # 15-byte datagrams carry 1 byte each
    assert len(fragment(bytes(65_535), 15, 1, 1)) == 65_535
    with pytest.raises(FramingError, match="65535"):
        fragment(bytes(65_536), 15, 1, 1)


def test_a_datagram_too_small_for_the_fragment_header():
    with pytest.raises(FramingError, match="cannot carry"):
        fragment(b"x" * 100, FRAGMENT.size, 1, 1)


def test_a_late_duplicate_is_not_counted_as_a_lost_frame():
    lost = Lost()
    reassembler = Reassembler(lost, timeout=1.0)
    pieces = fragment(b"q" * 300, 114, topic_id=8, frame_id=1)
    assert [reassembler.add("s", p) for p in pieces] == [None, None, b"q" * 300]
    assert reassembler.add("s", pieces[0]) is None   # the network duplicated a datagram
    reassembler.expire(now=time.monotonic() + 10)
    assert lost.calls == []


# --- bounds that hold under attack (issue 10) ---------------------------------------------------

class Clock:
    """time.monotonic for the framing module, moved by hand."""

    def __init__(self, monkeypatch, now: float = 1000.0):
        self.now = now
        monkeypatch.setattr("rosgate.builtin.time.monotonic", lambda: self.now)


def lone(index: int, count: int, topic: int, frame_id: int, chunk: bytes = b"x") -> bytes:
    return FRAGMENT.pack(b"RF", index, count, topic, frame_id) + chunk


def test_the_accounting_covers_what_a_partial_frame_really_costs():
    import tracemalloc

    # no partial may expire while 2,000 are added under tracemalloc on a busy machine
    reassembler = Reassembler(Lost(), timeout=3600.0, max_partials=10_000, source_partials=10_000)
    datagrams = [lone(0, 2, 5, i) for i in range(2000)]
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        for i, datagram in enumerate(datagrams):
            # a source address as recvfrom makes it: a new tuple and string each time
            reassembler.add((f"10.0.{i // 250}.{i % 250}", 40_000 + i), memoryview(datagram))
        used = tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()
    assert reassembler.pending == 2000
    assert used <= reassembler.pending_bytes, f"{used / 2000:.0f} B each, accounted " \
        f"{reassembler.pending_bytes / 2000:.0f}"


def test_partial_frames_expire_in_the_order_they_started(monkeypatch):
    clock = Clock(monkeypatch)
    lost = Lost()
    reassembler = Reassembler(lost, timeout=2.0)
    for i in range(10):
        reassembler.add("s", lone(0, 3, i, i))
        clock.now += 0.5
    reassembler.expire(now=clock.now)  # 5 s after the first: those older than 2 s go
    assert lost.calls == [(i, "fragment_lost") for i in range(6)]
    assert reassembler.pending == 4
    clock.now += 10
    reassembler.add("s", lone(0, 3, 99, 99))  # a new fragment expires the old ones first
    assert lost.calls[6:] == [(i, "fragment_lost") for i in range(6, 10)]
    assert reassembler.pending == 1


def test_one_source_cannot_crowd_out_another():
    lost = Lost()
    reassembler = Reassembler(lost, source_partials=4)
    frame = b"q" * 300
    legit = fragment(frame, 114, topic_id=1, frame_id=77)
    assert reassembler.add("legit", legit[0]) is None
    for i in range(100):
        reassembler.add("flood", lone(0, 2, 2, i))
    assert lost.calls == [(2, "reassembly_overflow")] * 96
    assert [reassembler.add("legit", p) for p in legit[1:]] == [None, frame]


def test_a_source_is_bounded_in_bytes_too():
    lost = Lost()
    per_frame = PARTIAL_COST + 2 + 2 * 1000
    reassembler = Reassembler(lost, source_bytes=3 * per_frame)
    for i in range(5):
        reassembler.add("s", lone(0, 2, i, i, bytes(1000)))
    assert lost.calls == [(0, "reassembly_overflow"), (1, "reassembly_overflow")]
    assert reassembler.pending_bytes == 3 * per_frame


def test_a_fragment_earns_no_buffer_for_a_frame_it_cannot_fill():
    # one fragment claiming 65,535 x 1,000 bytes: kept aside, not a 65 MB zeroed buffer
    reassembler = Reassembler(Lost(), max_message=100_000_000)
    reassembler.add("s", lone(0, 0xFFFF, 1, 1, bytes(1000)))
    assert reassembler.pending_bytes < PARTIAL_COST + 0xFFFF + 2000
    # a frame of 16 fragments earns its buffer with the first
    reassembler.add("s", lone(0, 16, 2, 2, bytes(1000)))
    assert reassembler.pending_bytes > 16_000


def test_the_frame_is_the_buffer_at_its_exact_length_whatever_the_order():
    rng = random.Random(40)
    for count_and_order in range(20):
        frame = rng.randbytes(rng.randint(201, 5000))
        pieces = fragment(frame, 114, topic_id=1, frame_id=count_and_order)
        rng.shuffle(pieces)
        reassembler = Reassembler(Lost())
        done = [f for f in (reassembler.add("s", p) for p in pieces) if f is not None]
        assert done == [frame] and type(done[0]) is bytearray
        assert reassembler.pending == reassembler.pending_bytes == 0


@pytest.mark.parametrize("second, message", [
    (lone(1, 3, 1, 1, b"yy"), "size changed"),            # a middle fragment of another size
    (lone(2, 3, 1, 1, b"zzzz"), "out of range"),          # a last fragment longer than the others
], ids=["middle", "last"])
def test_fragments_of_one_frame_agree_on_their_size(second, message):
    reassembler = Reassembler(Lost())
    reassembler.add("s", lone(0, 3, 1, 1, b"abc"))
    with pytest.raises(FramingError, match=message):
        reassembler.add("s", second)
    assert reassembler.add("s", lone(1, 3, 1, 1, b"def")) is None
    assert reassembler.add("s", lone(2, 3, 1, 1, b"g")) == b"abcdefg"


# -- chunks on streams ---------------------------------------------------------------------------
def test_a_frame_up_to_a_chunk_is_one_plain_record():
    assert stream_records(b"x" * CHUNK, 7) == [length_prefixed(b"x" * CHUNK)]


def test_long_frames_travel_in_chunks_and_come_back_whole_between_others():
    big = random.Random(1).randbytes(3 * CHUNK + 5)
    other = random.Random(2).randbytes(CHUNK * 2)
    records = stream_records(big, 1)
    assert len(records) == 4 and all(len(r) <= 8 + CHUNK for r in records)
    heads = [CHUNK_HEAD.unpack_from(r) for r in records]
    assert [h[0] & (CHUNKED | LAST) for h in heads] == [CHUNKED] * 3 + [CHUNKED | LAST]
    # another topic's chunks and a small frame between them, as the scheduler interleaves
    others = stream_records(other, 2)
    stream = [records[0], others[0], length_prefixed(b"twist"), records[1], others[1],
              records[2], records[3]]
    data = b"".join(stream)
    assert read_all(StreamReader(), [data]) == [b"twist", other, big]
    for cut in (1, 5, 9, CHUNK + 3, len(data) - 1):  # however the connection cuts it
        assert read_all(StreamReader(), [data[:cut], data[cut:]]) == [b"twist", other, big]


@pytest.mark.parametrize("record, why", [
    (LENGTH.pack(CHUNKED | 2) + b"ab", "a chunk without its head"),
    (CHUNK_HEAD.pack(CHUNKED | 1004, 1) + bytes(1000), "over the limit"),   # one chunk too long
])
def test_impossible_chunks_end_the_stream(record, why):
    with pytest.raises(FramingError, match=why):
        read_all(StreamReader(max_frame=100), [record])


def test_chunked_frames_are_bounded_in_size_and_number():
    # one message growing past the limit
    chunks = [CHUNK_HEAD.pack(CHUNKED | 64, 1) + bytes(60)] * 3
    with pytest.raises(FramingError, match="chunked frames over the limit 100"):
        read_all(StreamReader(max_frame=100), [b"".join(chunks)])
    # too many open at once
    opens = b"".join(CHUNK_HEAD.pack(CHUNKED | 5, n) + b"x" for n in range(MAX_OPEN_MESSAGES + 1))
    with pytest.raises(FramingError, match="chunked frames open at once"):
        read_all(StreamReader(), [opens])
