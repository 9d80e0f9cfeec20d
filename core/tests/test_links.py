"""Links over the real udp and tcp transports on loopback: frames of every size arrive byte-exact
(fragmented on UDP, length-prefixed on TCP), a full send queue is counted, bad input is counted
without killing the link, and a closed connection is noticed by the far end."""

from __future__ import annotations

import random
import socket
import threading
from typing import Any

import pytest
from polling import settles
from rosgate_compact import compact_fragment
from rosgate_transport_bt import BluetoothTransport
from rosgate_transport_tcp import TcpTransport
from rosgate_transport_udp import UdpTransport

from rosgate import builtin
from rosgate.errors import LinkError
from rosgate.links.datagram import DatagramLink
from rosgate.plugins import Plugins
from rosgate.spec import Delivery
from rosgate.streamlink.link import StreamLink, length_prefixed
from rosgate.streamlink.slot import LinkSlot, QueueLimits
from rosgate.wire import envelope
from rosgate.wire.framing import FRAGMENT, LENGTH

TOPIC = 5


class Inbox:
    """on_frame, on_lost and on_close callbacks, and senders whose drops land here too, that
    record what they are given; wait on them with a timeout."""

    def __init__(self) -> None:
        self.frames: list[tuple[bytes, Any, Any]] = []
        self.drops: list[tuple[int | None, str]] = []
        self.closed: list[Any] = []
        self._changed = threading.Condition()

    def on_frame(self, frame: bytes, link, source) -> None:
        with self._changed:
            self.frames.append((frame, link, source))
            self._changed.notify_all()

    def on_lost(self, topic_id: int | None, reason: str) -> None:
        with self._changed:
            self.drops.append((topic_id, reason))
            self._changed.notify_all()

    def sender(self, topic_id: int, reliable: bool = False) -> Sent:
        return Sent(topic_id, reliable, self)

    def on_close(self, link) -> None:
        with self._changed:
            self.closed.append(link)
            self._changed.notify_all()

    def wait(self, predicate, timeout: float = 10.0) -> bool:
        with self._changed:
            return self._changed.wait_for(predicate, timeout)

    def payloads(self) -> list[bytes]:
        with self._changed:
            return [frame for frame, _, _ in self.frames]


class Sent:
    """A route as a link sees it: the topic id its fragments carry, whether a slot holds its
    frames while down, and where its drops are counted."""

    def __init__(self, topic_id: int, reliable: bool, inbox: Inbox):
        self.topic_id = topic_id
        self.reliable = reliable
        self.max_delay: float | None = None
        self.inbox = inbox

    @property
    def delivery(self) -> Delivery:
        return Delivery(reliable=self.reliable, max_delay=self.max_delay)

    def drop(self, reason: str, detail: str = "") -> None:
        self.inbox.on_lost(self.topic_id, reason)

    def on_wire(self, size: int, again: bool) -> None:
        pass


def frame_of(seq: int, size: int, rng: random.Random) -> bytes:
    """A frame as routes make them: an envelope header, then the body."""
    header = envelope.pack(0, TOPIC, 1, seq, 0)
    return header + rng.randbytes(max(0, size - len(header)))


@pytest.fixture
def closing():
    things = []
    yield lambda thing: things.append(thing) or thing
    for thing in reversed(things):
        thing.close()


# --- datagram links ------------------------------------------------------------------------------

@pytest.fixture
def udp_pair(closing):
    transport = UdpTransport({})
    ends = []
    for name in ("a", "b"):
        inbox = Inbox()
        endpoint = transport.bind(("127.0.0.1", 0))
        address = endpoint.sock.getsockname()
        link = closing(DatagramLink(transport, endpoint, name, inbox.on_frame, inbox.on_lost))
        ends.append((link, inbox, address))
    return ends


def test_datagram_frames_of_every_size_arrive_byte_exact(udp_pair):
    (a, a_inbox, a_address), (b, b_inbox, b_address) = udp_pair
    rng = random.Random(1)
    frames = [b"\x01", frame_of(1, 10_000, rng), frame_of(2, 200_000, rng),
              frame_of(3, UdpTransport.max_frame, rng),
              frame_of(4, UdpTransport.max_frame + 1, rng)]
    for frame in frames:
        assert a.send(frame, a_inbox.sender(TOPIC), b_address) is True
    assert b_inbox.wait(lambda: len(b_inbox.frames) >= len(frames)), b_inbox.drops
    assert sorted(b_inbox.payloads()) == sorted(frames)
    assert all(link is b and source == a_address for _, link, source in b_inbox.frames)
    assert b_inbox.drops == [] and a_inbox.drops == [] and a_inbox.frames == []


def test_datagram_frames_both_ways(udp_pair):
    (a, a_inbox, a_address), (b, b_inbox, b_address) = udp_pair
    rng = random.Random(2)
    there, back = frame_of(1, 150_000, rng), frame_of(1, 70_000, rng)
    a.send(there, a_inbox.sender(TOPIC), b_address)
    b.send(back, b_inbox.sender(TOPIC), a_address)
    assert b_inbox.wait(lambda: b_inbox.frames) and a_inbox.wait(lambda: a_inbox.frames)
    assert b_inbox.payloads() == [there] and a_inbox.payloads() == [back]


def test_a_bad_fragment_is_counted_and_the_link_keeps_working(udp_pair):
    (_, _, _), (b, b_inbox, b_address) = udp_pair
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as raw:
        raw.sendto(b"RF" + b"\x00" * 5, b_address)                           # too short
        raw.sendto(FRAGMENT.pack(b"RF", 5, 2, TOPIC, 1) + b"x", b_address)    # index over count
        raw.sendto(b"\x02plain", b_address)
    assert b_inbox.wait(lambda: b_inbox.frames)
    assert b_inbox.payloads() == [b"\x02plain"]
    assert b_inbox.drops == [(None, "bad_fragment"), (None, "bad_fragment")]


def test_bare_mode_refuses_frames_that_do_not_fit(closing):
    transport = UdpTransport({})
    inbox = Inbox()
    endpoint = transport.bind(("127.0.0.1", 0))
    link = closing(DatagramLink(transport, endpoint, "bare", inbox.on_frame, inbox.on_lost,
                                bare=True))
    assert link.send(bytes(UdpTransport.max_frame + 1), inbox.sender(9), ("127.0.0.1", 9)) is False
    assert inbox.drops == [(9, "too_large_for_bare_framing")]


def test_bare_mode_hands_over_fragment_lookalikes_untouched(closing):
    transport = UdpTransport({})
    inbox = Inbox()
    endpoint = transport.bind(("127.0.0.1", 0))
    closing(DatagramLink(transport, endpoint, "bare", inbox.on_frame, inbox.on_lost, bare=True))
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as raw:
        raw.sendto(b"RF not a fragment", endpoint.sock.getsockname())
    assert inbox.wait(lambda: inbox.frames)
    assert inbox.payloads() == [b"RF not a fragment"] and inbox.drops == []


# --- coalescing, the send thread, scatter-gather -------------------------------------------------

class Recorder:
    """An endpoint wrapper that records every datagram sent (its parts when sent as parts, and
    the sending thread), and can hold sends until released."""

    def __init__(self, endpoint, parts: bool = True):
        self.endpoint = endpoint
        self.sent: list[bytes] = []
        self.parts: list[list] = []
        self.threads: list[str] = []
        self.released = threading.Event()
        self.released.set()
        self.entered = threading.Event()
        if parts:
            self.send_parts = self._send_parts

    def _record(self, datagram: bytes) -> None:
        self.entered.set()
        self.released.wait(10)
        self.sent.append(datagram)
        self.threads.append(threading.current_thread().name)

    def send(self, frame, to) -> None:
        self._record(bytes(frame))
        self.endpoint.send(frame, to)

    def _send_parts(self, parts, to) -> None:
        self.parts.append(list(parts))
        self._record(b"".join(parts))
        self.endpoint.send_parts(parts, to)

    def receive_into(self, buffer, timeout):
        return self.endpoint.receive_into(buffer, timeout)

    def close(self) -> None:
        self.released.set()
        self.endpoint.close()


def recorded_pair(closing, parts: bool = True, max_frame: int | None = 65_000):
    transport = UdpTransport({})
    if max_frame is not None:
        transport.max_frame = max_frame
    a_wire = Recorder(transport.bind(("127.0.0.1", 0)), parts)
    b_inbox, a_inbox = Inbox(), Inbox()
    a = closing(DatagramLink(transport, a_wire, "a", a_inbox.on_frame, a_inbox.on_lost))
    b_endpoint = transport.bind(("127.0.0.1", 0))
    b = closing(DatagramLink(transport, b_endpoint, "b", b_inbox.on_frame, b_inbox.on_lost))
    return a, a_wire, a_inbox, b, b_endpoint.sock.getsockname(), b_inbox


@pytest.mark.parametrize("parts", [True, False], ids=["send_parts", "send"])
def test_frames_handed_over_together_share_a_datagram(closing, parts):
    a, wire, a_inbox, b, to, b_inbox = recorded_pair(closing, parts)
    rng = random.Random(20)
    frames = [frame_of(i, rng.randint(28, 2500), rng) for i in range(20)]
    assert a.send_all(frames, a_inbox.sender(TOPIC), to) == 20
    assert b_inbox.wait(lambda: len(b_inbox.frames) >= 20), b_inbox.drops
    assert b_inbox.payloads() == frames  # in order, byte-exact
    assert len(wire.sent) == 1 and wire.sent[0][:2] == b"RB"
    assert a.counters.frames_out == a.counters.coalesced_out == 20 and a.counters.packets_out == 1
    assert b.counters.frames_in == b.counters.coalesced_in == 20 and b.counters.packets_in == 1
    assert a_inbox.drops == b_inbox.drops == []


def test_a_batch_never_exceeds_max_frame(closing):
    a, wire, a_inbox, b, to, b_inbox = recorded_pair(closing, max_frame=1000)
    rng = random.Random(21)
    frames = [frame_of(i, 300, rng) for i in range(10)]
    assert a.send_all(frames, a_inbox.sender(TOPIC), to) == 10
    assert b_inbox.wait(lambda: len(b_inbox.frames) >= 10), b_inbox.drops
    assert b_inbox.payloads() == frames
    # 2 + 3 * (4 + 300) = 914 bytes: three frames to a datagram, the tenth alone and plain
    assert [len(d) for d in wire.sent] == [914, 914, 914, 300]
    assert wire.sent[-1] == frames[-1]


def test_a_frame_alone_is_a_plain_datagram(closing):
    a, wire, a_inbox, b, to, b_inbox = recorded_pair(closing)
    frame = frame_of(1, 100, random.Random(22))
    assert a.send(frame, a_inbox.sender(TOPIC), to) is True
    assert b_inbox.wait(lambda: b_inbox.frames)
    assert wire.sent == [frame] and wire.parts == []  # what any earlier rosgate reads
    assert wire.threads == [threading.current_thread().name]  # no hand-off to the send thread


def test_bare_links_never_coalesce(closing):
    transport = UdpTransport({})
    wire = Recorder(transport.bind(("127.0.0.1", 0)))
    inbox = Inbox()
    link = closing(DatagramLink(transport, wire, "bare", inbox.on_frame, inbox.on_lost, bare=True))
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as far:
        far.bind(("127.0.0.1", 0))
        far.settimeout(5)
        messages = [b"\xa3one", b"\xa3two", b"\xa5three"]
        assert link.send_all(messages, inbox.sender(9), far.getsockname()) == 3
        assert [far.recv(100) for _ in messages] == messages  # one message per datagram
    assert wire.parts == []


def test_a_malformed_batch_is_counted_after_the_frames_before_it(udp_pair):
    (_, _, _), (b, b_inbox, b_address) = udp_pair
    good = frame_of(1, 50, random.Random(23))
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as raw:
        raw.sendto(b"RB" + LENGTH.pack(len(good)) + good + LENGTH.pack(1000) + b"short", b_address)
        raw.sendto(b"RB" + LENGTH.pack(len(good)) + good + b"\x00\x00", b_address)
    assert b_inbox.wait(lambda: len(b_inbox.drops) >= 2)
    assert b_inbox.payloads() == [good, good]
    assert b_inbox.drops == [(None, "bad_batch"), (None, "bad_batch")]


def test_frames_that_waited_leave_together_from_the_send_thread(closing):
    """While the send thread is busy (a large frame on a stalled wire), small frames of several
    topics queue in the scheduler; when it is free they leave in one batch datagram, in the
    order they came, and the one that does not fit goes next."""
    a, wire, a_inbox, b, to, b_inbox = recorded_pair(closing, max_frame=1200)
    wire.released.clear()
    big = frame_of(1, 70_000, random.Random(40))  # longer than what leaves inline
    assert a.send(big, a_inbox.sender(1), to) is True
    assert wire.entered.wait(5)  # its first fragment is on its way: the thread is held
    rng = random.Random(41)
    small = [frame_of(2 + i % 3, 200, rng) for i in range(6)]  # 6 x 228 B: five fit 1,200
    for i, frame in enumerate(small):
        assert a.send(frame, a_inbox.sender(2 + i % 3), to) is True
    wire.released.set()
    assert b_inbox.wait(lambda: len(b_inbox.frames) >= 7), b_inbox.drops
    assert sorted(b_inbox.payloads(), key=len) == sorted([big, *small], key=len)
    smalls = [p for p in b_inbox.payloads() if len(p) == len(small[0])]
    assert smalls == small  # in the order they came
    batches = [d for d in wire.sent if d[:2] == b"RB"]
    assert len(batches) == 1 and len(batches[0]) <= 1200
    # the send thread counts a datagram after the far end may have read it
    counted = lambda: (a.counters.coalesced_out, a.counters.frames_out)
    assert settles(lambda: counted() == (5, 7)), counted()


def test_a_large_frame_leaves_from_the_send_thread_in_scatter_gather_fragments(closing):
    a, wire, a_inbox, b, to, b_inbox = recorded_pair(closing)
    frame = frame_of(1, 200_000, random.Random(24))
    wire.released.clear()  # the wire stalls: the caller must not wait for it
    assert a.send(frame, a_inbox.sender(TOPIC), to) is True
    assert wire.entered.wait(5)
    small = frame_of(2, 100, random.Random(25))
    assert a.send(small, a_inbox.sender(TOPIC), to) is True  # queued behind it, not sent inline
    wire.released.set()
    assert b_inbox.wait(lambda: len(b_inbox.frames) >= 2), b_inbox.drops
    assert b_inbox.payloads() == [frame, small]
    assert set(wire.threads) == {"tx-a"}
    fragments = wire.parts
    assert len(fragments) == 4 and all(len(p) == 2 for p in fragments)
    # each fragment: its 14-byte header and a view of the frame itself (nothing joined)
    assert all(len(header) == FRAGMENT.size and chunk.obj is frame for header, chunk in fragments)


def test_a_full_send_queue_counts_queue_full_and_close_counts_what_waited(closing):
    transport = UdpTransport({})
    wire = Recorder(transport.bind(("127.0.0.1", 0)))
    inbox = Inbox()
    link = DatagramLink(transport, wire, "stuck", inbox.on_frame, inbox.on_lost, queue_frames=3)
    to = ("127.0.0.1", 9)
    wire.released.clear()
    assert link.send(bytes(100_000), inbox.sender(1), to) is True  # the send thread is stuck on it
    assert wire.entered.wait(5)
    assert [link.send(b"small", inbox.sender(2), to) for _ in range(5)] == [True] * 3 + [False] * 2
    assert inbox.drops == [(2, "queue_full")] * 2
    link.close()
    assert [drop for drop in inbox.drops[2:] if drop[0] == 2] == [(2, "link_down")] * 3
    # the frame whose fragments were going out: sent, or cut short by the close (counted once)
    assert [drop for drop in inbox.drops if drop[0] == 1] in ([], [(1, "send_error")],
                                                              [(1, "link_down")])
    assert link.send(b"late", inbox.sender(3), to) is False
    assert inbox.drops[-1] == (3, "link_down")


def test_a_best_effort_frame_that_waited_too_long_to_be_sent_is_dropped(closing):
    transport = UdpTransport({})
    wire = Recorder(transport.bind(("127.0.0.1", 0)))
    inbox = Inbox()
    link = closing(DatagramLink(transport, wire, "slow", inbox.on_frame, inbox.on_lost))
    to = ("127.0.0.1", 9)
    wire.released.clear()
    assert link.send(bytes(100_000), inbox.sender(1), to) is True  # the send thread is stuck
    assert wire.entered.wait(5)
    hasty, patient = inbox.sender(2), inbox.sender(3)
    hasty.max_delay = 1e-9  # with no time to lose
    assert link.send(b"hasty", hasty, to) and link.send(b"patient", patient, to)
    wire.released.set()
    assert inbox.wait(lambda: inbox.drops)
    assert inbox.wait(lambda: b"patient" in wire.sent)
    assert inbox.drops == [(2, "too_late")] and b"hasty" not in wire.sent


class Unpluggable:
    """A udp endpoint whose line can be pulled out, as a serial device vanishes: it says so
    through ``watch_line`` and refuses sends while it is gone."""

    def __init__(self, endpoint: Any):
        self.endpoint, self.gone = endpoint, False
        self.changed: Any = None

    def watch_line(self, changed) -> None:
        self.changed = changed

    def plug(self, there: bool) -> None:
        self.gone = not there
        self.changed(there)

    def send(self, frame: bytes, to) -> None:
        if self.gone:
            raise OSError("the line is gone")
        self.endpoint.send(frame, to)

    def receive(self, timeout: float):
        return self.endpoint.receive(timeout)

    def close(self) -> None:
        self.endpoint.close()


def test_while_its_line_is_gone_a_link_holds_reliable_frames_within_bounds(closing):
    """Reliable frames wait, the newest five (``hold_frames``), the oldest dropped first
    (``queue_full``); a best-effort one is dropped (``link_down``); once the line is back what
    waited leaves in order."""
    transport = UdpTransport({})
    far_inbox, inbox = Inbox(), Inbox()
    far_end = transport.bind(("127.0.0.1", 0))
    to = far_end.sock.getsockname()
    closing(DatagramLink(transport, far_end, "far", far_inbox.on_frame, far_inbox.on_lost))
    line = Unpluggable(transport.bind(("127.0.0.1", 0)))
    link = closing(DatagramLink(transport, line, "line", inbox.on_frame, inbox.on_lost,
                                hold_frames=5))
    reliable, best_effort = inbox.sender(1, reliable=True), inbox.sender(2)
    assert link.send(b"r0", reliable, to) and far_inbox.wait(lambda: far_inbox.frames)
    line.plug(False)
    assert [link.send(b"r%d" % i, reliable, to) for i in range(1, 9)] == [True] * 8
    assert link.send(b"b", best_effort, to) is False
    assert link.send_all([b"r9", b"r10"], reliable, to) == 2
    assert inbox.drops == [(1, "queue_full")] * 3 + [(2, "link_down")] + [(1, "queue_full")] * 2
    assert link.queued() == 5 and far_inbox.payloads() == [b"r0"]
    line.plug(True)
    assert far_inbox.wait(lambda: len(far_inbox.frames) >= 6)
    assert far_inbox.payloads() == [b"r0"] + [b"r%d" % i for i in range(6, 11)]
    assert len(inbox.drops) == 6


# --- reassembly under attack (issue 10) ------------------------------------------------------

def test_a_flood_of_one_byte_fragments_is_bounded_and_counted(closing):
    """15-byte fragments (a 1-byte chunk, count 2, a new frame id each) from one source: each
    starts a partial frame that never completes. The link keeps at most its per-source number of
    them, accounted at what they really cost, gives up the oldest first and counts each once;
    a fragmented frame from another source completes meanwhile."""
    transport = UdpTransport({})
    inbox = Inbox()
    endpoint = transport.bind(("127.0.0.1", 0))
    victim = closing(DatagramLink(transport, endpoint, "victim", inbox.on_frame, inbox.on_lost))
    to = endpoint.sock.getsockname()
    reassembler = victim.own.reassembler  # type: ignore[attr-defined]
    assert isinstance(reassembler, builtin.Reassembler)
    flood = 3000
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as attacker:
        for i in range(flood):
            attacker.sendto(FRAGMENT.pack(b"RF", 0, 2, TOPIC, i) + b"x", to)
        held = reassembler.source_partials
        assert inbox.wait(lambda: len(inbox.drops) >= flood - held), len(inbox.drops)
        assert inbox.drops == [(TOPIC, "reassembly_overflow")] * (flood - held)
        assert reassembler.pending == held
        # each: its bookkeeping, a byte per fragment slot, its buffer (2 x 1 byte, earned at once)
        assert reassembler.pending_bytes == held * (builtin.PARTIAL_COST + 2 + 2)
        # a real sender is not crowded out
        sender = closing(DatagramLink(transport, transport.bind(("127.0.0.1", 0)), "sender",
                                      Inbox().on_frame, Inbox().on_lost))
        frame = frame_of(1, 200_000, random.Random(30))
        assert sender.send(frame, inbox.sender(TOPIC), to) is True
        assert inbox.wait(lambda: inbox.frames), inbox.drops[-3:]
        assert inbox.payloads() == [frame]
        assert len(inbox.drops) == flood - held  # nothing of it given up
        # the flood's partial frames expire in time order, each counted once
        assert inbox.wait(lambda: reassembler.pending == 0, 10)
        assert inbox.drops[flood - held:] == [(TOPIC, "fragment_lost")] * held
        assert reassembler.pending_bytes == 0


def spoofed_udp(source, destination, payload: bytes) -> bytes:
    """An IPv4 + UDP packet from ``source`` to ``destination`` (host, port), no UDP checksum."""
    import struct
    udp = struct.pack("!HHHH", source[1], destination[1], 8 + len(payload), 0) + payload
    return struct.pack("!BBHHHBBH4s4s", 0x45, 0, 20 + len(udp), 0, 0, 64, socket.IPPROTO_UDP, 0,
                       socket.inet_aton(source[0]), socket.inet_aton(destination[0])) + udp


def raw_socket():
    try:
        return socket.socket(socket.AF_INET, socket.SOCK_RAW, socket.IPPROTO_RAW)
    except PermissionError:
        pytest.skip("spoofing a source address needs a raw socket (root)")


def test_a_spoofed_fragment_cannot_poison_a_frame_in_progress(closing):
    """An attacker who saw one fragmented frame go by guesses the next one's frame id and slips a
    fragment of its own into it, sent from the sender's address. Frame ids are random: the guess
    misses, the real frame arrives intact, and the forged fragment expires as a lost frame."""
    a, wire, a_inbox, b, to, b_inbox = recorded_pair(closing)
    rng = random.Random(31)
    first, second = frame_of(1, 150_000, rng), frame_of(2, 150_000, rng)
    assert a.send(first, a_inbox.sender(TOPIC), to) is True
    assert b_inbox.wait(lambda: b_inbox.frames)
    _, index, count, topic_id, frame_id = FRAGMENT.unpack(wire.parts[0][0])
    with raw_socket() as raw:
        for guess in (frame_id + 1, frame_id - 1, frame_id + 2):  # what a counter would give
            forged = FRAGMENT.pack(b"RF", 1, count, topic_id, guess & 0xFFFFFFFF) + \
                bytes(len(wire.parts[1][1]))
            raw.sendto(spoofed_udp(a.endpoint.endpoint.sock.getsockname(), to, forged), (to[0], 0))
    assert b_inbox.wait(lambda: b.counters.packets_in >= count + 3)
    assert a.send(second, a_inbox.sender(TOPIC), to) is True
    assert b_inbox.wait(lambda: len(b_inbox.frames) >= 2), b_inbox.drops
    assert b_inbox.payloads() == [first, second]  # byte-exact: nothing forged got in
    ids = [FRAGMENT.unpack(parts[0])[4] for parts in wire.parts]
    assert len(set(ids)) == 2 and abs(ids[-1] - ids[0]) > 2
    assert b_inbox.wait(lambda: len(b_inbox.drops) >= 3, 10)
    assert b_inbox.drops == [(TOPIC, "fragment_lost")] * 3


def test_fragment_frame_ids_are_unpredictable(closing):
    a, wire, a_inbox, b, to, b_inbox = recorded_pair(closing)
    for i in range(20):
        a.send(frame_of(i, 70_000, random.Random(i)), a_inbox.sender(TOPIC), to)
    assert b_inbox.wait(lambda: len(b_inbox.frames) >= 20), b_inbox.drops
    ids = [FRAGMENT.unpack(parts[0])[4] for parts in wire.parts[::2]]
    assert len(set(ids)) == 20
    steps = {(later - earlier) & 0xFFFFFFFF for earlier, later in zip(ids, ids[1:], strict=False)}
    assert len(steps) > 15  # no counter, no fixed stride


# --- datagram links with small frames (CAN-sized): the compact scheme -----------------------------

class Wire:
    """An endpoint wrapper that records the size of every datagram sent, and can lose one."""

    def __init__(self, endpoint, lose: int | None = None):
        self.endpoint = endpoint
        self.sizes: list[int] = []
        self.lose = lose  # the index of the datagram that never leaves

    def send(self, frame: bytes, to) -> None:
        self.sizes.append(len(frame))
        if len(self.sizes) - 1 != self.lose:
            self.endpoint.send(frame, to)

    def receive(self, timeout: float):
        return self.endpoint.receive(timeout)

    def close(self) -> None:
        self.endpoint.close()


def small_link_pair(closing, max_frame: int, lose: int | None = None):
    """Two links over real UDP sockets whose transport declares CAN-sized frames."""
    transport = UdpTransport({})
    transport.max_frame = max_frame
    ends = []
    for name in ("a", "b"):
        inbox = Inbox()
        wire = Wire(transport.bind(("127.0.0.1", 0)), lose)
        link = closing(DatagramLink(transport, wire, name, inbox.on_frame, inbox.on_lost))
        ends.append((link, inbox, wire))
    return ends


@pytest.mark.parametrize("max_frame, compact", [(8, True), (255, True), (256, False),
                                                (65_000, False)])
def test_the_fragment_scheme_follows_max_frame(closing, max_frame, compact):
    (a, _, _), _ = small_link_pair(closing, max_frame)
    assert a.cuts is compact
    assert a.own.name == ("compact" if compact else "fragments")


def test_a_small_link_without_its_packetizer_installed_names_the_distribution(closing):
    transport = UdpTransport({})
    transport.max_frame = 8
    endpoint = closing(transport.bind(("127.0.0.1", 0)))
    only_builtin = Plugins()
    only_builtin.add(builtin, "builtin")
    with pytest.raises(LinkError) as info:
        DatagramLink(transport, endpoint, "small", Inbox().on_frame, Inbox().on_lost,
                     packetizers=only_builtin)
    assert str(info.value) == ("small: no packetizer 'compact' is installed, which a link of "
                               "8-byte packets needs")
    assert info.value.fix == "pip install rosgate-compact"


def test_bare_links_never_use_the_compact_scheme(closing):
    transport = UdpTransport({})
    transport.max_frame = 8
    inbox = Inbox()
    link = closing(DatagramLink(transport, transport.bind(("127.0.0.1", 0)), "bare",
                                inbox.on_frame, inbox.on_lost, bare=True))
    assert link.cuts is False and link.own.name == "fragments"
    assert link.send(bytes(9), inbox.sender(9), ("127.0.0.1", 9)) is False
    assert inbox.drops == [(9, "too_large_for_bare_framing")]


@pytest.mark.parametrize("max_frame", [8, 64])
def test_small_frames_carry_frames_of_every_size_byte_exact(closing, max_frame):
    (a, a_inbox, a_wire), (b, b_inbox, b_wire) = small_link_pair(closing, max_frame)
    rng = random.Random(max_frame)
    # an envelope alone is 28 bytes: more than a classic CAN frame
    frames = [b"\x01", envelope.pack(0, TOPIC, 1, 1, 0), frame_of(2, 5_000, rng),
              frame_of(3, max_frame, rng), frame_of(4, 300, rng)]
    for frame in frames:
        assert a.send(frame, a_inbox.sender(TOPIC), b.endpoint.endpoint.sock.getsockname()) is True
    assert b_inbox.wait(lambda: len(b_inbox.frames) >= len(frames)), b_inbox.drops
    assert b_inbox.payloads() == frames
    assert max(a_wire.sizes) == max_frame
    assert b_inbox.drops == [] and a_inbox.drops == []


def test_frames_sent_at_once_to_one_destination_do_not_interleave(closing):
    (a, a_inbox, _), (b, b_inbox, _) = small_link_pair(closing, 8)
    to = b.endpoint.endpoint.sock.getsockname()
    rng = random.Random(5)
    # 2,000 datagrams of 8 bytes: within the receiving socket's buffer even when the machine is
    # too busy to read them meanwhile (4,000 overflowed it, and the kernel's drops are not ours)
    batches = [[frame_of(i, 200, rng) for i in range(20)] for _ in range(4)]
    threads = [threading.Thread(target=lambda batch=batch: [a.send(f, a_inbox.sender(TOPIC), to)
                                                            for f in batch])
               for batch in batches]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert b_inbox.wait(lambda: len(b_inbox.frames) >= 80), b_inbox.drops
    assert sorted(b_inbox.payloads()) == sorted(f for batch in batches for f in batch)
    assert b_inbox.drops == []


def test_a_lost_small_frame_drops_its_frame_only_and_counts_it_against_the_topic(closing):
    # the third frame's pieces are datagrams 100-149 of 8 bytes: lose one in its middle
    (a, a_inbox, _), (b, b_inbox, _) = small_link_pair(closing, 8, lose=120)
    to = b.endpoint.endpoint.sock.getsockname()
    rng = random.Random(6)
    frames = [frame_of(i, 5 + 49 * 7, rng) for i in range(5)]  # 5 bytes in the first piece
    assert all(len(compact_fragment(f, 8, 0)) == 50 for f in frames)
    for frame in frames:
        a.send(frame, a_inbox.sender(TOPIC), to)
    assert b_inbox.wait(lambda: len(b_inbox.frames) >= 4 and b_inbox.drops)
    assert b_inbox.payloads() == frames[:2] + frames[3:]
    assert b_inbox.drops == [(TOPIC, "fragment_lost")]


# --- stream links --------------------------------------------------------------------------------

@pytest.fixture(params=["tcp", "bt"])
def tcp_connections(request, closing, tmp_path_factory):
    """Make connected (client, server) stream connection pairs: TCP on 127.0.0.1, and the bt
    transport's own stream path over its AF_UNIX stand-in for a radio."""
    if request.param == "tcp":
        transport, address = TcpTransport({}), ("127.0.0.1", 0)
    else:
        transport = BluetoothTransport({"emulate_dir": str(tmp_path_factory.mktemp("bt"))})
        address = ("AA:BB:CC:DD:EE:01", 3)
    listener = closing(transport.listen(address))
    if request.param == "tcp":
        address = listener.sock.getsockname()

    def connect():
        client = transport.connect(address, 2.0)
        accepted = listener.accept(2.0)
        assert accepted is not None
        return client, accepted[0]

    return connect


def stream_link(connection, name: str, inbox: Inbox, **kwargs) -> StreamLink:
    peer = connection.sock.getpeername()[:2]
    return StreamLink(connection, name, peer, inbox.on_frame, inbox.on_lost, inbox.on_close,
                      **kwargs)


@pytest.fixture
def tcp_pair(closing, tcp_connections):
    client, server = tcp_connections()
    ends = []
    for connection, name in ((client, "client"), (server, "server")):
        inbox = Inbox()
        ends.append((closing(stream_link(connection, name, inbox)), inbox))
    return ends


def test_stream_frames_of_every_size_arrive_byte_exact_and_in_order(tcp_pair):
    (a, a_inbox), (b, b_inbox) = tcp_pair
    rng = random.Random(3)
    frames = [b"\x01", b"", frame_of(1, 10_000, rng), frame_of(2, 200_000, rng),
              frame_of(3, 5_000_000, rng)]
    frames += [frame_of(4 + i, rng.randint(1, 3000), rng) for i in range(200)]
    for frame in frames:
        assert a.send(frame, a_inbox.sender(TOPIC)) is True
    assert b_inbox.wait(lambda: len(b_inbox.frames) >= len(frames), 20), len(b_inbox.frames)
    assert b_inbox.payloads() == frames
    assert all(link is b and source == b.peer for _, link, source in b_inbox.frames)
    assert a_inbox.drops == [] and b_inbox.drops == []


def test_stream_frames_both_ways_at_once(tcp_pair):
    (a, a_inbox), (b, b_inbox) = tcp_pair
    rng = random.Random(4)
    there = [frame_of(i, rng.randint(1, 100_000), rng) for i in range(50)]
    back = [frame_of(i, rng.randint(1, 100_000), rng) for i in range(50)]
    for x, y in zip(there, back, strict=True):
        a.send(x, a_inbox.sender(TOPIC))
        b.send(y, b_inbox.sender(TOPIC))
    assert (b_inbox.wait(lambda: len(b_inbox.frames) >= 50)
            and a_inbox.wait(lambda: len(a_inbox.frames) >= 50))
    assert b_inbox.payloads() == there and a_inbox.payloads() == back


def blocked_writer(closing, tcp_connections, **kwargs) -> tuple[StreamLink, Inbox]:
    """A StreamLink whose writer thread is stuck sending 8 MB to a far end that never reads."""
    client, far_end = tcp_connections()
    closing(far_end)  # never read from
    # small kernel buffers: a few kB fill them
    client.sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4096)
    far_end.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    inbox = Inbox()
    link = closing(stream_link(client, "stuck", inbox, **kwargs))
    assert link.send(bytes(8_000_000), inbox.sender(1)) is True
    # the writer has taken it off the queue (and cannot finish writing it)
    assert settles(lambda: not link.queued(), 5), "the writer never took the frame"
    return link, inbox


def test_a_full_queue_counts_queue_full(closing, tcp_connections):
    link, inbox = blocked_writer(closing, tcp_connections, queue_frames=2)
    assert [link.send(b"small", inbox.sender(2)) for _ in range(6)] == [True, True, False, False,
                                                                         False, False]
    assert inbox.drops == [(2, "queue_full")] * 4
    assert not link.closed.is_set()


def test_a_queue_over_its_byte_bound_counts_queue_full(closing, tcp_connections):
    link, inbox = blocked_writer(closing, tcp_connections, queue_bytes=8_000_004)
    # 4,000,004 bytes with its length prefix
    assert link.send(bytes(4_000_000), inbox.sender(3)) is True
    assert link.send(bytes(3_999_996), inbox.sender(3)) is True   # exactly at the bound
    assert link.send(b"x", inbox.sender(4)) is False
    assert inbox.drops == [(4, "queue_full")]


def test_frames_still_queued_at_close_are_counted_as_link_down(closing, tcp_connections):
    link, inbox = blocked_writer(closing, tcp_connections, queue_frames=10)
    assert [link.send(b"waiting", inbox.sender(5)) for _ in range(3)] == [True, True, True]
    link.close()
    assert inbox.drops.count((5, "link_down")) == 3


def test_closing_one_end_fires_on_close_on_the_other(tcp_pair):
    (a, a_inbox), (b, b_inbox) = tcp_pair
    a.close()
    assert b_inbox.wait(lambda: b_inbox.closed, 5.0), "the far end never noticed"
    assert b_inbox.closed == [b] and a_inbox.closed == [a]
    assert b.closed.is_set()
    # a closed link refuses frames and counts them
    assert b.send(b"late", b_inbox.sender(7)) is False
    assert b_inbox.drops == [(7, "link_down")]


def test_close_is_idempotent_and_fires_on_close_once(tcp_pair):
    (a, a_inbox), (b, b_inbox) = tcp_pair
    a.close()
    a.close()
    assert b_inbox.wait(lambda: b_inbox.closed, 5.0)
    b.close()
    assert a_inbox.closed == [a] and b_inbox.closed == [b]


def test_a_corrupt_length_is_counted_and_closes_the_link(closing, tcp_connections):
    client, raw = tcp_connections()
    closing(raw)
    inbox = Inbox()
    link = closing(stream_link(client, "victim", inbox, max_message=1000))
    raw.send(length_prefixed(b"fine") + LENGTH.pack(1001) + b"x" * 1001)
    assert inbox.wait(lambda: inbox.closed, 5.0)
    assert inbox.payloads() == [b"fine"]
    assert inbox.drops == [(None, "bad_length")]
    assert link.closed.is_set()
    assert raw.receive(100, 2.0) == b""  # and the connection is gone


def test_a_frame_split_across_many_writes_arrives_whole(closing, tcp_connections):
    client, raw = tcp_connections()
    closing(raw)
    inbox = Inbox()
    closing(stream_link(client, "slow", inbox))
    record = length_prefixed(b"in pieces") + length_prefixed(b"")
    for i in range(len(record)):
        raw.send(record[i:i + 1])
    assert inbox.wait(lambda: len(inbox.frames) >= 2)
    assert inbox.payloads() == [b"in pieces", b""]
    assert inbox.drops == []


class Writes:
    """A stream connection wrapper that records who writes, and can take only part of a write
    without waiting."""

    def __init__(self, connection, take: int | None = None):
        self.connection = connection
        self.sock = connection.sock
        self.take = take  # send_nowait writes at most this much
        self.calls: list[tuple[str, str, int]] = []

    def send_nowait(self, data: bytes) -> int:
        part = data if self.take is None else data[:self.take]
        self.calls.append(("nowait", threading.current_thread().name, len(part)))
        return self.connection.send_nowait(part)

    def send(self, data: bytes) -> None:
        self.calls.append(("send", threading.current_thread().name, len(data)))
        self.connection.send(data)

    def receive_into(self, buffer, timeout):
        return self.connection.receive_into(buffer, timeout)

    def close(self) -> None:
        self.connection.close()


def test_a_large_stream_frame_is_the_handlers_to_cut(closing, tcp_connections):
    """Read into place, a large frame is a bytearray nobody else holds: a route cuts its header
    off in place (del frame[:28]) before handing it to rclpy."""
    client, server = tcp_connections()
    inbox = Inbox()

    def on_frame(frame, link, source) -> None:
        if type(frame) is bytearray:
            del frame[:envelope.SIZE]
        inbox.on_frame(bytes(frame), link, source)

    closing(StreamLink(server, "far", ("client", 0), on_frame, inbox.on_lost))
    link = closing(stream_link(client, "near", Inbox()))
    frames = [frame_of(i, size, random.Random(i)) for i, size in enumerate([1_000_000, 300_000])]
    assert link.send_all(frames, Inbox().sender(TOPIC)) == 2
    assert inbox.wait(lambda: len(inbox.frames) >= 2), inbox.drops
    assert inbox.payloads() == [frame[envelope.SIZE:] for frame in frames]


def test_a_stream_frame_alone_is_written_from_the_callers_thread(closing, tcp_connections):
    client, server = tcp_connections()
    writes = Writes(client)
    inbox = Inbox()
    link = closing(stream_link(writes, "near", Inbox()))
    closing(stream_link(server, "far", inbox))
    frame = frame_of(1, 2500, random.Random(60))
    assert link.send(frame, inbox.sender(TOPIC)) is True
    assert inbox.wait(lambda: inbox.frames)
    assert inbox.payloads() == [frame]
    assert writes.calls == [("nowait", threading.current_thread().name, 2504)]


def test_what_a_write_without_waiting_left_goes_first_from_the_writer(closing, tcp_connections):
    client, server = tcp_connections()
    writes = Writes(client, take=1000)
    inbox = Inbox()
    link = closing(stream_link(writes, "near", Inbox()))
    closing(stream_link(server, "far", inbox))
    rng = random.Random(61)
    frames = [frame_of(i, 700, rng) for i in range(3)]  # 3 x 704 bytes, 1000 written at once
    assert link.send_all(frames, inbox.sender(TOPIC)) == 3
    later = [frame_of(3 + i, 300, rng) for i in range(3)]
    for frame in later:
        link.send(frame, inbox.sender(TOPIC))
    assert inbox.wait(lambda: len(inbox.frames) >= 6), inbox.drops
    assert inbox.payloads() == frames + later  # the stream was never interleaved
    assert writes.calls[0] == ("nowait", threading.current_thread().name, 1000)
    assert {name for kind, name, _ in writes.calls[1:] if kind == "send"} == {"tx-near"}


# --- a slot for a link that comes and goes -------------------------------------------------------

def test_a_slot_holds_reliable_frames_while_down_and_sends_them_first_in_order(closing,
                                                                               tcp_connections):
    drops = Inbox()
    slot = closing(LinkSlot("slot", QueueLimits(frames=3, bytes=1000)))
    reliable, best_effort = drops.sender(1, reliable=True), drops.sender(2)
    assert [slot.send(f"r{i}".encode(), reliable) for i in range(5)] == [True] * 5
    assert slot.send(b"best effort", best_effort) is False
    # oldest first out: r0 and r1 over the 3-frame bound; the best-effort frame was never held
    assert drops.drops == [(1, "queue_full"), (1, "queue_full"), (2, "link_down")]
    assert slot.waiting == 3
    client, server = tcp_connections()
    inbox = Inbox()
    closing(stream_link(server, "far", inbox))
    slot.attach(closing(stream_link(client, "near", Inbox())))
    assert slot.send(b"after", best_effort) is True
    assert inbox.wait(lambda: len(inbox.frames) >= 4)
    assert inbox.payloads() == [b"r2", b"r3", b"r4", b"after"]
    assert slot.waiting == 0


def test_a_slot_bounds_bytes_and_discards_on_request():
    drops = Inbox()
    slot = LinkSlot("slot", QueueLimits(frames=100, bytes=10))
    held = drops.sender(7, reliable=True)
    slot.send(b"123456", held)
    slot.send(b"7890", held)   # exactly 10 bytes held
    assert drops.drops == []
    slot.send(b"x", held)      # 11: the oldest goes
    assert drops.drops == [(7, "queue_full")] and slot.waiting == 2
    slot.discard("session_reset")
    assert drops.drops[1:] == [(7, "session_reset")] * 2 and slot.waiting == 0
    slot.close()
    assert slot.send(b"late", held) is False and drops.drops[-1] == (7, "link_down")
