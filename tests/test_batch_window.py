"""A topic's batch window between two real bridges (client/server, the session's cipher): what
a publisher sends within a window arrives, every message, in order and byte for byte, in far
fewer datagrams or stream writes than messages; no message waits much longer than the window,
the last one included (no later message closes its window); and every message of the first
window waited for it (the window is really there).

The window is 20 ms and the publisher sends one 2.5 kB message a millisecond, so a window holds
about 20 of them; the timing assertions have a margin of 200 ms for a loaded machine."""

from __future__ import annotations

import re
import time
from pathlib import Path

import pytest
from conftest import free_port
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

WINDOW = 0.02
COUNT = 400
MARGIN = 0.2  # seconds a loaded machine may add to a message's way


def text(i: int) -> str:
    return f"{i:06d}-{time.time_ns():019d}-" + "x" * 2_473  # 2,500 bytes, with when it left


def link_line(log: str, link: str) -> tuple[int, int]:
    """A link's frames out and the datagrams (or stream writes) that carried them."""
    found = re.search(rf"link {link}[^\n]*?: out (\d+) frames in (\d+) packets", log)
    assert found, log
    return int(found.group(1)), int(found.group(2))


def drops_of(log: str, topic: str) -> str:
    line = [line for line in log.splitlines() if topic in line and "drops:" in line][-1]
    return line.rsplit("drops: ", 1)[1]


@pytest.mark.parametrize("reliability, transport, link", [
    ("best_effort", "udp", "udp"), ("reliable", "udp", "udp"),
    ("reliable", "tcp", "main")])  # a client's tcp topics share its main line
def test_a_window_of_messages_arrives_whole_in_order_in_few_datagrams(
        tmp_path: Path, domain, ros_side, bridge, reliability, transport, link):
    server_domain, client_domain = domain(), domain()
    port = free_port()
    (tmp_path / "server.yaml").write_text(
        f"bridge: {{name: base, role: server, server: 127.0.0.1:{port}}}\n")
    (tmp_path / "robot1.yaml").write_text(f"""
bridge: {{name: robot1, role: client, server: 127.0.0.1:{port}}}
topics:
  - {{topic: /scan, type: std_msgs/msg/String, direction: transmit, transport: {transport},
     qos: {{reliability: {reliability}, depth: 1000}}, batch: {WINDOW * 1e3:g}ms}}
""")
    base = bridge(tmp_path / "server.yaml", server_domain)
    robot = bridge(tmp_path / "robot1.yaml", client_domain)
    far, near = ros_side(server_domain, "far"), ros_side(client_domain, "near")
    qos = QoSProfile(depth=10_000, reliability=getattr(ReliabilityPolicy, reliability.upper()))
    arrived: list[tuple[int, str]] = []
    far.ros.subscribe(String, "/scan", qos, lambda m: arrived.append((time.time_ns(), m.data)),
                      raw=False)
    publisher = near.publisher("/scan", String, qos)

    deadline = time.monotonic() + 30
    while not arrived:  # the session is up and DDS has matched both ends
        assert time.monotonic() < deadline, "nothing crossed the bridge"
        publisher.publish(String(data="warmup"))
        time.sleep(0.1)
    time.sleep(2 * WINDOW + MARGIN)  # the warm-ups' windows are closed
    warmups = len(arrived)

    start = time.monotonic()
    for i in range(COUNT):  # one a millisecond, paced from the start (no drift)
        delay = start + i * 0.001 - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        publisher.publish(String(data=text(i)))
    mine = lambda: [(at, data) for at, data in arrived[warmups:] if data != "warmup"]
    deadline = time.monotonic() + 20
    while len(mine()) < COUNT and time.monotonic() < deadline:  # a late warm-up is not one
        time.sleep(0.01)
    got = mine()

    # every message, in order, byte for byte
    assert [int(data[:6]) for _, data in got] == list(range(COUNT))
    assert all(len(data) == 2_500 and data.endswith("x" * 2_473) for _, data in got)
    # each waited for its window, and not much longer
    waits = [(at - int(data[7:26])) / 1e9 for at, data in got]
    assert max(waits) <= WINDOW + MARGIN, sorted(waits)[-10:]
    assert waits[0] >= WINDOW * 0.9, waits[:5]  # the first message of a window waits it out
    assert got[-1][0] - int(got[-1][1][7:26]) <= (WINDOW + MARGIN) * 1e9  # the last one too

    assert robot.stop() == 0 and base.stop() == 0  # their last lines: the counters
    assert drops_of(robot.log, "/scan") == "none", robot.log
    assert drops_of(base.log, "/scan") == "none", base.log
    frames, packets = link_line(robot.log, link)
    # ~20 messages a window: at most a quarter as many datagrams (writes) as frames
    assert frames >= COUNT and packets <= frames / 4, robot.log
