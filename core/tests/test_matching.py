"""The hold in front of a publisher the bridge makes (rosgate.matching): what comes before the
publisher has matched its subscribers is published after, in order; the hold is bounded in
count (the oldest out, counted) and in time; a replacement publisher takes the backlog first.
The end-to-end tests (tests/test_publisher_appears.py) prove it against real subscribers."""

from __future__ import annotations

import threading
import time

from polling import settles

from rosgate import matching
from rosgate.matching import PublishGate


class Sink:
    """Where a gate publishes, and what it reports."""

    def __init__(self) -> None:
        self.published: list[int] = []
        self.lost: list[tuple[str, int]] = []
        self.direct: list[object] = []
        self.matched = threading.Event()

    def gate(self) -> PublishGate:
        return PublishGate(self.published.append, self.matched.is_set,
                           lambda why, n: self.lost.append((why, n)),
                           lambda exc: self.lost.append((repr(exc), 1)), self.direct.append)


def test_held_until_matched_then_published_in_order_then_straight_through():
    sink = Sink()
    gate = sink.gate()
    for n in range(5):
        gate(n)
    time.sleep(3 * matching.LOOK_EVERY)  # the gate looks, and must still hold
    assert sink.published == [] and not gate.open
    sink.matched.set()
    assert settles(lambda: gate.open, 5)
    assert sink.published == [0, 1, 2, 3, 4]
    assert sink.direct == [sink.published.append]  # the route publishes without the gate now
    gate(5)
    assert sink.published == [0, 1, 2, 3, 4, 5] and sink.lost == []


def test_the_hold_is_bounded_in_count_and_the_oldest_go_counted(monkeypatch):
    monkeypatch.setattr(matching, "HOLD_COUNT", 3)
    sink = Sink()
    gate = sink.gate()
    for n in range(5):
        gate(n)
    assert sink.lost == [("full", 1), ("full", 1)]
    sink.matched.set()
    assert settles(lambda: gate.open, 5)
    assert sink.published == [2, 3, 4]


def test_the_hold_is_bounded_in_time_matched_or_not(monkeypatch):
    monkeypatch.setattr(matching, "HOLD_FOR", 0.2)
    sink = Sink()
    gate = sink.gate()
    gate(1)
    assert settles(lambda: gate.open, 5)  # nobody matched: published all the same
    assert sink.published == [1]


def test_a_new_publisher_takes_the_backlog_first_and_what_still_comes_to_the_old():
    old_sink, new_sink = Sink(), Sink()
    old, new = old_sink.gate(), new_sink.gate()
    old(1)
    old(2)
    new(3)
    old.hand_over(new)
    old(4)  # a frame that found the old gate still in the route
    new(5)
    new_sink.matched.set()
    assert settles(lambda: new.open, 5)
    assert new_sink.published == [1, 2, 3, 4, 5] and old_sink.published == []


def test_a_route_that_ends_while_it_holds_counts_what_it_held():
    sink = Sink()
    gate = sink.gate()
    gate(1)
    gate(2)
    gate.close()
    assert sink.lost == [("closed", 2)]
    sink.matched.set()
    time.sleep(3 * matching.LOOK_EVERY)
    assert sink.published == []


def test_a_reliable_release_waits_for_acknowledgements_after_each_history_worth():
    sink, paced = Sink(), []
    gate = PublishGate(sink.published.append, sink.matched.is_set,
                       lambda why, n: sink.lost.append((why, n)),
                       lambda exc: sink.lost.append((repr(exc), 1)), sink.direct.append,
                       pace=lambda: paced.append(len(sink.published)), every=10)
    for n in range(25):
        gate(n)
    sink.matched.set()
    assert settles(lambda: gate.open, 5)
    assert sink.published == list(range(25)) and paced == [10, 20]


def test_nobody_to_wait_for_opens_at_once():
    sink = Sink()
    gate = PublishGate(sink.published.append, lambda: None, lambda why, n: None,
                       lambda exc: None, sink.direct.append)
    gate(1)
    assert settles(lambda: gate.open, 1)
    assert sink.published == [1]
