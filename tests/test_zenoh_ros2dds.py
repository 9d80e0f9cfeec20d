"""Interoperation with zenoh-bridge-ros2dds: ``framing: none`` + ``codec: cdr`` on a zenoh topic
speaks its convention, checked against a plain zenoh publisher and subscriber that follow it.

The convention, from zenoh-plugin-ros2dds (``ros2_utils.rs`` ``ros2_name_to_key_expr``,
``route_publisher.rs``, ``route_subscriber.rs``): the key is the ROS name without its leading
slash, under the bridge's ``namespace`` when that is not ``/`` (``/bot1`` + ``/cmd_vel`` ->
``bot1/cmd_vel``); the payload is the serialized sample as DDS carries it, CDR with its 4-byte
encapsulation header — what ``rclpy.serialization.serialize_message`` gives — with no encoding
and no attachment."""

from __future__ import annotations

import json
import random
import threading
import time

import pytest
import zenoh
from conftest import wait_until
from geometry_msgs.msg import Twist
from rclpy.serialization import serialize_message
from sensor_msgs.msg import Image
from test_zenoh_fleet import Router, zenoh_plugin

TIMEOUT = 20.0


@pytest.fixture
def router():
    r = Router()
    yield r
    r.stop()


@pytest.fixture
def plain(router):
    """A plain zenoh session, as a zenoh-bridge-ros2dds base would have one."""
    session = zenoh.open(zenoh.Config.from_json5(json.dumps({
        "mode": "client", "connect": {"endpoints": [router.endpoint]},
        "scouting": {"multicast": {"enabled": False}}})))
    yield session
    session.close()  # a session with callbacks must be closed, or the process may hang


def twist() -> Twist:
    t = Twist()
    t.linear.x, t.linear.y, t.angular.z = 1.5, -0.25, 0.75
    return t


def image() -> Image:
    rng = random.Random(7)
    return Image(height=480, width=640, encoding="rgb8", is_bigendian=0, step=640 * 3,
                 data=rng.randbytes(640 * 480 * 3))


@pytest.fixture
def bot1(tmp_path, router, bridge, domain):
    d = domain()
    path = tmp_path / "bot1.yaml"
    path.write_text(f"""\
bridge: {{name: bot1, role: peer, defaults: {{transport: zenoh, codec: cdr}}}}
{zenoh_plugin(router, ", namespace: /bot1")}topics:
  - {{topic: /cmd_vel, type: geometry_msgs/msg/Twist, direction: transmit, framing: none}}
  - {{topic: /camera/image_raw, type: sensor_msgs/msg/Image, direction: transmit, framing: none}}
  - {{topic: /cmd_vel_in, type: geometry_msgs/msg/Twist, direction: receive, framing: none}}
  - {{topic: /image_in, type: sensor_msgs/msg/Image, direction: receive, framing: none}}
""")
    bridge(path, d)
    return d


@pytest.mark.parametrize("topic, key, make", [
    ("/cmd_vel", "bot1/cmd_vel", twist),
    ("/camera/image_raw", "bot1/camera/image_raw", image),
], ids=["Twist", "Image 640x480"])
def test_rosgate_feeds_a_ros2dds_base_byte_for_byte(bot1, plain, ros_side, topic, key, make):
    message = make()
    expected = serialize_message(message)
    got: list[tuple[str, bytes]] = []
    arrived = threading.Event()

    def sample(s: zenoh.Sample) -> None:
        got.append((str(s.key_expr), s.payload.to_bytes()))
        arrived.set()

    subscriber = plain.declare_subscriber(key, zenoh.handlers.Callback(sample, indirect=False))
    publisher = ros_side(bot1, "robot").publisher(topic, type(message))
    deadline = time.monotonic() + TIMEOUT
    while not arrived.wait(0.2):  # ROS discovery and the subscription's spread take a moment
        assert time.monotonic() < deadline, "nothing arrived on the key"
        # the serialized bytes themselves: rclpy leaves CDR padding bytes uninitialised, so two
        # serializations of one message may differ there (README, Security)
        publisher.publish(expected)
    subscriber.undeclare()
    assert got[0][0] == key
    assert got[0][1] == expected
    assert expected[:4] in (b"\x00\x01\x00\x00", b"\x00\x00\x00\x00")  # the CDR header is kept


@pytest.mark.parametrize("topic, key, make", [
    ("/cmd_vel_in", "bot1/cmd_vel_in", twist),
    ("/image_in", "bot1/image_in", image),
], ids=["Twist", "Image 640x480"])
def test_a_ros2dds_base_feeds_rosgate_byte_for_byte(bot1, plain, ros_side, topic, key, make):
    message = make()
    payload = serialize_message(message)
    got: list[bytes] = []
    side = ros_side(bot1, "robot")
    side.ros.subscribe(type(message), topic, 10, got.append, raw=True)
    publisher = plain.declare_publisher(key)
    deadline = time.monotonic() + TIMEOUT
    while not wait_until(lambda: bool(got), 0.2):
        assert time.monotonic() < deadline, "nothing was published on the ROS side"
        publisher.put(payload)
    publisher.undeclare()
    assert got[0] == payload
