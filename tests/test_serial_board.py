"""A microcontroller simulator on a pseudo-terminal: tests/data/serial_board/board.c, C written
to the interface of CVRA's lib/serial-datagram (a send function, a receive handler fed byte by
byte) and to its firmware's message layout, compiled here with ``cc``. Its frames agree byte for
byte with rosgate's framing and the shared vectors, and it exchanges topics both ways with a
bridge over the serial link."""

from __future__ import annotations

import shutil
import subprocess
import threading
import time
from pathlib import Path

import msgpack
import pytest
import serial
from conftest import wait_until
from geometry_msgs.msg import Pose2D, Twist
from rosgate_emulator.serial import LineProfile, PtyRelay
from rosgate_mcu_cvra import serial_datagram
from test_serial_link import board_peer

ROOT = Path(__file__).resolve().parents[1]
SOURCE = ROOT / "tests" / "data" / "serial_board" / "board.c"
VECTORS = ROOT / "plugins" / "mcu_cvra" / "tests" / "vectors" / "serial_datagram.txt"
POSITION = msgpack.packb(["position", [1.0, 0.5, 0.25]], use_single_float=True)

pytestmark = pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler (cc)")


@pytest.fixture(scope="module")
def board_program(tmp_path_factory) -> Path:
    program = tmp_path_factory.mktemp("board") / "board"
    subprocess.run(["cc", "-O2", "-Wall", "-Wextra", "-Werror", "-std=c11", "-D_DEFAULT_SOURCE",
                    "-o", str(program), str(SOURCE)], check=True, timeout=60)
    return program


class Board:
    """The simulator running on one end of a line; its output lines, as they come."""

    def __init__(self, program: Path, device: str, seconds: float = 60):
        self.proc = subprocess.Popen([str(program), device, str(seconds)],
                                     stdout=subprocess.PIPE, text=True)
        self.lines: list[str] = []
        self.cond = threading.Condition()
        self.reader = threading.Thread(target=self._read, daemon=True)
        self.reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            with self.cond:
                self.lines.append(line.rstrip("\n"))
                self.cond.notify_all()

    def wait_for(self, predicate, timeout: float = 10.0) -> bool:
        with self.cond:
            return self.cond.wait_for(lambda: predicate(self.lines), timeout)

    def stop(self) -> None:
        self.proc.terminate()
        self.proc.wait(10)
        self.reader.join(5)


def vectors() -> list[tuple[bytes, bytes]]:
    pairs = []
    for line in VECTORS.read_text().splitlines():
        if "->" in line and not line.startswith("#"):
            payload, frame = (part.strip() for part in line.split("->"))
            pairs.append((b"" if payload == "(empty)" else bytes.fromhex(payload),
                          bytes.fromhex(frame)))
    return pairs


def test_the_board_frames_byte_for_byte_as_rosgate_and_reads_every_vector(
        board_program, tmp_path):
    with PtyRelay(tmp_path, LineProfile(baud=1_000_000)) as relay:
        line = serial.Serial(relay.a, timeout=5)
        board = Board(board_program, relay.b)
        try:
            expected = serial_datagram.encode(POSITION)
            assert line.read(len(expected)) == expected
            spoilt = bytearray(serial_datagram.encode(b"spoilt"))
            spoilt[0] ^= 1
            frames = [frame for _, frame in vectors()]
            line.write(b"".join(frames[:2]) + bytes(spoilt) + frames[2])
            payloads = [payload for payload, _ in vectors()]
            want = [f"got {payloads[0].hex()}", f"got {payloads[1].hex()}", "error 2",
                    f"got {payloads[2].hex()}"]
            assert board.wait_for(lambda lines: len(lines) >= 4), board.lines
            # a datagram is printed as it completes, an error once its read is done
            assert sorted(board.lines[:4]) == sorted(want)
        finally:
            board.stop()
            line.close()


def test_the_board_and_a_bridge_exchange_topics_both_ways(
        board_program, engines, domain, ros_side, tmp_path):
    with PtyRelay(tmp_path, LineProfile(baud=115_200)) as relay:
        d = domain()
        engines(board_peer(relay.a), d)
        side = ros_side(d, "robot")
        positions = side.listen("/position", Pose2D)
        cmd_vel = side.publisher("/cmd_vel", Twist)
        board = Board(board_program, relay.b)
        command = Twist()
        command.linear.x, command.angular.z = 0.75, -0.5
        expected = msgpack.packb(["cmd_vel", {"linear": {"x": 0.75, "y": 0.0, "z": 0.0},
                                              "angular": {"x": 0.0, "y": 0.0, "z": -0.5}}],
                                 use_single_float=True).hex()
        try:
            deadline = time.monotonic() + 30
            while not board.wait_for(lambda lines: f"got {expected}" in lines, 0.2):
                assert time.monotonic() < deadline, board.lines[-5:]
                cmd_vel.publish(command)
            assert positions.wait_count(10, 10), len(positions.items)
        finally:
            board.stop()
        assert all(p == Pose2D(x=1.0, y=0.5, theta=0.25) for p in positions.items)
        assert all(line == f"got {expected}" or line.startswith("error ")
                   for line in board.lines), board.lines


def test_the_bridge_calls_the_board_over_the_line_and_a_call_carries_its_id(
        board_program, engines, domain, ros_side, tmp_path):
    """A Trigger served by the board: the bridge writes ``["ping", {}, id]`` and the board
    answers ``[id, [true, "pong"]]`` on the line that carries its topics; the topic port is not
    troubled by the calls."""
    from std_srvs.srv import Trigger
    from test_services import Caller

    with PtyRelay(tmp_path, LineProfile(baud=115_200)) as relay:
        d = domain()
        robot = engines(f"""
bridge: {{name: robot, role: peer, peer: board, listen: board, insecure: true,
         defaults: {{codec: msgpack, transport: serial}}}}
plugins:
  serial: {{device: {relay.a}, baud: 115200, multiplex: false}}
topics:
  - {{topic: /position, type: geometry_msgs/msg/Pose2D, direction: receive, port: 1,
     framing: none}}
services:
  - {{service: /ping, type: std_srvs/srv/Trigger, direction: transmit, port: 2,
     framing: serial_datagram, timeout: 2}}
""", d)
        side = ros_side(d, "robot")
        positions = side.listen("/position", Pose2D)
        board = Board(board_program, relay.b)
        try:
            ping = Caller(side, Trigger, "/ping")
            answers = [ping.call(Trigger.Request(), timeout=5) for _ in range(3)]
            assert positions.wait_count(10, 10), len(positions.items)
        finally:
            board.stop()
        assert answers == [Trigger.Response(success=True, message="pong")] * 3
        calls = [bytes.fromhex(line[4:]) for line in board.lines if line.startswith("got ")]
        first = msgpack.unpackb(calls[0])[2]
        assert [msgpack.unpackb(c) for c in calls[:3]] == [
            ["ping", {}, first], ["ping", {}, first + 1], ["ping", {}, first + 2]], calls
        route = next(r for r in robot.routes() if r.label == "/ping")
        assert (route.counters.sent, route.counters.received) == (3, 3)
        assert robot.link_drops == {}, robot.link_drops


def test_a_board_calls_a_ros_service_over_the_line(engines, domain, ros_side, tmp_path):
    """The board (here: the test, on the pseudo-terminal) calls ``["reset", {}, id]``: the
    bridge serves it with the ROS server and answers ``[id, value]``; a call for a service the
    line does not serve is counted ``unknown_service`` and not answered. The file is
    docs/microcontrollers.md's: topics, the board's services and ROS's share the line."""
    from std_srvs.srv import Trigger
    from test_services import DEEP, pong

    with PtyRelay(tmp_path, LineProfile(baud=115_200)) as relay:
        d = domain()
        robot = engines(f"""
bridge: {{name: robot, role: peer, peer: board, listen: board, insecure: true,
         defaults: {{codec: msgpack, transport: serial}}}}
plugins:
  serial: {{device: {relay.a}, baud: 115200, multiplex: false}}
topics:
  - {{topic: /position, type: geometry_msgs/msg/Pose2D, direction: receive, port: 1,
     framing: none}}
services:
  - {{service: /mcu/ping, type: std_srvs/srv/Trigger, direction: transmit, port: 2,
     remote: ping, framing: serial_datagram, timeout: 1}}
  - {{service: /reset, type: std_srvs/srv/Trigger, direction: receive, port: 3,
     framing: serial_datagram, timeout: 2}}
""", d)
        side = ros_side(d, "robot")
        side.ros.node.create_service(Trigger, "/reset", pong, qos_profile=DEEP)
        line = serial.Serial(relay.b, 115200, timeout=0.1)
        decoder = serial_datagram.Decoder(lambda reason, detail: None)
        try:
            answers: list = []
            deadline = time.monotonic() + 30
            ident = 100
            while not any(a[1] == {"success": True, "message": "pong"} for a in answers):
                assert time.monotonic() < deadline, answers  # until the ROS server is found
                ident += 1
                line.write(serial_datagram.encode(msgpack.packb(["reset", {}, ident])))
                answers += [msgpack.unpackb(f) for f in decoder.feed(line.read(1000))]
            line.write(serial_datagram.encode(msgpack.packb(["launch", {}, 1])))
            answered = {a[0] for a in answers}
            assert wait_until(lambda: robot.link_drops.get("unknown_service") == 1, 5), \
                robot.link_drops
            answers += [msgpack.unpackb(f) for f in decoder.feed(line.read(1000))]
        finally:
            line.close()
        assert all(a[0] in range(101, ident + 1) for a in answers), answers
        assert answers[-1] == [ident, {"success": True, "message": "pong"}]
        assert 1 not in answered and all(a[0] != 1 for a in answers)
        assert robot.link_drops == {"unknown_service": 1}, robot.link_drops  # nothing else
