"""ROS 2 actions over zenoh: real ``rosgate router`` and ``rosgate run`` processes on loopback,
rclpy's own ActionServer in one DDS domain and its ActionClient in another, so goals, feedback,
cancels and results can only cross through the bus."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from test_actions import (
    Goal,
    check_a_goal_crosses,
    fibonacci,
    ready,
    settled,
    warmed_up,
)
from test_msgs.action import Fibonacci
from test_zenoh_fleet import Router, zenoh_plugin


@pytest.fixture
def router():
    r = Router()
    yield r
    r.stop()


def action_file(tmp: Path, name: str, router: Router, direction: str, timeout: float = 5) -> Path:
    """A bridge on the bus with the actions /fib and /nested (``direction``), both keyed under
    ``fleet/``, so the two bridges meet on the same keys."""
    path = tmp / f"{name}.yaml"
    path.write_text(f"""\
bridge: {{name: {name}, role: peer, defaults: {{transport: zenoh}}}}
{zenoh_plugin(router)}actions:
  - {{action: /fib, type: test_msgs/action/Fibonacci, direction: {direction},
      remote: fleet/fib, timeout: {timeout}}}
  - {{action: /nested, type: test_msgs/action/NestedMessage, direction: {direction},
      remote: fleet/nested}}
""")
    return path


@pytest.mark.parametrize("caller", ["robot", "base"])
def test_goals_feedback_cancels_and_results_cross_zenoh(tmp_path, router, bridge, domain,
                                                        action_side, caller):
    """Either bridge may be the one whose goals are served on the other: the caller's file says
    transmit, the other's receive."""
    d = {"robot": domain(), "base": domain()}
    server = "base" if caller == "robot" else "robot"
    bridge(action_file(tmp_path, caller, router, "transmit"), d[caller])
    bridge(action_file(tmp_path, server, router, "receive"), d[server])
    check_a_goal_crosses(action_side(d[caller], caller), action_side(d[server], server))


@pytest.mark.parametrize("serving_bridge", [True, False])
def test_a_goal_nobody_serves_over_zenoh_is_rejected_within_its_timeout(
        tmp_path, router, bridge, domain, action_side, serving_bridge):
    """With a bridge on the far side but no ROS action server behind it, and with no bridge on
    the far side at all: the goal is answered "not accepted" within the entry's timeout."""
    d_robot, d_base = domain(), domain()
    robot = bridge(action_file(tmp_path, "robot", router, "transmit", timeout=1), d_robot)
    if serving_bridge:
        bridge(action_file(tmp_path, "base", router, "receive", timeout=1), d_base)
    client = ready(action_side(d_robot, "caller").client(Fibonacci, "/fib"))
    start = time.monotonic()
    goal = Goal(client, Fibonacci.Goal(order=3))
    took = time.monotonic() - start
    assert not goal.handle.accepted
    if serving_bridge:  # the far bridge waited for an action server that never came
        assert 0.7 <= took < 1.0 + 0.3
    else:  # no queryable on the key: zenoh ends the query at once
        assert took < 1.0 + 0.3
        assert robot.wait_log("/fib/_action/send_goal: dropped (no_server)", 5)


def test_a_serving_bridge_that_leaves_mid_goal_ends_the_goal_aborted(
        tmp_path, router, bridge, domain, action_side):
    """The calling side's get_result is a query to the serving bridge's queryable; when that
    bridge stops, zenoh ends the query unanswered and the goal ends aborted."""
    from action_msgs.msg import GoalStatus

    d_robot, d_base = domain(), domain()
    bridge(action_file(tmp_path, "robot", router, "transmit"), d_robot)
    base = bridge(action_file(tmp_path, "base", router, "receive"), d_base)
    keep = action_side(d_base, "base").fibonacci_server("/fib")
    client = warmed_up(action_side(d_robot, "robot").client(Fibonacci, "/fib"),
                       Fibonacci.Goal(order=1))
    goal = Goal(client, Fibonacci.Goal(order=400))
    assert goal.handle.accepted and goal.wait_feedback(3, 10)
    pending = goal.handle.get_result_async()
    start = time.monotonic()
    assert base.stop() == 0  # the serving bridge goes, mid-goal
    answer = settled(pending, 15)
    assert answer.status == GoalStatus.STATUS_ABORTED
    # zenoh ends the query when its queryable goes: not the result's hour (1.8 s measured)
    assert time.monotonic() - start < 10
    del keep


def test_a_base_sends_goals_to_each_robot_by_one_fleet_action(tmp_path, router, bridge, domain,
                                                              action_side):
    """``action: /{robot}/fib`` on the base: each robot's action, found by the robot's
    liveliness token, is offered as /<robot>/fib; its feedback and status come from the
    robot's keys."""
    from action_msgs.msg import GoalStatus

    base_path = tmp_path / "base.yaml"
    base_path.write_text(f"""\
bridge: {{name: base, role: peer, defaults: {{transport: zenoh}}}}
{zenoh_plugin(router)}actions:
  - {{action: "/{{robot}}/fib", type: test_msgs/action/Fibonacci, direction: transmit,
      remote: "fleet/{{robot}}/fib"}}
""")
    d = {"base": domain(), "robot1": domain(), "robot2": domain()}
    bridge(base_path, d["base"])
    keep = []
    for name in ("robot1", "robot2"):
        path = tmp_path / f"{name}.yaml"
        path.write_text(f"""\
bridge: {{name: {name}, role: peer, defaults: {{transport: zenoh}}}}
{zenoh_plugin(router)}actions:
  - {{action: /fib, type: test_msgs/action/Fibonacci, direction: receive,
      remote: fleet/{name}/fib}}
""")
        bridge(path, d[name])
        keep.append(action_side(d[name], name).fibonacci_server("/fib"))
    base = action_side(d["base"], "base")
    for name, order in (("robot1", 20), ("robot2", 16)):
        client = warmed_up(base.client(Fibonacci, f"/{name}/fib"), Fibonacci.Goal(order=1))
        goal = Goal(client, Fibonacci.Goal(order=order))
        assert goal.handle.accepted
        answer = goal.result()
        assert answer.status == GoalStatus.STATUS_SUCCEEDED
        assert list(answer.result.sequence) == fibonacci(order + 1)
        got = [list(f.sequence) for f in goal.feedback]
        assert len(got) >= order * 3 // 4, got
        assert got == [fibonacci(len(s) - 1) for s in got]
    del keep
