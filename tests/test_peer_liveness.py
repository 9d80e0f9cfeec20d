"""A peer that goes away mid-goal: the goal ends ABORTED on the calling side within seconds,
not when its result's timeout (an hour) runs out. rclpy's ActionServer behind a ``rosgate run``
process that is killed (SIGKILL: no goodbye), rclpy's ActionClient behind a bridge in this
process; with and without identities (a handshake line, or only what the peer sends)."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from conftest import Bridge, free_port, wait_until
from test_actions import Goal, settled, warmed_up
from test_msgs.action import Fibonacci
from test_sessions_peer import identities

from rosgate.roles.peer import silent_for

HEARTBEAT, PEER_TIMEOUT = 0.5, 1.5


def files(tmp_path: Path, secure: bool) -> tuple[str, str]:
    """The calling peer's file (a) and the serving one's (b)."""
    port, handshake = free_port(), free_port()
    keys = identities(tmp_path, a_initiates=True)
    bridges = {}
    for name, other, direction in (("a", "b", "transmit"), ("b", "a", "receive")):
        extra = f"heartbeat: {HEARTBEAT}, peer_timeout: {PEER_TIMEOUT}"
        if secure:
            extra += (f", identity: {keys[name][0]}, peer_key: {keys[other][1]}, "
                      f"handshake_port: {handshake}")
        bridges[name] = f"""
bridge: {{name: {name}, role: peer, peer: 127.0.0.1, listen: 127.0.0.1, {extra}}}
actions: [{{action: /fib, type: test_msgs/action/Fibonacci, direction: {direction},
            port: {port}}}]
"""
    return bridges["a"], bridges["b"]


@pytest.mark.parametrize("secure", [False, True], ids=["open", "identities"])
def test_a_goal_ends_aborted_soon_after_the_serving_peer_dies(
        tmp_path, engines, domain, action_side, logs, secure):
    from action_msgs.msg import GoalStatus

    da, db = domain(), domain()
    calling, serving = files(tmp_path, secure)
    (tmp_path / "b.yaml").write_text(serving)
    far = Bridge(tmp_path / "b.yaml", db)
    try:
        a = engines(calling, da)
        server = action_side(db, "b").fibonacci_server("/fib")
        client = warmed_up(action_side(da, "a").client(Fibonacci, "/fib"),
                           Fibonacci.Goal(order=1), timeout=30)
        goal = Goal(client, Fibonacci.Goal(order=400))  # 20 s of work
        assert goal.handle.accepted and goal.wait_feedback(3, 10)
        pending = goal.handle.get_result_async()
    finally:
        far.proc.kill()  # the serving bridge dies, mid-goal
        far.proc.wait(10)
    killed = time.monotonic()
    answer = settled(pending, 20)
    took = time.monotonic() - killed
    assert answer.status == GoalStatus.STATUS_ABORTED
    # the handshake line breaks at once; an open peer is lost after its silence
    bound = 2.0 if secure else silent_for(PEER_TIMEOUT) + 2 * HEARTBEAT + 2.0
    assert took < bound, took
    result = next(r for r in a.routes() if r.label.startswith("/fib/_action/get_result"))
    assert result.counters.drops["link_down"] >= 1
    if not secure:
        assert logs.wait("taken for lost", 1, 5)
        assert wait_until(lambda: a.role.lost)
    del server


def test_a_quiet_goal_on_a_live_open_peer_is_not_taken_for_a_lost_peer(
        tmp_path, engines, domain, action_side, logs):
    """No feedback for longer than the silence that loses a peer: the far side's announcements
    keep it alive, and the goal succeeds."""
    from action_msgs.msg import GoalStatus
    from rclpy.action import ActionServer

    da, db = domain(), domain()
    calling, serving = files(tmp_path, secure=False)
    engines(serving, db)
    a = engines(calling, da)
    quiet = silent_for(PEER_TIMEOUT) + 3 * HEARTBEAT

    def execute(goal_handle):
        if goal_handle.request.order > 1:
            side.stopping.wait(quiet)  # the action's work: long, and without a word
        goal_handle.succeed()
        return Fibonacci.Result(sequence=[goal_handle.request.order])

    side = action_side(db, "b")
    server = ActionServer(side.node, Fibonacci, "/fib", execute)
    client = warmed_up(action_side(da, "a").client(Fibonacci, "/fib"), Fibonacci.Goal(order=1),
                       timeout=30)
    goal = Goal(client, Fibonacci.Goal(order=2))
    assert goal.handle.accepted
    answer = goal.result(timeout=quiet + 10)
    assert answer.status == GoalStatus.STATUS_SUCCEEDED and list(answer.result.sequence) == [2]
    assert not a.role.lost and logs.having("taken for lost") == []
    del server


def test_an_open_peer_is_lost_after_two_and_a_half_announcement_periods():
    from rosgate.announce import ANNOUNCE_EVERY

    assert silent_for(1.0) == 2.5 * ANNOUNCE_EVERY
    assert silent_for(60.0) == 60.0  # a longer peer_timeout wins
