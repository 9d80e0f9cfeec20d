"""No gap when a publisher appears: a volatile publisher that starts publishing the moment it
has matched the bridge's subscription gets every message across, from its first; and a
subscriber that was there before the receiving bridge started gets the first message sent
first. Real ``rosgate run`` processes (client/server with identities, peers, zenoh through a
``rosgate router``), a real publisher and subscriber in DDS domains of their own.

The publisher is reliable and volatile as ROS's default, with a deep history (so that a
listener the machine's load stalls for a moment does not make the talker itself overwrite what
was not acknowledged yet), and waits on its own match count (``get_subscription_count``), as a
node that publishes "once somebody listens" does; what it publishes after that is ROS's promise,
and the bridge must keep it."""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import pytest
from conftest import Inbox, free_port, settle, wait_until
from rclpy.qos import QoSProfile
from std_msgs.msg import String
from test_zenoh_fleet import Router, zenoh_plugin

COUNT = 400
EVERY = 0.01  # seconds between two messages: 100 Hz
DEEP = QoSProfile(depth=1000)  # the talker and the listener keep what a burst brings


class EagerTalker:
    """A publisher that publishes ``COUNT`` numbered messages from the moment it has matched a
    subscription (the bridge's), in a thread of its own."""

    def __init__(self, side: Any, topic: str):
        self.publisher = side.publisher(topic, String, DEEP)
        self.matched_at: float | None = None
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        deadline = time.monotonic() + 60
        while self.publisher.get_subscription_count() == 0:
            if time.monotonic() > deadline:
                return
            time.sleep(0.001)
        self.matched_at = time.monotonic()
        start = time.monotonic()
        for n in range(COUNT):
            delay = start + n * EVERY - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            self.publisher.publish(String(data=f"m{n}"))

    def done(self, timeout: float) -> bool:
        self.thread.join(timeout)
        return self.matched_at is not None and not self.thread.is_alive()


def arrived(inbox: Inbox, bridges: list[Any]) -> list[int]:
    """The numbers that arrived, in order, once all came (or 20 s passed with no new one)."""
    wait_until(lambda: len(inbox.items) >= COUNT, 20)
    numbers = [int(m.data[1:]) for m in inbox.items]
    missing = sorted(set(range(COUNT)) - set(numbers))
    if numbers != list(range(COUNT)):
        for b in bridges:  # their counters, for the message
            b.stop()
    logs = "\n\n".join(b.log for b in bridges)
    assert numbers == list(range(COUNT)), (
        f"{len(numbers)} of {COUNT} arrived; missing {missing[:20]} ({len(missing)} in all); "
        f"first {numbers[:5]}\n{logs}")
    return numbers


def write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


@pytest.mark.parametrize("talker_on", ["client", "server"])
def test_a_publisher_that_publishes_once_matched_loses_nothing_client_server(
        tmp_path, domain, ros_side, bridge, talker_on):
    """The default file (client/server, identities, udp): the talker and the listener exist
    before either bridge; the bridge on the talker's side subscribes once the session is up
    and the talker publishes at once; the listener's bridge makes its publisher then too."""
    server_domain, client_domain = domain(), domain()
    port = free_port()
    direction = "transmit" if talker_on == "client" else "receive"
    server = write(tmp_path / "base.yaml",
                   f"bridge: {{name: base, role: server, server: 127.0.0.1:{port}}}\n")
    client = write(tmp_path / "robot1.yaml", f"""
bridge: {{name: robot1, role: client, server: 127.0.0.1:{port}}}
topics:
  - {{topic: /chatter, type: std_msgs/msg/String, direction: {direction}}}
""")
    talker_domain, listener_domain = ((client_domain, server_domain) if talker_on == "client"
                                      else (server_domain, client_domain))
    inbox = ros_side(listener_domain, "listener").listen("/chatter", String, DEEP)
    talker = EagerTalker(ros_side(talker_domain, "talker"), "/chatter")
    base = bridge(server, server_domain)
    robot = bridge(client, client_domain)
    assert talker.done(60), "the talker never matched the bridge"
    arrived(inbox, [robot, base])


def peer_files(tmp_path: Path) -> tuple[Path, Path]:
    port = free_port()
    entry = ("{topic: /chatter, type: std_msgs/msg/String, direction: %s, port: " + str(port)
             + "}")
    a = write(tmp_path / "a.yaml", f"""
bridge: {{name: a, role: peer, peer: 127.0.0.1, listen: 127.0.0.1}}
topics: [{entry % "transmit"}]
""")
    b = write(tmp_path / "b.yaml", f"""
bridge: {{name: b, role: peer, peer: 127.0.0.1, listen: 127.0.0.1}}
topics: [{entry % "receive"}]
""")
    return a, b


def zenoh_files(tmp_path: Path, router: Router) -> tuple[Path, Path]:
    entry = "{{topic: /chatter, type: std_msgs/msg/String, direction: {}, remote: bot/chatter}}"
    files = []
    for name, direction in (("a", "transmit"), ("b", "receive")):
        files.append(write(tmp_path / f"{name}.yaml", f"""\
bridge: {{name: {name}, role: peer, defaults: {{transport: zenoh}}}}
{zenoh_plugin(router)}topics: [{entry.format(direction)}]
"""))
    return files[0], files[1]


@pytest.fixture
def zenoh_router():
    r = Router()
    yield r
    r.stop()


@pytest.mark.parametrize("kind", ["peer", "zenoh"])
def test_a_publisher_that_publishes_once_matched_loses_nothing_peer_and_zenoh(
        tmp_path, domain, ros_side, bridge, kind, request):
    """Peers (no handshake) and zenoh entries: the listener and its (receiving) bridge first,
    then the talker's bridge; the talker publishes the moment that bridge subscribes."""
    da, db = domain(), domain()
    a, b = (peer_files(tmp_path) if kind == "peer"
            else zenoh_files(tmp_path, request.getfixturevalue("zenoh_router")))
    inbox = ros_side(db, "listener").listen("/chatter", String, DEEP)
    receiving = bridge(b, db)
    talker = EagerTalker(ros_side(da, "talker"), "/chatter")
    sending = bridge(a, da)
    assert talker.done(60), "the talker never matched the bridge"
    arrived(inbox, [sending, receiving])


class SteadyTalker:
    """Numbered messages at 100 Hz from now until ``stop()``, matched or not."""

    def __init__(self, side: Any, topic: str):
        self.publisher = side.publisher(topic, String, DEEP)
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        start, n = time.monotonic(), 0
        while not self._stop.wait(max(0.0, start + n * 0.01 - time.monotonic())):
            self.publisher.publish(String(data=f"m{n}"))
            n += 1

    def stop(self) -> None:
        self._stop.set()
        self.thread.join(5)


def test_a_restarted_base_publishes_all_it_takes_to_a_subscriber_that_waited(
        tmp_path, domain, ros_side, bridge):
    """The base stops and starts again while the robot streams; the base's subscriber stays.
    Whatever the restarted base takes from the robot reaches that subscriber, from the first
    it took: its new publisher waits to be matched instead of publishing into the void."""
    from test_default_file_speed import counters

    server_domain, client_domain = domain(), domain()
    port = free_port()
    fast = "heartbeat: 0.2, reconnect: {min: 0.05, max: 0.3}"
    server = write(tmp_path / "base.yaml",
                   f"bridge: {{name: base, role: server, server: 127.0.0.1:{port}, {fast}}}\n")
    client = write(tmp_path / "robot1.yaml", f"""
bridge: {{name: robot1, role: client, server: 127.0.0.1:{port}, {fast}}}
topics:
  - {{topic: /chatter, type: std_msgs/msg/String, direction: transmit}}
""")
    inbox = ros_side(server_domain, "listener").listen("/chatter", String, DEEP)
    first = bridge(server, server_domain)
    robot = bridge(client, client_domain)
    talker = SteadyTalker(ros_side(client_domain, "talker"), "/chatter")
    try:
        assert inbox.wait_count(20, 30), robot.log
        assert first.stop() == 0
        assert robot.wait_log("server 'base' down", 10), robot.log
        before = len(inbox.items)
        second = bridge(server, server_domain)
        assert wait_until(lambda: sum("server 'base' up" in x for x in robot.lines) == 2, 20)
        assert inbox.wait_count(before + 200, 30), f"{len(inbox.items) - before} after the restart"
    finally:
        talker.stop()
    settle(inbox)
    assert second.stop() == 0
    _, taken, drops = counters(second.log, "/chatter (from robot1)")
    after = [int(m.data[1:]) for m in inbox.items[before:]]
    assert after == sorted(set(after)), "out of order or twice"
    assert len(after) == taken, (f"the restarted base took {taken} and its subscriber got "
                                 f"{len(after)} (first {after[:3]})\n{second.log}")
    assert drops == {}, second.log
