"""Goals belong to the client that sent them: two clients a server allows the same action, as
real ``rosgate run`` processes, each client's ROS side in a DDS domain of its own.

The attack: robot1 sends a long goal; robot2, allowed the same action, reads robot1's goal id
from the action's status, cancels it and asks for its result. Before goals had owners, robot1's
goal ended CANCELED and robot2 read its result. Now robot2's cancel is answered as ROS answers
a cancel of an unknown goal, its result request as ROS answers one for an unknown goal, it sees
no status or feedback of robot1's goal, and robot1's goal succeeds. A rule that says
``shared: true`` brings the shared behaviour back.
"""

from __future__ import annotations

import re
import threading
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

from conftest import AUTH, Inbox, free_port
from test_actions import Goal, ready, settled
from test_msgs.action import Fibonacci

FAST = "heartbeat: 0.2, peer_timeout: 0.8, reconnect: {min: 0.05, max: 0.5}"
LONG = 40  # the order of a long goal: it runs until the test releases it


def server_file(tmp_path: Path, port: int, robot2_rule: str = "") -> Path:
    rule = "{name: /fib, direction: transmit, types: [test_msgs/action/Fibonacci]"
    path = tmp_path / "server.yaml"
    path.write_text(f"""
bridge: {{name: base, role: server, server: 127.0.0.1:{port}, {FAST},
          identity: {AUTH.identity("server")}}}
clients:
  robot1:
    key: {AUTH.public["robot1"]}
    actions: [{rule}}}]
  robot2:
    key: {AUTH.public["robot2"]}
    actions: [{rule}{robot2_rule}}}]
""")
    return path


def client_file(tmp_path: Path, port: int, name: str) -> Path:
    path = tmp_path / f"{name}.yaml"
    path.write_text(f"""
bridge: {{name: {name}, role: client, server: 127.0.0.1:{port}, {FAST},
          identity: {AUTH.identity(name)}, server_key: {AUTH.public["server"]}}}
actions: [{{action: /fib, type: test_msgs/action/Fibonacci, direction: transmit, timeout: 3}}]
""")
    return path


class HeldServer:
    """The server side's action server: a goal of order ``LONG`` gives feedback until the test
    releases it (or it is cancelled), then succeeds; any other goal succeeds at once."""

    def __init__(self, side: Any):
        from rclpy.action import ActionServer, CancelResponse

        self.side = side
        self.release = threading.Event()
        self.server = ActionServer(side.node, Fibonacci, "/fib", self._execute,
                                   cancel_callback=lambda _: CancelResponse.ACCEPT)

    def _execute(self, goal_handle: Any) -> Any:
        with self.side.ended:  # the side waits for its goals before it closes
            self.side.running += 1
        try:
            return self._work(goal_handle)
        finally:
            with self.side.ended:
                self.side.running -= 1
                self.side.ended.notify_all()

    def _work(self, goal_handle: Any) -> Any:
        order = goal_handle.request.order
        step = 0
        while order == LONG and not self.release.wait(0.05):
            if self.side.stopping.is_set():
                goal_handle.abort()
                return Fibonacci.Result()
            if goal_handle.is_cancel_requested:
                goal_handle.canceled()
                return Fibonacci.Result(sequence=[step])
            step += 1
            goal_handle.publish_feedback(Fibonacci.Feedback(sequence=[step]))
        goal_handle.succeed()
        return Fibonacci.Result(sequence=[order, step])


class Snoop:
    """robot2's own look at the action's internals in its domain: the status and feedback the
    bridge publishes there, and direct calls of cancel_goal and get_result."""

    def __init__(self, side: Any):
        from action_msgs.msg import GoalStatusArray
        from action_msgs.srv import CancelGoal
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

        node = side.node
        latched = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.status, self.feedback = Inbox(), Inbox()
        node.create_subscription(GoalStatusArray, "/fib/_action/status", self.status.put, latched)
        node.create_subscription(Fibonacci.Impl.FeedbackMessage, "/fib/_action/feedback",
                                 self.feedback.put, 100)
        self.cancel = node.create_client(CancelGoal, "/fib/_action/cancel_goal")
        self.result = node.create_client(Fibonacci.Impl.GetResultService, "/fib/_action/get_result")

    def goals_seen(self) -> set[bytes]:
        """The goal ids robot2 saw in status arrays and feedback."""
        seen = {bytes(s.goal_info.goal_id.uuid) for a in list(self.status.items)
                for s in a.status_list}
        return seen | {bytes(f.goal_id.uuid) for f in list(self.feedback.items)}

    def cancel_goal(self, uuid: bytes, stamp: tuple[int, int] = (0, 0)) -> Any:
        """A cancel as ROS reads it: no id and no time, every goal; a time, those accepted
        before it."""
        from action_msgs.srv import CancelGoal

        request = CancelGoal.Request()
        request.goal_info.goal_id.uuid = list(uuid)
        request.goal_info.stamp.sec, request.goal_info.stamp.nanosec = stamp
        assert self.cancel.wait_for_service(timeout_sec=15)
        return settled(self.cancel.call_async(request), 10)

    def get_result(self, uuid: bytes) -> Any:
        request = Fibonacci.Impl.GetResultService.Request()
        request.goal_id.uuid = list(uuid)
        assert self.result.wait_for_service(timeout_sec=15)
        return settled(self.result.call_async(request), 10)


def warm(client: Any, timeout: float = 30.0) -> Any:
    """The client, once a goal crosses and is accepted. A goal sent before the bridge's side
    of the action is matched may go to a server gone from this domain that DDS still lists
    (an earlier test's): unanswered, it is sent again."""
    ready(client)
    deadline = time.monotonic() + timeout
    while True:
        sent = client.send_goal_async(Fibonacci.Goal(order=1))
        answered = threading.Event()
        sent.add_done_callback(lambda _, this=answered: this.set())
        if answered.wait(5) and sent.result().accepted:
            settled(sent.result().get_result_async(), 20)  # so the server forgets it
            return client
        assert time.monotonic() < deadline, "no goal was ever accepted"
        time.sleep(0.1)  # pacing the retries of a goal answered "not accepted"


def two_clients(tmp_path: Path, domain: Any, bridge: Any, action_side: Any,
                robot2_rule: str = "") -> SimpleNamespace:
    """The server's bridge and action server, robot1's ROS side, robot2's snoop; robot1's goal
    running (after 3 of its feedbacks), robot2's own goal done."""
    ds, d1, d2, port = domain(), domain(), domain(), free_port()
    server = bridge(server_file(tmp_path, port, robot2_rule), ds)
    bridge(client_file(tmp_path, port, "robot1"), d1)
    bridge(client_file(tmp_path, port, "robot2"), d2)
    held = HeldServer(action_side(ds, "base"))
    robot1, robot2 = action_side(d1, "robot1"), action_side(d2, "robot2")
    snoop = Snoop(robot2)
    one, two = warm(robot1.client(Fibonacci, "/fib")), warm(robot2.client(Fibonacci, "/fib"))
    own = Goal(two, Fibonacci.Goal(order=2))
    assert own.handle.accepted and list(own.result().result.sequence) == [2, 0]
    goal = Goal(one, Fibonacci.Goal(order=LONG))
    assert goal.handle.accepted and goal.wait_feedback(3, 10)
    return SimpleNamespace(server=server, held=held, goal=goal, snoop=snoop, own=own,
                           robot1=robot1)


def test_a_client_cannot_cancel_read_or_watch_another_clients_goal(tmp_path, domain, bridge,
                                                                   action_side):
    """Before goals had owners: robot1's goal CANCELED by robot2, its result read by robot2,
    its id and feedback in robot2's status and feedback topics."""
    from action_msgs.msg import GoalStatus
    from action_msgs.srv import CancelGoal

    run = two_clients(tmp_path, domain, bridge, action_side)
    server, held, goal, snoop = run.server, run.held, run.goal, run.snoop
    victim = bytes(goal.handle.goal_id.uuid)
    mine = bytes(run.own.handle.goal_id.uuid)

    cancel = snoop.cancel_goal(victim)
    assert cancel.return_code == CancelGoal.Response.ERROR_UNKNOWN_GOAL_ID
    assert list(cancel.goals_canceling) == []
    everything = snoop.cancel_goal(bytes(16))  # every goal: robot2's own, none running
    assert everything.return_code == CancelGoal.Response.ERROR_NONE
    assert list(everything.goals_canceling) == []
    result = snoop.get_result(victim)
    assert result.status == GoalStatus.STATUS_UNKNOWN
    assert list(result.result.sequence) == []

    held.release.set()
    answer = goal.result()
    assert answer.status == GoalStatus.STATUS_SUCCEEDED  # robot1's goal ran to its end
    assert answer.result.sequence[0] == LONG and len(goal.feedback) >= 3

    # robot2 saw its own goal's status (so the topic crosses to it), never robot1's goal
    assert snoop.status.wait_for(lambda arrays: any(
        bytes(s.goal_info.goal_id.uuid) == mine and s.status == GoalStatus.STATUS_SUCCEEDED
        for a in arrays for s in a.status_list), 10)
    assert victim not in snoop.goals_seen()
    assert server.stop() == 0  # its counters, in its log at the end
    for part in ("cancel_goal (from robot2)", "get_result (from robot2)"):
        assert re.search(re.escape(part) + r": .*drops: foreign_goal=1$", server.log, re.M), \
            server.log
    assert re.search(r"feedback \(to robot2\): sent 0 .*drops: foreign_goal=([3-9]|\d\d+)$",
                     server.log, re.M), server.log


def test_a_cancel_of_every_goal_reaches_only_the_clients_own(tmp_path, domain, bridge,
                                                            action_side):
    """robot1 cancels every goal (no id, no time), then robot2 every goal accepted before now:
    robot1's goal is cancelled, the goal the server side's own ROS client sent runs on (and that
    client sees robot1's goal in its status, as ROS shows it), robot2 cancels nothing."""
    from action_msgs.msg import GoalStatus
    from action_msgs.srv import CancelGoal

    run = two_clients(tmp_path, domain, bridge, action_side)
    victim = bytes(run.goal.handle.goal_id.uuid)
    local = Goal(ready(run.held.side.client(Fibonacci, "/fib")), Fibonacci.Goal(order=LONG))
    assert local.handle.accepted and local.wait_feedback(2, 10)
    theirs = bytes(local.handle.goal_id.uuid)
    base = Snoop(run.held.side)
    assert base.status.wait_for(lambda _: {victim, theirs} <= base.goals_seen(), 10)

    later = time.time_ns() + 10**9  # a cancel of every goal accepted before a time
    robot2 = run.snoop.cancel_goal(bytes(16), (later // 10**9, later % 10**9))
    assert robot2.return_code == CancelGoal.Response.ERROR_NONE
    assert list(robot2.goals_canceling) == []
    robot1 = Snoop(run.robot1).cancel_goal(bytes(16))
    assert robot1.return_code == CancelGoal.Response.ERROR_NONE
    assert [bytes(g.goal_id.uuid) for g in robot1.goals_canceling] == [victim]
    assert run.goal.result().status == GoalStatus.STATUS_CANCELED

    count = len(local.feedback)
    assert local.wait_feedback(count + 3, 10)  # the server side's own goal runs on
    run.held.release.set()
    assert local.result().status == GoalStatus.STATUS_SUCCEEDED


def test_a_shared_action_lets_clients_cancel_each_others_goals(tmp_path, domain, bridge,
                                                               action_side):
    """``shared: true`` on robot2's rule: it sees robot1's goal and may cancel it."""
    from action_msgs.msg import GoalStatus
    from action_msgs.srv import CancelGoal

    run = two_clients(tmp_path, domain, bridge, action_side, ", shared: true")
    goal, snoop = run.goal, run.snoop
    victim = bytes(goal.handle.goal_id.uuid)
    assert snoop.status.wait_for(lambda _: victim in snoop.goals_seen(), 10)

    cancel = snoop.cancel_goal(victim)
    assert cancel.return_code == CancelGoal.Response.ERROR_NONE
    assert [bytes(g.goal_id.uuid) for g in cancel.goals_canceling] == [victim]
    assert goal.result().status == GoalStatus.STATUS_CANCELED
    assert snoop.get_result(victim).status == GoalStatus.STATUS_CANCELED


def test_a_topic_or_service_rule_does_not_reach_inside_an_action(tmp_path, domain, bridge,
                                                                 ros_side):
    """Before: a client allowed topics and services under /robot1/** (no action rule) could
    publish on /robot1/fib/_action/status and call /robot1/fib/_action/cancel_goal, the
    internals of the server side's action. Now both entries are refused, said in both logs,
    nothing is published or served for them, and its other topic runs."""
    from action_msgs.msg import GoalStatus, GoalStatusArray
    from conftest import cross
    from std_msgs.msg import String

    ds, dc, port = domain(), domain(), free_port()
    path = tmp_path / "server.yaml"
    path.write_text(f"""
bridge: {{name: base, role: server, server: 127.0.0.1:{port}, {FAST},
          identity: {AUTH.identity("server")}}}
clients:
  robot1:
    key: {AUTH.public["robot1"]}
    topics: [{{name: /robot1/**, direction: both}}]
    services: [{{name: /robot1/**, direction: both}}]
""")
    server = bridge(path, ds)
    robot1 = tmp_path / "robot1.yaml"
    robot1.write_text(f"""
bridge: {{name: robot1, role: client, server: 127.0.0.1:{port}, {FAST},
          identity: {AUTH.identity("robot1")}, server_key: {AUTH.public["server"]}}}
topics:
  - {{topic: /chatter, type: std_msgs/msg/String, direction: transmit, remote: /robot1/chatter}}
  - {{topic: /forged, type: action_msgs/msg/GoalStatusArray, direction: transmit,
      remote: /robot1/fib/_action/status}}
services:
  - {{service: /cancel, type: action_msgs/srv/CancelGoal, direction: transmit,
      remote: /robot1/fib/_action/cancel_goal}}
""")
    client = bridge(robot1, dc)
    side, robot = ros_side(ds, "base"), ros_side(dc, "robot")
    forged_in = side.listen("/robot1/fib/_action/status", GoalStatusArray)
    forged = robot.publisher("/forged", GoalStatusArray)
    chatter, chatter_in = robot.publisher("/chatter", String), side.listen("/robot1/chatter",
                                                                         String)
    numbered = lambda i: String(data="warm-up" if i is None else f"m{i}")
    is_warmup = lambda m: m.data == "warm-up"
    cross(chatter, chatter_in, numbered, is_warmup, 0)  # the session runs
    lie = GoalStatusArray(status_list=[GoalStatus(status=GoalStatus.STATUS_CANCELED)])
    for _ in range(20):
        forged.publish(lie)
    got = cross(chatter, chatter_in, numbered, is_warmup, 3)  # what was sent before is in
    assert [m.data for m in got] == ["m0", "m1", "m2"]
    assert forged_in.items == []
    for entry in ("/robot1/fib/_action/status", "service /robot1/fib/_action/cancel_goal"):
        sentence = f"robot1 may not transmit {entry}: it is part of an action"
        assert server.wait_log(sentence, 5), server.log
        assert client.wait_log(sentence, 5), client.log
    node = side.ros.node
    assert node.count_publishers("/robot1/fib/_action/status") == 0
    assert node.count_clients("/robot1/fib/_action/cancel_goal") == 0


# -- the record of goals, the policy and check, without processes ------------------------------
class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def status(goal: bytes, state: int, sec: int = 1) -> Any:
    from action_msgs.msg import GoalStatus

    s = GoalStatus(status=state)
    s.goal_info.goal_id.uuid = list(goal)
    s.goal_info.stamp.sec = sec
    return s


def test_goals_are_their_senders_and_forgotten_a_while_after_they_end():
    from rosgate.actions import Goals
    from rosgate.drops import Drop

    clock = Clock()
    goals = Goals(keep=10, cap=2, clock=clock)
    a, b, c = b"a" * 16, b"b" * 16, b"c" * 16
    assert goals.claim(a, "robot1") is None and goals.claim(a, "robot1") is None
    assert goals.claim(a, "robot2") is Drop.FOREIGN_GOAL  # another's id
    assert goals.owns("robot1", a) and not goals.owns("robot2", a)
    assert goals.claim(b, "robot1") is None
    assert goals.claim(c, "robot1") is Drop.TOO_MANY_GOALS  # two running: its cap
    assert goals.claim(b"d" * 16, "robot2") is None  # a cap per client: robot1 blocks no other
    goals.update([status(a, 4)])  # a succeeded
    assert goals.claim(c, "robot1") is None  # its oldest ended goal made room
    assert not goals.owns("robot1", a) and goals.owns("robot1", c)
    goals.release(c, "robot1")  # not accepted: nobody's
    goals.update([status(b, 6)])
    clock.now = 9.9
    goals.claim(bytes(16), "robot3")  # forgetting happens as goals come
    assert goals.owns("robot1", b)
    clock.now = 10.1
    goals.claim(bytes(16), "robot3")
    assert not goals.owns("robot1", b)


def test_a_cancel_covers_the_clients_goals_as_ros_reads_it():
    from rosgate.actions import NO_GOAL, Goals

    goals = Goals()
    early, late, other, done = b"e" * 16, b"l" * 16, b"o" * 16, b"d" * 16
    for goal in (early, late, done):
        goals.claim(goal, "robot1")
    goals.claim(other, "robot2")
    goals.update([status(early, 2, sec=5), status(late, 2, sec=9), status(other, 2, sec=1),
                  status(done, 4, sec=1)])
    assert sorted(goals.covered("robot1", NO_GOAL, (0, 0))) == sorted([early, late])
    assert goals.covered("robot1", NO_GOAL, (5, 0)) == [early]
    assert sorted(goals.covered("robot1", late, (5, 0))) == sorted([early, late])
    assert goals.covered("robot1", other, (0, 0)) == []
    goals.update([status(late, 2, sec=9)])  # the server no longer lists early (restarted)
    assert goals.covered("robot1", NO_GOAL, (0, 0)) == [late]
    assert goals.owns("robot1", early)  # ended: remembered a while yet


def test_feedback_and_status_carry_only_the_clients_goals_as_cdr():
    from action_msgs.msg import GoalStatusArray
    from rclpy.serialization import deserialize_message, serialize_message

    from rosgate.actions import Goals, client_goals

    goals = Goals()
    mine, theirs = b"m" * 16, b"t" * 16
    goals.claim(mine, "robot1")
    goals.claim(theirs, "robot2")
    feedback = client_goals(goals, "robot1", "/fib/_action/feedback",
                            Fibonacci.Impl.FeedbackMessage, raw=True)
    for goal, kept in ((mine, True), (theirs, False)):
        message = Fibonacci.Impl.FeedbackMessage()
        message.goal_id.uuid = list(goal)
        message.feedback.sequence = [1, 2]
        data = serialize_message(message)
        assert (feedback.select(data) == data) is kept
    watch = client_goals(goals, "robot1", "/fib/_action/status", GoalStatusArray, raw=True)
    both = serialize_message(GoalStatusArray(status_list=[status(theirs, 2), status(mine, 4)]))
    seen = deserialize_message(watch.select(both), GoalStatusArray)
    assert [(bytes(s.goal_info.goal_id.uuid), s.status) for s in seen.status_list] == [(mine, 4)]
    only_theirs_changed = GoalStatusArray(status_list=[status(theirs, 4), status(mine, 4)])
    assert watch.select(serialize_message(only_theirs_changed)) is None  # nothing new to it
    as_objects = client_goals(goals, "robot2", "/fib/_action/status", GoalStatusArray, raw=False)
    seen = as_objects.select(deserialize_message(both, GoalStatusArray))
    assert [bytes(s.goal_info.goal_id.uuid) for s in seen.status_list] == [theirs]


def test_only_an_action_rule_reaches_inside_an_action_and_says_shared():
    from rosgate.config import (
        ActionConfig,
        ClientPolicy,
        Direction,
        Rule,
        ServiceConfig,
        TopicConfig,
    )
    from rosgate.policy import refusal, shared

    policy = ClientPolicy("robot1", bytes(32), topics=(Rule("/robot1/**", "both"),),
                          services=(Rule("/robot1/**", "both"),),
                          actions=(Rule("/robot1/fib", "transmit"),
                                   Rule("/robot1/dock", "transmit", shared=True)))
    topic = TopicConfig("/s", "action_msgs/msg/GoalStatusArray", Direction.TRANSMIT,
                        "/robot1/fib/_action/status", cipher="aead")
    assert refusal(policy, topic, {"none"}) == (
        "robot1 may not transmit /robot1/fib/_action/status: it is part of an action (only an "
        "actions: entry, allowed by an actions: rule, carries an action)")
    call = ServiceConfig("/c", "action_msgs/srv/CancelGoal", Direction.TRANSMIT,
                         "/robot1/fib/_action/cancel_goal", cipher="aead")
    assert refusal(policy, call, {"none"}).startswith(
        "robot1 may not transmit service /robot1/fib/_action/cancel_goal: it is part of an action")
    plain = TopicConfig("/s", "std_msgs/msg/String", Direction.TRANSMIT, "/robot1/my_action",
                        cipher="aead")
    assert refusal(policy, plain, {"none"}) is None  # a name that only looks like one
    action = lambda name: ActionConfig(name, "test_msgs/action/Fibonacci", Direction.TRANSMIT,
                                       name, cipher="aead")
    assert refusal(policy, action("/robot1/fib"), {"none"}) is None
    assert not shared(policy, action("/robot1/fib"), {"none"})
    assert shared(policy, action("/robot1/dock"), {"none"})
    assert not shared(policy, action("/robot1/other"), {"none"})  # refused: not shared either


def test_check_says_when_a_topic_rule_names_a_part_of_an_action(tmp_path):
    import subprocess

    from conftest import ROSGATE

    path = tmp_path / "server.yaml"
    path.write_text(f"""bridge: {{name: base, role: server, server: 127.0.0.1:12000,
         identity: {AUTH.identity("server")}}}
clients:
  robot1:
    key: {AUTH.public["robot1"]}
    topics:
      - {{name: /robot1/fib/_action/status, direction: both}}
    services:
      - {{name: /robot1/**, direction: both, shared: true}}
    actions:
      - {{name: /robot1/fib, direction: transmit, shared: true}}
""")
    result = subprocess.run([ROSGATE, "check", str(path)], capture_output=True, text=True,
                            timeout=60)
    assert result.returncode == 0, result.stderr
    assert (f"{path}:7: clients.robot1.topics[0].name: /robot1/fib/_action/status names a part "
            "of an action: no topic rule allows it, only an actions: rule for the action does\n"
            "  fix: allow the action with an actions: rule, e.g. - {name: /robot1/fib, "
            "direction: transmit}") in result.stderr
    assert (f"{path}:9: clients.robot1.services[0].shared: shared applies to actions: rules, "
            "not to services") in result.stderr
    assert "actions[0].shared" not in result.stderr


def test_a_reload_that_shares_the_action_gives_a_connected_client_every_goal(
        tmp_path, domain, bridge, action_side):
    """SIGHUP after ``shared: true`` is added to robot2's rule: robot2, connected all along,
    sees robot1's running goal and may cancel it."""
    import signal

    from action_msgs.msg import GoalStatus
    from action_msgs.srv import CancelGoal

    run = two_clients(tmp_path, domain, bridge, action_side)
    victim = bytes(run.goal.handle.goal_id.uuid)
    assert run.snoop.cancel_goal(victim).return_code == CancelGoal.Response.ERROR_UNKNOWN_GOAL_ID
    path = run.server.config
    text = path.read_text()
    path.write_text(text[:text.rindex("]}") + 1] + ", shared: true}]\n")
    run.server.proc.send_signal(signal.SIGHUP)
    assert run.server.wait_log("applied the policy of 2 client(s)", 10), run.server.log
    assert run.snoop.status.wait_for(lambda _: victim in run.snoop.goals_seen(), 10)
    cancel = run.snoop.cancel_goal(victim)
    assert [bytes(g.goal_id.uuid) for g in cancel.goals_canceling] == [victim]
    assert run.goal.result().status == GoalStatus.STATUS_CANCELED
