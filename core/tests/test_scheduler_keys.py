"""The scheduler reads a sender's queue key (topic id, class) once and remembers it, boundedly:
senders of one message each (service calls) do not grow it, and a forgotten sender's key goes
with its queue."""

from __future__ import annotations

from rosgate.scheduler import CONTROL, KEYS_KEPT, Outgoing, Scheduler
from rosgate.spec import Delivery


class Sender:
    def __init__(self, topic_id: int, priority: int = 5):
        self.topic_id = topic_id
        self.delivery = Delivery(reliable=True, priority=priority)
        self.dropped: list[str] = []

    def drop(self, reason: str, detail: str = "") -> None:
        self.dropped.append(reason)


def message(sender: Sender) -> Outgoing:
    return Outgoing(sender, ("127.0.0.1", 9), 10, lambda: [b"x" * 10], 0.0)


def test_each_sender_keeps_its_own_queue_and_class():
    scheduler = Scheduler(clock=lambda: 0.0)
    data, control = Sender(1), Sender(1, priority=CONTROL)  # a route and its announcer
    for _ in range(3):
        assert scheduler.put(message(data))
    assert scheduler.put(message(control))
    assert scheduler.depth(data) == 3 and scheduler.depth(control) == 1
    due = scheduler.next(0.0)
    assert due is not None and not isinstance(due, float) and due.sender is control
    scheduler.forget(data)
    assert id(data) not in scheduler._keys  # its key went with its queue
    assert scheduler.depth(data) == 0 and scheduler.waiting == 0


def test_senders_of_one_message_each_do_not_grow_what_is_remembered():
    scheduler = Scheduler(clock=lambda: 0.0)
    senders = [Sender(7) for _ in range(KEYS_KEPT + 10)]
    for sender in senders:
        assert scheduler.put(message(sender))
    assert len(scheduler._keys) <= KEYS_KEPT
    assert scheduler.depth(senders[0]) == len(senders)  # one topic: one queue, whoever sent
    assert scheduler.waiting == len(senders)
