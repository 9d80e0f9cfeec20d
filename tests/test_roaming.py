"""A robot whose address changes while it streams (a Wi-Fi roam, a DHCP renewal) keeps its
session and loses nothing: real ``rosgate run`` processes in two network namespaces joined by a
veth pair, the client's address moved under a reliable topic at 100 Hz."""

from __future__ import annotations

import contextlib
import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from conftest import free_port

SIDE = str(Path(__file__).with_name("roam_side.py"))
COUNT, RATE = 1000, 100.0
ROAM_AT = 300  # messages sent before the address moves
MAX_GAP = 1.5  # seconds, the longest a roam may hold the stream up


@pytest.fixture
def hosts():
    """Two network namespaces: ``a`` (the robot) and ``b`` (the base), deleted afterwards."""
    from rosgate_emulator import NetnsPair

    why = NetnsPair.unavailable()
    if why is not None:
        pytest.skip(why)
    with NetnsPair() as pair:
        yield pair


class Side:
    """A ROS talker or listener (tests/roam_side.py) inside a namespace; its lines kept."""

    def __init__(self, pair, host: str, domain_id: int, *argv: str):
        env = dict(os.environ, ROS_DOMAIN_ID=str(domain_id), PYTHONUNBUFFERED="1")
        self.proc = pair.popen(host, [sys.executable, SIDE, *argv], env=env, text=True,
                               stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                               stderr=subprocess.STDOUT)
        self.lines: list[str] = []
        self._cond = threading.Condition()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            with self._cond:
                self.lines.append(line.rstrip("\n"))
                self._cond.notify_all()

    def wait(self, predicate, timeout: float) -> bool:
        with self._cond:
            return self._cond.wait_for(lambda: predicate(self.lines), timeout)

    def say(self, line: str) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()


def numbered(lines: list[str]) -> list[tuple[int, float]]:
    """The listener's numbered messages: (number, receive time), in arrival order."""
    got = []
    for line in lines:
        data, _, stamp = line.partition(" ")
        if data.isdigit():
            got.append((int(data), float(stamp)))
    return got


def roam(pair, old: str, new: str) -> None:
    """Move host a from ``old`` to ``new``: add the new address, send from it, remove the old
    one (its secondaries promoted, not deleted with it)."""
    ns, dev = pair.namespaces["a"], pair.devices["a"]
    net = old.rsplit(".", 1)[0] + ".0/24"
    for argv in (["sysctl", "-qw", f"net.ipv4.conf.{dev}.promote_secondaries=1"],
                 ["ip", "addr", "add", f"{new}/24", "dev", dev],
                 ["ip", "route", "replace", net, "dev", dev, "src", new],
                 ["ip", "addr", "del", f"{old}/24", "dev", dev]):
        done = subprocess.run(["ip", "netns", "exec", ns, *argv], capture_output=True, text=True)
        assert done.returncode == 0, f"{argv}: {done.stderr}"


@pytest.mark.parametrize("transport", ["udp", "tcp"])
@pytest.mark.parametrize("direction", ["transmit", "receive"])
def test_a_robot_that_roams_mid_stream_loses_nothing(hosts, bridge, domain, tmp_path, transport,
                                                     direction):
    """1,000 reliable messages at 100 Hz, from the robot (transmit) or to it (receive); after
    300 the robot's address moves (new address added, routes switched to it, old address
    removed): all 1,000 arrive, in order, once each, and the stream stalls for at most 1.5 s."""
    port, da, db = free_port(), domain(), domain()
    base_host, old = hosts.address("b"), hosts.address("a")
    new = old.rsplit(".", 1)[0] + ".3"
    link = "recovery: retransmit" if transport == "udp" else "transport: tcp"
    # qos 1000, reliable: a history of 10 (the default) keeps only the last 10 messages when a
    # bridge is not scheduled for 0.1 s on a busy machine; this test is about the link
    (tmp_path / "base.yaml").write_text(
        f"bridge: {{name: base, role: server, server: '{base_host}:{port}'}}\n")
    (tmp_path / "robot1.yaml").write_text(
        f"bridge: {{name: robot1, role: client, server: '{base_host}:{port}'}}\n"
        "topics:\n"
        f"  - {{topic: /chatter, type: std_msgs/msg/String, direction: {direction}, qos: 1000, "
        f"{link}}}\n")
    base = bridge(tmp_path / "base.yaml", db, prefix=hosts.command("b", []))
    robot = bridge(tmp_path / "robot1.yaml", da, prefix=hosts.command("a", []))
    assert robot.wait_log("server 'base' up", 30), robot.log
    (talks, td), (listens, ld) = ("a", da), ("b", db)
    if direction == "receive":
        (talks, td), (listens, ld) = (listens, ld), (talks, td)
    listener = Side(hosts, listens, ld, "listen", "/chatter")
    assert listener.wait(lambda lines: "ready" in lines, 60), listener.lines
    talker = Side(hosts, talks, td, "talk", "/chatter", str(COUNT), str(RATE))
    assert listener.wait(lambda lines: any(line.startswith("warm ") for line in lines), 60), \
        (listener.lines[-5:], robot.log)
    talker.say("go")
    assert talker.wait(lambda lines: f"sent {ROAM_AT}" in lines, 30), talker.lines[-5:]
    roam(hosts, old, new)
    assert talker.wait(lambda lines: "done" in lines, 60), talker.lines[-5:]
    listener.wait(lambda lines: len(numbered(lines)) >= COUNT, 15)
    got = numbered(listener.lines)
    talker.proc.stdin.close()  # type: ignore[union-attr]
    robot.stop()  # their last lines count what each carried and dropped
    base.stop()
    said = f"robot:\n{robot.log}\nbase:\n{base.log}"
    numbers = [n for n, _ in got]
    times = [t for _, t in got]
    gap = max((b - a for a, b in zip(times, times[1:], strict=False)), default=0.0)
    missing = sorted(set(range(COUNT)) - set(numbers))
    print(f"roam over {transport}, {direction}: {len(set(numbers))} of {COUNT} arrived, "
          f"{len(numbers) - len(set(numbers))} twice, longest gap {gap:.3f} s, "
          f"missing {missing[:20]}")
    assert f"client 'robot1' up: connected from {new} with 1 topic(s) and 0 service(s), " \
        "its session kept" in base.log, said
    # its main line given up as soon as its address went, not after peer_timeout's silence
    assert "down (this host no longer has the address it connected from)" in robot.log, said
    if transport == "udp":  # its first genuine datagram from there moved it, not a heartbeat
        assert f"client 'robot1' moved from {old}:" in base.log, said
    assert len(set(numbers)) == COUNT, f"missing {missing}\n{said}"
    assert numbers == list(range(COUNT)), "out of order or twice"
    assert gap <= MAX_GAP, gap


def test_a_client_behind_a_nat_that_rebinds_is_followed_and_replays_move_nobody(
        bridge, domain, ros_side, tmp_path):
    """WireGuard's rule, on loopback: the server answers a client where its genuine frames come
    from. An eavesdropper who sends every datagram it captured again, as it was or with a byte
    changed, from an address of its own, gets nothing and moves nothing; a NAT that rebinds
    (the client's datagrams from a new port) loses none of the client's messages and the
    server's follow it there."""
    from faults import FaultProxy
    from std_msgs.msg import String

    server_port, relay_port, da, db = free_port(), free_port(), domain(), domain()
    (tmp_path / "base.yaml").write_text(
        f"bridge: {{name: base, role: server, server: '127.0.0.1:{server_port}'}}\n")
    (tmp_path / "robot1.yaml").write_text(
        f"bridge: {{name: robot1, role: client, server: '127.0.0.1:{relay_port}'}}\n"
        "topics:\n"
        "  - {topic: /up, type: std_msgs/msg/String, direction: transmit}\n"
        "  - {topic: /down, type: std_msgs/msg/String, direction: receive}\n")
    relay = FaultProxy(relay_port, server_port)
    try:
        base = bridge(tmp_path / "base.yaml", db)
        robot_bridge = bridge(tmp_path / "robot1.yaml", da)
        assert robot_bridge.wait_log("server 'base' up", 30), robot_bridge.log
        robot, station = ros_side(da, "robot"), ros_side(db, "base")
        ups, downs = station.listen("/up", String, qos=1000), robot.listen("/down", String,
                                                                           qos=1000)
        up, down = robot.publisher("/up", String, qos=1000), station.publisher(
            "/down", String, qos=1000)

        def stream(publisher, inbox, tag: str, count: int, warm: bool = True) -> list[str]:
            """Warm-ups until one crosses, then ``count`` numbered ones: those that came."""
            start = len(inbox.items)
            while warm and not inbox.wait_count(start + 1, 0.2):
                publisher.publish(String(data="warm"))
            for i in range(count):
                publisher.publish(String(data=f"{tag} {i}"))
                time.sleep(0.01)  # paces the publisher; nothing waits on this
            mine = lambda items: [m.data for m in items if m.data.startswith(f"{tag} ")]
            inbox.wait_for(lambda items: len(mine(items)) >= count, 10)
            return mine(list(inbox.items))

        assert stream(up, ups, "before", 20) == [f"before {i}" for i in range(20)]
        assert stream(down, downs, "before", 20) == [f"before {i}" for i in range(20)]

        # the eavesdropper: every datagram the client sent, again, and each with its last byte
        # changed (its cipher's tag no longer matches), from an address of its own
        captured = [data for upstream, data in relay.udp.captured if upstream]
        assert len(captured) >= 20
        attacker = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        attacker.bind(("127.0.0.1", 0))
        attacker.settimeout(0.2)
        try:
            for data in captured:
                attacker.sendto(data, ("127.0.0.1", server_port))
                attacker.sendto(data[:-1] + bytes([data[-1] ^ 1]), ("127.0.0.1", server_port))
            assert stream(down, downs, "replayed", 50) == [f"replayed {i}" for i in range(50)]
            got = []
            with contextlib.suppress(TimeoutError):
                while True:
                    got.append(attacker.recvfrom(65536)[0])
            assert got == [], f"the server sent {len(got)} datagram(s) to the eavesdropper"
        finally:
            attacker.close()
        assert "moved" not in base.log, base.log

        relay.udp.rebind()  # the NAT's new port: the server hears the client from there
        # at once, no warm-up: the first of them is the first the server hears from there
        assert stream(up, ups, "rebound", 100, warm=False) == [f"rebound {i}" for i in range(100)]
        assert base.wait_log("client 'robot1' moved from 127.0.0.1:", 5), base.log
        assert stream(down, downs, "rebound", 50) == [f"rebound {i}" for i in range(50)]
    finally:
        relay.close()
