"""No gap when a publisher appears: a volatile publisher that starts publishing the moment it
has matched the bridge's subscription gets every message across, from its first; and a
subscriber that was there before the receiving bridge started gets the first message sent
first. Real ``rosgate run`` processes (client/server with identities, peers, zenoh through a
``rosgate router``), a real publisher and subscriber in DDS domains of their own.

The publisher is ROS's default (reliable, volatile, depth 10) and waits on its own match count
(``get_subscription_count``), as a node that publishes "once somebody listens" does; what it
publishes after that is ROS's promise, and the bridge must keep it."""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import pytest
from conftest import Inbox, free_port, wait_until
from rclpy.qos import QoSProfile
from std_msgs.msg import String
from test_zenoh_fleet import Router, zenoh_plugin

COUNT = 400
EVERY = 0.005  # seconds between two messages: 200 Hz
DEEP = QoSProfile(depth=1000)  # the listener keeps what a burst brings


class EagerTalker:
    """A publisher that publishes ``COUNT`` numbered messages from the moment it has matched a
    subscription (the bridge's), in a thread of its own."""

    def __init__(self, side: Any, topic: str):
        self.publisher = side.publisher(topic, String, QoSProfile(depth=10))
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
