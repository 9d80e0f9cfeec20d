"""1 MB images across the file a user writes (an authenticated client/server session, udp as it
comes, cdr, the session's aead cipher): sealed into their frames, cut into fragments, put back
together and opened where they lie. Every image arrives once, byte for byte, in order, and
neither bridge counts a drop."""

from __future__ import annotations

import time
from pathlib import Path

from conftest import free_port, warm_up
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Image
from test_default_file_speed import counters

COUNT = 12
SIDE = 1024  # a 1024 x 1024 mono8 image: 1 MiB of pixels


def image(i: int) -> Image:
    img = Image()
    img.header.frame_id = f"camera-{i}"
    img.height, img.width, img.encoding, img.step = SIDE, SIDE, "mono8", SIDE
    # every image differs, at both ends and in the middle (a fragment out of place shows)
    img.data = bytes([i]) * 1000 + bytes(range(256)) * (SIDE * SIDE // 256 - 8) + bytes(
        [255 - i]) * (8 * 256 - 1000)
    return img


def camera_pair(tmp_path: Path, msg_type: str, qos: str) -> tuple[Path, Path]:
    """The files a user writes for a camera: a server (base) and a client (robot1) whose
    /camera of ``msg_type`` crosses to it with the entry's ``qos``."""
    port = free_port()
    server = tmp_path / "server.yaml"
    server.write_text(f"bridge: {{name: base, role: server, server: 127.0.0.1:{port}}}\n")
    client = tmp_path / "robot1.yaml"
    client.write_text(f"""
bridge: {{name: robot1, role: client, server: 127.0.0.1:{port}}}
topics:
  - {{topic: /camera, type: {msg_type}, direction: transmit, qos: {qos}}}
""")
    return server, client


def test_1mb_images_cross_the_default_file_byte_for_byte(tmp_path: Path, domain, ros_side,
                                                          bridge):
    server_domain, client_domain = domain(), domain()
    server, client = camera_pair(tmp_path, "sensor_msgs/msg/Image",
                                 "{reliability: reliable, depth: 20}")
    base = bridge(server, server_domain)
    robot = bridge(client, client_domain)
    far, near = ros_side(server_domain, "far"), ros_side(client_domain, "near")
    qos = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
    inbox = far.listen("/camera", Image, qos)
    publisher = near.publisher("/camera", Image, qos)

    warm = Image(height=1, width=1, encoding="mono8", step=1, data=b"\x00")
    warm.header.frame_id = "warmup"
    warm_up(publisher, inbox, warm, every=0.3)
    for i in range(COUNT):
        publisher.publish(image(i))
        time.sleep(0.05)  # a camera's pace: 20 images a second
    assert inbox.wait_for(lambda items: sum(m.header.frame_id != "warmup" for m in items)
                          >= COUNT, 30), f"{len(inbox.items)} arrived"
    got = [m for m in inbox.items if m.header.frame_id != "warmup"]
    assert [m.header.frame_id for m in got] == [f"camera-{i}" for i in range(COUNT)]
    for i, m in enumerate(got):
        expected = image(i)
        assert (m.height, m.width, m.encoding, m.step) == (SIDE, SIDE, "mono8", SIDE)
        assert bytes(m.data) == bytes(expected.data), f"image {i} differs"

    assert robot.stop() == 0 and base.stop() == 0  # their last lines: the counters
    sent, _, drops = counters(robot.log, "/camera")
    assert drops == {} and sent >= COUNT, robot.log
    _, received, far_drops = counters(base.log, "/camera")
    assert far_drops == {} and received == sent, base.log
