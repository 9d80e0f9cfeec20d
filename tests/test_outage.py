"""A base that restarts loses nothing of what the robot sent meanwhile: the file a user writes
(client/server, identities, the session's cipher), a topic with ROS's default QoS (reliable) at
20 Hz for 26 s, the base bridge stopped 4 s into the stream and started again 10 s later, the
listener on the base kept alive throughout. Every message arrives at the listener, once, in
order — over the default udp and over tcp, and with the base killed (SIGKILL) between two
messages (the next one published once the robot has seen the base go: without
acknowledgements, a message in flight at a crash is lost) — and no bridge counts a drop."""

from __future__ import annotations

import re
import signal
import threading
import time
from pathlib import Path

import pytest
from conftest import Bridge, free_port, wait_until, warm_up
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

RATE = 20          # messages a second
SECONDS = 26       # of publishing: 520 messages, 12 s of them after the base's restart
STOP_AT = 4        # seconds into the stream when the base stops (80 crossed: the stream flows)
DOWN = 10          # seconds it stays down
COUNT = RATE * SECONDS


def counters(log: str, topic: str) -> tuple[int, int, str]:
    """The last counters a bridge logged for ``topic``: sent, received, drops."""
    line = [line for line in log.splitlines() if topic in line and "drops:" in line][-1]
    sent, received = (int(re.search(rf"{word} (\d+)", line).group(1))  # type: ignore[union-attr]
                      for word in ("sent", "received"))
    return sent, received, line.rsplit("drops: ", 1)[1]


class Talker(threading.Thread):
    """Publishes ``0``, ``1``, ... at RATE in a thread of its own (:meth:`wait_published` waits
    for its progress); with ``pause_at``, waits before that message until :attr:`go` is set,
    then catches up."""

    def __init__(self, publisher, pause_at: int | None = None):
        super().__init__(daemon=True)
        self.publisher = publisher
        self.published = 0
        self.pause_at = pause_at
        self.go = threading.Event()
        self._progress = threading.Condition()

    def run(self) -> None:
        start = time.monotonic()
        for i in range(COUNT):
            if i == self.pause_at:
                self.go.wait(30)
            delay = start + i / RATE - time.monotonic()
            if delay > 0:
                time.sleep(delay)  # the stream's own pace; nothing waits on this
            self.publisher.publish(String(data=str(i)))
            with self._progress:
                self.published = i + 1
                self._progress.notify_all()

    def wait_published(self, n: int, timeout: float) -> bool:
        with self._progress:
            return self._progress.wait_for(lambda: self.published >= n, timeout)


@pytest.mark.parametrize("transport, how", [("udp", "stop"), ("tcp", "stop"), ("udp", "kill")])
def test_a_base_restarted_mid_stream_gets_every_message_once_in_order(
        tmp_path: Path, domain, ros_side, bridge, transport, how):
    server_domain, client_domain = domain(), domain()
    port = free_port()
    server_file = tmp_path / "base.yaml"
    server_file.write_text(f"bridge: {{name: base, role: server, server: 127.0.0.1:{port}}}\n")
    (tmp_path / "robot1.yaml").write_text(f"""
bridge: {{name: robot1, role: client, server: 127.0.0.1:{port}}}
topics:
  - {{topic: /chatter, type: std_msgs/msg/String, direction: transmit, transport: {transport}}}
""")
    # a base killed is no bridge of the fixture's, which wants a clean exit of each
    base = Bridge(server_file, server_domain) if how == "kill" else bridge(server_file,
                                                                            server_domain)
    robot = bridge(tmp_path / "robot1.yaml", client_domain)
    far, near = ros_side(server_domain, "far"), ros_side(client_domain, "near")
    reliable = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
    inbox = far.listen("/chatter", String, reliable)
    publisher = near.publisher("/chatter", String, QoSProfile(depth=10))  # ROS's default QoS

    warmups = warm_up(publisher, inbox, String(data="warmup"))
    talker = Talker(publisher, pause_at=STOP_AT * RATE if how == "kill" else None)
    talker.start()
    assert talker.wait_published(STOP_AT * RATE, STOP_AT + 10)
    if how == "kill":
        # between two messages, once the robot has seen it: what is in flight when a base dies,
        # or sent before the robot sees the connection end, is lost (no acknowledgements)
        last = str(STOP_AT * RATE - 1)
        assert inbox.wait_for(lambda items: any(m.data == last for m in items), 10)
        base.proc.kill()
        assert base.proc.wait(10) == -signal.SIGKILL
        assert robot.wait_log("server 'base' down", 10), robot.log
        talker.go.set()
    else:
        assert base.stop() == 0
    first_base = base.log
    assert talker.wait_published((STOP_AT + DOWN) * RATE, DOWN + 10)
    base = bridge(server_file, server_domain)
    talker.join(SECONDS + 10)
    numbered = lambda items: [m.data for m in items if m.data != "warmup"]
    inbox.wait_for(lambda items: len(numbered(items)) >= COUNT, 60)
    got = [int(n) for n in numbered(list(inbox.items))]

    assert robot.stop() == 0 and base.stop() == 0  # their last lines: the counters
    sent, _, robot_drops = counters(robot.log, "/chatter")
    _, before, first_drops = (counters(first_base, "/chatter") if how == "stop"
                              else (0, -1, "none"))  # a killed base says nothing
    _, after, base_drops = counters(base.log, "/chatter")
    missing = sorted(set(range(COUNT)) - set(got))
    seen = (f"{len(got)} of {COUNT} at the listener ({len(set(got))} distinct, missing "
            f"{missing[:10]}); the base's "
            f"routes received {before} + {after}; robot sent {sent}, drops: {robot_drops}; "
            f"base drops: {first_drops} / {base_drops}")
    print(seen)
    assert got == list(range(COUNT)), seen  # every one, once, in order
    assert robot_drops == "none", robot.log
    assert COUNT <= sent <= COUNT + warmups, seen  # each taken once (a copy sent again is not)
    # a killed base never told the robot its session ended: the robot's repairs of what it sent
    # the dead base may reach the new one, which cannot open them (counted, never published)
    stale = re.fullmatch(r"unknown_key=\d+", base_drops) and how == "kill"
    assert first_drops == "none" and (base_drops == "none" or stale), seen


FAST = "heartbeat: 0.2, peer_timeout: 0.8, reconnect: {min: 0.05, max: 0.5}"


def test_what_waits_for_a_stopped_server_is_bounded_and_every_drop_is_counted(
        engines, domain, ros_side, logs):
    """Reliable messages past ``bridge.queue`` drop the oldest (``queue_full``, one warning
    for the burst); best-effort ones do not wait for a server that said it stops (``link_down``);
    the newest that waited reach the restarted server once each; what still waits when the
    client stops is counted ``link_down``."""
    ds, dc, port = domain(), domain(), free_port()
    server_yaml = f"bridge: {{name: base, role: server, server: 127.0.0.1:{port}, {FAST}}}"
    server = engines(server_yaml, ds)
    client = engines(f"""
bridge: {{name: robot1, role: client, server: 127.0.0.1:{port}, {FAST},
         queue: {{frames: 5, bytes: 1000000}}}}
topics:
  - {{topic: /rel, type: std_msgs/msg/String, direction: transmit, qos: 100}}
  - {{topic: /fresh, type: std_msgs/msg/String, direction: transmit,
     qos: {{reliability: best_effort, depth: 100}}}}""", dc)
    robot, base = ros_side(dc, "robot"), ros_side(ds, "base")
    best_effort = QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT)
    rel, rel_in = robot.publisher("/rel", String, 100), base.listen("/rel", String, 100)
    fresh = robot.publisher("/fresh", String, best_effort)
    fresh_in = base.listen("/fresh", String, best_effort)
    warm_up(rel, rel_in, String(data="warmup"))
    warm_up(fresh, fresh_in, String(data="warmup"))
    role = client.role
    mine = {r.topic.topic: r for r in client.routes()}

    server.stop()
    assert role.hold.down
    for i in range(20):
        rel.publish(String(data=f"m{i}"))
        fresh.publish(String(data=f"f{i}"))
    assert wait_until(lambda: mine["/rel"].counters.drops.get("queue_full") == 15
                      and mine["/fresh"].counters.drops.get("link_down") == 20), (
        mine["/rel"].counters.drops, mine["/fresh"].counters.drops)
    assert role.hold.waiting == 5 and mine["/rel"].queue_depth == 5  # as status shows it
    assert len(logs.having("past bridge.queue")) == 1  # one burst, one warning

    server = engines(server_yaml, ds)
    assert wait_until(lambda: role.connected.is_set() and not role.hold.down)
    far = {r.topic.topic: r for r in server.routes()}
    assert wait_until(lambda: far["/rel"].counters.received == 5), far["/rel"].counters
    assert role.hold.waiting == 0 and far["/fresh"].counters.received == 0
    assert far["/rel"].counters.drops == {} and far["/rel"].counters.lost == 0

    server.stop()
    for i in range(2):
        rel.publish(String(data=f"n{i}"))
    assert wait_until(lambda: role.hold.waiting == 2)
    client.stop()
    assert mine["/rel"].counters.drops == {"queue_full": 15, "link_down": 2}


@pytest.mark.parametrize("entry", ["transport: udp", "transport: tcp",
                                   "transport: tcp, port: {port}"])
def test_what_waited_reaches_a_restarted_server_on_every_kind_of_link(
        engines, domain, ros_side, entry):
    """The main line, a datagram link and a stream port of its own: messages taken while the
    server was down reach the restarted one, once each, sealed under its new session."""
    ds, dc, port = domain(), domain(), free_port()
    server_yaml = f"bridge: {{name: base, role: server, server: 127.0.0.1:{port}, {FAST}}}"
    server = engines(server_yaml, ds)
    client = engines(f"""
bridge: {{name: robot1, role: client, server: 127.0.0.1:{port}, {FAST}}}
topics:
  - {{topic: /rel, type: std_msgs/msg/String, direction: transmit, qos: 100,
     {entry.format(port=free_port())}}}""", dc)
    robot, base = ros_side(dc, "robot"), ros_side(ds, "base")
    rel, rel_in = robot.publisher("/rel", String, 100), base.listen("/rel", String, 100)
    warm_up(rel, rel_in, String(data="warmup"))
    role = client.role
    mine = client.routes()[0]

    server.stop()
    for i in range(5):
        rel.publish(String(data=f"m{i}"))
    assert wait_until(lambda: role.hold.waiting == 5), role.hold.waiting
    server = engines(server_yaml, ds)
    assert wait_until(lambda: role.connected.is_set() and server.routes())
    far = server.routes()[0]
    assert wait_until(lambda: far.counters.received == 5, 15), (far.counters, mine.counters)
    assert far.counters.drops == {} and far.counters.lost == 0 and mine.counters.drops == {}
    # the one thing the restarted server may drop: a hello of the client's old session, sent
    # (or a port reconnected with it) before the client learnt that the server had restarted
    assert set(server.link_drops) <= {"bad_hello"}, server.link_drops


def test_a_client_between_two_connections_keeps_its_heartbeat_thread(engines, domain,
                                                                     ros_side):
    """While the main line is down the session's keys are forgotten until the next welcome; the
    datagram hellos the ping loop sends meanwhile must wait for them, not end the loop (it once
    died there on NoKey, and the client sent no heartbeat or hello again until it stopped)."""
    ds, dc, port = domain(), domain(), free_port()
    engines(f"bridge: {{name: base, role: server, server: 127.0.0.1:{port}, {FAST}}}", ds)
    client = engines(f"""
bridge: {{name: robot1, role: client, server: 127.0.0.1:{port}, {FAST}}}
topics:
  - {{topic: /rel, type: std_msgs/msg/String, direction: transmit}}""", dc)
    rel, rel_in = ros_side(dc, "robot").publisher("/rel", String), \
        ros_side(ds, "base").listen("/rel", String)
    warm_up(rel, rel_in, String(data="warmup"))
    role = client.role
    assert role.schedule is not None and role.hello_to  # a session, and a datagram link
    role.schedule.forget()  # as a main line that closed leaves it
    role._say_hello()  # what the ping loop does next: nothing to seal with, nothing sent
