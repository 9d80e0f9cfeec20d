"""Real links, end to end through two engines: compression, and (below) the scheduler,
latest-only replacement, loss recovery and budgets through the link emulator.

Nothing here is timed: what arrived is compared with what was sent, and counters with what
must have happened. Speed, rates and latencies are measured in bench/constrained.py.
"""

from __future__ import annotations

import os
import time

import pytest
from conftest import cross, free_port, wait_until
from nav_msgs.msg import OccupancyGrid
from sensor_msgs.msg import Image


def peer_pair(engines, domain, topics_a: str, topics_b: str, bridge_a: str = "",
              bridge_b: str = ""):
    """Bridge a (transmitting) and bridge b (receiving), peers on 127.0.0.1."""
    da, db = domain(), domain()
    a = engines(f"""
bridge: {{name: a, role: peer, peer: 127.0.0.1, listen: 127.0.0.1{bridge_a}}}
topics:
{topics_a}""", da)
    b = engines(f"""
bridge: {{name: b, role: peer, peer: 127.0.0.1, listen: 127.0.0.1{bridge_b}}}
topics:
{topics_b}""", db)
    return a, b, da, db


def mostly_unknown_map(width: int, height: int, seed: int) -> OccupancyGrid:
    """A map that is 95 % unknown (-1): a square explored area of free cells (0) with a few
    walls (100), as a robot's map early in a run."""
    grid = OccupancyGrid()
    grid.info.width, grid.info.height, grid.info.resolution = width, height, 0.05
    cells = bytearray(b"\xff" * (width * height))
    side = int((0.05 * width * height) ** 0.5)
    noise = os.urandom(side * side)
    for row in range(side):
        start = (height // 3 + row) * width + width // 3
        row_noise = noise[row * side:(row + 1) * side]
        cells[start:start + side] = bytes(100 if n < 8 else 0 for n in row_noise)
    grid.data = memoryview(cells).cast("b").tolist()
    grid.header.frame_id = f"map{seed}"
    return grid


def test_compressed_topics_cross_byte_for_byte_and_count_what_they_saved(engines, domain,
                                                                        ros_side):
    port = free_port()
    a, b, da, db = peer_pair(engines, domain, f"""\
  - {{topic: /map, type: nav_msgs/msg/OccupancyGrid, direction: transmit, port: {port},
      compression: zstd}}
  - {{topic: /noise, type: sensor_msgs/msg/Image, direction: transmit, port: {port},
      compression: {{zstd: {{level: 1}}}}}}""",
        # the receiver's file need not say compression: the envelope says it per frame
        f"""\
  - {{topic: /map, type: nav_msgs/msg/OccupancyGrid, direction: receive, port: {port}}}
  - {{topic: /noise, type: sensor_msgs/msg/Image, direction: receive, port: {port}}}""")
    robot, base = ros_side(da, "robot"), ros_side(db, "base")
    maps = base.listen("/map", OccupancyGrid, qos=10)
    sent = [mostly_unknown_map(1000, 1000, seed) for seed in range(3)]
    got = cross(robot.publisher("/map", OccupancyGrid, qos=10), maps,
                lambda i: mostly_unknown_map(200, 200, 99) if i is None else sent[i],
                lambda m: m.header.frame_id == "map99", 3, interval=0.2)
    assert [(m.header.frame_id, list(m.data)) for m in got] == \
        [(m.header.frame_id, list(m.data)) for m in sent]
    route = next(r for r in a.routes() if r.label == "/map")
    c = route.counters
    assert c.not_compressed == 0
    assert c.bytes_before_compression > 3 * 1_000_000
    assert c.bytes_before_compression > 10 * c.bytes_after_compression
    assert c.bytes_sent < c.bytes_before_compression / 10  # frames: compressed, then sealed

    # camera noise does not shrink: sent as it was, and counted so
    noise = base.listen("/noise", Image)
    pixels = [os.urandom(64 * 64) for _ in range(5)]
    got = cross(robot.publisher("/noise", Image), noise,
                lambda i: image(b"" if i is None else pixels[i]), lambda m: not m.data, 5)
    assert [bytes(m.data) for m in got] == pixels
    route = next(r for r in a.routes() if r.label == "/noise")
    assert wait_until(lambda: route.counters.not_compressed >= 5)
    c = route.counters
    assert c.bytes_before_compression - c.bytes_after_compression < 100  # a warm-up's header
    receiver = next(r for r in b.routes() if r.label == "/noise")
    assert not receiver.counters.drops


def image(pixels: bytes) -> Image:
    return Image(height=64 if pixels else 0, width=64 if pixels else 0, encoding="mono8",
                 step=64 if pixels else 0, data=pixels)


def through_relay(engines, domain, profile, topics: str, bridge_a: str = "", plugins: str = ""):
    """Bridge a (transmitting) sends every topic to a relay of the link emulator, which passes
    it on to bridge b through ``profile`` — and b's NACKs and ACKs back. ``plugins``: a
    ``plugins:`` line for both files."""
    from rosgate_emulator import UdpRelay

    da, db, port = domain(), domain(), free_port()
    b = engines(f"""
bridge: {{name: b, role: peer, peer: 127.0.0.1, listen: 127.0.0.1}}
{plugins}topics:
{topics.format(direction="receive", port=port)}""", db)
    relay = UdpRelay(profile, target=("127.0.0.1", port))
    a = engines(f"""
bridge: {{name: a, role: peer, peer: 127.0.0.1, listen: 127.0.0.1{bridge_a}}}
{plugins}topics:
{topics.format(direction="transmit", port=relay.address[1])}""", da)
    return a, b, da, db, relay


def megabyte(i: int | None) -> Image:
    """A 1024 x 1024 mono8 image (1 MiB of pixels); the warm-up is tiny."""
    side = 8 if i is None else 1024
    picture = Image(height=side, width=side, encoding="mono8", step=side)
    picture.header.frame_id = "warmup" if i is None else f"image {i}"
    picture.data = os.urandom(side * side) if i is not None else bytes(side * side)
    return picture


@pytest.mark.parametrize("recovery", ["fec", "retransmit"])
def test_a_megabyte_image_crosses_2_percent_loss_with_recovery(engines, domain, ros_side,
                                                              recovery):
    """870 datagrams of 1,200 bytes (as on a path whose MTU is not known; loopback's would
    carry 65,000): without recovery it would arrive 0.00002 % of the time."""
    from rosgate_emulator import Profile

    a, b, da, db, relay = through_relay(
        engines, domain, Profile(delay=0.005, loss=0.02, seed=7),
        f"  - {{{{topic: /camera, type: sensor_msgs/msg/Image, direction: {{direction}}, "
        f"port: {{port}}, recovery: {recovery}, qos: 5}}}}",
        plugins="plugins: {udp: {max_frame: 1200}}\n")
    try:
        inbox = ros_side(db, "base").listen("/camera", Image, qos=10)
        sent = [megabyte(i) for i in range(6)]
        got = cross(ros_side(da, "robot").publisher("/camera", Image, qos=10), inbox,
                    lambda i: megabyte(None) if i is None else sent[i],
                    lambda m: m.header.frame_id == "warmup", 6, timeout=60, interval=0.3)
        # published as each completes: one that waited for a fragment sent again may come
        # after a later one
        assert sorted((m.header.frame_id, bytes(m.data)) for m in got) == \
            sorted((m.header.frame_id, bytes(m.data)) for m in sent)
        assert relay.up.dropped["loss"] > 30
        receiver = next(r for r in b.routes() if r.label == "/camera")
        sender = next(r for r in a.routes() if r.label == "/camera")
        assert receiver.counters.recovered >= 5 and not receiver.counters.drops
        assert sender.counters.bytes_on_wire > sender.counters.bytes_sent
        if recovery == "retransmit":
            assert sender.counters.retransmitted >= relay.up.dropped["loss"] * 0.5
    finally:
        relay.close()


def test_latest_only_and_priorities_on_a_budget_count_what_they_replaced(engines, domain,
                                                                          ros_side):
    """A 2 Mbit/s budget, a 300 kB camera at 10 Hz (12x the budget) and a Twist at 50 Hz:
    every Twist arrives, in order; the camera's unsent frames are replaced, counted, and its
    queue never holds more than the frame in progress and one waiting."""
    from geometry_msgs.msg import Twist
    from rosgate_emulator import Profile

    from rosgate.rostypes import qos_profile

    a, b, da, db, relay = through_relay(
        engines, domain, Profile(delay=0.002),
        "  - {{topic: /camera, type: sensor_msgs/msg/Image, direction: {direction}, "
        "port: {port}, qos: sensor_data, priority: data_low}}\n"
        "  - {{topic: /cmd_vel, type: geometry_msgs/msg/Twist, direction: {direction}, "
        "port: {port}, priority: interactive_high, qos: 100}}",
        bridge_a=", links: {udp: {bandwidth: 2mbit}}")
    try:
        robot, base = ros_side(da, "robot"), ros_side(db, "base")
        twists = base.listen("/cmd_vel", Twist)
        cameras = base.listen("/camera", Image, qos=qos_profile("sensor_data"))
        camera = robot.publisher("/camera", Image, qos=qos_profile("sensor_data"))
        cmd = robot.publisher("/cmd_vel", Twist)
        warm = cross(cmd, twists, lambda i: Twist() if i is None else Twist(),
                     lambda m: m.linear.x == 0, 0)
        assert warm == []
        route = next(r for r in a.routes() if r.label == "/camera")
        depths = []
        for i in range(60):  # 1.2 s
            if i % 5 == 0:
                picture = Image(height=300, width=1000, encoding="mono8", step=1000,
                                data=os.urandom(300_000))
                picture.header.frame_id = f"frame {i}"
                camera.publish(picture)
            message = Twist()
            message.linear.x = float(i + 1)
            cmd.publish(message)
            depths.append(route.queue_depth)
            time.sleep(0.02)  # paces the publisher
        assert twists.wait_for(lambda items: sum(m.linear.x > 0 for m in items) >= 60, 20)
        assert [m.linear.x for m in twists.items if m.linear.x > 0] == \
            [float(i + 1) for i in range(60)]
        assert wait_until(lambda: route.counters.drops["superseded"] >= 5, 10), route.counters
        assert max(depths) <= 2
        assert cameras.wait_count(2, 10)  # some frames made it, the newest ones
        assert b.stats()["routes"]["/cmd_vel"]["received"] >= 60
        assert a.stats()["routes"]["/camera"]["queue_depth"] <= 2
    finally:
        relay.close()
