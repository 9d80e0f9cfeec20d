"""The CAN link of examples/transport_can, installed from its own distribution, between two
engines in this process on one python-can ``virtual`` channel (the in-process bus): Twist and
100 kB images cross classic CAN and CAN FD both ways, with cdr and msgpack, with and without
fernet; a lost CAN frame drops that message only and is counted; wrong options are located."""

from __future__ import annotations

import itertools
import os
import subprocess
from pathlib import Path

import can
import pytest
import rosgate_transport_can
import rosgate_transport_udp
from can.interfaces.virtual import VirtualBus
from conftest import ROSGATE, cross
from cryptography.fernet import Fernet
from geometry_msgs.msg import Twist
from sensor_msgs.msg import Image

from rosgate import builtin
from rosgate.config import loads
from rosgate.engine import Engine
from rosgate.errors import ConfigError
from rosgate.plugins import Plugins

_channels = itertools.count()


def bus(**options) -> str:
    """A fresh virtual channel: no test hears another's frames."""
    options = {"interface": "virtual", "channel": f"rosgate-test-{os.getpid()}-{next(_channels)}",
               **options}
    return "{" + ", ".join(f"{k}: {v}" for k, v in options.items()) + "}"


def side(name: str, can_options: str, topics: list[tuple], key: Path | None = None) -> str:
    """A peer bringup.yaml with its topics on the CAN bus: (name, type, direction, port), and
    optionally codec and cipher."""
    keys = f"\n  fernet: {{key_file: {key}}}" if key else ""
    entries = "".join(f"\n  - {{topic: {topic}, type: {msg}, direction: {direction}, port: {port},"
                      f" transport: can, codec: {codec}, cipher: {cipher}}}"
                      for topic, msg, direction, port, codec, cipher
                      in (t + ("cdr", "none")[len(t) - 4:] for t in topics))
    return f"""
bridge: {{name: {name}, role: peer, peer: can0, listen: can0, insecure: true}}
plugins:
  can: {can_options}{keys}
topics:{entries}
"""


def twist(i: int | None) -> Twist:
    message = Twist()
    message.linear.x = -1.0 if i is None else float(i)
    message.angular.z = 0.25
    return message


def image(size: int):
    """Images of ``size`` bytes of pixels; warm-ups (which only wait for discovery) are small."""
    def make(i: int | None) -> Image:
        pixels = 1000 if i is None else size
        message = Image(encoding="mono8", height=pixels // 1000, width=1000, step=1000)
        message.header.frame_id = "warmup" if i is None else f"f{i}"
        message.data = bytes((n * 7 + (i or 0)) % 256 for n in range(256)) * (pixels // 256) \
            + bytes(pixels % 256)
        return message
    return make


def is_warm_twist(m: Twist) -> bool:
    return m.linear.x == -1.0


def is_warm_image(m: Image) -> bool:
    return m.header.frame_id == "warmup"


@pytest.mark.parametrize("fd", [False, True], ids=["classic", "fd"])
def test_twist_and_100_kB_images_cross_both_ways_with_every_codec_and_cipher(
        tmp_path, engines, domain, ros_side, fd):
    key = tmp_path / "secret.key"
    key.write_bytes(Fernet.generate_key())
    key.chmod(0o600)
    # one engine pair, sixteen topics on one bus: Twist and Image, each way, for every codec
    # and cipher (one pair per combination would spend most of its time on DDS discovery)
    make_image = image(100_000)
    plan = [(f"/{kind}_{codec}_{cipher}_{way}", cls, make, warm, count, way, codec, cipher)
            for kind, cls, make, warm, count in [("twist", Twist, twist, is_warm_twist, 5),
                                                 ("image", Image, make_image, is_warm_image, 2)]
            for way in ("there", "back")
            for codec in ("cdr", "msgpack")
            for cipher in ("none", "fernet")]
    types = {Twist: "geometry_msgs/msg/Twist", Image: "sensor_msgs/msg/Image"}

    def topics(sends: str) -> list[tuple]:
        return [(topic, types[cls], "transmit" if way == sends else "receive", port, codec, cipher)
                for port, (topic, cls, _, _, _, way, codec, cipher) in enumerate(plan, 1)]

    options = bus(fd="true" if fd else "false", bitrate=500000, data_bitrate=2000000)
    da, db = domain(), domain()
    a = engines(side("a", options, topics("there"), key), da)
    b = engines(side("b", options, topics("back"), key), db)
    ros = {"there": (ros_side(da, "a"), ros_side(db, "b")),
           "back": (ros_side(db, "b"), ros_side(da, "a"))}
    # every endpoint first, so that DDS discovers them all at once
    ends = [(ros[way][0].publisher(topic, cls), ros[way][1].listen(topic, cls))
            for topic, cls, _, _, _, way, _, _ in plan]
    for (publisher, inbox), (topic, _, make, warm, count, _, _, _) in zip(ends, plan, strict=True):
        got = cross(publisher, inbox, make, warm, count, interval=0.02)
        assert got == [make(i) for i in range(count)], topic
    for engine in (a, b):
        assert all(route.counters.drops == {} for route in engine.routes()), engine.stats()
        assert engine.link_drops == {}


class LossyVirtualBus(VirtualBus):
    """python-can's virtual bus, except that it loses the ``countdown``-th frame it is given to
    send once armed: a python-can interface like any other, found through python-can's registry."""

    countdown: int | None = None
    lost: list[can.Message] = []

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        cls = type(self)
        if cls.countdown is not None:
            cls.countdown -= 1
            if cls.countdown == 0:
                cls.countdown = None
                cls.lost.append(msg)
                return
        super().send(msg, timeout)


@pytest.fixture
def lossy_interface(monkeypatch):
    # python-can reads its interfaces' entry points once, at import: register as that would have
    monkeypatch.setitem(can.interfaces.BACKENDS, "lossy_virtual", (__name__, "LossyVirtualBus"))
    monkeypatch.setattr(can.util, "VALID_INTERFACES", can.util.VALID_INTERFACES | {"lossy_virtual"})
    monkeypatch.setattr(LossyVirtualBus, "countdown", None)
    monkeypatch.setattr(LossyVirtualBus, "lost", [])
    return LossyVirtualBus


@pytest.mark.parametrize("fd", [False, True], ids=["classic", "fd"])
def test_a_lost_frame_drops_that_message_only_and_is_counted(engines, domain, ros_side,
                                                             lossy_interface, fd):
    options = bus(fd="true" if fd else "false")
    topic = [("/camera", "sensor_msgs/msg/Image", "transmit", 7)]
    da, db = domain(), domain()
    engines(side("a", options.replace("virtual", "lossy_virtual"), topic), da)
    b = engines(side("b", options, [topic[0][:2] + ("receive", 7)]), db)
    publisher = ros_side(da, "a").publisher("/camera", Image)
    inbox = ros_side(db, "b").listen("/camera", Image)
    make = image(4_000)  # 4 kB: 583 classic frames, 66 CAN FD frames
    assert cross(publisher, inbox, make, is_warm_image, 1) == [make(0)]
    lossy_interface.countdown = 30  # a frame in the middle of the next message
    for i in (1, 2, 3):
        publisher.publish(make(i))
    assert inbox.wait_for(lambda items: items[-1] == make(3), 10)
    assert [m for m in inbox.items if not is_warm_image(m)] == [make(0), make(2), make(3)]
    assert len(lossy_interface.lost) == 1
    assert 0 < lossy_interface.lost[0].data[0] < 0x80  # a continuation piece was lost
    assert b.routes()[0].counters.drops == {"fragment_lost": 1}


def test_several_receivers_and_senders_share_one_bus_by_port(engines, domain, ros_side):
    # three topics from a on ports 1-3 of one bus; b takes 1 and 3 only
    options = bus(base_id="0x700")
    names = [(f"/t{p}", "geometry_msgs/msg/Twist") for p in (1, 2, 3)]
    da, db = domain(), domain()
    engines(side("a", options, [(t, m, "transmit", p) for p, (t, m) in enumerate(names, 1)]), da)
    b = engines(side("b", options, [(t, m, "receive", p) for p, (t, m) in enumerate(names, 1)
                                    if p != 2]), db)
    ros_a, ros_b = ros_side(da, "a"), ros_side(db, "b")
    ends = [(ros_a.publisher(topic, Twist), ros_b.listen(topic, Twist)) for topic in ("/t1", "/t3")]
    for publisher, inbox in ends:
        assert cross(publisher, inbox, twist, is_warm_twist, 3) == [twist(i) for i in range(3)]
    # /t2's frames (id 0x702) are filtered out on b's bus: not even counted as unknown
    ros_a.publisher("/t2", Twist).publish(twist(9))
    assert b.link_drops == {}


@pytest.mark.parametrize("option, value, message", [
    ("bitrate", "500k", "plugins.can.bitrate: expected an integer >= 1 or null, got '500k'"),
    ("interface", "socketcann", "plugins.can.interface: python-can has no interface 'socketcann'"),
    ("fd", "maybe", "plugins.can.fd: expected true or false, got 'maybe'"),
    ("base_id", "0x800", "plugins.can.base_id: must be an arbitration id from 0 to 2046"),
])
def test_wrong_options_are_located_in_the_file(option, value, message):
    text = side("a", bus(**{option: value}), [("/t", "geometry_msgs/msg/Twist", "receive", 1)])
    with pytest.raises(ConfigError) as error:
        Engine(loads(text, file="x.yaml")).prepare()
    assert str(error.value).startswith(f"x.yaml:4: {message}")


def test_a_bus_python_can_cannot_open_is_a_clear_error_at_the_topic(domain):
    # socketcan on an interface this machine does not have: python-can's own words reach the user
    text = side("a", "{interface: socketcan, channel: rosgate-nope0}",
                [("/t", "geometry_msgs/msg/Twist", "receive", 1)])
    engine = Engine(loads(text, file="x.yaml"), domain_id=domain())
    with pytest.raises(ConfigError) as error:
        engine.prepare().start()
    text = str(error.value)
    # here: "[Errno 97] Address family not supported by protocol" (no SocketCAN in this kernel)
    assert text.startswith("x.yaml:6: topics[0].port: python-can cannot open socketcan channel "
                           "rosgate-nope0: "), text
    assert text.endswith("\n  fix: check the interface, its channel and its driver (SocketCAN: "
                         "ip link set <channel> up type can bitrate <bits/s>)"), text


def test_a_port_past_the_last_arbitration_id_is_refused(domain):
    text = side("a", bus(base_id="0x7f0"), [("/t", "geometry_msgs/msg/Twist", "receive", 16)])
    engine = Engine(loads(text, file="x.yaml"), domain_id=domain())
    with pytest.raises(ConfigError) as error:
        engine.prepare().start()
    assert str(error.value) == ("x.yaml:6: topics[0].port: port 16 is arbitration id 0x800, past "
                                "the last standard id 0x7ff\n"
                                "  fix: use a smaller port or base_id, or extended: true")


def test_listed_by_rosgate_plugins():
    registration = Plugins.discover().get("transport", "can")
    assert (registration.distribution, registration.plugin) == ("rosgate-transport-can", "can")
    listing = subprocess.run([ROSGATE, "plugins"], capture_output=True, text=True, timeout=60)
    assert any(line.split()[:3] == ["transport", "can", "rosgate-transport-can"]
               for line in listing.stdout.splitlines()), listing.stdout


def test_with_the_plugin_blocked_the_user_is_told_how_to_get_it_back(tmp_path):
    path = tmp_path / "bringup.yaml"
    path.write_text(side("a", bus(), [("/t", "geometry_msgs/msg/Twist", "receive", 1)]))
    result = subprocess.run([ROSGATE, "check", str(path)], capture_output=True, text=True,
                            timeout=60, env=dict(os.environ, ROSGATE_DISABLE_PLUGINS="can"))
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
    assert "topics[0].transport: unknown transport 'can'" in result.stderr
    assert "blocked by ROSGATE_DISABLE_PLUGINS" in result.stderr
    # blocked, so installed: the fix is to unblock it, not to install it again
    assert "fix: remove can from ROSGATE_DISABLE_PLUGINS, or pick an installed transport" \
        in result.stderr


def test_without_the_compact_packetizer_the_file_is_refused_naming_its_distribution():
    plugins = Plugins()
    plugins.add(builtin, "builtin")
    plugins.add(rosgate_transport_can, "can")
    plugins.add(rosgate_transport_udp, "udp")  # the file's default transport
    text = side("a", bus(), [("/t", "geometry_msgs/msg/Twist", "transmit", 1)])
    with pytest.raises(ConfigError) as error:
        Engine(loads(text, file="x.yaml"), plugins).prepare()
    e = error.value
    assert (e.file, e.line, e.key) == ("x.yaml", 6, "topics[0].transport"), str(e)
    assert e.message == ("can carries packets of 8 bytes, which its links cut with the packetizer "
                         "'compact': unknown packetizer 'compact' (installed packetizers: "
                         "fragments)")
    assert e.fix == "pip install the distribution that provides it (rosgate-compact)"


def test_with_the_compact_packetizer_blocked_rosgate_check_says_so_at_the_topic(tmp_path):
    path = tmp_path / "bringup.yaml"
    path.write_text(side("a", bus(fd="true"), [("/t", "geometry_msgs/msg/Twist", "receive", 1)]))
    result = subprocess.run([ROSGATE, "check", str(path)], capture_output=True, text=True,
                            timeout=60, env=dict(os.environ, ROSGATE_DISABLE_PLUGINS="compact"))
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
    assert ("topics[0].transport: can carries packets of 64 bytes, which its links cut with the "
            "packetizer 'compact': unknown packetizer 'compact'") in result.stderr
    assert "fix: remove compact from ROSGATE_DISABLE_PLUGINS\n" in result.stderr + "\n"


def test_check_counts_every_frame_in_compact_pieces(tmp_path, capsys):
    """rosgate check's budget on a CAN link: a Twist (52 B of CDR, the 28-byte envelope) takes 12
    classic CAN frames of a head byte each, one length byte in the first."""
    from rosgate.cli import main

    path = tmp_path / "bringup.yaml"
    text = side("a", bus(), [("/t", "geometry_msgs/msg/Twist", "transmit", 1)])
    path.write_text(text.replace("insecure: true}",
                                 "insecure: true, links: {can: {bandwidth: 500kbit}}}")
                    .replace("transport: can,", "transport: can, max_rate: 50,"))
    assert main(["check", str(path)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[out.index("budget of can: 500.0 kbit/s per peer") + 1] == \
        "  /t  50 Hz x 52 B = 93 B on the wire (12 packets) -> 37.2 kbit/s"
