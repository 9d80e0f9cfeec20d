"""The echo guard: each message a bridge published is taken back once, within its wait, and
nothing else is."""

from __future__ import annotations

from rosgate.echo import EchoGuard


def test_each_publication_is_taken_back_once_and_only_within_the_wait() -> None:
    now = [0.0]
    guard = EchoGuard(wait=5.0, clock=lambda: now[0])
    guard.publishing(b"same")
    guard.publishing(b"same")
    assert [guard.returned(b"same") for _ in range(3)] == [True, True, False]
    assert not guard.returned(b"other")  # a user's message of other bytes always goes
    guard.publishing(b"late")
    now[0] = 5.1
    assert not guard.returned(b"late")  # its echo never came: forgotten, not held against one
    guard.publishing(b"x")
    now[0] = 6.0
    guard.publishing(b"x")
    assert guard.returned(b"x")  # the first one's echo
    now[0] = 10.5  # past the first one's wait: the one taken back goes, the second still waits
    assert guard.returned(b"x") and not guard.returned(b"x")


def test_a_message_object_is_judged_by_its_cdr() -> None:
    from rclpy.serialization import serialize_message
    from std_msgs.msg import String

    guard = EchoGuard()
    guard.publishing(String(data="hi"))
    assert guard.returned(serialize_message(String(data="hi")))
