"""A link that stays behind: best effort sheds its oldest messages, and what arrives is fresh.

The file a user writes (client/server, identities, udp, cdr, the session's cipher) with a budget
of 4 Mbit/s on the client's udp link, about 190 messages a second of 2.5 kB, and a best-effort
topic that is not latest-only offered twice that for 3 s. The send queue grows until the topic
has been behind for 200 ms on end; from then on the client sheds what waited over 20 ms
(counted ``overload``) and what arrives is a few milliseconds old. Without the shedding it
waited up to the link's ``max_delay``, a second.

Stalls shorter than that drop nothing: tests/test_stalls.py; the rules themselves, on a
simulated clock and on a real link: core/tests/test_scheduler.py, core/tests/test_late_drops.py.
"""

from __future__ import annotations

import statistics
import time
from pathlib import Path

import pytest
from conftest import Inbox, free_port, warm_up
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import String
from test_default_file_speed import counters

RATE = 380       # messages a second: twice what the budget carries
SECONDS = 3.0
SETTLED = 1.0    # seconds into the run after which what arrives must be fresh


def text(i: int) -> str:
    """Message ``i``, saying when it was published (time.time_ns()), 2,500 bytes in all."""
    head = f"{i:06d}-{time.time_ns():019d}-"
    return head + "x" * (2_500 - len(head))


@pytest.mark.alone  # it asserts messages' ages, which other tests' load on the cores would add to
def test_a_budget_offered_twice_what_it_carries_sheds_and_delivers_fresh(tmp_path: Path, domain,
                                                                          ros_side, bridge):
    server_domain, client_domain = domain(), domain()
    port = free_port()
    (tmp_path / "server.yaml").write_text(
        f"bridge: {{name: base, role: server, server: 127.0.0.1:{port}}}\n")
    (tmp_path / "robot1.yaml").write_text(f"""
bridge: {{name: robot1, role: client, server: 127.0.0.1:{port},
         links: {{udp: {{bandwidth: 4mbit}}}}}}
topics:
  - {{topic: /scan, type: std_msgs/msg/String, direction: transmit, latest_only: false,
     qos: {{reliability: best_effort, depth: 1000}}}}
""")
    base = bridge(tmp_path / "server.yaml", server_domain)
    robot = bridge(tmp_path / "robot1.yaml", client_domain)
    far, near = ros_side(server_domain, "far"), ros_side(client_domain, "near")
    deep = QoSProfile(depth=10_000, reliability=ReliabilityPolicy.BEST_EFFORT)
    inbox = Inbox()  # (when it arrived, its data)
    far.ros.subscribe(String, "/scan", deep, lambda m: inbox.put((time.time_ns(), m.data)),
                      raw=False)
    publisher = near.publisher("/scan", String, deep)

    # the session is up and DDS has matched both ends
    warmups_sent = warm_up(publisher, inbox, String(data="warmup"))
    inbox.wait_for(lambda items: False, 0.5)  # what the warm-up queued is gone
    warmups = len(inbox.items)

    count = int(RATE * SECONDS)
    start = time.monotonic()
    for i in range(count):
        delay = start + i / RATE - time.monotonic()
        if delay > 0:
            time.sleep(delay)  # paces the publisher
        publisher.publish(String(data=text(i)))
    while inbox.wait_count(len(inbox.items) + 1, 0.5):
        pass  # until what the send queue held has arrived: nothing more for 0.5 s
    assert robot.stop() == 0 and base.stop() == 0  # their last lines: the counters
    sent, _, drops = counters(robot.log, "/scan")
    _, received, far_drops = counters(base.log, "/scan")
    got = [(at, data) for at, data in inbox.items[warmups:] if data != "warmup"]

    # the client took them all and shed in its send queue, for no other reason; the server
    # took every frame that left
    assert count + warmups_sent >= sent >= 0.9 * count, robot.log
    assert set(drops) == {"overload"}, robot.log
    assert drops["overload"] > count / 4, robot.log
    assert far_drops == {} and received == sent - drops["overload"], base.log
    # in order, each once, byte for byte
    numbers = [int(data[:6]) for _, data in got]
    assert numbers == sorted(set(numbers))
    assert all(len(data) == 2_500 and data.endswith("x" * 2_400) for _, data in got)
    assert len(got) >= 0.9 * (received - warmups_sent)
    # fresh once settled: a few ms on the link, at most the 20 ms the queue may lag besides
    published = [int(data[7:26]) for _, data in got]
    ages = [(sent_at, (at - sent_at) / 1e9) for (at, _), sent_at in zip(got, published,
                                                                         strict=True)]
    first = published[0]
    settled = sorted(age for sent_at, age in ages if sent_at - first > SETTLED * 1e9)
    assert len(settled) > 200, len(settled)
    assert statistics.median(settled) < 0.05, settled
    assert settled[int(0.95 * len(settled))] < 0.15, settled
