"""ROS 2 services across the link: real rclpy servers and callers on each side, two engines in
this process, each in its own DDS domain, so the only way between them is the bridge."""

from __future__ import annotations

import socket
import threading
import time
from collections import Counter
from collections.abc import Callable
from typing import Any

import pytest
from conftest import free_port, wait_until
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

    def warm_up(self, request: Any, *engines: Any, timeout: float = 30.0) -> tuple[Any, Drops]:
        """Call until the bridges are ready and return the first real answer, with the drop
        counters of ``engines`` from then on (warm-up is not what a test counts).

        Until a stream link has connected and the far bridge has discovered its ROS server, the
        bridge answers with a failure at once. A call made just after discovery can be lost
        inside ROS (Fast DDS drops an answer to a reader it has not discovered yet: "client will
        not receive response"); the bridge answers it with a timeout, and a late answer may
        follow, so then warm-up lasts one service timeout longer for it to land."""
        deadline = time.monotonic() + timeout
        lost = False
        while True:
            assert time.monotonic() < deadline, "the bridges never got ready"
            future = self.client.call_async(request)
            done = threading.Event()
            future.add_done_callback(lambda _, done=done: done.set())  # this attempt's event
            if not done.wait(10):  # lost between this caller and the bridge
                self.client.remove_pending_request(future)
                lost = True
                continue
            answer = future.result()
            if not answer.message.startswith("rosgate: "):
                break
            lost = lost or "within" in answer.message
            time.sleep(0.1)  # pacing the retries; each answer is waited on above
        if lost:
            time.sleep(max(r.service.timeout for e in engines for r in e.routes()) + 0.2)
        return answer, Drops(engines)


class Drops:
    """Each route's drops counted since this was made, by engine name and route label."""

    def __init__(self, engines: tuple[Any, ...]):
        self.engines = engines
        self.start = self._now()

    def _now(self) -> dict[str, Counter]:
        return {f"{e.config.name} {r.label}": Counter(r.counters.drops)
                for e in self.engines for r in e.routes()}

    def since(self) -> dict[str, dict[str, int]]:
        return {label: dict(now - self.start.get(label, Counter()))
                for label, now in self._now().items()}


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
                 f"transport: {transport}, timeout: 2",
                 f"service: /trig, type: std_srvs/srv/Trigger, direction: receive, port: {p2}, "
                 f"transport: {transport}, timeout: 2"]
    a = engines(peer_yaml("a", a_entries), da)
    b = engines(peer_yaml("b", [flip(e) for e in a_entries]), db)
    side_a, side_b = ros_side(da, "a"), ros_side(db, "b")
    side_b.ros.node.create_service(SetBool, "/set", echo_set_bool, qos_profile=DEEP)
    side_a.ros.node.create_service(Trigger, "/trig", pong, qos_profile=DEEP)

    set_bool, trigger = Caller(side_a, SetBool, "/set"), Caller(side_b, Trigger, "/trig")
    assert set_bool.warm_up(SetBool.Request(data=True))[0] == \
        SetBool.Response(success=True, message="data=True")
    answer, drops = trigger.warm_up(Trigger.Request(), a, b)
    assert answer == Trigger.Response(success=True, message="pong")
    assert set_bool.call(SetBool.Request(data=False)) == \
        SetBool.Response(success=True, message="data=False")
    assert trigger.call(Trigger.Request()) == Trigger.Response(success=True, message="pong")
    assert drops.since() == {"a /set": {}, "a /trig": {}, "b /set": {}, "b /trig": {}}


def test_client_server_calls_cross_both_ways_on_udp_and_a_tcp_port_of_their_own(
        engines, domain, ros_side):
    ds, dc = domain(), domain()
    main = free_port()
    server = engines(f"bridge: {{name: base, role: server, server: 127.0.0.1:{main}}}", ds)
    client = engines(f"""
bridge: {{name: robot1, role: client, server: 127.0.0.1:{main}}}
services:
  - {{service: /set, type: std_srvs/srv/SetBool, direction: transmit, remote: /base/set,
     codec: msgpack, timeout: 2}}
  - {{service: /trig, type: std_srvs/srv/Trigger, direction: receive, transport: tcp, timeout: 2,
     port: {free_port()}}}
""", dc)
    robot, base = ros_side(dc, "robot"), ros_side(ds, "base")
    base.ros.node.create_service(SetBool, "/base/set", echo_set_bool, qos_profile=DEEP)
    robot.ros.node.create_service(Trigger, "/trig", pong, qos_profile=DEEP)
    set_bool, trigger = Caller(robot, SetBool, "/set"), Caller(base, Trigger, "/trig")
    assert set_bool.warm_up(SetBool.Request(data=True))[0].message == "data=True"
    answer, drops = trigger.warm_up(Trigger.Request(), client, server)
    assert answer == Trigger.Response(success=True, message="pong")
    assert set_bool.call(SetBool.Request(data=False)) == \
        SetBool.Response(success=True, message="data=False")
    assert trigger.call(Trigger.Request()) == Trigger.Response(success=True, message="pong")
    assert drops.since() == {"robot1 /set (to base)": {}, "robot1 /trig (from base)": {},
                             "base /base/set (from robot1)": {}, "base /trig (to robot1)": {}}


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
             f"transport: {transport}, timeout: 3")
    a = engines(peer_yaml("a", [entry]), da)
    b = engines(peer_yaml("b", [flip(entry)]), db)
    side_a, side_b = ros_side(da, "a"), ros_side(db, "b")
    server = HoldingServer(side_b, "/set", 50)
    caller = Caller(side_a, SetBool, "/set")
    _, drops = caller.warm_up(SetBool.Request(data=True), a, b)
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
    assert drops.since() == {"a /set": {}, "b /set": {}} and not a.routes()[0].calls
    print(f"\n{transport}: one call {sorted(latencies)[10] * 1000:.1f} ms (median of 20), "
          f"50 concurrent calls {elapsed * 1000:.0f} ms")


def test_slow_server_answered_as_failure_within_timeout_and_the_late_answer_dropped(
        engines, domain, ros_side):
    da, db, port = domain(), domain(), free_port()
    entry = (f"service: /set, type: std_srvs/srv/SetBool, direction: transmit, port: {port}, "
             "timeout: 0.5")
    a = engines(peer_yaml("a", [entry]), da)
    # the serving bridge waits longer than the caller's: with the same 0.5 s, on a loaded
    # machine its own failure ("the ROS server /set did not answer") could reach the caller
    # before the caller's timer ran, and the caller would answer with that instead
    b = engines(peer_yaml("b", [flip(entry).replace("timeout: 0.5", "timeout: 1.5")]), db)
    side_a, side_b = ros_side(da, "a"), ros_side(db, "b")
    server = HoldingServer(side_b, "/set", 2)  # holds the first call until a second comes
    caller = Caller(side_a, SetBool, "/set")
    _, drops_a = caller.warm_up(SetBool.Request(data=True), a)
    drops_b = Drops((b,))
    server.holding = True
    start = time.monotonic()
    answer = caller.call(SetBool.Request(data=True), timeout=5)
    elapsed = time.monotonic() - start
    assert answer == SetBool.Response(success=False, message="rosgate: no answer within 0.5 s")
    assert 0.5 <= elapsed < 2.0  # answered at the timeout, not left hanging (loose: CI load)
    # the serving bridge gives up on its ROS server too, and says so: too late for the caller
    wait = time.monotonic() + 5
    while drops_a.since()["a /set"].get("late_answer") != 1 and time.monotonic() < wait:
        time.sleep(0.02)
    assert drops_a.since() == {"a /set": {"timeout": 1, "late_answer": 1}}
    assert drops_b.since() == {"b /set": {"timeout": 1}}
    # a second call releases both: its own answer crosses; the first one's, which the serving
    # bridge stopped waiting for, does not (rclpy drops it) and nothing more is counted
    assert caller.call(SetBool.Request(data=False), timeout=5).message == "data=False"
    assert drops_a.since() == {"a /set": {"timeout": 1, "late_answer": 1}}
    assert drops_b.since() == {"b /set": {"timeout": 1}}


def test_missing_server_answered_as_failure_within_its_timeout(engines, domain, ros_side):
    da, db, port = domain(), domain(), free_port()
    entry = (f"service: /set, type: std_srvs/srv/SetBool, direction: transmit, port: {port}, "
             "timeout: 4")
    a = engines(peer_yaml("a", [entry]), da)
    b = engines(peer_yaml("b", [flip(entry)]), db)
    caller = Caller(ros_side(da, "a"), SetBool, "/set")
    start = time.monotonic()
    answer = caller.call(SetBool.Request(data=True), timeout=8)
    # the serving bridge waits most of the timeout (3.2 s) for a server to appear, then says so
    # in time: the caller's own 4 s timeout never fires (it would answer with its own words and
    # count a timeout, as the assertions below would see). A 4 s timeout leaves the answer
    # 800 ms to come back, which a loaded machine needs; the bound on the clock is loose for it.
    assert 3.1 < time.monotonic() - start < 5.0
    assert answer == SetBool.Response(
        success=False, message="rosgate: no ROS server /set is running on the serving side")
    assert dict(b.routes()[0].counters.drops) == {"no_server": 1}
    assert dict(a.routes()[0].counters.drops) == {"remote_failure": 1}


@pytest.mark.parametrize("delay", [1.0, 2.0])
def test_a_call_waits_for_a_server_that_appears_after_it(engines, domain, ros_side, delay):
    """The ROS server starts ``delay`` seconds after the call was made: the call is answered by
    it, within the entry's timeout, and nothing is counted as a failure."""
    da, db, port = domain(), domain(), free_port()
    entry = (f"service: /late, type: std_srvs/srv/SetBool, direction: transmit, port: {port}, "
             "timeout: 4")
    a = engines(peer_yaml("a", [entry]), da)
    b = engines(peer_yaml("b", [flip(entry)]), db)
    side_b = ros_side(db, "b")
    caller = Caller(ros_side(da, "a"), SetBool, "/late")
    start = time.monotonic()
    future = caller.client.call_async(SetBool.Request(data=True))
    done = threading.Event()
    future.add_done_callback(lambda _: done.set())
    assert not done.wait(delay)  # nobody serves /late yet: the call waits
    side_b.ros.node.create_service(SetBool, "/late", echo_set_bool, qos_profile=DEEP)
    assert done.wait(4.5), "the call was never answered"
    took = time.monotonic() - start
    assert future.result() == SetBool.Response(success=True, message="data=True")
    assert delay <= took < 4.0
    assert dict(a.routes()[0].counters.drops) == {}
    assert dict(b.routes()[0].counters.drops) == {}


def test_peer_gone_answered_as_failure_within_timeout(engines, domain, ros_side):
    da, port = domain(), free_port()
    entry = (f"service: /set, type: std_srvs/srv/SetBool, direction: transmit, port: {port}, "
             "timeout: 0.3, transport: tcp")
    a = engines(peer_yaml("a", [entry]), da)  # nobody listens on the port
    caller = Caller(ros_side(da, "a"), SetBool, "/set")
    answer = caller.call(SetBool.Request(data=True), timeout=5)
    assert answer == SetBool.Response(success=False,
                                      message=f"rosgate: tcp->127.0.0.1:{port} is down")
    assert dict(a.routes()[0].counters.drops) == {"link_down": 1}


def test_forged_duplicated_and_oversized_service_frames_are_dropped_and_counted(
        engines, domain, ros_side):
    from rclpy.serialization import deserialize_message, serialize_message

    from rosgate.wire import envelope
    from rosgate.wire.envelope import topic_id_for

    da, db, port = domain(), domain(), free_port()
    entry = (f"service: /set, type: std_srvs/srv/SetBool, direction: transmit, port: {port}, "
             "max_request: 100, timeout: 2")
    a = engines(peer_yaml("a", [entry]), da)
    b = engines(peer_yaml("b", [flip(entry)]), db)
    side_a, side_b = ros_side(da, "a"), ros_side(db, "b")
    calls: list[bool] = []

    def counting(request: Any, response: Any) -> Any:
        calls.append(request.data)
        return echo_set_bool(request, response)

    side_b.ros.node.create_service(SetBool, "/set", counting, qos_profile=DEEP)
    caller = Caller(side_a, SetBool, "/set")
    _, drops = caller.warm_up(SetBool.Request(data=True), a, b)
    link_drops = dict(b.link_drops)
    served = len(calls)
    sid = topic_id_for("/set")
    request = lambda seq, body: envelope.pack(envelope.FLAG_REQUEST, sid, 99, seq, 0) + body
    cdr = serialize_message(SetBool.Request(data=False))
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        s.settimeout(5)
        for frame in [request(1, cdr), request(1, cdr),           # the second is a replay
                      request(2, b"\x00\x01\x00\x00"),            # a SetBool request without data
                      request(3, cdr + bytes(100)),               # over max_request
                      envelope.pack(envelope.FLAG_REQUEST, sid ^ 1, 99, 4, 0) + cdr]:  # no such id
            s.sendto(frame, ("127.0.0.1", port))
        answer = s.recv(1000)  # the one served request is answered to where it came from
    header = envelope.unpack(answer)
    assert (header.flags, header.topic_id, header.epoch, header.seq) == \
        (envelope.FLAG_REPLY, sid, 99, 1)
    assert deserialize_message(answer[envelope.SIZE:], SetBool.Response) == \
        SetBool.Response(success=True, message="data=False")
    # an answer nobody asked for: the caller bridge drops it
    route_a = a.routes()[0]
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        reply = envelope.pack(envelope.FLAG_REPLY, sid, route_a.keys.epoch(), 10**6, 0)
        s.sendto(reply + answer[envelope.SIZE:], route_a.link.endpoint.sock.getsockname())
    # a and b count on their own receive threads
    expected = {"a /set": {"late_answer": 1},
                "b /set": {"duplicate": 1, "decode_error": 1, "too_large": 1}}
    # the frame of no service comes last: its link drop may be counted after the rest
    unknown = lambda: Counter(b.link_drops) - Counter(link_drops)
    wait_until(lambda: drops.since() == expected and unknown() == {"unknown_service": 1}, 5)
    assert drops.since() == expected
    assert unknown() == {"unknown_service": 1}
    assert calls[served:] == [False]
    assert caller.call(SetBool.Request(data=False)).message == "data=False"  # still working
