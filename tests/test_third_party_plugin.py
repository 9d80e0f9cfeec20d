"""A plugin from another distribution works by installation alone: the ``unixdgram`` transport
in tests/thirdparty/ is found through its entry point and carries topics, including messages
that the core must fragment to fit its 16000-byte datagrams; the ``json`` codec there, written
from the docs on rosgate_message_tree's to_tree/from_tree, carries topics as JSON text. A plugin
that declares no Options takes none, and carries topics."""

from __future__ import annotations

import base64
import json
import socket
import types
from pathlib import Path

import pytest
from conftest import cross, free_port, wait_until
from rosgate_transport_udp import UdpEndpoint
from sensor_msgs.msg import Image
from std_msgs.msg import String

from rosgate import DatagramTransport
from rosgate.config import loads
from rosgate.engine import Engine
from rosgate.errors import ConfigError
from rosgate.plugins import Plugins


def peer(name: str, directory: str, direction: str, port: int, msg: str, extra: str = "") -> str:
    return f"""
bridge: {{name: {name}, role: peer, peer: {directory}, listen: {directory}, insecure: true}}
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
    warm = ((lambda m: m.data == "warmup") if size == 0
            else (lambda m: m.header.frame_id == "warmup"))
    got = cross(ros_side(da, "a").publisher("/data", cls), ros_side(db, "b").listen("/data", cls),
                make, warm, 5, interval=0.02)
    assert got == [make(i) for i in range(5)]
    assert b.routes()[0].counters.drops == {}


def test_its_options_are_checked_with_file_and_line(tmp_path):
    text = peer("a", str(tmp_path), "receive", 5, "std_msgs/msg/String",
                "plugins:\n  unixdgram: {max_frame: 10}")
    with pytest.raises(ConfigError) as error:
        Engine(loads(text, file="x.yaml")).prepare()
    assert str(error.value).startswith("x.yaml:4: plugins.unixdgram.max_frame: expected an "
                                       "integer 64..200000, got 10")


# --- json: a codec written by a third party on the tree mapping ----------------------------------

def udp_peer(name: str, direction: str, port: int, msg: str, extra: str = "",
             topic: str = "codec: json") -> str:
    return f"""
bridge: {{name: {name}, role: peer, peer: 127.0.0.1, listen: 127.0.0.1, insecure: true}}
{extra}
topics:
  - {{topic: /data, type: {msg}, direction: {direction}, port: {port}, {topic}}}
"""


def image(i: int | None) -> Image:
    picture = Image(encoding="mono8", height=10, width=100, step=100)
    picture.header.frame_id = "warmup" if i is None else f"caméra {i}"
    picture.data = bytes([(i or 0) % 256, 255, 0]) * 333 + b"\x01"
    return picture


def test_json_is_found_through_its_entry_point():
    registration = Plugins.discover().get("codec", "json")
    assert registration is not None
    assert (registration.distribution, registration.plugin) == ("rosgate-codec-json", "json")


@pytest.mark.parametrize("extra", ["", "plugins:\n  json: {indent: 2, ascii: false}"],
                         ids=["defaults", "options"])
def test_json_carries_a_topic_end_to_end(engines, domain, ros_side, extra):
    da, db, port = domain(), domain(), free_port()
    engines(udp_peer("a", "transmit", port, "sensor_msgs/msg/Image", extra), da)
    b = engines(udp_peer("b", "receive", port, "sensor_msgs/msg/Image", extra), db)
    got = cross(ros_side(da, "a").publisher("/data", Image),
                ros_side(db, "b").listen("/data", Image), image,
                lambda m: m.header.frame_id == "warmup", 5, interval=0.02)
    assert got == [image(i) for i in range(5)]
    assert b.routes()[0].counters.drops == {}


def test_json_on_the_wire_is_what_a_web_page_reads(engines, domain, ros_side):
    """framing: none, cipher none: each datagram is the JSON text alone, bytes in base64."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as far:
        far.bind(("127.0.0.1", 0))
        far.settimeout(0.05)
        da = domain()
        engines(udp_peer("a", "transmit", far.getsockname()[1], "sensor_msgs/msg/Image",
                         topic="codec: json, framing: none"), da)
        publisher = ros_side(da, "a").publisher("/data", Image)
        datagram = None
        for _ in range(400):  # until discovery has matched the bridge's subscription
            publisher.publish(image(7))
            try:
                datagram = far.recv(65536)
                break
            except TimeoutError:
                continue
    assert datagram is not None, "nothing arrived"
    tree = json.loads(datagram.decode("ascii"))  # non-ASCII escaped by default (\u00e9)
    assert tree["header"]["frame_id"] == "caméra 7"
    assert base64.b64decode(tree["data"], validate=True) == bytes([7, 255, 0]) * 333 + b"\x01"
    assert (tree["height"], tree["width"], tree["encoding"]) == (10, 100, "mono8")


# --- deflate and twice: a compressor and a packetizer written by a third party -------------------

def test_deflate_and_twice_carry_a_topic_end_to_end(engines, domain, ros_side):
    """The sender's file picks both (deflate at level 9); the receiver's says neither: the
    envelope names the transform, the packets' magic the packetizer."""
    da, db, port = domain(), domain(), free_port()
    a = engines(udp_peer("a", "transmit", port, "std_msgs/msg/String",
                         topic="compression: {deflate: {level: 9}}, recovery: twice"), da)
    b = engines(udp_peer("b", "receive", port, "std_msgs/msg/String", topic="codec: cdr"), db)
    make = lambda i: String(data="warmup" if i is None else f"command {i}; " * 50)
    got = cross(ros_side(da, "a").publisher("/data", String),
                ros_side(db, "b").listen("/data", String), make,
                lambda m: m.data == "warmup", 5, interval=0.02)
    assert got == [make(i) for i in range(5)]
    sender, receiver = a.routes()[0].counters, b.routes()[0].counters
    assert receiver.drops == {} and sender.drops == {}
    # the five commands shrink; the short warm-ups do not, and go as they were
    assert sender.sent - sender.not_compressed == 5
    assert sender.bytes_after_compression < sender.bytes_before_compression / 5
    # every packet went twice: twice the frames' bytes and an 11-byte header each time
    assert sender.bytes_on_wire == 2 * (sender.bytes_sent + 11 * sender.sent)
    assert a.resolver.plugins.get("packetizer", "twice").distribution == \
        "rosgate-packetizer-twice"
    # every packet the sender's link sent reached the receiver's link (the second copies a moment
    # after the first), and each of the topic's frames came in two packets: the link's other
    # frames (the type announcements) in one each
    out = a.stats()["links"]["udp"]
    into = lambda: b.stats()["links"][f"udp:{port}"]
    assert wait_until(lambda: into()["packets_in"] == out["packets_out"], 5.0), (out, into())
    assert into()["packets_in"] - into()["frames_in"] == sender.sent, (sender, into())


@pytest.mark.parametrize("source", [
    "compress_deflate/src/rosgate_compress_deflate/__init__.py",
    "packetizer_twice/src/rosgate_packetizer_twice/__init__.py"])
def test_the_guide_shows_each_example_whole_and_as_it_is(source):
    """docs/plugins.md prints both examples in full: what it shows is what runs here."""
    root = Path(__file__).resolve().parent
    code = (root / "thirdparty" / source).read_text()
    assert len(code.splitlines()) <= 60
    assert f"```python\n{code}```" in (root.parent / "docs" / "plugins.md").read_text()


def test_a_topic_s_options_for_deflate_are_checked_where_they_are_written():
    text = udp_peer("a", "transmit", 9, "std_msgs/msg/String",
                    topic="compression: {deflate: {level: 10}}")
    with pytest.raises(ConfigError) as error:
        Engine(loads(text, file="x.yaml")).prepare()
    assert str(error.value).startswith(
        "x.yaml:5: topics[0].compression.deflate.level: expected an integer 1..9, got 10")


# --- a plugin that declares no options ----------------------------------------------------------

def legacy_module() -> types.ModuleType:
    """A transport that declares no Options: it takes none."""
    class LegacyUdp(DatagramTransport):
        name = "legacyudp"

        def __init__(self, options):
            super().__init__(options)
            self.max_frame = 1400

        def bind(self, address):
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            sock.bind(address)
            return UdpEndpoint(sock)

    module = types.ModuleType("rosgate_transport_legacyudp")
    module.rosgate_transports = lambda register: register(LegacyUdp)
    return module


def test_a_plugin_without_declared_options_takes_none_and_carries_topics(domain, ros_side):
    plugins = Plugins.discover()
    plugins.add(legacy_module(), "legacyudp", "rosgate-transport-legacyudp")
    assert plugins.failures == []
    da, db, port = domain(), domain(), free_port()
    given = udp_peer("a", "transmit", port, "std_msgs/msg/String",
                     "plugins:\n  legacyudp: {max_frame: 500}", topic="transport: legacyudp")
    with pytest.raises(ConfigError, match="plugins.legacyudp.max_frame: unknown key 'max_frame'\n"
                                          "  fix: legacyudp takes no options: remove it"):
        Engine(loads(given, file="x.yaml"), plugins, domain_id=da).prepare()
    started = []
    try:
        for name, direction, domain_id in (("a", "transmit", da), ("b", "receive", db)):
            text = udp_peer(name, direction, port, "std_msgs/msg/String",
                            topic="transport: legacyudp")
            engine = Engine(loads(text, file="x.yaml"), plugins, domain_id=domain_id)
            engine.prepare()
            assert engine.resolver.transports["legacyudp"].options == {}
            started.append(engine.start())
        make = lambda i: String(data="warmup" if i is None else f"{i}" * 2000)
        got = cross(ros_side(da, "a").publisher("/data", String),
                    ros_side(db, "b").listen("/data", String), make,
                    lambda m: m.data == "warmup", 5, interval=0.02)
        assert got == [make(i) for i in range(5)]  # 2 kB each: fragmented to 1400-byte frames
        assert started[1].routes()[0].counters.drops == {}
    finally:
        for engine in started:
            engine.stop()
