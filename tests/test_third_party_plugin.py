"""A plugin from another distribution works by installation alone: the ``unixdgram`` transport
in tests/thirdparty/ is found through its entry point and carries topics, including messages
that the core must fragment to fit its 16000-byte datagrams."""

from __future__ import annotations

import pytest
from conftest import cross
from sensor_msgs.msg import Image
from std_msgs.msg import String

from rosgate.config import loads
from rosgate.engine import Engine
from rosgate.errors import ConfigError
from rosgate.plugins import Plugins


def peer(name: str, directory: str, direction: str, port: int, msg: str, extra: str = "") -> str:
    return f"""
bridge: {{name: {name}, role: peer, peer: {directory}, listen: {directory}}}
{extra}
topics:
  - {{topic: /data, type: {msg}, direction: {direction}, port: {port}, transport: unixdgram}}
"""


def test_found_through_its_entry_point():
    registration = Plugins.discover().get("transport", "unixdgram")
    assert registration is not None
    assert (registration.distribution, registration.plugin) == ("rosgate-transport-unixdgram",
                                                                "unixdgram")


@pytest.mark.parametrize("msg, make, size", [
    ("std_msgs/msg/String", lambda i: String(data="warmup" if i is None else f"s{i}" * 10), 0),
    ("sensor_msgs/msg/Image", None, 100_000),
])
def test_carries_topics_and_fragmented_messages(tmp_path, engines, domain, ros_side,
                                                msg, make, size):
    da, db = domain(), domain()
    engines(peer("a", str(tmp_path), "transmit", 5, msg), da)
    b = engines(peer("b", str(tmp_path), "receive", 5, msg), db)
    cls = String if size == 0 else Image
    if make is None:
        def make(i):
            img = Image(encoding="mono8", height=100, width=1000, step=1000)
            img.header.frame_id = "warmup" if i is None else f"f{i}"
            img.data = bytes([(i or 0) % 256]) * size
            return img
    warm = (lambda m: m.data == "warmup") if size == 0 else (lambda m: m.header.frame_id == "warmup")
    got = cross(ros_side(da, "a").publisher("/data", cls), ros_side(db, "b").listen("/data", cls),
                make, warm, 5, interval=0.02)
    assert got == [make(i) for i in range(5)]
    assert b.routes()[0].counters.drops == {}


def test_its_options_are_checked_with_file_and_line(tmp_path):
    text = peer("a", str(tmp_path), "receive", 5, "std_msgs/msg/String",
                "plugins:\n  unixdgram: {max_frame: 10}")
    with pytest.raises(ConfigError) as error:
        Engine(loads(text, file="x.yaml")).prepare()
    assert str(error.value).startswith("x.yaml:4: plugins.unixdgram.max_frame: must be")
