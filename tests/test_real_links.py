"""Real links, end to end through two engines: compression, and (below) the scheduler,
latest-only replacement, loss recovery and budgets through the link emulator.

Nothing here is timed: what arrived is compared with what was sent, and counters with what
must have happened. Speed, rates and latencies are measured in bench/constrained.py.
"""

from __future__ import annotations

import os

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
    common = f"port: {port}, compression: zstd"
    a, b, da, db = peer_pair(engines, domain, f"""\
  - {{topic: /map, type: nav_msgs/msg/OccupancyGrid, direction: transmit, {common}}}
  - {{topic: /noise, type: sensor_msgs/msg/Image, direction: transmit, {common},
      compression_level: 1}}""",
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
