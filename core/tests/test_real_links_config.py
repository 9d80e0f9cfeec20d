"""bringup.yaml's keys for real links: bridge.links (a budget per transport) and, per topic,
latest_only, recovery, compression (each a plugin, by name or with its options) and typical_size
— parsed values, and one located error per mistake (file, line, key, fix), whether the file's
reader finds it or the resolver (the plugin and its options)."""

from __future__ import annotations

import pytest

from rosgate.config import loads, parse_bandwidth, topic_from_mapping, topic_to_mapping
from rosgate.engine import Engine
from rosgate.errors import ConfigError

HEAD = "bridge:\n  name: robot1\n  role: peer\n  peer: 127.0.0.2\n"
TOPIC = "topics:\n  - topic: /camera\n    type: sensor_msgs/msg/Image\n    direction: transmit\n"


def error(text: str) -> ConfigError:
    with pytest.raises(ConfigError) as info:
        loads(text, file="bringup.yaml")
    return info.value


def test_a_budget_per_transport_and_the_keys_of_a_topic():
    cfg = loads(HEAD + """\
  links:
    udp: {bandwidth: 20mbit, max_delay: 0.5}
    tcp: {bandwidth: 2500000}
""" + TOPIC + """\
    port: 9
    priority: data_low
    latest_only: true
    max_delay: 0.05
    recovery: {fec: {overhead: 0.2}}
    compression:
      zstd: {level: -3}
    typical_size: 921600
  - {topic: /cmd_vel, type: geometry_msgs/msg/Twist, direction: transmit, port: 9}
""")
    udp, tcp = cfg.links["udp"], cfg.links["tcp"]
    assert (udp.bandwidth, udp.max_delay, udp.line) == (20e6, 0.5, 6)
    assert (tcp.bandwidth, tcp.max_delay) == (2.5e6, 1.0)
    camera, twist = cfg.topics
    assert (camera.priority, camera.latest_only, camera.max_delay, camera.recovery,
            camera.recovery_options, camera.compression, camera.compression_options,
            camera.typical_size) == (6, True, 0.05, "fec", {"overhead": 0.2}, "zstd",
                                     {"level": -3}, 921600)
    # defaults: recovery by the QoS (None), the rest as rosgate did before real links
    assert (twist.priority, twist.latest_only, twist.max_delay, twist.recovery,
            twist.compression, twist.typical_size) == (None, None, None, None, "none", None)


def test_a_client_s_entry_crosses_to_the_server_with_its_keys():
    cfg = loads(HEAD + TOPIC + "    recovery: retransmit\n    compression: {zstd: {level: 19}}\n"
                "    latest_only: false\n")
    mapping = topic_to_mapping(cfg.topics[0])
    assert mapping["recovery"] == "retransmit" and mapping["compression"] == {"zstd": {"level": 19}}
    assert "recovery_options" not in mapping  # written as the user would
    again = topic_from_mapping(mapping, {}, "client robot1", index=0)
    assert (again.recovery, again.compression, again.compression_options, again.latest_only) == (
        "retransmit", "zstd", {"level": 19}, False)


@pytest.mark.parametrize("text, bits", [
    ("20mbit", 20e6), ("20 Mbit/s", 20e6), ("500kbit", 5e5), ("1.5gbit", 1.5e9), ("20M", 20e6),
    ("64000", 64e3), (2e7, 2e7), ("300bit/s", 300)])
def test_bandwidths(text, bits):
    assert parse_bandwidth(text) == bits


@pytest.mark.parametrize("text", ["20mbps", "20MB", "2.5 MB/s", "fast", "0", "-1mbit", True])
def test_what_is_not_a_bandwidth(text):
    with pytest.raises(ValueError):
        parse_bandwidth(text)


ERRORS = {
    "bytes_per_second": (
        HEAD + "  links: {udp: {bandwidth: 2MB/s}}\n", 5, "bridge.links.udp.bandwidth",
        "expected a bandwidth in bits per second, got '2MB/s'", "2.5 megabytes per second"),
    "unknown_link_key": (
        HEAD + "  links:\n    udp: {bandwith: 1mbit}\n", 6, "bridge.links.udp.bandwith",
        "unknown key 'bandwith' (did you mean 'bandwidth'?)", "valid keys are bandwidth"),
    "link_not_a_mapping": (
        HEAD + "  links:\n    udp: 20mbit\n", 6, "bridge.links.udp", "expected a mapping",
        "udp: {bandwidth: 20mbit}"),
    "max_delay": (
        HEAD + "  links:\n    udp:\n      max_delay: 0\n", 7, "bridge.links.udp.max_delay",
        "expected a number of seconds > 0", "max_delay: 1.0"),
    "latest_only_not_a_flag": (
        HEAD + TOPIC + "    latest_only: yes please\n", 9, "topics[0].latest_only",
        "expected true or false", "latest_only: true"),
    "recovery_not_a_name": (
        HEAD + TOPIC + "    recovery: 5\n", 9, "topics[0].recovery",
        "expected a plugin's name, got 5", "recovery: fec"),
    "two_compressions": (
        HEAD + TOPIC + "    compression: {zstd: {}, lz4: {}}\n", 9, "topics[0].compression",
        "expected one compression plugin with its options, got 2 names",
        "compression: zstd (or with options: {zstd: {level: 19}})"),
    "options_not_a_mapping": (
        HEAD + TOPIC + "    recovery: {fec: 0.2}\n", 9, "topics[0].recovery",
        "expected a name and a mapping of its options, got 'fec': 0.2",
        "{fec: {overhead: 0.25}}"),
    "level_without_compression": (
        HEAD + TOPIC + "    compression_level: 9\n", 9, "topics[0].compression_level",
        "unknown key 'compression_level'", "valid keys are"),
    "compression_on_bare_framing": (
        HEAD + TOPIC + "    framing: none\n    compression: zstd\n", 10, "topics[0].compression",
        "compression needs the envelope (framing: rosgate)", "use framing: rosgate"),
    "recovery_on_bare_framing": (
        HEAD + TOPIC + "    framing: none\n    recovery: fec\n", 10, "topics[0].recovery",
        "recovery needs the envelope", "remove recovery:"),
    "topic_max_delay": (
        HEAD + TOPIC + "    max_delay: -1\n", 9, "topics[0].max_delay",
        "expected a number of seconds > 0", "max_delay: 0.05"),
    "typical_size": (
        HEAD + TOPIC + "    typical_size: 1.5\n", 9, "topics[0].typical_size",
        "expected a number of bytes >= 1", "typical_size: 921600"),
}


@pytest.mark.parametrize("text, line, key, message, fix", ERRORS.values(), ids=ERRORS.keys())
def test_error(text, line, key, message, fix):
    e = error(text)
    assert (e.file, e.line, e.key) == ("bringup.yaml", line, key), str(e)
    assert message in e.message, str(e)
    assert fix in e.fix, str(e)


# what only the installed plugins can tell: their names, and their options (checked as every
# plugin's are, located where the topic or the plugins: table wrote them)
PLUGIN_ERRORS = {
    "unknown_recovery": (
        HEAD + TOPIC + "    recovery: arq\n", 9, "topics[0].recovery",
        "unknown packetizer 'arq' (installed packetizers: compact, fec, fragments, retransmit",
        "pick an installed packetizer"),
    "a_link_s_own_packetizer": (
        HEAD + TOPIC + "    recovery: compact\n", 9, "topics[0].recovery",
        "compact is what links of small frames cut every frame with, by themselves",
        "remove recovery: from this entry"),
    "overhead_of_retransmit": (
        HEAD + TOPIC + "    recovery: {retransmit: {overhead: 0.1}}\n", 9,
        "topics[0].recovery.retransmit.overhead", "unknown key 'overhead'",
        "retransmit takes no options: remove it"),
    "overhead_out_of_range": (
        HEAD + TOPIC + "    recovery:\n      fec: {overhead: 1.5}\n", 10,
        "topics[0].recovery.fec.overhead", "expected a number at most 1, got 1.5", "overhead:"),
    "overhead_zero": (
        HEAD + TOPIC + "    recovery: {fec: {overhead: 0}}\n", 9,
        "topics[0].recovery.fec.overhead", "must be more than 0, not 0", "overhead: 0.1"),
    "unknown_compression": (
        HEAD + TOPIC + "    compression: zstandard\n", 9, "topics[0].compression",
        "unknown transform 'zstandard' (installed transforms: ",
        "pick an installed transform"),
    "level_zero": (
        HEAD + TOPIC + "    compression:\n      zstd:\n        level: 0\n", 11,
        "topics[0].compression.zstd.level", "must not be 0", "level: 3"),
    "level_in_the_plugins_table": (
        HEAD + "plugins:\n  zstd: {level: 23}\n" + TOPIC + "    compression: zstd\n", 6,
        "plugins.zstd.level", "expected an integer -7..22, got 23", "level: zstd's level"),
}


@pytest.mark.parametrize("text, line, key, message, fix", PLUGIN_ERRORS.values(),
                         ids=PLUGIN_ERRORS.keys())
def test_plugin_error(text, line, key, message, fix):
    with pytest.raises(ConfigError) as info:
        Engine(loads(text, file="bringup.yaml")).prepare()
    e = info.value
    assert (e.file, e.line, e.key) == ("bringup.yaml", line, key), str(e)
    assert message in e.message, str(e)
    assert fix in e.fix, str(e)


def test_check_shows_the_budget_arithmetic(tmp_path, capsys):
    """rosgate check, with a bandwidth and max_rates in the file: each topic's rate x its size
    on the wire (envelope, fragment headers, repair fragments, IP and UDP headers) against the
    bandwidth, and what it cannot count."""
    from rosgate.cli import main

    path = tmp_path / "robot.yaml"
    path.write_text(HEAD + """\
  insecure: true
  links: {udp: {bandwidth: 20mbit}}
plugins: {udp: {max_frame: 1472}}
topics:
  - {topic: /camera, type: sensor_msgs/msg/Image, direction: transmit, port: 9, max_rate: 2.5,
     typical_size: 921655, recovery: {fec: {overhead: 0.05}}}
  - {topic: /cmd_vel, type: geometry_msgs/msg/Twist, direction: transmit, port: 9, max_rate: 50}
  - {topic: /odom, type: nav_msgs/msg/Odometry, direction: transmit, port: 9, max_rate: 20}
  - {topic: /map, type: nav_msgs/msg/OccupancyGrid, direction: receive, port: 9}
""")
    assert main(["check", str(path)]) == 0
    out = capsys.readouterr().out.splitlines()
    budget = out[out.index("budget of udp: 20.0 Mbit/s per peer"):]
    assert budget == [
        "budget of udp: 20.0 Mbit/s per peer",
        # 921,683 B frames in 636 chunks of 1,450 B + 33 repair fragments, 21 + 28 B each
        "  /camera   2.5 Hz x 921,655 B = 1,002,831 B on the wire (669 packets) -> 20.1 Mbit/s; "
        "cannot fit: more than the whole budget by itself",
        # 52 B of CDR, the 28-byte envelope, retransmit's 14-byte fragment header (a reliable
        # topic is repaired by default), 28 bytes of IP and UDP
        "  /cmd_vel  50 Hz x 52 B = 122 B on the wire (1 packet) -> 48.8 kbit/s",
        "  /odom     not counted (nav_msgs/msg/Odometry varies in size: give typical_size)",
        "  total 20.1 Mbit/s of 20.0 Mbit/s (100.5 %): over budget: latest_only topics send less "
        "often, others wait in the queue (reliable) or are dropped late (best effort)"]


def test_a_monitors_wrong_option_is_located_at_its_key():
    """A monitor's table is read like any plugin's: the error names the file, line and key."""
    text = """bridge: {name: a, role: peer, peer: 127.0.0.1, insecure: true}
plugins:
  diagnostics:
    periodd: 1
"""
    with pytest.raises(ConfigError) as caught:
        Engine(loads(text, file="bringup.yaml")).prepare()
    assert str(caught.value) == ("bringup.yaml:4: plugins.diagnostics.periodd: unknown key "
                                 "'periodd'\n  fix: diagnostics takes no options: remove it")
