"""The parts a roaming client relies on, one by one: a server's datagram ports take strangers'
datagrams on probation within a rate, a replay window says what it took, and a link slot writes
again what a dead connection carried and the far side did not take (tests/test_roaming.py runs
them together across network namespaces)."""

from __future__ import annotations

import errno
import threading

from polling import settles
from test_links import Inbox, closing, stream_link, tcp_connections  # noqa: F401 (fixtures)

from rosgate.admission import KnownSources
from rosgate.streamlink.slot import LinkSlot, QueueLimits
from rosgate.wire import envelope

TOPIC = 5
HOME, ELSEWHERE = ("10.0.0.1", 4000), ("10.0.0.3", 4000)


def test_strangers_datagrams_are_read_on_probation_within_the_rate():
    now = [100.0]
    sources = KnownSources(strangers=10, clock=lambda: now[0])
    sources.learn(HOME)
    data = envelope.pack(0, TOPIC, 1, 1, 0) + b"body"
    taken = sum(sources.admits(ELSEWHERE, data) for _ in range(50))
    assert taken == 10  # a second's worth at once, then no more
    assert all(sources.admits(HOME, data) for _ in range(50))  # a client it knows: always
    hello = envelope.pack(envelope.FLAG_HELLO, 1, 0, 1, 0) + b"sealed"
    assert sources.admits(ELSEWHERE, hello)  # a hello: always, the server opens it
    now[0] += 0.25  # the rate refills with time
    assert sum(sources.admits(ELSEWHERE, data) for _ in range(50)) == 2
    assert sources.knows(HOME) and not sources.knows(ELSEWHERE)
    nobody = KnownSources()  # no probation: only hellos from strangers
    assert not nobody.admits(ELSEWHERE, data) and nobody.admits(ELSEWHERE, hello)


def test_a_replay_window_says_the_newest_it_took_per_epoch():
    window = envelope.ReplayWindow()
    assert window.newest() == {}
    for epoch, seq in [(1, 1), (1, 2), (1, 5), (1, 3), (2, 1)]:
        assert window.accept(epoch, seq) is None
    assert window.newest() == {1: 5, 2: 1}


def frame(seq: int, flags: int = 0, topic: int = TOPIC) -> bytes:
    return envelope.pack(flags, topic, 1, seq, 0) + b"message %d" % seq


def test_a_slot_writes_again_what_a_dead_connection_carried_and_the_far_side_did_not_take(
        closing, tcp_connections):  # noqa: F811 (test_links's fixtures)
    drops = Inbox()
    slot = closing(LinkSlot("slot", QueueLimits(frames=100, bytes=100_000), resends=True))
    reliable, best_effort = drops.sender(TOPIC, reliable=True), drops.sender(9)
    client, server = tcp_connections()
    first = Inbox()
    closing(stream_link(server, "far", first))
    near = closing(stream_link(client, "near", Inbox()))
    slot.attach(near)
    written = [frame(seq) for seq in range(1, 6)]
    assert slot.send_all(written, reliable) == 5
    announcement = frame(7, envelope.FLAG_ANNOUNCE)
    slot.send(announcement, reliable)
    slot.send(frame(1, topic=9), best_effort)
    assert first.wait(lambda: len(first.frames) >= 7)
    near.fail("its address is gone")
    waited = frame(6)
    assert slot.send(waited, reliable)  # while down: waits
    # the far side says it took up to 2 of epoch 1 (3 to 5 died with the connection's buffers)
    client, server = tcp_connections()
    second = Inbox()
    closing(stream_link(server, "far again", second))
    slot.attach(closing(stream_link(client, "near again", Inbox())), {TOPIC: {1: 2}, 9: {}})
    assert second.wait(lambda: len(second.frames) >= 4)
    # what was not taken first, in order, then what waited; never an announcement, never a
    # best-effort frame, never what was taken
    assert second.payloads() == written[2:] + [waited]
    assert drops.drops == []


def test_a_slot_forgets_what_it_wrote_for_a_new_session(closing, tcp_connections):  # noqa: F811
    drops = Inbox()
    slot = closing(LinkSlot("slot", QueueLimits(frames=3, bytes=100_000), resends=True))
    reliable = drops.sender(TOPIC, reliable=True)
    client, server = tcp_connections()
    first = Inbox()
    closing(stream_link(server, "far", first))
    near = closing(stream_link(client, "near", Inbox()))
    slot.attach(near)
    slot.send_all([frame(seq) for seq in range(1, 6)], reliable)
    assert first.wait(lambda: len(first.frames) >= 5)
    near.fail("gone")
    client, server = tcp_connections()
    second = Inbox()
    closing(stream_link(server, "far again", second))
    # a far side that took nothing of epoch 1: only the last 3 were kept (queue.frames)
    slot.attach(closing(stream_link(client, "near again", Inbox())), {TOPIC: {}})
    assert second.wait(lambda: len(second.frames) >= 3)
    assert second.payloads() == [frame(seq) for seq in (3, 4, 5)]
    slot.current.fail("gone again")
    slot.forget_written()  # a new session: nothing of the old one goes again
    client, server = tcp_connections()
    third = Inbox()
    closing(stream_link(server, "far at last", third))
    slot.attach(closing(stream_link(client, "near at last", Inbox())), {TOPIC: {}})
    slot.send(frame(9), reliable)
    assert third.wait(lambda: len(third.frames) >= 1)
    assert third.payloads() == [frame(9)]


def test_what_a_far_side_says_it_took_is_read_or_ignored_never_a_crash():
    from rosgate.roles.mainline import read_taken

    assert read_taken([[5, [[1, 2], [3, 4]]], [6, []]]) == {5: {1: 2, 3: 4}, 6: {}}
    for said in (None, "x", {"5": []}, [[5, [[1, float("inf")]]]], [[5, [[1, float("nan")]]]],
                 [[5, "ab"]], [[5, {"a": 1}]], [[5, [[1]]]], [[None, []]], [5], [[1, 2, 3]]):
        assert read_taken(said) is None, said


def test_a_connection_whose_address_this_host_still_has_is_not_gone(tcp_connections):  # noqa: F811
    client, server = tcp_connections()
    gone = getattr(client, "address_gone", None)
    if gone is not None:  # TCP's; the radio's stand-in (a Unix socket) has no address to lose
        assert gone() is False and server.address_gone() is False


def test_a_slot_that_does_not_resend_keeps_nothing_it_wrote(closing, tcp_connections):  # noqa: F811
    """A dedicated port's or a peer's slot: no handshake says what the far side took."""
    slot = closing(LinkSlot("slot", QueueLimits(frames=100, bytes=100_000)))
    client, server = tcp_connections()
    first = Inbox()
    closing(stream_link(server, "far", first))
    near = closing(stream_link(client, "near", Inbox()))
    slot.attach(near)
    slot.send_all([frame(seq) for seq in range(1, 4)], Inbox().sender(TOPIC, reliable=True))
    assert first.wait(lambda: len(first.frames) >= 3)
    near.fail("gone")
    client, server = tcp_connections()
    second = Inbox()
    closing(stream_link(server, "far again", second))
    slot.attach(closing(stream_link(client, "near again", Inbox())), {TOPIC: {}})
    slot.send(frame(9), Inbox().sender(TOPIC, reliable=True))
    assert second.wait(lambda: len(second.frames) >= 1)
    assert second.payloads() == [frame(9)]


class NoRoute:
    """A real UDP endpoint whose sends fail (no route to the far side) while ``down``: a host
    between its old address and its new one."""

    def __init__(self, endpoint) -> None:
        self.endpoint = endpoint
        self.down = threading.Event()
        self.refused = 0

    def send(self, frame: bytes, to) -> None:
        if self.down.is_set():
            self.refused += 1
            raise OSError(errno.ENETUNREACH, "Network is unreachable")
        self.endpoint.send(frame, to)

    def receive(self, timeout: float):
        return self.endpoint.receive(timeout)

    def close(self) -> None:
        self.endpoint.close()


def test_a_message_the_system_would_not_send_is_repaired_once_there_is_a_route(closing):  # noqa: F811
    """``recovery: retransmit``: what could not leave while the host had no address is sent
    again once it has one (before: counted ``send_error`` and never sent)."""
    from rosgate_transport_udp import UdpTransport
    from test_links_real import Receiver, Topic, frame

    from rosgate.links.datagram import DatagramLink

    transport = UdpTransport({})
    rx = Receiver()
    far = transport.bind(("127.0.0.1", 0))
    closing(DatagramLink(transport, far, "far", rx.on_frame, rx.on_lost))
    near = NoRoute(transport.bind(("127.0.0.1", 0)))
    link = closing(DatagramLink(transport, near, "near", Receiver().on_frame,
                                Receiver().on_lost))
    topic = Topic(TOPIC, recovery="retransmit")
    frames = [frame(TOPIC, seq, 300) for seq in range(1, 6)]
    near.down.set()
    for f in frames:
        link.send(f, topic, far.sock.getsockname())
    assert settles(lambda: near.refused >= 5), near.refused
    near.down.clear()
    assert rx.wait(lambda: len(rx.frames) >= 5, 10), (rx.frames, topic.drops)
    assert sorted(rx.frames) == sorted(frames) and topic.drops == []
