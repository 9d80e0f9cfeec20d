"""A reliable topic loses nothing on a lossy datagram link; a best-effort one beside it stays
fresh. The README's default file (client/server, identities, udp, aead) between two
``rosgate run`` processes, with a fault proxy (faults.py) on the server's port: UDP datagrams
dropped, duplicated and reordered each way, the TCP main line untouched.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest
from conftest import cross, free_port, settle, warm_up
from faults import FaultProxy, UdpRates
from std_msgs.msg import String

from rosgate.rostypes import qos_profile

RATE = 20.0  # Hz, each topic
BEST_EFFORT = {"reliability": "best_effort", "depth": 100}


def client_file(tmp_path: Path, port: int) -> Path:
    """The README's client file: /chatter with no qos (ROS's default: reliable), and a
    best-effort topic beside it."""
    path = tmp_path / "robot1.yaml"
    path.write_text(f"""
bridge: {{name: robot1, role: client, server: 127.0.0.1:{port}}}
topics:
  - {{topic: /chatter, type: std_msgs/msg/String, direction: transmit}}
  - {{topic: /fresh, type: std_msgs/msg/String, direction: transmit, qos: sensor_data}}
""")
    return path


def server_file(tmp_path: Path, port: int) -> Path:
    path = tmp_path / "base.yaml"
    path.write_text(f"bridge: {{name: base, role: server, server: 127.0.0.1:{port}}}\n")
    return path


def numbered(i: int | None) -> String:
    return String(data="warmup" if i is None else f"m{i}")


def fresh_stream(publisher, stop: threading.Event) -> None:
    """The best-effort topic: its send time in each message, at RATE until ``stop``."""
    while not stop.wait(1 / RATE):
        publisher.publish(String(data=f"{time.monotonic():.6f}"))


def p99(values: list[float]) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(0.99 * len(ordered)))]


def route_line(log: str, label: str) -> str:
    """The summary line a bridge logs for one route at stop ("/fresh (to base): sent ...")."""
    return next(line for line in log.splitlines() if line.split("] ", 1)[-1].startswith(
        f"INFO {label} (") and "): sent " in line)


@pytest.mark.parametrize(("drop", "count"), [(0.05, 400), (0.20, 200)])
def test_a_reliable_topic_crosses_datagram_loss_whole_in_order_and_once(
        tmp_path, domain, ros_side, bridge, drop, count):
    """Its ``data`` fields arrive as they were sent, each once; the best-effort topic beside it
    is carried unrepaired (nothing sent again) and stays fresh (its p99, stamp to listener)."""
    ds, dc, port = domain(), domain(), free_port()
    proxy = FaultProxy(free_port(), port,
                       UdpRates(drop=drop, duplicate=0.02, reorder=0.02), seed=3)
    try:
        base = bridge(server_file(tmp_path, port), ds)
        robot = bridge(client_file(tmp_path, proxy.port), dc)
        listener, talker = ros_side(ds, "listener"), ros_side(dc, "talker")
        inbox = listener.listen("/chatter", String, 1000)
        late: list[float] = []  # the best-effort topic's, seconds from publish to listener
        listener.ros.subscribe(String, "/fresh", qos_profile(BEST_EFFORT),
                               lambda m: late.append(time.monotonic() - float(m.data)), raw=False)
        publisher = talker.publisher("/chatter", String, 10)  # ROS's default QoS
        fresh = talker.publisher("/fresh", String, qos_profile("sensor_data"))
        stop = threading.Event()
        beside = threading.Thread(target=fresh_stream, args=(fresh, stop), daemon=True)
        beside.start()
        try:
            got = cross(publisher, inbox, numbered, lambda m: m.data == "warmup", count,
                        timeout=count / RATE + 30, interval=1 / RATE)
        finally:
            stop.set()
            beside.join()
    finally:
        proxy.close()
    base.stop()
    robot.stop()
    received = [m.data for m in got]
    fresh_p99 = p99(late) if late else float("inf")
    print(f"\n{drop:.0%} loss each way: {len(received)} of {count} reliable messages, in order: "
          f"{received == sorted(received, key=lambda d: int(d[1:]))}; proxy "
          f"{dict(proxy.udp.counts)}; {route_line(base.log, '/chatter')}; best effort beside: "
          f"{len(late)} arrived, p99 {fresh_p99 * 1e3:.1f} ms")
    assert proxy.udp.counts["dropped"] > count * drop * 0.5  # the link did lose datagrams
    assert received == [f"m{i}" for i in range(count)], (
        f"{len(received)} of {count}, {len(set(received))} distinct",
        route_line(base.log, "/chatter"))
    assert "retransmitted" in route_line(robot.log, "/chatter")
    assert "retransmitted" not in route_line(robot.log, "/fresh")
    assert len(late) > count * (1 - drop) ** 2 * 0.5  # its p99 is printed: bench/ measures it


def test_a_receiver_that_expects_repairs_from_a_sender_that_makes_none_stops_waiting(
        engines, domain, ros_side, logs):
    """Peer files that disagree: the sender says recovery: none, the receiver repairs by
    default. Its first gap is waited for (2 s) and never filled: from then on frames are
    published as they come, and the log says why."""
    from faults import UdpFaults

    da, db, port, front = domain(), domain(), free_port(), free_port()
    relay = UdpFaults(front, port, UdpRates(drop=0.1), seed=2)
    topic = "topic: /t, type: std_msgs/msg/String"
    try:
        b = engines(f"""
bridge: {{name: b, role: peer, peer: 127.0.0.1, listen: 127.0.0.1}}
topics: [{{{topic}, direction: receive, port: {port}}}]""", db)
        engines(f"""
bridge: {{name: a, role: peer, peer: 127.0.0.1, listen: 127.0.0.1}}
topics: [{{{topic}, direction: transmit, port: {front}, recovery: none}}]""", da)
        inbox = ros_side(db, "listener").listen("/t", String, 1000)
        talker = ros_side(da, "talker").publisher("/t", String, 1000)
        warm_up(talker, inbox, numbered(None))
        start = len(inbox.items)
        for n in range(100):
            talker.publish(numbered(n))
            time.sleep(0.03)  # paces the publisher; nothing waits on this
        assert logs.wait("never sent again: its sender does not repair", timeout=10)
        # the relay forwarded or dropped each: what the receiver publishes is in once the
        # listener has been quiet (the relay dropped some, so not all 100 come)
        settle(inbox, quiet=1.0)
        got = [m for m in inbox.items[start:] if m.data != "warmup"]
    finally:
        relay.close()
    order = b.routes()[0].order
    assert order is not None and order.stage.unrepaired
    assert len(got) >= 100 - 2 * relay.counts["dropped"] - 5, len(got)
