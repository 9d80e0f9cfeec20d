"""ROS 2 services across the link: real rclpy servers and callers on each side, two engines in
this process, each in its own DDS domain, so the only way between them is the bridge."""

from __future__ import annotations

import threading
import time
from typing import Any, Callable

import pytest
from conftest import free_port
from rclpy.qos import QoSProfile
from std_srvs.srv import SetBool, Trigger

DEEP = QoSProfile(depth=1000)


def echo_set_bool(request: Any, response: Any) -> Any:
    response.success = True
    response.message = f"data={request.data}"
    return response


def pong(request: Any, response: Any) -> Any:
    response.success = True
    response.message = "pong"
    return response


class Caller:
    """A ROS service client on one side; waits on futures, never sleeps for a result."""

    def __init__(self, side: Any, srv_type: type, name: str):
        self.srv_type = srv_type
        self.client = side.ros.node.create_client(srv_type, name, qos_profile=DEEP)
        assert self.client.wait_for_service(timeout_sec=10), f"{name} never appeared"

    def call_many(self, requests: list[Any], timeout: float) -> list[Any]:
        done = threading.Semaphore(0)
        futures = [self.client.call_async(r) for r in requests]
        for f in futures:
            f.add_done_callback(lambda _: done.release())
        deadline = time.monotonic() + timeout
        for _ in futures:
            assert done.acquire(timeout=max(0.0, deadline - time.monotonic())), "no answer in time"
        return [f.result() for f in futures]

    def call(self, request: Any, timeout: float = 10.0) -> Any:
        return self.call_many([request], timeout)[0]

    def until_served(self, request: Any, timeout: float = 15.0) -> Any:
        """Call until the far bridge has discovered its ROS server (until then it answers
        "no ROS server"), and return the first real answer."""
        deadline = time.monotonic() + timeout
        while True:
            answer = self.call(request)
            if "no ROS server" not in answer.message:
                return answer
            assert time.monotonic() < deadline, answer.message
            time.sleep(0.1)  # pacing the retries; the result is waited on above


WARMUP = {"no_server", "remote_failure"}  # until_served: before the far bridge saw its server


def drops_after_warmup(engine: Any) -> dict[str, dict[str, int]]:
    return {r.label: {k: v for k, v in r.counters.drops.items() if k not in WARMUP}
            for r in engine.routes()}


def peer_yaml(name: str, entries: list[str]) -> str:
    return (f"bridge: {{name: {name}, role: peer, peer: 127.0.0.1, listen: 127.0.0.1}}\n"
            "services:\n" + "".join(f"  - {{{e}}}\n" for e in entries))


def flip(entry: str) -> str:
    return entry.replace("transmit", "@").replace("receive", "transmit").replace("@", "receive")


@pytest.mark.parametrize("transport", ["udp", "tcp"])
def test_peer_set_bool_and_trigger_cross_both_ways(engines, domain, ros_side, transport):
    da, db = domain(), domain()
    p1, p2 = free_port(), free_port()
    a_entries = [f"service: /set, type: std_srvs/srv/SetBool, direction: transmit, port: {p1}, "
                 f"transport: {transport}",
                 f"service: /trig, type: std_srvs/srv/Trigger, direction: receive, port: {p2}, "
                 f"transport: {transport}"]
    a = engines(peer_yaml("a", a_entries), da)
    b = engines(peer_yaml("b", [flip(e) for e in a_entries]), db)
    side_a, side_b = ros_side(da, "a"), ros_side(db, "b")
    side_b.ros.node.create_service(SetBool, "/set", echo_set_bool, qos_profile=DEEP)
    side_a.ros.node.create_service(Trigger, "/trig", pong, qos_profile=DEEP)

    set_bool = Caller(side_a, SetBool, "/set")
    assert set_bool.until_served(SetBool.Request(data=True)) == \
        SetBool.Response(success=True, message="data=True")
    assert set_bool.call(SetBool.Request(data=False)) == \
        SetBool.Response(success=True, message="data=False")
    trigger = Caller(side_b, Trigger, "/trig")
    assert trigger.until_served(Trigger.Request()) == Trigger.Response(success=True, message="pong")
    assert drops_after_warmup(a) == drops_after_warmup(b) == {"/set": {}, "/trig": {}}


def test_client_server_calls_cross_both_ways_on_the_main_line_and_udp(engines, domain, ros_side):
    ds, dc = domain(), domain()
    main = free_port()
    engines(f"bridge: {{name: base, role: server, server: 127.0.0.1:{main}}}", ds)
    client = engines(f"""
bridge: {{name: robot1, role: client, server: 127.0.0.1:{main}}}
services:
  - {{service: /set, type: std_srvs/srv/SetBool, direction: transmit, remote: /base/set,
     codec: msgpack}}
  - {{service: /trig, type: std_srvs/srv/Trigger, direction: receive, transport: tcp}}
""", dc)
    robot, base = ros_side(dc, "robot"), ros_side(ds, "base")
    base.ros.node.create_service(SetBool, "/base/set", echo_set_bool, qos_profile=DEEP)
    robot.ros.node.create_service(Trigger, "/trig", pong, qos_profile=DEEP)
    set_bool = Caller(robot, SetBool, "/set")
    assert set_bool.until_served(SetBool.Request(data=True)).message == "data=True"
    assert set_bool.call(SetBool.Request(data=False)) == \
        SetBool.Response(success=True, message="data=False")
    trigger = Caller(base, Trigger, "/trig")
    assert trigger.until_served(Trigger.Request()) == Trigger.Response(success=True, message="pong")
    assert drops_after_warmup(client) == {"/set (to base)": {}, "/trig (from base)": {}}


class HoldingServer:
    """A SetBool server that holds calls until ``n`` have come, then answers them in reverse
    order: answers cross the link out of order, so a bridge that matched them by arrival
    would give each caller another call's answer."""

    def __init__(self, side: Any, name: str, n: int):
        self.n = n
        self.held: list[tuple[Any, Callable[[Any], None]]] = []
        self.holding = False
        self._lock = threading.Lock()
        side.ros.deferred_service(SetBool, name, DEEP, self.on_request)

    def on_request(self, request: Any, respond: Callable[[Any], None]) -> None:
        with self._lock:
            if not self.holding:
                respond(echo_set_bool(request, SetBool.Response()))
                return
            self.held.append((request, respond))
            if len(self.held) < self.n:
                return
            held, self.held = self.held, []
        for request, respond in reversed(held):
            respond(echo_set_bool(request, SetBool.Response()))


@pytest.mark.parametrize("transport", ["udp", "tcp"])
def test_fifty_concurrent_calls_each_get_their_own_answer(engines, domain, ros_side, transport):
    da, db, port = domain(), domain(), free_port()
    entry = (f"service: /set, type: std_srvs/srv/SetBool, direction: transmit, port: {port}, "
             f"transport: {transport}")
    a = engines(peer_yaml("a", [entry]), da)
    engines(peer_yaml("b", [flip(entry)]), db)
    side_a, side_b = ros_side(da, "a"), ros_side(db, "b")
    server = HoldingServer(side_b, "/set", 50)
    caller = Caller(side_a, SetBool, "/set")
    caller.until_served(SetBool.Request(data=True))
    latencies = []
    for _ in range(20):
        start = time.monotonic()
        caller.call(SetBool.Request(data=True))
        latencies.append(time.monotonic() - start)
    server.holding = True
    requests = [SetBool.Request(data=i % 3 == 0) for i in range(50)]
    start = time.monotonic()
    answers = caller.call_many(requests, timeout=10)
    elapsed = time.monotonic() - start
    assert [a.message for a in answers] == [f"data={r.data}" for r in requests]
    assert all(a.success for a in answers)
    route = a.routes()[0]
    assert route.counters.drops.get("timeout") is None and not route.calls
    print(f"\n{transport}: one call {sorted(latencies)[10] * 1000:.1f} ms (median of 20), "
          f"50 concurrent calls {elapsed * 1000:.0f} ms")


def test_slow_server_answered_as_failure_within_timeout_and_the_late_answer_dropped(
        engines, domain, ros_side):
    da, db, port = domain(), domain(), free_port()
    entry = (f"service: /set, type: std_srvs/srv/SetBool, direction: transmit, port: {port}, "
             "timeout: 0.5")
    a = engines(peer_yaml("a", [entry]), da)
    b = engines(peer_yaml("b", [flip(entry)]), db)
    side_a, side_b = ros_side(da, "a"), ros_side(db, "b")
    server = HoldingServer(side_b, "/set", 2)  # holds the first call until a second comes
    caller = Caller(side_a, SetBool, "/set")
    caller.until_served(SetBool.Request(data=True))
    server.holding = True
    start = time.monotonic()
    answer = caller.call(SetBool.Request(data=True), timeout=5)
    elapsed = time.monotonic() - start
    assert answer == SetBool.Response(success=False, message="rosgate: no answer within 0.5 s")
    assert 0.5 <= elapsed < 0.8
    caller_route, server_route = a.routes()[0], b.routes()[0]
    # the serving bridge gives up on its ROS server too, and says so: too late for the caller
    wait = time.monotonic() + 5
    while caller_route.counters.drops["late_answer"] < 1 and time.monotonic() < wait:
        time.sleep(0.02)
    assert caller_route.counters.drops["timeout"] == 1
    assert caller_route.counters.drops["late_answer"] == 1
    assert server_route.counters.drops["timeout"] == 1
    # a second call releases both: its own answer crosses; the first one's, which the serving
    # bridge stopped waiting for, does not (rclpy drops it) and nothing more is counted
    assert caller.call(SetBool.Request(data=False), timeout=5).message == "data=False"
    assert dict(caller_route.counters.drops) == {"timeout": 1, "late_answer": 1}
    assert dict(server_route.counters.drops) == {"timeout": 1}


def test_missing_server_answered_as_failure_at_once(engines, domain, ros_side):
    da, db, port = domain(), domain(), free_port()
    entry = f"service: /set, type: std_srvs/srv/SetBool, direction: transmit, port: {port}"
    a = engines(peer_yaml("a", [entry]), da)
    b = engines(peer_yaml("b", [flip(entry)]), db)
    caller = Caller(ros_side(da, "a"), SetBool, "/set")
    start = time.monotonic()
    answer = caller.call(SetBool.Request(data=True), timeout=5)
    assert time.monotonic() - start < 1.0
    assert answer == SetBool.Response(
        success=False, message="rosgate: no ROS server /set is running on the serving side")
    assert dict(b.routes()[0].counters.drops) == {"no_server": 1}
    assert dict(a.routes()[0].counters.drops) == {"remote_failure": 1}


def test_peer_gone_answered_as_failure_within_timeout(engines, domain, ros_side):
    da, port = domain(), free_port()
    entry = (f"service: /set, type: std_srvs/srv/SetBool, direction: transmit, port: {port}, "
             "timeout: 0.3, transport: tcp")
    a = engines(peer_yaml("a", [entry]), da)  # nobody listens on the port
    caller = Caller(ros_side(da, "a"), SetBool, "/set")
    answer = caller.call(SetBool.Request(data=True), timeout=5)
    assert answer == SetBool.Response(success=False, message=f"rosgate: tcp->127.0.0.1:{port} is down")
    assert dict(a.routes()[0].counters.drops) == {"link_down": 1}
