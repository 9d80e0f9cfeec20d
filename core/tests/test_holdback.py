"""The holdback on its own: what waits, what goes out at once, what is sent again, and what is
counted, with routes that record what they are asked to do."""

from __future__ import annotations

import time
from collections import Counter

from rosgate.drops import Drop
from rosgate.holdback import Held, Holdback


class Route:
    def __init__(self, label: str, max_wait_ns: int = 0, hold: Holdback | None = None):
        self.label = label
        self.max_wait_ns = max_wait_ns
        self.drops: Counter = Counter()
        self.sent: list[bytes] = []
        self.hold = hold  # a link that fails while the held go out

    def drop(self, reason, detail: str = "") -> None:
        self.drops[reason] += 1

    def send_again(self, held: list[Held], again: bool) -> None:
        assert all(h.sent == again for h in held)
        self.sent += [h.payload for h in held]
        if self.hold is not None:
            self.hold.fail()


def messages(*names: str, stamp: int | None = None) -> list[tuple[bytes, int, int]]:
    return [(name.encode(), 0, time.time_ns() if stamp is None else stamp) for name in names]


def test_while_up_everything_goes_out_and_nothing_waits():
    hold, route = Holdback(10, 1000), Route("/a")
    assert hold.take(route, messages("m0"), reliable=True, datagram=False)
    assert hold.waiting == 0


def test_a_stream_links_reliable_messages_wait_and_go_first_in_order():
    hold, a, b = Holdback(10, 1000), Route("/a"), Route("/b")
    hold.fail()
    assert not hold.take(a, messages("a0", "a1"), reliable=True, datagram=False)
    assert not hold.take(b, messages("b0"), reliable=True, datagram=False)
    assert not hold.take(a, messages("a2"), reliable=True, datagram=False)
    assert hold.waiting == 4 and (hold.depth(a), hold.depth(b)) == (3, 1)
    hold.resume(new_session=False)
    assert (a.sent, b.sent) == ([b"a0", b"a1", b"a2"], [b"b0"])
    assert not hold.down and hold.waiting == 0
    assert hold.take(a, messages("a3"), reliable=True, datagram=False)  # up: sent as usual


def test_datagram_copies_are_forgotten_by_the_same_session_and_sent_again_to_a_new_one():
    for new_session, again in ((False, []), (True, [b"m0", b"m1"])):
        hold, route = Holdback(10, 1000), Route("/a")
        hold.fail()
        assert hold.take(route, messages("m0", "m1"), reliable=True, datagram=True)  # sent too
        hold.resume(new_session)
        assert route.sent == again and route.drops == {}


def test_after_bye_or_during_a_handshake_nothing_reliable_goes_out():
    for stop in (Holdback.leave, Holdback.handshake):
        hold, route = Holdback(10, 1000), Route("/a")
        stop(hold)
        hold.fail()  # the line then closes: still nothing goes out
        assert not hold.take(route, messages("m0"), reliable=True, datagram=True)
        hold.resume(new_session=False)
        assert route.sent == [b"m0"]


def test_best_effort_never_waits_and_is_counted_where_it_was_lost():
    hold, route = Holdback(10, 1000), Route("/a")
    hold.fail()
    assert hold.take(route, messages("f0", "f1"), reliable=False, datagram=True)  # sent
    assert hold.take(route, messages("f2"), reliable=False, datagram=False)  # the link counts
    assert hold.waiting == 0 and route.drops == {}
    hold.resume(new_session=True)  # the server restarted: the two sent were lost
    assert route.drops == {Drop.LINK_DOWN: 2} and route.sent == []
    hold.leave()
    assert not hold.take(route, messages("f3"), reliable=False, datagram=True)
    assert route.drops == {Drop.LINK_DOWN: 3}


def test_the_bounds_drop_the_oldest_counted_and_copies_past_them_count_if_lost():
    hold, route = Holdback(3, 1000), Route("/a")
    hold.leave()
    assert not hold.take(route, messages(*(f"m{i}" for i in range(5))), True, False)
    assert route.drops == {Drop.QUEUE_FULL: 2} and hold.waiting == 3
    hold.resume(new_session=True)
    assert route.sent == [b"m2", b"m3", b"m4"]
    small, other = Holdback(10, 6), Route("/b")  # bytes: two of three bytes each
    small.fail()
    small.take(other, messages("c00", "c01", "c02"), reliable=True, datagram=True)
    assert other.drops == {} and small.waiting == 2  # the oldest copy went out already
    small.resume(new_session=True)
    assert other.drops == {Drop.LINK_DOWN: 1} and other.sent == [b"c01", b"c02"]


def test_a_message_older_than_its_max_delay_is_too_late():
    hold, route = Holdback(10, 1000), Route("/a", max_wait_ns=int(1e9))
    hold.leave()
    hold.take(route, messages("old", stamp=time.time_ns() - int(2e9)) + messages("new"),
              reliable=True, datagram=False)
    hold.resume(new_session=False)
    assert route.sent == [b"new"] and route.drops == {Drop.TOO_LATE: 1}


def test_a_main_line_lost_while_the_held_go_out_keeps_them_waiting_after():
    hold = Holdback(10, 1000)
    route = Route("/a", hold=hold)
    hold.leave()
    hold.take(route, messages("m0"), reliable=True, datagram=False)
    hold.resume(new_session=False)  # its send fails the line, on this thread
    assert hold.down
    assert not hold.take(route, messages("m1"), reliable=True, datagram=False)


def test_what_waits_at_the_stop_is_counted_and_a_gone_route_is_forgotten():
    hold, a, b = Holdback(10, 1000), Route("/a"), Route("/b")
    hold.fail()
    hold.take(a, messages("a0"), reliable=True, datagram=False)
    hold.take(a, messages("a1"), reliable=True, datagram=True)  # a copy went out
    hold.take(b, messages("b0"), reliable=True, datagram=False)
    hold.forget(b)
    hold.close()
    assert a.drops == {Drop.LINK_DOWN: 1} and b.drops == {}
