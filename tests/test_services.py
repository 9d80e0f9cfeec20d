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
    for engine in (a, b):
        assert {r.label: dict(r.counters.drops) for r in engine.routes()
                if r.counters.drops.get("no_server") is None} == \
            {r.label: {} for r in engine.routes() if r.counters.drops.get("no_server") is None}


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
    assert {r.label for r in client.routes()} == {"/set (to base)", "/trig (from base)"}
