"""The CVRA microcontroller profile end to end: a bridge (in this process) and the simulator in
examples/mcu_simulator.py (a subprocess with its own sockets, nothing from rosgate) exchange
topics both ways and call services both ways; then hostile bytes on both ports."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgpack
import pytest
from conftest import free_port, wait_until
from geometry_msgs.msg import Pose2D, Twist
from rosgate_mcu_cvra import serial_datagram
from std_msgs.msg import Float32
from std_srvs.srv import SetBool, Trigger
from test_services import DEEP, Caller

import rosgate.builtin
from rosgate.config import load, loads, service_to_mapping, topic_to_mapping
from rosgate.errors import ConfigError
from rosgate.plugins import Plugins
from rosgate.resolver.plan import Resolver

SIMULATOR = Path(__file__).parent.parent / "examples" / "mcu_simulator.py"


class Mcu:
    """The simulator as a subprocess; its JSON lines collected for the test to wait on."""

    def __init__(self, *args: str):
        self.lines: list[dict[str, Any]] = []
        self._cond = threading.Condition()
        self.proc = subprocess.Popen([sys.executable, str(SIMULATOR), *args],
                                     stdout=subprocess.PIPE, text=True)
        threading.Thread(target=self._read, daemon=True).start()
        assert self.wait(lambda line: line["kind"] == "ready", 10), "the simulator did not start"

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for text in self.proc.stdout:
            with self._cond:
                self.lines.append(json.loads(text))
                self._cond.notify_all()

    def wait(self, predicate: Callable[[dict[str, Any]], bool], timeout: float) -> dict | None:
        with self._cond:
            self._cond.wait_for(lambda: any(map(predicate, self.lines)), timeout)
            return next((line for line in self.lines if predicate(line)), None)

    def close(self) -> None:
        self.proc.terminate()
        self.proc.wait(5)


@pytest.fixture
def mcu():
    started: list[Mcu] = []

    def start(*args: str) -> Mcu:
        started.append(Mcu(*args))
        return started[-1]

    yield start
    for m in started:
        m.close()


def bridge_yaml(ports: dict[str, int], extra: str = "", layout: str = "") -> str:
    return f"""
bridge: {{name: robot, role: peer, peer: 127.0.0.1, listen: 127.0.0.1,
          defaults: {{codec: msgpack}}}}
topics:
  - {{topic: /position, type: geometry_msgs/msg/Pose2D, direction: receive, port: {ports['in']},
     framing: none}}
  - {{topic: /distance, type: std_msgs/msg/Float32, direction: receive, port: {ports['in']},
     remote: base/distance/measured, framing: none}}
  - {{topic: /cmd_vel, type: geometry_msgs/msg/Twist, direction: transmit, port: {ports['out']},
     framing: none{layout}}}
services:
  - {{service: /mcu/ping, type: std_srvs/srv/Trigger, direction: transmit, remote: ping,
     transport: tcp, port: {ports['mcu']}, framing: serial_datagram, args: value}}
  - {{service: /mcu/set_led, type: std_srvs/srv/SetBool, direction: transmit, remote: set_led,
     transport: tcp, port: {ports['mcu']}, framing: serial_datagram, args: value}}
  - {{service: /mcu/silent, type: std_srvs/srv/Trigger, direction: transmit, remote: silent,
     transport: tcp, port: {ports['mcu']}, framing: serial_datagram, no_answer: nil}}
  - {{service: /reset, type: std_srvs/srv/Trigger, direction: receive, transport: tcp,
     port: {ports['bridge']}, framing: serial_datagram{extra}}}
"""


def ports() -> dict[str, int]:
    return {"in": free_port(), "out": free_port(), "mcu": free_port(), "bridge": free_port()}


def single(value: Any) -> bytes:
    """What CVRA's firmware and cvra_rpc write: msgpack.packb(..., use_single_float=True)."""
    return msgpack.packb(value, use_single_float=True)


def test_a_board_as_cvra_rpc_writes_exchanges_topics_and_calls_both_ways(
        engines, domain, ros_side, mcu):
    d, p = domain(), ports()
    engine = engines(bridge_yaml(p), d)
    side = ros_side(d, "ros")
    resets: list[str] = []

    def reset(request: Any, response: Any) -> Any:
        resets.append("reset")
        response.success, response.message = True, f"reset {len(resets)}"
        return response

    side.ros.node.create_service(Trigger, "/reset", reset, qos_profile=DEEP)
    positions = side.listen("/position", Pose2D)
    distances = side.listen("/distance", Float32)
    sim = mcu("--topic-port", str(p["out"]), "--bridge-topic-port", str(p["in"]),
              "--service-port", str(p["mcu"]), "--bridge-service-port", str(p["bridge"]),
              "--rate", "50", "--call", "reset", "--call-every", "0.2")
    # board -> ROS: ["position", [x, y, theta]] onto a Pose2D by field order, and
    # ["base/distance/measured", 0.125 * n] (a bare float 32) onto a Float32
    assert positions.wait_count(3, 10) and distances.wait_count(3, 10)
    for pose in positions.items:
        assert (pose.y, pose.theta) == (0.5, 0.25) and pose.x == int(pose.x) >= 0
    assert [pose.x for pose in positions.items] == sorted(pose.x for pose in positions.items)
    for distance in distances.items:
        assert distance.data / 0.125 == int(distance.data / 0.125) >= 0
    assert len({d.data for d in distances.items}) == len(distances.items)
    # ROS -> board: a Twist as [name, {fields}], every float a float 32, as the board packs it
    talker = side.publisher("/cmd_vel", Twist)
    twist = Twist()
    twist.linear.x, twist.angular.z = 1.5, -0.25
    deadline = time.monotonic() + 10
    while not sim.wait(lambda line: line["kind"] == "topic", 0.2):
        assert time.monotonic() < deadline, "no cmd_vel reached the board"
        talker.publish(twist)
    got = sim.wait(lambda line: line["kind"] == "topic", 0)
    fields = {"linear": {"x": 1.5, "y": 0.0, "z": 0.0}, "angular": {"x": 0.0, "y": 0.0, "z": -0.25}}
    assert got is not None and (got["name"], got["args"]) == ("cmd_vel", fields)
    assert bytes.fromhex(got["hex"]) == single(["cmd_vel", fields])
    assert not [line for line in sim.lines if line["kind"] == "ignored"]
    # board -> ROS service: ["reset", nil] onto an empty Trigger request; the answer a map
    answer = sim.wait(lambda line: line["kind"] == "answer" and line["answer"]
                      and line["answer"]["success"], 10)
    assert answer is not None and answer["answer"]["message"].startswith("reset ")
    assert set(answer["answer"]) == {"success", "message"}
    assert bytes.fromhex(answer["hex"]) == msgpack.packb(answer["answer"])
    # ROS -> board services: "pong" reaches ROS as a successful Trigger; SetBool's request goes
    # as the bare bool the board reads, its [true, "led on"] answer fills the response in order
    assert Caller(side, Trigger, "/mcu/ping").call(Trigger.Request()) == \
        Trigger.Response(success=True, message="pong")
    led = Caller(side, SetBool, "/mcu/set_led")
    assert led.call(SetBool.Request(data=True)) == SetBool.Response(success=True, message="led on")
    assert led.call(SetBool.Request(data=False)) == SetBool.Response(success=True,
                                                                     message="led off")
    # a handler that returns None answers no byte at all: no_answer: nil takes that for success
    assert Caller(side, Trigger, "/mcu/silent").call(Trigger.Request()) == \
        Trigger.Response(success=True, message="")
    served = lambda: [line for line in sim.lines if line["kind"] == "served"]
    assert sim.wait(lambda line: len(served()) == 4, 5)  # it prints before it answers
    assert [(line["name"], line["args"]) for line in served()] == \
        [("ping", None), ("set_led", True), ("set_led", False), ("silent", {})]
    assert bytes.fromhex(served()[0]["hex"]) == bytes.fromhex("92a470696e67c0")  # ["ping", nil]
    assert bytes.fromhex(served()[1]["hex"]) == single(["set_led", True])
    assert bytes.fromhex(served()[3]["hex"]) == single(["silent", {}])
    stats = {label: s["drops"] for label, s in engine.stats()["routes"].items()}
    assert stats["/position"] == stats["/distance"] == stats["/cmd_vel"] == {}
    assert stats["/mcu/ping"] == stats["/mcu/set_led"] == stats["/mcu/silent"] == {}
    assert set(stats["/reset"]) <= {"no_server"}  # calls before the bridge saw the ROS server
    assert not engine.link_drops


def test_the_readme_layout_name_then_args_still_works(engines, domain, ros_side):
    """name then args, two MessagePack objects: read without a setting, written on request."""
    d, p = domain(), ports()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as board:
        board.bind(("127.0.0.1", p["out"]))
        board.settimeout(0.2)
        engine = engines(bridge_yaml(p, layout=", layout: pair"), d)
        side = ros_side(d, "ros")

        def reset(request: Any, response: Any) -> Any:
            response.success, response.message = True, "done"
            return response

        side.ros.node.create_service(Trigger, "/reset", reset, qos_profile=DEEP)
        positions = side.listen("/position", Pose2D)
        deadline = time.monotonic() + 10
        while not positions.wait_count(1, 0.2):
            assert time.monotonic() < deadline
            board.sendto(msgpack.packb("position") + msgpack.packb({"x": 1.0, "theta": -0.5}),
                         ("127.0.0.1", p["in"]))
        assert positions.items[0] == Pose2D(x=1.0, y=0.0, theta=-0.5)
        talker = side.publisher("/cmd_vel", Twist)
        twist = Twist()
        twist.angular.z = 0.75
        deadline = time.monotonic() + 10
        while True:
            talker.publish(twist)
            try:
                datagram = board.recv(65535)
                break
            except TimeoutError:
                assert time.monotonic() < deadline, "no cmd_vel reached the board"
    assert datagram == single("cmd_vel") + single(
        {"linear": {"x": 0.0, "y": 0.0, "z": 0.0}, "angular": {"x": 0.0, "y": 0.0, "z": 0.75}})
    deadline = time.monotonic() + 10
    pair = serial_datagram.encode(msgpack.packb("reset") + msgpack.packb({}))
    while (answer := msgpack.unpackb(call_raw(p["bridge"], pair))) != \
            {"success": True, "message": "done"}:
        assert answer["message"].startswith("rosgate: no ROS server")
        assert time.monotonic() < deadline
    assert not engine.link_drops


def test_a_datagram_in_neither_layout_is_dropped_and_counted(engines, domain, ros_side):
    d, p = domain(), ports()
    engine = engines(bridge_yaml(p), d)
    positions = ros_side(d, "ros").listen("/position", Pose2D)
    neither = [single(["position"]),                      # an array of one
               single(["position", [1.0, 2.0], "x"]),      # an array of three
               single([7, [1.0]]),                         # [name, args] whose name is no str
               single({"position": [1.0]})]                # a map
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        for datagram in neither:
            s.sendto(datagram, ("127.0.0.1", p["in"]))
        deadline = time.monotonic() + 10
        while not positions.wait_count(1, 0.2):  # the port still takes the real layout
            assert time.monotonic() < deadline
            s.sendto(single(["position", [2.0, 3.0, 0.5]]), ("127.0.0.1", p["in"]))
    assert positions.items[0] == Pose2D(x=2.0, y=3.0, theta=0.5)
    assert wait_until(lambda: engine.link_drops.get("unnamed_frame") == len(neither))
    assert engine.link_drops == {"unnamed_frame": len(neither)}
    for payload in neither:  # and as a call
        assert call_raw(p["bridge"], serial_datagram.encode(payload)) == b""
    assert wait_until(lambda: engine.link_drops.get("unnamed_request") == len(neither))
    route = next(r for r in engine.routes() if r.label == "/position")
    assert not route.counters.drops


@pytest.mark.parametrize("datagram, reason", [
    (single(["position", [1.0, 2.0, 3.0, 4.0]]), r"\[3\]: an array of 4 values for 3 fields"),
    (single(["position", "fast"]), "no field takes str 'fast'"),
    (single(["position", [1.0, "north"]]), "y: expected double"),
    (single(["base/distance/measured", True]), "no field takes True"),
    (msgpack.packb(["base/distance/measured", 1e39]), "data: expected float"),
])
def test_args_that_fit_no_field_are_dropped_naming_the_field(engines, domain, ros_side, caplog,
                                                             datagram, reason):
    d, p = domain(), ports()
    engine = engines(bridge_yaml(p), d)
    ros_side(d, "ros")
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.sendto(datagram, ("127.0.0.1", p["in"]))
    label = "/distance" if b"distance" in datagram else "/position"
    route = next(r for r in engine.routes() if r.label == label)
    assert wait_until(lambda: route.counters.drops.get("decode_error") == 1)
    assert dict(route.counters.drops) == {"decode_error": 1} and not engine.link_drops
    import re
    assert [r for r in caplog.records if re.search(reason, r.getMessage())], \
        [r.getMessage() for r in caplog.records]


def call_raw(port: int, data: bytes, read: bool = True) -> bytes:
    """Write ``data`` to the bridge's call port; return all it answers before it closes."""
    with socket.create_connection(("127.0.0.1", port), 5) as s:
        s.settimeout(5)
        s.sendall(data)
        answer = b""
        while read and (chunk := s.recv(4096)):
            answer += chunk
        return answer


def request(name: str, fields: dict) -> bytes:
    return serial_datagram.encode(msgpack.packb(name) + msgpack.packb(fields))


def test_bad_datagrams_are_dropped_and_counted_and_missing_fields_take_defaults(
        engines, domain, ros_side):
    d, p = domain(), ports()
    engine = engines(bridge_yaml(p), d)
    positions = ros_side(d, "ros").listen("/position", Pose2D)
    pack = msgpack.packb
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        for datagram in [pack("nope") + pack({"x": 1.0}),         # no topic of that name
                         pack("position") + pack({"z": 1.0}),     # no field z
                         pack("position") + pack({"x": "one"}),   # x is not a number
                         pack("position") + b"\xc1",              # not MessagePack
                         b"\xc1",                                 # no name at all
                         pack(7) + pack({})]:                     # a name that is no str
            s.sendto(datagram, ("127.0.0.1", p["in"]))
        deadline = time.monotonic() + 10
        while not positions.wait_count(1, 0.2):  # a good one, with fields left out
            assert time.monotonic() < deadline
            s.sendto(pack("position") + pack({"y": 2.0}), ("127.0.0.1", p["in"]))
    assert positions.items[0] == Pose2D(x=0.0, y=2.0, theta=0.0)
    route = next(r for r in engine.routes() if r.label == "/position")
    assert dict(route.counters.drops) == {"decode_error": 3}
    assert engine.link_drops == {"unknown_topic": 1, "unnamed_frame": 2}


def test_bad_calls_are_dropped_and_counted_and_good_ones_still_answered(engines, domain, ros_side):
    d, p = domain(), ports()
    engine = engines(bridge_yaml(p, ", timeout: 0.5, max_request: 64"), d)
    side = ros_side(d, "ros")

    def reset(request: Any, response: Any) -> Any:
        response.success, response.message = True, "done"
        return response

    side.ros.node.create_service(Trigger, "/reset", reset, qos_profile=DEEP)
    port = p["bridge"]
    good = request("reset", {})
    bad_crc = bytearray(good)
    bad_crc[2] ^= 0x01
    assert call_raw(port, bytes(bad_crc)) == b""
    assert call_raw(port, b"\x92\xdb\x41" + good) == b""                 # ESC then neither
    assert call_raw(port, b"\x01\x02\xc0") == b""                        # shorter than a CRC
    assert call_raw(port, request("reset", {"pad": "x" * 100})) == b""   # over max_request
    assert call_raw(port, request("nope", {})) == b""                    # no such service
    assert call_raw(port, request("reset", {"force": True})) == b""      # no such field
    assert call_raw(port, serial_datagram.encode(b"\xc1")) == b""        # no name
    start = time.monotonic()
    assert call_raw(port, b"") == b""                                    # says nothing
    assert 0.5 <= time.monotonic() - start < 1.5
    assert call_raw(port, good[:5]) == b""                               # half a request
    with socket.create_connection(("127.0.0.1", port), 5) as s:          # gives up early
        s.sendall(good[:5])
    assert wait_until(lambda: engine.link_drops.get("closed_early") == 1)
    # a good call (until the bridge has seen the ROS server), from a caller that never closes:
    # the bridge answers and closes
    deadline = time.monotonic() + 10
    while (answer := msgpack.unpackb(call_raw(port, good))) != {"success": True, "message": "done"}:
        assert answer["message"] == "rosgate: no ROS server /reset is running on the serving side"
        assert time.monotonic() < deadline
    route = next(r for r in engine.routes() if r.label == "/reset")
    assert {k: v for k, v in route.counters.drops.items() if k != "no_server"} == \
        {"decode_error": 1}
    assert engine.link_drops == {"bad_crc": 1, "bad_escape": 1, "too_short": 1, "too_long": 1,
                                 "unknown_service": 1, "unnamed_request": 1, "request_timeout": 2,
                                 "closed_early": 1}


def test_microcontroller_that_never_answers_fails_the_call_within_timeout(
        engines, domain, ros_side):
    d, p = domain(), ports()
    with socket.socket() as silent:  # accepts, reads, never answers, never closes
        silent.bind(("127.0.0.1", p["mcu"]))
        silent.listen(4)
        yaml = bridge_yaml(p).replace("remote: ping,", "remote: ping, timeout: 0.4,")
        engine = engines(yaml, d)
        caller = Caller(ros_side(d, "ros"), Trigger, "/mcu/ping")
        start = time.monotonic()
        answer = caller.call(Trigger.Request(), timeout=5)
        assert 0.4 <= time.monotonic() - start < 0.8
        assert answer == Trigger.Response(
            success=False, message=f"rosgate: no answer from 127.0.0.1:{p['mcu']} within 0.4 s")
        conn, _ = silent.accept()
        with conn:
            # what it was sent: ["ping", nil] (args: value, and Trigger's request has no field)
            frames = serial_datagram.Decoder(lambda *e: None).feed(conn.recv(4096))
            assert next(frames) == msgpack.packb(["ping", None]) == bytes.fromhex("92a470696e67c0")
    route = next(r for r in engine.routes() if r.label == "/mcu/ping")
    assert dict(route.counters.drops) == {"timeout": 1}


@pytest.mark.parametrize("answer, close, expected, reason", [
    # answers, never closes: the bridge takes the answer and closes itself
    (msgpack.packb({"success": True, "message": "pong"}), False,
     Trigger.Response(success=True, message="pong"), None),
    # not MessagePack, then closes
    (b"\xc1", True, None, "decode_error"),
    # a field Trigger's response does not have
    (msgpack.packb({"succes": True}), True, None, "decode_error"),
    # closes without a word
    (b"", True, None, "no_answer"),
    # what the firmware answers: a bare str, or nil when its handler wrote nothing
    (msgpack.packb("pong"), True, Trigger.Response(success=True, message="pong"), None),
    (msgpack.packb(None), True, Trigger.Response(success=True, message=""), None),
    (msgpack.packb([False, "busy"]), True, Trigger.Response(success=False, message="busy"), None),
    # a value no field of Trigger's response takes
    (msgpack.packb(1.5), True, None, "decode_error"),
])
def test_what_a_microcontroller_answers_is_checked(engines, domain, ros_side, answer, close,
                                                   expected, reason):
    d, p = domain(), ports()
    with socket.socket() as fake:
        fake.bind(("127.0.0.1", p["mcu"]))
        fake.listen(4)

        closed_by_bridge: list[bool] = []

        def serve() -> None:
            conn, _ = fake.accept()
            conn.recv(4096)
            conn.sendall(answer)
            if not close:  # keep it open until the bridge closes it
                conn.settimeout(5)
                closed_by_bridge.append(conn.recv(1) == b"")
            conn.close()
        server = threading.Thread(target=serve)
        server.start()
        engine = engines(bridge_yaml(p).replace("remote: ping,", "remote: ping, timeout: 2,"), d)
        got = Caller(ros_side(d, "ros"), Trigger, "/mcu/ping").call(Trigger.Request(), timeout=5)
        server.join(5)
        assert not server.is_alive()
    route = next(r for r in engine.routes() if r.label == "/mcu/ping")
    assert closed_by_bridge == ([] if close else [True])
    if expected is not None:
        assert got == expected and not route.counters.drops
    else:
        assert not got.success and got.message.startswith("rosgate: ")
        assert dict(route.counters.drops) == {reason: 1}


def test_random_bytes_on_both_ports_are_each_dropped_once(engines, domain, ros_side):
    import random

    d, p = domain(), ports()
    engine = engines(bridge_yaml(p, ", max_request: 200"), d)
    positions = ros_side(d, "ros").listen("/position", Pose2D)
    rng = random.Random(4)
    blobs = [rng.randbytes(rng.randint(0, 300)) + b"\xc0" for _ in range(40)]
    for blob in blobs:  # each ends in END: one frame, never valid (its CRC would have to match)
        assert call_raw(p["bridge"], blob) == b""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        for blob in blobs:
            s.sendto(blob, ("127.0.0.1", p["in"]))
        deadline = time.monotonic() + 10
        while not positions.wait_count(1, 0.2):  # still flowing
            assert time.monotonic() < deadline
            s.sendto(msgpack.packb("position") + msgpack.packb({"x": 1.0}), ("127.0.0.1", p["in"]))
    calls = {"bad_crc", "bad_escape", "too_short", "too_long"}
    assert wait_until(lambda: sum(engine.link_drops.get(k, 0) for k in calls) == 40)
    topic_drops = sum(engine.link_drops.get(k, 0) for k in ("unknown_topic", "unnamed_frame"))
    position = next(r for r in engine.routes() if r.label == "/position")
    assert topic_drops + sum(position.counters.drops.values()) == 40
    assert positions.items[0] == Pose2D(x=1.0)


@pytest.mark.parametrize("allow, crosses", [("[10.9.9.9, 192.168.0.0/16]", False),
                                            ("[10.9.9.9, 127.0.0.0/8]", True)],
                         ids=["elsewhere", "allowed"])
def test_an_address_allow_list_guards_a_keyless_microcontroller_port(engines, domain, ros_side,
                                                                    allow, crosses):
    """The CVRA profile has no keys; ``bridge.allow`` takes datagrams and calls only from the
    listed addresses: the others are dropped, counted ``not_allowed``, never published."""
    d, port, call_port = domain(), free_port(), free_port()
    bridge = engines(f"""
bridge: {{name: robot, role: peer, peer: 127.0.0.1, listen: 127.0.0.1, allow: {allow},
          defaults: {{codec: msgpack}}}}
topics:
  - {{topic: /position, type: geometry_msgs/msg/Pose2D, direction: receive, port: {port},
     framing: none}}
services:
  - {{service: /reset, type: std_srvs/srv/Trigger, direction: receive, transport: tcp,
     port: {call_port}, framing: serial_datagram}}
""", d)
    inbox = ros_side(d, "listener").listen("/position", Pose2D)
    datagram = msgpack.packb("position") + msgpack.packb({"x": 1.0, "y": 2.0, "theta": 0.5})
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        for _ in range(20):
            s.sendto(datagram, ("127.0.0.1", port))
            if inbox.wait_count(1, 0.1):
                break
    with socket.create_connection(("127.0.0.1", call_port), timeout=5) as call:
        call.sendall(serial_datagram.encode(msgpack.packb("reset") + msgpack.packb({})))
        call.settimeout(10)
        answer = call.recv(1000)
    assert bool(inbox.items) is crosses
    if crosses:
        assert answer  # answered (a failure: no ROS server /reset runs here)
        assert "not_allowed" not in bridge.link_drops
    else:
        assert answer == b""  # closed at once
        assert wait_until(lambda: bridge.link_drops.get("not_allowed") == 21)


# -- configuration ------------------------------------------------------------------------------

MCU_TOPIC = """
bridge: {name: robot, role: peer, peer: 127.0.0.1, listen: 127.0.0.1}
topics:
  - topic: /cmd_vel
    type: geometry_msgs/msg/Twist
    direction: transmit
    port: 20000
    codec: msgpack
"""


@pytest.mark.parametrize("entry, key, message", [
    ("    layout: pair\n", "topics[0].layout", "layout is for microcontroller entries"),
    ("    framing: none\n    layout: list\n", "topics[0].layout",
     "'list' is not one of array, pair"),
    ("    framing: none\n    args: dict\n", "topics[0].args", "'dict' is not one of map, array"),
    ("    framing: none\n    floats: 32\n", "topics[0].floats",
     "32 is not one of float32, float64"),  # a number, as YAML read it
    ("    floats: float32\n", "topics[0].floats", "floats is for microcontroller entries"),
])
def test_microcontroller_keys_are_checked_where_they_are_written(tmp_path, entry, key, message):
    path = tmp_path / "bringup.yaml"
    path.write_text(MCU_TOPIC.lstrip() + entry)
    with pytest.raises(ConfigError) as error:
        load(path)
    assert error.value.key == key and message in error.value.message
    assert error.value.line == len(MCU_TOPIC.lstrip().splitlines()) + entry.count("\n")
    assert error.value.fix


def test_no_answer_belongs_to_calls_made_to_a_board():
    services = """
services:
  - {service: /reset, type: std_srvs/srv/Trigger, direction: receive, transport: tcp,
     port: 20001, framing: serial_datagram, codec: msgpack, no_answer: nil}
"""
    with pytest.raises(ConfigError, match="no_answer is for calls this bridge makes"):
        loads(MCU_TOPIC + services)
    config = loads(MCU_TOPIC + "    framing: none\n" + services.replace(
        "direction: receive", "direction: transmit"))
    (topic,), (service,) = config.topics, config.services
    assert (topic.layout, topic.args, topic.floats) == ("array", "map", "float32")
    assert (service.layout, service.no_answer) == ("array", "nil")
    assert "layout" in topic_to_mapping(topic) and service_to_mapping(service)["no_answer"] == "nil"
    envelope = loads(MCU_TOPIC).topics[0]
    assert not {"layout", "args", "floats"} & set(topic_to_mapping(envelope))


def test_check_names_the_distribution_that_makes_the_calls_when_it_is_missing():
    """Service calls with a board are the plugin rosgate-mcu-cvra's; without it, the entry's
    framing is the error, with the distribution to install."""
    import rosgate_codec_msgpack
    import rosgate_transport_tcp
    import rosgate_transport_udp

    services = """
services:
  - {service: /mcu/ping, type: std_srvs/srv/Trigger, direction: transmit, remote: ping,
     transport: tcp, port: 20001, framing: serial_datagram, codec: msgpack}
"""
    config = loads(MCU_TOPIC + "    framing: none\n" + services)
    without = Plugins()
    for name, module in (("builtin", rosgate.builtin), ("tcp", rosgate_transport_tcp),
                         ("udp", rosgate_transport_udp), ("msgpack", rosgate_codec_msgpack)):
        without.add(module, name)
    with pytest.raises(ConfigError) as error:
        Resolver(config, without).plan()
    assert (error.value.key, error.value.line) == ("services[0].framing", 13)
    assert error.value.message == ("unknown service framing 'serial_datagram' (installed service "
                                   "framings: none)")
    assert error.value.fix == ("pip install the distribution that provides it (rosgate-mcu-cvra), "
                               "or pick an installed service framing")
    with_it = Plugins.discover()
    plan = Resolver(config, with_it).plan()
    assert plan.services[0].service_framing is with_it.get("service_framing",
                                                           "serial_datagram").cls
    assert with_it.get("service_framing", "serial_datagram").distribution == "rosgate-mcu-cvra"
