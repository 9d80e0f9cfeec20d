"""A bridge that is not scheduled for a while drops nothing on an idle link: the file a user
writes (client/server, identities, udp, cdr, the session's cipher), a best-effort topic at
1,000 messages a second of 2.5 kB, and each bridge process stopped (SIGSTOP) for 50 ms again
and again while it flows — the client between taking and sending, the server between receiving
and publishing. Loopback is idle throughout, so neither side may count a ``too_late`` or
``superseded`` drop (nor any other), and every message arrives, byte for byte.

The drops that remain when the link is the bottleneck are tested in
core/tests/test_late_drops.py."""

from __future__ import annotations

import re
import subprocess
import sys
import time
from pathlib import Path

from conftest import free_port, warm_up
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

RATE = 1_000
COUNT = 2_000
STALL = 0.05      # seconds each stop lasts
BETWEEN = 0.2     # seconds between two stops


def text(i: int) -> str:
    return f"{i:06d}-" + "x" * 2_493


def counters(log: str, topic: str) -> tuple[int, int, str]:
    line = [line for line in log.splitlines() if topic in line and "drops:" in line][-1]
    sent, received = (int(re.search(rf"{word} (\d+)", line).group(1))  # type: ignore[union-attr]
                      for word in ("sent", "received"))
    return sent, received, line.rsplit("drops: ", 1)[1]


# The stopper runs in a process of its own: a thread of the test's process, which publishes
# 1,000 messages a second, may wait for the GIL long enough on a loaded machine to stop the
# bridges fewer times than the test needs.
STALLER = f"""
import os, select, signal, sys, time
pids, stops, turn = [int(p) for p in sys.argv[1:]], [0] * (len(sys.argv) - 1), 0
while not select.select([sys.stdin], [], [], {BETWEEN})[0]:  # until the test closes stdin
    pid = pids[turn % len(pids)]
    os.kill(pid, signal.SIGSTOP)
    try:
        time.sleep({STALL})  # the stall itself: what the test is about
    finally:
        os.kill(pid, signal.SIGCONT)
    stops[turn % len(pids)] += 1
    turn += 1
print(*stops)
"""


def stall(pids: list[int]) -> subprocess.Popen:
    """Stop each process in turn for STALL seconds, every BETWEEN seconds, until :func:`stops`."""
    return subprocess.Popen([sys.executable, "-c", STALLER, *map(str, pids)],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)


def stops(staller: subprocess.Popen) -> list[int]:
    """End the stopper; how many times it stopped each process."""
    out, _ = staller.communicate("", timeout=10)
    return [int(n) for n in out.split()]


def test_stopping_either_bridge_for_50_ms_loses_nothing(tmp_path: Path, domain, ros_side,
                                                         bridge):
    server_domain, client_domain = domain(), domain()
    port = free_port()
    (tmp_path / "server.yaml").write_text(
        f"bridge: {{name: base, role: server, server: 127.0.0.1:{port}}}\n")
    (tmp_path / "robot1.yaml").write_text(f"""
bridge: {{name: robot1, role: client, server: 127.0.0.1:{port}}}
topics:
  - {{topic: /scan, type: std_msgs/msg/String, direction: transmit,
     qos: {{reliability: best_effort, depth: 1000}}}}
""")
    base = bridge(tmp_path / "server.yaml", server_domain)
    robot = bridge(tmp_path / "robot1.yaml", client_domain)
    far, near = ros_side(server_domain, "far"), ros_side(client_domain, "near")
    deep = QoSProfile(depth=10_000, reliability=ReliabilityPolicy.BEST_EFFORT)
    inbox = far.listen("/scan", String, deep)
    publisher = near.publisher("/scan", String, deep)

    # the session is up and DDS has matched both ends
    warmups_sent = warm_up(publisher, inbox, String(data="warmup"))
    warmups = len(inbox.items)

    staller = stall([robot.proc.pid, base.proc.pid])
    try:
        start = time.monotonic()
        for i in range(COUNT):
            if i % 10 == 0:  # a steady rate, in bursts of 10
                delay = start + i / RATE - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            publisher.publish(String(data=text(i)))
    finally:
        stopped = stops(staller)
    inbox.wait_for(lambda items: len(items) >= warmups + COUNT, 20)
    got = [m.data for m in inbox.items if m.data != "warmup"]

    assert min(stopped) >= 3, stopped  # each bridge was stopped, several times, while it flowed
    assert robot.stop() == 0 and base.stop() == 0  # their last lines: the counters
    sent, _, robot_drops = counters(robot.log, "/scan")
    _, received, base_drops = counters(base.log, "/scan")
    assert robot_drops == "none", robot.log
    assert base_drops == "none", base.log
    assert COUNT <= sent <= COUNT + warmups_sent, robot.log  # it took every one
    assert received == sent, base.log
    assert got == [text(i) for i in range(COUNT)]  # every one, in order, byte for byte
