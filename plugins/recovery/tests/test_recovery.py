"""Loss recovery, the wire parts: FEC fragments rebuilt from any k of each block, and selective
repeat (NACKs, ACKs, probes) between a sender's store and a receiver, over a simulated lossy
channel with a seeded RNG and a simulated clock (nothing here waits)."""

from __future__ import annotations

import heapq
import random

import pytest
from rosgate_recovery import wire as recovery
from rosgate_recovery.wire import (
    FEC,
    FecReassembler,
    RepeatReassembler,
    RetransmitStore,
    block_limit,
    fec_fragments,
    repeat_fragments,
)

from rosgate import FramingError

TOPIC = 7


class Log:
    def __init__(self) -> None:
        self.lost: list[tuple[int | None, str]] = []
        self.recovered: list[int] = []

    def on_lost(self, topic_id, reason):
        self.lost.append((topic_id, reason))

    def on_recovered(self, topic_id):
        self.recovered.append(topic_id)


def frame_of(size: int, seed: int) -> bytes:
    return random.Random(seed).randbytes(size)


# -- FEC ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("overhead, limit", [(0.1, 232), (0.05, 243), (1.0, 128), (0.5, 170)])
def test_blocks_fit_gf256(overhead, limit):
    assert block_limit(overhead) == limit
    assert limit + -(-int(limit * overhead * 1000) // 1000) <= 256


@pytest.mark.parametrize("size", [1, 28, 1179, 1180, 5000, 921_600, 1_000_000])
def test_fec_fragments_fit_and_every_block_has_its_repair(size):
    frame = frame_of(size, size)
    fragments = fec_fragments(frame, 1200, TOPIC, 42, 0.1)
    assert all(len(f) <= 1200 for f in fragments)
    headers = [FEC.unpack_from(f) for f in fragments]
    blocks = headers[0][5]
    assert {h[4] for h in headers} == set(range(blocks))
    for block in range(blocks):
        k, m = next((h[7], h[8]) for h in headers if h[4] == block)
        assert m == -(-k // 10)  # ceil(k * 0.1): one repair per ten, at least one
        assert sorted(h[6] for h in headers if h[4] == block) == list(range(k + m))
    # interleaved: the first fragment of every block comes before any block's second
    assert [h[4] for h in headers[:blocks]] == list(range(blocks))
    # whole, from the data fragments alone
    log = Log()
    rx = FecReassembler(log.on_lost, log.on_recovered)
    out = [rx.add("a", f, 0.0) for f in fragments if FEC.unpack_from(f)[6] < FEC.unpack_from(f)[7]]
    assert [o for o in out if o is not None] == [frame]
    assert log.lost == [] and log.recovered == []


def test_fec_rebuilds_from_any_k_of_each_block():
    frame = frame_of(921_600, 1)
    fragments = fec_fragments(frame, 1200, TOPIC, 42, 0.1)
    rng = random.Random(3)
    by_block: dict[int, list[bytes]] = {}
    for f in fragments:
        by_block.setdefault(FEC.unpack_from(f)[4], []).append(f)
    kept = []
    for block_fragments in by_block.values():
        m = FEC.unpack_from(block_fragments[0])[8]
        lose = set(rng.sample(range(len(block_fragments)), m))  # as many as there are repairs
        kept += [f for i, f in enumerate(block_fragments) if i not in lose]
    rng.shuffle(kept)  # in any order
    log = Log()
    rx = FecReassembler(log.on_lost, log.on_recovered)
    assert [o for o in (rx.add("a", f, 0.0) for f in kept) if o is not None] == [frame]
    assert log.recovered == [TOPIC] and log.lost == []
    # late fragments of the finished frame start nothing
    assert all(rx.add("a", f, 0.1) is None for f in fragments[:5])
    rx.expire(10.0)
    assert log.lost == []


def test_fec_frame_with_one_loss_too_many_is_lost_once_at_the_deadline():
    fragments = fec_fragments(frame_of(20_000, 2), 1200, TOPIC, 9, 0.1)  # one block, m = 2
    log = Log()
    rx = FecReassembler(log.on_lost, log.on_recovered, timeout=2.0)
    assert all(rx.add("a", f, 0.0) is None for f in fragments[3:])
    rx.expire(1.9)
    assert log.lost == []
    rx.expire(2.1)
    assert log.lost == [(TOPIC, "fragment_lost")] and log.recovered == []


def test_fec_of_a_small_frame_is_a_copy():
    frame = b"RG" + bytes(50)
    fragments = fec_fragments(frame, 1200, TOPIC, 1, 0.1)
    assert len(fragments) == 2  # k = 1, m = ceil(0.1) = 1
    log = Log()
    rx = FecReassembler(log.on_lost, log.on_recovered)
    assert rx.add("a", fragments[1], 0.0) == frame  # the repair alone
    assert log.recovered == [TOPIC]


@pytest.mark.parametrize("mangle", [
    lambda f: f[:FEC.size],                                        # no chunk
    lambda f: f[:18] + bytes([9, 1, 0]) + f[21:],                  # index over k + m
    lambda f: f[:19] + bytes([0, 0]) + f[21:],                     # k = 0
    lambda f: f[:19] + bytes([200, 100]) + f[21:],                 # k + m over 256
    lambda f: f[:10] + (1 << 30).to_bytes(4, "big") + f[14:],      # longer than a message
    lambda f: f[:14] + (5).to_bytes(2, "big") + f[16:],            # block over blocks
])
def test_fec_headers_out_of_range_are_refused(mangle):
    good = fec_fragments(frame_of(3000, 5), 1200, TOPIC, 1, 0.1)[0]
    with pytest.raises(FramingError):
        FecReassembler(Log().on_lost, Log().on_recovered).add("a", mangle(good), 0.0)


def test_fec_memory_is_bounded():
    log = Log()
    rx = FecReassembler(log.on_lost, log.on_recovered, max_pending_bytes=50_000)
    for fid in range(20):
        for f in fec_fragments(frame_of(20_000, fid), 1200, TOPIC, fid, 0.1)[:10]:
            rx.add("a", f, 0.0)
    assert 0 < len(log.lost) < 20 and {r for _, r in log.lost} == {"reassembly_overflow"}


# -- selective repeat --------------------------------------------------------------------------
def test_nack_and_ack_round_trip():
    assert recovery.parse_nack(recovery.nack(5, [1, 2, 3, 7, 9, 10])) == (5, [1, 2, 3, 7, 9, 10])
    assert recovery.parse_ack(recovery.ack([1, 2**32 - 1])) == [1, 2**32 - 1]
    for bad in (b"RN", recovery.nack(5, [1])[:-1], b"RA\x00\x02" + bytes(4)):
        with pytest.raises(FramingError):
            (recovery.parse_nack if bad[:2] == b"RN" else recovery.parse_ack)(bad)


class Channel:
    """Two ends, one lossy link each way with a fixed delay: a discrete-event simulation."""

    def __init__(self, loss: float, delay: float, seed: int, gap: float = 0.0005):
        self.rng = random.Random(seed)
        self.loss, self.delay, self.gap = loss, delay, gap
        self.now = 0.0
        self.events: list[tuple[float, int, str, bytes]] = []
        self._n = 0
        self.sent = {"a": 0, "b": 0}
        self.busy_until = 0.0

    def send(self, side: str, datagram: bytes, again: bool = False) -> None:
        """``side`` sends; it arrives at the other side unless lost. Side a's first sends are
        paced (one per ``gap``); what it sends again goes first, as a link's scheduler sends a
        topic's repairs before the rest of its queue."""
        self.sent[side] += 1
        start = max(self.now, self.busy_until) if side == "a" and not again else self.now
        if side == "a" and not again:
            self.busy_until = start + self.gap
        if self.rng.random() >= self.loss:
            self._n += 1
            heapq.heappush(self.events, (start + self.delay, self._n, side, datagram))


def run_repeat(frames: list[bytes], loss: float, seed: int, delay: float = 0.01):
    log = Log()
    ch = Channel(loss, delay, seed)
    store = RetransmitStore()
    got: list[bytes] = []
    rx = RepeatReassembler(log.on_lost, log.on_recovered,
                           send=lambda d, source: ch.send("b", d))
    resent = 0
    for fid, frame in enumerate(frames):
        packets = repeat_fragments(frame, 1200, TOPIC, fid)
        store.keep("b", fid, packets, "route", ch.now)
        for p in packets:
            ch.send("a", p)
        store.sent("b", fid, ch.busy_until)
    end = ch.now + 5.0
    while ch.now < end:
        times = [t for t in (store.next_probe(), rx.next_poll()) if t is not None]
        if ch.events:
            times.append(ch.events[0][0])
        if not times:
            break
        ch.now = max(ch.now, min(times))
        while ch.events and ch.events[0][0] <= ch.now:
            _, _, side, d = heapq.heappop(ch.events)
            if side == "a":
                frame = rx.add("a", d, ch.now)
                if frame is not None:
                    got.append(frame)
            elif d[:2] == b"RN":
                again = store.on_nack("b", d)
                if again:
                    resent += len(again[1])
                    for p in again[1]:
                        ch.send("a", p, again=True)
            else:
                store.on_ack("b", d, ch.now)
        rx.poll(ch.now)
        for _, _, p in store.probes(ch.now):
            resent += 1
            ch.send("a", p, again=True)
    return got, log, store, resent


def test_selective_repeat_delivers_everything_at_5_percent_loss():
    frames = [frame_of(size, size) for size in (10, 1100, 1180, 5000, 100_000, 921_600)] * 3
    got, log, store, resent = run_repeat(frames, 0.05, seed=1)
    assert sorted(got) == sorted(frames)
    assert log.lost == []
    assert len(log.recovered) >= 6  # the large frames lost something and got it back
    assert len(store) == 0  # every frame acknowledged
    total = sum(len(repeat_fragments(f, 1200, TOPIC, 0)) for f in frames)
    assert 0.03 * total < resent < 0.2 * total  # about what was lost, not everything again


def test_selective_repeat_recovers_a_frame_whose_every_fragment_was_lost():
    """Nothing reaches the receiver: only the sender's probe (its last fragment again, after
    the probe timeout) lets the receiver ask for the rest."""
    frames = [frame_of(6000, 1)]
    got, log, store, resent = run_repeat(frames, 0.0, seed=1)
    assert got == frames and resent == 0
    log = Log()
    store = RetransmitStore()
    sent: list[bytes] = []
    rx = RepeatReassembler(log.on_lost, log.on_recovered, send=lambda d, s: sent.append(d))
    packets = repeat_fragments(frames[0], 1200, TOPIC, 3)
    store.keep("b", 3, packets, "route", 0.0)
    store.sent("b", 3, 0.001)   # ... and all of them lost
    assert store.probes(0.1) == []
    probe = store.probes(0.3)   # 2 x the initial RTT (0.1 s) + 10 ms after the last one left
    assert [p for _, _, p in probe] == [packets[-1]]
    assert rx.add("a", probe[0][2], 0.31) is None  # asks at once for 0..2, three places behind
    rx.poll(0.4)                                   # and, when nothing more came, for the rest
    answers = [store.on_nack("b", d) for d in sent]
    assert {owner for owner, _ in answers} == {"route"}
    again = [p for _, ps in answers for p in ps]
    assert sorted(again) == sorted(packets[:-1])
    out = [rx.add("a", p, 0.45) for p in again]
    assert out[-1] == frames[0] and log.recovered == [TOPIC]
    store.on_ack("b", sent[-1], 0.46)  # the ACK the last fragment brought
    assert len(store) == 0


def test_a_frame_lost_whole_is_sent_again_once_three_later_ones_are_acknowledged():
    """A small message is lost whole: the ACKs of the frames sent after it say so before its
    probe timeout does (at the third, so that a frame merely overtaken is not sent twice)."""
    store = RetransmitStore()
    for fid in range(1, 6):
        store.keep("b", fid, [b"p%d" % fid], "route", 0.0)
        store.sent("b", fid, 0.001 * fid)
    store.keep("c", 9, [b"other"], "route", 0.0)  # another destination: not its business
    store.sent("c", 9, 0.0)
    store.on_ack("b", recovery.ack([2, 3]), 0.010)
    assert store.probes(0.011) == []
    store.on_ack("b", recovery.ack([4]), 0.012)
    assert store.probes(0.012) == [("route", "b", b"p1")]  # long before its probe timeout
    store.on_ack("b", recovery.ack([5]), 0.013)
    assert store.probes(0.014) == []  # once: after that, its probe timeout backs off


def test_the_probe_timeout_follows_how_much_the_round_trip_varies():
    """A slow line's acknowledgements come at 10 ms mostly and at 200 ms one time in five (its
    queue comes and goes): a frame is not probed before a slow acknowledgement is due (the
    timeout takes four deviations of the round trip, RFC 6298's), so it is not sent twice for
    nothing. On a steady line the timeout stays short. With twice the smoothed round trip alone
    the timeout was ~0.1-0.17 s there, and every slow acknowledgement came after a probe."""
    def trained(delays: list[float]) -> tuple[RetransmitStore, float]:
        store, now = RetransmitStore(), 0.0
        for fid, delay in enumerate(delays, 1):
            store.keep("b", fid, [b"p%d" % fid], "route", now)
            store.sent("b", fid, now)
            store.on_ack("b", recovery.ack([fid]), now + delay)
            now += 0.3
        store.keep("b", 999, [b"last"], "route", now)
        store.sent("b", 999, now)
        return store, now

    slow, sent = trained([0.2 if n % 5 == 0 else 0.01 for n in range(40)])
    assert slow.probes(sent + 0.2) == []  # a slow acknowledgement is on its way, not a loss
    assert slow.probes(sent + 0.6) == [("route", "b", b"last")]
    steady, sent = trained([0.01] * 40)
    assert steady.probes(sent + 0.05) == [("route", "b", b"last")]


def test_a_nack_is_answered_only_for_the_address_the_frame_went_to():
    store = RetransmitStore()
    store.keep(("10.0.0.2", 1), 5, [b"p0", b"p1"], "route", 0.0)
    assert store.on_nack(("10.0.0.3", 1), recovery.nack(5, [0])) is None
    assert store.on_nack(("10.0.0.2", 1), recovery.nack(6, [0])) is None  # another frame id
    assert store.on_nack(("10.0.0.2", 1), recovery.nack(5, [0, 1, 99])) == ("route", [b"p0", b"p1"])


def test_an_outage_of_the_line_does_not_run_the_deadline_down():
    """The line was gone for 5 s (its timers not run): what was on the way when it went is
    probed as soon as it is back and kept its 2 s from there, on both sides; without the
    outage pushed on, the first look after it gives them up."""
    log = Log()
    sent: list[bytes] = []
    store, rx = RetransmitStore(), RepeatReassembler(log.on_lost, log.on_recovered,
                                                     send=lambda d, s: sent.append(d))
    packets = repeat_fragments(frame_of(3000, 1), 1200, TOPIC, 4)
    store.keep("b", 4, packets, "route", 0.0)
    store.sent("b", 4, 0.01)
    assert rx.add("a", packets[0], 0.01) is None  # its first fragment came; then the line went
    store.resumed(5.0, 5.1)
    rx.resumed(5.0, 5.1)
    assert [p for _, _, p in store.probes(5.1)] == [packets[-1]]
    rx.poll(5.1)
    assert log.lost == [] and recovery.parse_nack(sent[-1]) == (4, [1, 2])
    assert store.probes(6.9) == [] and len(store) == 1  # 2 s after it left, outage aside
    assert store.probes(7.1) == [] and len(store) == 0
    assert rx.add("a", packets[1], 6.0) is None and rx.add("a", packets[2], 6.0) is not None


def test_a_far_side_that_moved_gets_what_was_kept_for_its_old_address_at_once():
    """A roam: frames sent to the old address were lost with it; once the far side is heard
    at its new one, they are probed there at once, their deadline counted afresh, and its
    NACKs are answered there (never at the old one)."""
    old, new, other = ("10.0.0.1", 9), ("10.0.0.3", 9), ("10.0.0.2", 9)
    store = RetransmitStore(deadline=2.0)
    store.keep(old, 1, [b"p0", b"p1"], "route", 0.0)
    store.keep(other, 2, [b"q0"], "other", 0.0)
    store.sent(old, 1, 0.0)
    assert [(to, p) for _, to, p in store.probes(0.3)] == [(old, b"p1")]  # lost with it
    store.moved(old, new, 1.9)
    assert [(to, p) for _, to, p in store.probes(1.9)] == [(new, b"p1")]
    assert store.on_nack(other, recovery.nack(2, [0])) == ("other", [b"q0"])  # untouched
    assert store.on_nack(old, recovery.nack(1, [0])) is None
    assert store.on_nack(new, recovery.nack(1, [0])) == ("route", [b"p0"])
    store.probes(3.0)  # 2 s from the move, not from when it first left
    assert store.on_nack(new, recovery.nack(1, [1])) is not None
    store.probes(4.0)
    assert store.on_nack(new, recovery.nack(1, [1])) is None  # gone at last


def test_a_frame_in_progress_from_a_far_side_that_moved_is_finished_from_there():
    log, sent = Log(), []
    old, new = ("10.0.0.1", 9), ("10.0.0.3", 9)
    rx = RepeatReassembler(log.on_lost, log.on_recovered, send=lambda d, s: sent.append((d, s)))
    frame = frame_of(3000, 4)
    packets = repeat_fragments(frame, 1200, TOPIC, 11)
    assert rx.add(old, packets[0], 0.0) is None
    rx.moved(old, new)
    assert [rx.add(new, p, 0.1) for p in packets[1:]][-1] == frame
    assert log.lost == [] and sent[-1][1] == new  # acknowledged at the new address


def test_every_fragment_is_sent_a_bounded_number_of_times():
    store = RetransmitStore()
    store.keep("b", 1, [b"p0"], "route", 0.0)
    answers = [store.on_nack("b", recovery.nack(1, [0])) for _ in range(20)]
    assert sum(a is not None for a in answers) == recovery.MAX_SENDS - 1


def test_the_store_forgets_after_the_deadline_and_beyond_its_memory():
    store = RetransmitStore(deadline=2.0, max_bytes=10_000)
    assert store.keep("b", 1, [bytes(4000)], "r1", 0.0) == []
    assert store.keep("b", 2, [bytes(4000)], "r2", 0.0) == []
    # over 10,000 bytes: the oldest goes, its owner named to be counted
    assert store.keep("b", 3, [bytes(4000)], "r3", 0.0) == ["r1"]
    assert store.on_nack("b", recovery.nack(1, [0])) is None
    assert store.on_nack("b", recovery.nack(2, [0])) is not None
    store.sent("b", 2, 0.5)  # the last fragment of each left
    store.sent("b", 3, 1.0)
    store.probes(2.6)
    assert len(store) == 1  # the deadline runs from there
    store.probes(3.1)
    assert len(store) == 0


def test_a_frame_still_going_out_is_kept_past_the_deadline():
    """A 16 MB map on a 20 Mbit/s link takes 6.4 s to leave: its fragments stay askable for
    until DEADLINE after its last one left, not after it started."""
    store = RetransmitStore(deadline=2.0)
    store.keep("b", 1, [bytes(100)] * 3, "r", 0.0)
    store.probes(6.0)
    assert store.on_nack("b", recovery.nack(1, [0])) is not None
    store.sent("b", 1, 6.4)
    store.probes(8.0)
    assert len(store) == 1
    store.probes(8.5)
    assert len(store) == 0


def test_the_receiver_waits_for_a_frame_while_its_fragments_keep_coming():
    log = Log()
    rx = RepeatReassembler(log.on_lost, log.on_recovered, send=lambda d, s: None, timeout=2.0)
    packets = repeat_fragments(frame_of(5000, 1), 1200, TOPIC, 1)
    at = 0.0
    for packet in packets[:-1]:  # one fragment every 1.5 s: 6 s in all, never 2 s silent
        assert rx.add("a", packet, at) is None
        rx.poll(at + 1.0)
        at += 1.5
    assert rx.add("a", packets[-1], at) == frame_of(5000, 1)
    assert log.lost == []


def test_the_receiver_gives_up_at_the_deadline_once():
    log = Log()
    rx = RepeatReassembler(log.on_lost, log.on_recovered, send=lambda d, s: None, timeout=2.0)
    packets = repeat_fragments(frame_of(5000, 1), 1200, TOPIC, 1)
    rx.add("a", packets[0], 0.0)
    rx.poll(1.0)
    rx.poll(2.5)
    rx.poll(3.0)
    assert log.lost == [(TOPIC, "fragment_lost")]
    assert rx.next_poll() is None


def test_an_fec_frame_is_waited_for_while_its_fragments_keep_coming():
    log = Log()
    rx = FecReassembler(log.on_lost, log.on_recovered, timeout=2.0)
    frame = frame_of(20_000, 2)
    packets = fec_fragments(frame, 1200, TOPIC, 1, 0.1)
    at, got = 0.0, None
    for packet in packets:  # one every 0.5 s: far longer than the timeout in all
        got = rx.add("a", packet, at) or got
        rx.expire(at)
        at += 0.5
    assert got == frame and log.lost == []
