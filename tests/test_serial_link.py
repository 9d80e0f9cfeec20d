"""Two bridges over a serial line: a pseudo-terminal pair joined by the emulator's relay
(rosgate_emulator.serial) at 57,600 baud that flips one bit in 10,000 bytes. A Twist at 20 Hz
and a 200-byte status at 1 Hz cross under the aead cipher, a Trigger service crosses; every
spoilt frame is counted and none is published. The line is unplugged for 3 s and comes back
under new device paths behind the same names: traffic resumes within a second, no reliable
message is lost and the best-effort ones sent meanwhile are counted. A topic too big
for the line is named by rosgate check and, forced on it, shed without delaying a Twist; a board
on the line speaks CVRA's layouts; the docs' files check."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest
from conftest import wait_until
from geometry_msgs.msg import Twist
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from rosgate_crypto_aead import AeadCipher
from rosgate_emulator.serial import LineProfile, PtyRelay
from rosgate_testing import write_key
from rosgate_top.client import StatusClient
from std_msgs.msg import String
from std_srvs.srv import Trigger
from test_services import DEEP, Caller, pong

from rosgate import identity

#: what the serial link counts when the line spoils a frame (rosgate_mcu_cvra.serial_datagram)
LINE_DROPS = ("bad_crc", "bad_escape", "too_short", "too_long")


def peer(name: str, device: str, key: Path, sends: bool) -> str:
    way = {True: "transmit", False: "receive"}
    return f"""
bridge: {{name: {name}, role: peer, peer: line, listen: line, insecure: true}}
plugins:
  serial: {{device: {device}, baud: 57600}}
  aead: {{key_file: {key}}}
topics:
  - {{topic: /cmd_vel, type: geometry_msgs/msg/Twist, direction: {way[sends]}, port: 1,
     transport: serial, cipher: aead, qos: 100}}
  - {{topic: /status, type: std_msgs/msg/String, direction: {way[sends]}, port: 2,
     transport: serial, cipher: aead, qos: 100}}
services:
  - {{service: /trigger, type: std_srvs/srv/Trigger, direction: {way[sends]}, port: 3,
     transport: serial, cipher: aead, timeout: 3}}
"""


def board_peer(device: str) -> str:
    """A peer's file for a microcontroller on ``device``: CVRA layouts, one serial datagram per
    message, ``/position`` from the board and ``/cmd_vel`` to it on one port."""
    return f"""
bridge: {{name: robot, role: peer, peer: board, listen: board, insecure: true,
         defaults: {{codec: msgpack}}}}
plugins:
  serial: {{device: {device}, baud: 115200, multiplex: false}}
topics:
  - {{topic: /position, type: geometry_msgs/msg/Pose2D, direction: receive, port: 1,
     transport: serial, framing: none}}
  - {{topic: /cmd_vel, type: geometry_msgs/msg/Twist, direction: transmit, port: 1,
     transport: serial, framing: none}}
"""


def twist(i: int) -> Twist:
    message = Twist()
    message.linear.x = float(i)
    message.angular.z = -0.5
    return message


def status(i: int) -> String:
    return String(data=f"{i:04d}" + "s" * 196)  # 200 bytes


def line_drops(engine) -> int:
    return sum(engine.link_drops.get(reason, 0) for reason in LINE_DROPS)


class Talker:
    """Publishes Twists at 20 Hz and a status at 1 Hz, numbered, until stopped."""

    def __init__(self, side):
        self.twists = side.publisher("/cmd_vel", Twist)
        self.status = side.publisher("/status", String)
        self.sent = 0
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        start = time.monotonic()
        while not self.stop.wait(max(0.0, start + self.sent * 0.05 - time.monotonic())):
            self.twists.publish(twist(self.sent))
            if self.sent % 20 == 0:
                self.status.publish(status(self.sent // 20))
            self.sent += 1

    def close(self) -> None:
        self.stop.set()
        self.thread.join()


@pytest.fixture
def line(tmp_path):
    with PtyRelay(tmp_path,
                  LineProfile(baud=57_600, flip=1e-4, seed=3)) as relay:
        yield relay


@pytest.fixture
def key(tmp_path):
    return write_key(tmp_path / "aead.key", AeadCipher.generate_key())


def test_twist_status_and_trigger_cross_a_noisy_57600_baud_line(
        engines, domain, ros_side, line, key):
    da, db = domain(), domain()
    a = engines(peer("a", line.a, key, sends=True), da)
    b = engines(peer("b", line.b, key, sends=False), db)
    side_a, side_b = ros_side(da, "a"), ros_side(db, "b")
    twists, statuses = side_b.listen("/cmd_vel", Twist), side_b.listen("/status", String)
    side_b.ros.node.create_service(Trigger, "/trigger", pong, qos_profile=DEEP)
    talker = Talker(side_a)
    try:
        trigger = Caller(side_a, Trigger, "/trigger")
        assert trigger.warm_up(Trigger.Request(), a, b)[0] == \
            Trigger.Response(success=True, message="pong")
        # until the line has spoilt frames both ways, and ten statuses have crossed
        assert wait_until(lambda: line.up.flipped >= 2 and len(statuses.items) >= 10, 60), \
            (line.up, len(statuses.items))
        for _ in range(3):
            assert trigger.call(Trigger.Request()) == \
                Trigger.Response(success=True, message="pong")
    finally:
        talker.close()
    sent = talker.sent
    first = lambda: min(m.linear.x for m in twists.items)
    # the Twists sent after the first one crossed, less the ones the flips spoilt, arrive
    # (what is still on the line lands within seconds at 57,600 baud)
    assert wait_until(lambda: len(twists.items) >= sent - first() - 2 * line.up.flipped - 2,
                      15), (sent, first(), len(twists.items), line.up.flipped)
    got = [m.linear.x for m in twists.items]
    assert all(m == twist(int(m.linear.x)) for m in twists.items), "a spoilt Twist was published"
    assert len(set(got)) == len(got), "a Twist published twice"
    assert all(m == status(int(m.data[:4])) for m in statuses.items), "a spoilt status"
    # every flipped bit spoils the frame it lands in (CRC-32 misses no single-bit error), and
    # at most two (a bit that makes or unmakes a delimiter); one more may be the frame a port
    # cuts when it opens mid-frame. Announcements still flow: wait for the frame of the last flip
    for far, way in ((b, line.up), (a, line.down)):
        assert wait_until(lambda far=far, way=way: line_drops(far) >= way.flipped, 10), \
            (way.flipped, far.link_drops)
        assert line_drops(far) <= 2 * way.flipped + 1, (way.flipped, far.link_drops)
    assert all(route.counters.drops.get("auth_failed", 0) == 0 for route in b.routes())


def unplug_peer(name: str, device: str, key: Path, sends: bool) -> str:
    """A reliable counter and a best-effort Twist on one line; ``max_frame: 300``, so the
    counter is repaired by ``retransmit`` (a line of smaller frames has no room for it)."""
    way = {True: "transmit", False: "receive"}[sends]
    return f"""
bridge: {{name: {name}, role: peer, peer: line, listen: line, insecure: true}}
plugins:
  serial: {{device: {device}, baud: 57600, max_frame: 300}}
  aead: {{key_file: {key}}}
topics:
  - {{topic: /count, type: std_msgs/msg/UInt32, direction: {way}, port: 1,
     transport: serial, cipher: aead, qos: {{reliability: reliable, depth: 1000}}}}
  - {{topic: /cmd_vel, type: geometry_msgs/msg/Twist, direction: {way}, port: 2,
     transport: serial, cipher: aead, qos: sensor_data}}
"""


def test_unplugged_for_3_s_and_back_under_new_paths_loses_no_reliable_message(
        engines, domain, ros_side, tmp_path, key, logs):
    """A reliable counter at 20 Hz and a best-effort Twist beside it, published throughout a
    3-second unplug and a return under new device paths behind the same names: traffic
    resumes within a second of the return; every number arrives, once, in order (held by the
    link while its line was gone, the frames on the way when it went sent again by
    ``retransmit``); the Twists published meanwhile are counted ``link_down``."""
    from std_msgs.msg import UInt32

    deep = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
    with PtyRelay(tmp_path, LineProfile(baud=57_600)) as relay:
        da, db = domain(), domain()
        a = engines(unplug_peer("a", relay.a, key, sends=True), da)
        engines(unplug_peer("b", relay.b, key, sends=False), db)
        side_a, side_b = ros_side(da, "a"), ros_side(db, "b")
        counts = side_b.listen("/count", UInt32, qos=deep)
        twists = side_b.listen("/cmd_vel", Twist, qos=qos_profile_sensor_data)
        count_pub = side_a.publisher("/count", UInt32, qos=deep)
        twist_pub = side_a.publisher("/cmd_vel", Twist, qos=qos_profile_sensor_data)
        sent, stop = [0], threading.Event()

        def talk() -> None:
            start = time.monotonic()
            while not stop.wait(max(0.0, start + sent[0] * 0.05 - time.monotonic())):
                count_pub.publish(UInt32(data=sent[0]))
                twist_pub.publish(twist(sent[0]))
                sent[0] += 1

        talker = threading.Thread(target=talk, daemon=True)
        talker.start()
        try:
            assert counts.wait_count(20, 30) and twists.wait_count(20, 30), \
                "nothing crossed the line"
            relay.unplug()
            assert logs.wait("(unplugged?)", count=2, timeout=5)
            unplugged = sent[0]
            threading.Event().wait(3)  # the outage itself
            arrived = len(counts.items) + len(twists.items)
            relay.replug()
            back = time.monotonic()
            assert wait_until(lambda: len(counts.items) + len(twists.items) > arrived, 5)
            resumed = time.monotonic() - back
            assert logs.wait("is back", count=2, timeout=5)
            assert twists.wait_for(  # fresh traffic, published after the return, crosses
                lambda items: any(m.linear.x > unplugged + 70 for m in items), 20)
            # the counter catches up at the line's spare capacity, behind what it held
            assert counts.wait_for(lambda items: items[-1].data > unplugged + 70, 30)
            print(f"resumed {resumed:.2f} s and the counter caught up "
                  f"{time.monotonic() - back:.2f} s after the return")
        finally:
            stop.set()
            talker.join()
        first = counts.items[0].data
        assert counts.wait_count(sent[0] - first, 30), (sent[0], first, len(counts.items))
        assert resumed < 1.0, f"traffic resumed {resumed:.2f} s after the device returned"
        assert relay.paths[2:] != relay.paths[:2] and not set(relay.paths[2:]) & set(
            relay.paths[:2]), relay.paths
        gone, returned = logs.having("(unplugged?)"), logs.having("is back")
        assert sorted(m.split()[2] for m in gone) == sorted([relay.a, relay.b]), gone
        assert len(returned) == 2, returned  # logged once per device, each way
        # every number, once, in order, field for field, those published while unplugged too
        assert counts.items == [UInt32(data=i) for i in range(first, sent[0])], \
            [m.data for m in counts.items]
        routes = {route.label: route for route in a.routes()}
        assert not routes["/count"].counters.drops, routes["/count"].counters.drops
        # best effort is not held: what was published while the line was gone is counted
        shed = routes["/cmd_vel"].counters.drops
        got = {int(m.linear.x) for m in twists.items}
        missing = [i for i in range(int(twists.items[0].linear.x), sent[0]) if i not in got]
        assert 40 <= shed.get("link_down", 0) <= len(missing), (shed, missing)


def test_check_budgets_the_line_from_its_baud_rate_and_names_what_cannot_fit(tmp_path, capsys):
    from rosgate.cli import main

    path = tmp_path / "radio.yaml"
    path.write_text("""
bridge: {name: a, role: peer, peer: line, listen: line, insecure: true}
plugins:
  serial: {device: /dev/serial/by-id/usb-radio-if00, baud: 57600}
topics:
  - {topic: /cmd_vel, type: geometry_msgs/msg/Twist, direction: transmit, port: 1,
     transport: serial, max_rate: 20}
  - {topic: /status, type: std_msgs/msg/String, direction: transmit, port: 2,
     transport: serial, max_rate: 1, typical_size: 200}
  - {topic: /big, type: std_msgs/msg/String, direction: transmit, port: 3,
     transport: serial, max_rate: 100, typical_size: 1000}
""")
    assert main(["check", str(path)]) == 0
    out = capsys.readouterr().out.splitlines()
    # 57,600 baud at 10 bits a byte (start, 8 data, stop): 5,760 B/s = 46.08 kbit/s of frames,
    # 95 % of which is the budget
    assert out[out.index("budget of serial: 43.8 kbit/s per peer (the link's own)"):] \
        == [
        "budget of serial: 43.8 kbit/s per peer (the link's own)",
        # 52 B of CDR, the 28-byte envelope, a compact piece's head and length (2 B), and 9 B:
        # ports, CRC, END
        "  /cmd_vel  20 Hz x 52 B = 91 B on the wire (1 packet) -> 14.6 kbit/s",
        "  /status   1 Hz x 200 B = 240 B on the wire (1 packet) -> 1.92 kbit/s",
        "  /big      100 Hz x 1,000 B = 1,080 B on the wire (5 packets) -> 864.0 kbit/s; "
        "cannot fit: more than the whole budget by itself",
        "  total 880.5 kbit/s of 43.8 kbit/s (2011.3 %): over budget: latest_only topics send "
        "less often, others wait in the queue (reliable) or are dropped late (best effort)"]


def test_recovery_on_a_line_of_small_frames_is_refused_saying_how(tmp_path, capsys):
    """Below 256 bytes the line cuts every frame into compact pieces, which carry no numbers
    to repair: a ``recovery:`` there would recover nothing while its receiver waited for it."""
    from rosgate.cli import main

    path = tmp_path / "radio.yaml"
    path.write_text("""
bridge: {name: a, role: peer, peer: line, listen: line, insecure: true}
plugins:
  serial: {device: /dev/serial/by-id/usb-radio-if00, baud: 57600}
topics:
  - {topic: /cmd_vel, type: geometry_msgs/msg/Twist, direction: transmit, port: 1,
     transport: serial, recovery: retransmit}
""")
    assert main(["check", str(path)]) != 0
    err = capsys.readouterr().err
    assert "radio.yaml:7: topics[0].recovery: serial carries frames of 250 bytes" in err, err
    assert "fix: give serial a max_frame of 256 or more, or remove recovery:" in err, err
    assert "Traceback" not in err


def test_a_board_on_the_line_speaks_cvra_layouts_both_ways(engines, domain, ros_side, tmp_path):
    """A microcontroller at the far end of the line (here: this test, through the pseudo-
    terminal) writes and reads one serial datagram per message, ``[name, args]`` in
    MessagePack with 32-bit floats, no ports: ``multiplex: false``."""
    import msgpack
    import serial
    from geometry_msgs.msg import Pose2D
    from rosgate_mcu_cvra import serial_datagram

    with PtyRelay(tmp_path, LineProfile(baud=115_200)) as relay:
        d = domain()
        engines(board_peer(relay.a), d)
        side = ros_side(d, "robot")
        positions = side.listen("/position", Pose2D)
        cmd_vel = side.publisher("/cmd_vel", Twist)
        board = serial.Serial(relay.b, 115200, timeout=0.1)
        try:
            decoder = serial_datagram.Decoder(lambda reason, detail: None)
            heard: list[bytes] = []
            deadline = time.monotonic() + 30
            while not positions.items or not heard:  # until both ways have crossed
                assert time.monotonic() < deadline, (positions.items, heard)
                board.write(serial_datagram.encode(
                    msgpack.packb(["position", [1.0, 0.5, 0.25]], use_single_float=True)))
                cmd_vel.publish(twist(7))
                heard += decoder.feed(board.read(1000))  # waits up to 0.1 s
        finally:
            board.close()
        assert positions.items[0] == Pose2D(x=1.0, y=0.5, theta=0.25)
        assert msgpack.unpackb(heard[0]) == ["cmd_vel", {
            "linear": {"x": 7.0, "y": 0.0, "z": 0.0}, "angular": {"x": 0.0, "y": 0.0, "z": -0.5}}]


@pytest.mark.parametrize("page, heading", [("real-links.md", "## Serial lines"),
                                           ("microcontrollers.md", "## Over a serial line")])
def test_the_files_of_the_docs_check(tmp_path, capsys, page, heading):
    from rosgate.cli import main

    text = (Path(__file__).resolve().parents[1] / "docs" / page).read_text()
    section = text[text.index(heading):]
    section = section[:section.find("\n## ", 1)]
    files = [block.split("```", 1)[0] for block in section.split("```yaml\n")[1:]]
    assert files, f"no yaml block under {heading}"
    write_key(tmp_path / "line.key", AeadCipher.generate_key())
    identity.write_private(tmp_path / "robot.key", identity.generate())
    public = identity.encode(identity.public_of(identity.generate()))
    for n, text in enumerate(files):
        path = tmp_path / f"{n}.yaml"
        path.write_text(text.replace("<the base's public key>", public))
        assert main(["check", str(path)]) == 0, capsys.readouterr()
        assert ": ok (peer " in capsys.readouterr().out


def test_a_topic_too_big_for_the_line_is_dropped_by_the_budget_not_the_twist(
        bridge, domain, ros_side, line_57600, tmp_path):
    """1,000-byte messages at 100 Hz want 15 times the line: forced on it anyway (background
    priority, best effort), they are shed by the budget while a real-time Twist at 20 Hz keeps
    crossing, all of it, each behind at most the budget's burst (four packets, 180 ms at
    57,600 baud) in the port's buffer: p50 95 ms, p99 205 ms measured (three runs). The line's
    budget is one for all its ports: with a budget per destination, as on UDP, both topics took
    the whole line and the Twist waited behind the port's full buffer (p50 1.0 s, p99 1.9 s)."""
    relay = line_57600
    da, db = domain(), domain()

    def big_side(name: str, device: str, way: str) -> str:
        return f"""
bridge: {{name: {name}, role: peer, peer: line, listen: line, insecure: true}}
plugins:
  serial: {{device: {device}, baud: 57600}}
topics:
  - {{topic: /cmd_vel, type: geometry_msgs/msg/Twist, direction: {way}, port: 1,
     transport: serial, qos: 100, priority: real_time}}
  - {{topic: /big, type: std_msgs/msg/String, direction: {way}, port: 2,
     transport: serial, qos: sensor_data, priority: background}}
"""

    # bridges of their own (rosgate run): the relay's thread has this process to itself
    (tmp_path / "a.yaml").write_text(big_side("a", relay.a, "transmit"))
    (tmp_path / "b.yaml").write_text(big_side("b", relay.b, "receive"))
    bridge(tmp_path / "a.yaml", da)
    bridge(tmp_path / "b.yaml", db)
    side_a, side_b = ros_side(da, "a"), ros_side(db, "b")
    latencies: list[float] = []
    twists = side_b.listen("/cmd_vel", Twist)
    side_b.ros.subscribe(Twist, "/cmd_vel", 100, lambda m: m.linear.x >= 0 and latencies.append(
        time.time() - m.linear.y), raw=False)  # warm-ups (-1) not counted
    bigs = side_b.listen("/big", String, qos=qos_profile_sensor_data)
    twist_pub = side_a.publisher("/cmd_vel", Twist)
    big_pub = side_a.publisher("/big", String, qos_profile_sensor_data)
    stop = threading.Event()

    def flood() -> None:
        n = 0
        while not stop.wait(0.01):
            big_pub.publish(String(data=f"{n:06d}" + "b" * 994))
            n += 1

    flooder = threading.Thread(target=flood, daemon=True)
    flooder.start()
    try:
        first = Twist()
        first.linear.x = -1.0
        deadline = time.monotonic() + 30
        while not twists.wait_count(1, 0.2):  # discovery
            assert time.monotonic() < deadline, "no Twist crossed"
            first.linear.y = time.time()
            twist_pub.publish(first)
        start = len(twists.items)
        for i in range(100):  # 5 s at 20 Hz, under the flood
            message = twist(i)
            message.linear.y = time.time()
            twist_pub.publish(message)
            stop.wait(0.05)
        numbered = lambda items: [m.linear.x for m in items[start:] if m.linear.x >= 0]
        assert twists.wait_for(lambda items: len(numbered(items)) >= 100, 10), \
            numbered(twists.items)
    finally:
        stop.set()
        flooder.join()
    got = numbered(twists.items)
    assert got == [float(i) for i in range(100)]
    ordered = sorted(latencies)
    p50, p99 = ordered[len(ordered) // 2], ordered[98]
    print(f"Twist under the flood: p50 {p50 * 1000:.0f} ms, p99 {p99 * 1000:.0f} ms")
    # the median, not the tail: behind a full port buffer it was 1.0 s; a loaded machine
    # stretches the tail (p99 1.4 s seen with 3 test workers beside 3 other runs), not the median
    assert p50 < 0.5, f"Twist p50 {p50 * 1000:.0f} ms"
    with StatusClient("a") as ask:
        shed = next(e for e in ask.status()["entries"] if e["name"] == "/big")["drops"]
    assert sum(shed.values()) > 100 and 0 < len(bigs.items), (shed, len(bigs.items))


@pytest.fixture
def line_57600(tmp_path):
    with PtyRelay(tmp_path, LineProfile(baud=57_600)) as relay:
        yield relay
