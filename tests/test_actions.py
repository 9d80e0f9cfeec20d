"""ROS 2 actions across the link: rclpy's own ActionServer on one side, its ActionClient on
the other, each in its own DDS domain, so goals, feedback, cancels and results can only cross
through the bridges."""

from __future__ import annotations

import re
import threading
import time
from typing import Any

import pytest
from action_sides import ActionSide
from conftest import free_port, wait_until
from test_msgs.action import Fibonacci, NestedMessage


def fibonacci(order: int) -> list[int]:
    sequence = [0, 1]
    while len(sequence) < order + 1:
        sequence.append(sequence[-1] + sequence[-2])
    return sequence


def settled(future: Any, timeout: float) -> Any:
    """What ``future`` (an rclpy future, done on the executor's threads) gave."""
    done = threading.Event()
    future.add_done_callback(lambda _: done.set())
    assert done.wait(timeout), "no answer in time"
    return future.result()


class Goal:
    """One goal from an ActionClient: its feedback as it comes, its handle, its result."""

    def __init__(self, client: Any, goal: Any, timeout: float = 10.0):
        self.feedback: list[Any] = []
        self._more = threading.Condition()
        self.handle = settled(client.send_goal_async(goal, feedback_callback=self._feedback),
                              timeout)

    def _feedback(self, message: Any) -> None:
        with self._more:
            self.feedback.append(message.feedback)
            self._more.notify_all()

    def wait_feedback(self, count: int, timeout: float) -> bool:
        with self._more:
            return self._more.wait_for(lambda: len(self.feedback) >= count, timeout)

    def result(self, timeout: float = 20.0) -> Any:
        return settled(self.handle.get_result_async(), timeout)


def ready(client: Any) -> Any:
    """The client, once the bridge's side of the action is discovered."""
    assert client.wait_for_server(timeout_sec=15), "the bridged action never appeared"
    return client


def warmed_up(client: Any, goal: Any, timeout: float = 20.0) -> Any:
    """The client, once a goal crosses and is accepted: until both bridges are up and the far
    one has discovered the action server, a goal is answered "not accepted" (and its result
    fetched, so the server forgets it)."""
    ready(client)
    deadline = time.monotonic() + timeout
    while not (first := Goal(client, goal)).handle.accepted:
        assert time.monotonic() < deadline, "no goal was ever accepted"
        time.sleep(0.1)  # pacing the retries; each answer is waited on in Goal
    first.result()
    return client


def client_server(engines, domain, direction: str, timeout: float = 5) -> tuple[int, int]:
    """A server, and a client whose file has the action /fib (``direction``) and /nested;
    returned once the server knows where the client's datagrams come from."""
    ds, dc, main = domain(), domain(), free_port()
    server = engines(f"bridge: {{name: base, role: server, server: '127.0.0.1:{main}'}}", ds)
    engines(f"""
bridge: {{name: robot1, role: client, server: '127.0.0.1:{main}'}}
actions:
  - {{action: /fib, type: test_msgs/action/Fibonacci, direction: {direction}, timeout: {timeout}}}
  - {{action: /nested, type: test_msgs/action/NestedMessage, direction: {direction}}}
""", dc)
    assert wait_until(lambda: any(s.addresses for s in server.role.sessions.values()), 15)
    return ds, dc


def peers(engines, domain, timeout: float = 5) -> tuple[int, int]:
    """Two peers: goals sent on a are served on b (udp: a port for calls, the next for
    feedback and status)."""
    da, db = domain(), domain()
    fib, nested = free_port(), free_port()
    for name, direction, domain_id in (("a", "transmit", da), ("b", "receive", db)):
        engines(f"""
bridge: {{name: {name}, role: peer, peer: 127.0.0.1, listen: 127.0.0.1}}
actions:
  - {{action: /fib, type: test_msgs/action/Fibonacci, direction: {direction}, port: {fib},
      timeout: {timeout}}}
  - {{action: /nested, type: test_msgs/action/NestedMessage, direction: {direction},
      port: {nested}}}
""", domain_id)
    return da, db


def check_a_goal_crosses(caller: ActionSide, server: ActionSide) -> None:
    """A 20-step goal: accepted, >= 15 feedbacks in order, the exact result; a cancel after 5
    feedbacks: acknowledged, and the goal ends canceled; nested messages exact."""
    from action_msgs.msg import GoalStatus
    from action_msgs.srv import CancelGoal

    keep = [server.fibonacci_server("/fib"), server.nested_server("/nested")]
    client = warmed_up(caller.client(Fibonacci, "/fib"), Fibonacci.Goal(order=1))
    goal = Goal(client, Fibonacci.Goal(order=20))
    assert goal.handle.accepted
    answer = goal.result()
    assert answer.status == GoalStatus.STATUS_SUCCEEDED
    assert list(answer.result.sequence) == fibonacci(21)
    sequences = [list(f.sequence) for f in goal.feedback]
    assert len(sequences) >= 15, sequences
    assert sequences == [fibonacci(len(s) - 1) for s in sequences]  # each one exact
    assert [len(s) for s in sequences] == sorted({len(s) for s in sequences})  # in order

    goal = Goal(client, Fibonacci.Goal(order=200))
    assert goal.handle.accepted and goal.wait_feedback(5, 10)
    cancel = settled(goal.handle.cancel_goal_async(), 10)
    assert cancel.return_code == CancelGoal.Response.ERROR_NONE
    assert [bytes(g.goal_id.uuid) for g in cancel.goals_canceling] == \
        [bytes(goal.handle.goal_id.uuid)]
    answer = goal.result()
    assert answer.status == GoalStatus.STATUS_CANCELED
    assert len(answer.result.sequence) < 200

    from builtin_interfaces.msg import Time
    from test_msgs.msg import BasicTypes, Builtins

    nested = NestedMessage.Goal(
        nested_field=BasicTypes(bool_value=True, int64_value=-2**63, float64_value=-0.0,
                                uint8_value=255, char_value=7),
        nested_field_no_pkg=Builtins(),
        nested_different_pkg=Time(sec=-5, nanosec=999_999_999))
    nested.nested_field_no_pkg.time_value.sec = 17
    goal = Goal(warmed_up(caller.client(NestedMessage, "/nested"), nested), nested)
    assert goal.handle.accepted
    answer = goal.result()
    assert answer.status == GoalStatus.STATUS_SUCCEEDED
    for got in (answer.result, goal.feedback[0]):
        assert (got.nested_field, got.nested_field_no_pkg, got.nested_different_pkg) == \
            (nested.nested_field, nested.nested_field_no_pkg, nested.nested_different_pkg)
    del keep


@pytest.mark.parametrize("direction", ["transmit", "receive"])
def test_goals_feedback_cancels_and_results_cross_client_server(engines, domain, action_side,
                                                                 direction):
    ds, dc = client_server(engines, domain, direction)
    robot, base = action_side(dc, "robot"), action_side(ds, "base")
    caller, server = (robot, base) if direction == "transmit" else (base, robot)
    check_a_goal_crosses(caller, server)


def test_goals_feedback_cancels_and_results_cross_a_peer_link(engines, domain, action_side):
    da, db = peers(engines, domain)
    check_a_goal_crosses(action_side(da, "a"), action_side(db, "b"))


def test_a_goal_for_an_action_nobody_serves_is_rejected_within_its_timeout(
        engines, domain, action_side):
    """Between peers the proxy is there from the start (client/server: it appears only with a
    real action server on the far side, tests/test_far_graph.py)."""
    calling, _ = peers(engines, domain, timeout=1)
    client = ready(action_side(calling, "caller").client(Fibonacci, "/fib"))
    start = time.monotonic()
    goal = Goal(client, Fibonacci.Goal(order=3))
    assert not goal.handle.accepted
    # the serving bridge waited for an action server that never came, then said so in time
    assert 0.7 <= time.monotonic() - start < 1.0 + 0.3


def test_a_session_lost_mid_goal_ends_the_goal_aborted(engines, domain, action_side):
    from action_msgs.msg import GoalStatus

    ds, dc, main = domain(), domain(), free_port()
    server = engines(f"bridge: {{name: base, role: server, server: '127.0.0.1:{main}'}}", ds)
    engines(f"""
bridge: {{name: robot1, role: client, server: '127.0.0.1:{main}'}}
actions: [{{action: /fib, type: test_msgs/action/Fibonacci, direction: transmit}}]
""", dc)
    robot, base = action_side(dc, "robot"), action_side(ds, "base")
    keep = base.fibonacci_server("/fib")
    goal = Goal(warmed_up(robot.client(Fibonacci, "/fib"), Fibonacci.Goal(order=1)),
                Fibonacci.Goal(order=400))
    assert goal.handle.accepted and goal.wait_feedback(3, 10)
    pending = goal.handle.get_result_async()
    server.stop()  # the server's bridge goes, mid-goal
    answer = settled(pending, 10)
    assert answer.status == GoalStatus.STATUS_ABORTED
    del keep


# -- the file and the policy --------------------------------------------------------------------
def test_an_action_entry_becomes_three_services_and_two_topics():
    from rosgate.actions import parts
    from rosgate.config import ServiceConfig, TopicConfig, loads

    cfg = loads("""
bridge: {name: a, role: peer, peer: 127.0.0.1}
actions:
  - {action: /fib, type: test_msgs/action/Fibonacci, direction: transmit, remote: /r/fib,
     port: 12300, timeout: 2, transport: tcp}
""")
    (action,) = cfg.actions
    got = [(type(p).__name__, p.topic if isinstance(p, TopicConfig) else p.service, p.type,
            str(p.direction), p.remote, p.port, p.transport) for p in parts(action)]
    assert got == [
        ("ServiceConfig", "/fib/_action/send_goal", "test_msgs/action/Fibonacci_SendGoal",
         "transmit", "/r/fib/_action/send_goal", 12300, "tcp"),
        ("ServiceConfig", "/fib/_action/cancel_goal", "action_msgs/srv/CancelGoal",
         "transmit", "/r/fib/_action/cancel_goal", 12300, "tcp"),
        ("ServiceConfig", "/fib/_action/get_result", "test_msgs/action/Fibonacci_GetResult",
         "transmit", "/r/fib/_action/get_result", 12300, "tcp"),
        ("TopicConfig", "/fib/_action/feedback", "test_msgs/action/Fibonacci_FeedbackMessage",
         "receive", "/r/fib/_action/feedback", 12301, "tcp"),
        ("TopicConfig", "/fib/_action/status", "action_msgs/msg/GoalStatusArray", "receive",
         "/r/fib/_action/status", 12301, "tcp")]
    timeouts = [p.timeout for p in parts(action) if isinstance(p, ServiceConfig)]
    assert timeouts == [2, 2, 3600]  # a result waits as long as its goal runs
    status = parts(action)[4]
    assert isinstance(status, TopicConfig)
    assert status.qos == {"reliability": "reliable", "durability": "transient_local", "depth": 1}


@pytest.mark.parametrize("entry, error", [
    ("{action: /fib, type: test_msgs/action/Fibonacci, direction: transmit, codek: cdr}",
     "actions[0].codek: unknown key 'codek'"),
    ("{action: /fib, type: test_msgs/srv/Fibonacci, direction: transmit}",
     "actions[0].type: 'test_msgs/srv/Fibonacci' is a 'srv' type, but an action needs "
     "package/action/Type"),
    ("{action: /fib, type: test_msgs/action/Fibonacci, direction: transmit, timeout: 0}",
     "actions[0].timeout"),
])
def test_action_entries_are_checked_like_services(entry, error):
    from rosgate.config import loads
    from rosgate.errors import ConfigError

    with pytest.raises(ConfigError, match=re.escape(error)):
        loads(f"bridge: {{name: a, role: peer, peer: 127.0.0.1}}\nactions: [{entry}]\n")


def test_a_servers_policy_judges_actions_by_their_own_rules():
    from rosgate.config import ActionConfig, ClientPolicy, Direction, Rule
    from rosgate.policy import refusal

    policy = ClientPolicy("robot1", bytes(32), services=(Rule("/**", "both"),),
                          actions=(Rule("/robot1/**", "transmit",
                                        types=("nav2_msgs/action/*",)),))
    goal = lambda name, kind="nav2_msgs/action/NavigateToPose", way=Direction.TRANSMIT: \
        ActionConfig(name, kind, way, name, cipher="aead")
    assert refusal(policy, goal("/robot1/navigate"), {"none"}) is None
    assert refusal(policy, goal("/base/navigate"), {"none"}) == (
        "robot1 may not transmit action /base/navigate (policy for robot1 allows /robot1/**)")
    assert refusal(policy, goal("/robot1/fib", "test_msgs/action/Fibonacci"), {"none"}) == (
        "robot1 may not transmit action /robot1/fib with type test_msgs/action/Fibonacci "
        "(policy for robot1 allows types nav2_msgs/action/* for /robot1/**)")
    assert refusal(policy, goal("/robot1/navigate", way=Direction.RECEIVE), {"none"}) == (
        "robot1 may not receive action /robot1/navigate (policy for robot1 allows no actions "
        "it receives)")


def test_an_action_anyone_could_write_to_is_refused_as_other_entries_are():
    """An action's feedback and status reach ROS on the calling side, its calls on the serving
    side: on a peer link without identities or a keyed cipher it is an open door."""
    from rosgate.config import loads
    from rosgate.engine import Engine
    from rosgate.errors import ConfigError

    entry = ("actions: [{action: /fib, type: test_msgs/action/Fibonacci, direction: transmit, "
             "port: 12300}]\n")
    with pytest.raises(ConfigError, match=re.escape(
            "actions[0].cipher: anyone who reaches this bridge can write to action /fib: cipher "
            "none on udp:12300")):
        Engine(loads(f"bridge: {{name: a, role: peer, peer: 127.0.0.1}}\n{entry}")).prepare()
    engine = Engine(loads(f"bridge: {{name: a, role: peer, peer: 127.0.0.1, insecure: true}}\n"
                          f"{entry}", file="a.yaml")).prepare()
    assert engine.insecure_warning() == (
        "INSECURE: a.yaml says insecure: true: anyone who can reach it can write to actions[0]"
        ".cipher (action /fib: cipher none on udp:12300). Set up identities or keyed ciphers: "
        "docs/security.md")
