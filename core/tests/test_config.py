"""bringup.yaml: parsed values, defaults and normalisation, and one located ConfigError per
mistake."""

from __future__ import annotations

import dataclasses
import json
import textwrap
from pathlib import Path

import pytest

from rosgate.config import (
    BridgeConfig,
    ServiceConfig,
    TopicConfig,
    load,
    loads,
    service_from_mapping,
    service_to_mapping,
    topic_from_mapping,
    topic_to_mapping,
)
from rosgate.errors import ConfigError

DATA = Path(__file__).resolve().parents[2] / "tests" / "data"
LEGACY = sorted((DATA / "legacy").glob("*.yaml"))
DEFAULTS = {"transport": "udp", "codec": "cdr", "cipher": "none"}


def write(tmp_path: Path, text: str, name: str = "bringup.yaml") -> Path:
    path = tmp_path / name
    path.write_text(textwrap.dedent(text).lstrip("\n"))
    return path


def load_error(tmp_path: Path, text: str) -> tuple[ConfigError, Path]:
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        load(path)
    return info.value, path


# --- valid files ---------------------------------------------------------------------------------

CLIENT = """
bridge:
  name: robot1
  role: client
  server: 127.0.0.1:12000
  defaults: {transport: tcp, codec: msgpack}
  stale_after: 30
  stale_warnings: 0
  heartbeat: 0.5
plugins:
  fernet: {key_file: secret.key}
  nacl:
topics:
  - topic: chatter
    type: std_msgs/String
    direction: transmit
  - topic: /robot1/cmd_vel
    type: geometry_msgs/msg/Twist
    direction: receive
    remote: cmd_vel
    transport: udp
    codec: cdr
    cipher: fernet
    port: 12001
    qos: qos_profile_sensor_data
    max_rate: 20
  - topic: /scan
    type: sensor_msgs/msg/LaserScan
    direction: transmit
    qos: "10"
  - topic: /map
    type: nav_msgs/msg/OccupancyGrid
    direction: transmit
    qos: {reliability: reliable, durability: transient_local, depth: 1}
  - topic: /chatter
    type: std_msgs/msg/String
    direction: receive
    remote: /robot2/chatter
services:
  - service: /mcu/ping
    type: std_srvs/Trigger
    direction: transmit
    port: 20001
    timeout: 2
"""


def test_client_file(tmp_path: Path) -> None:
    path = write(tmp_path, CLIENT)
    config = load(path)

    assert (config.file, config.base_dir) == (str(path), tmp_path)
    assert (config.name, config.role, config.server, config.main_line) == (
        "robot1", "client", "127.0.0.1:12000", "tcp")
    assert (config.peer, config.listen) == (None, None)
    assert config.defaults == {"transport": "tcp", "codec": "msgpack", "cipher": "none"}
    assert (config.stale_after, config.stale_warnings, config.heartbeat) == (30.0, 0, 0.5)
    assert isinstance(config.stale_after, float)
    assert config.plugins == {"fernet": {"key_file": "secret.key"}, "nacl": {}}

    chatter, cmd_vel, scan, map_, chatter_in = config.topics
    assert chatter == TopicConfig(topic="/chatter", type="std_msgs/msg/String",
                                  direction="transmit", remote="/chatter", transport="tcp",
                                  codec="msgpack", cipher="none", port=None, framing="rosgate",
                                  qos=10, max_rate=None, line=13,
                                  lines={"topic": 13, "type": 14, "direction": 15})
    assert (cmd_vel.remote, cmd_vel.transport, cmd_vel.codec, cmd_vel.cipher) == (
        "/cmd_vel", "udp", "cdr", "fernet")
    assert (cmd_vel.port, cmd_vel.qos, cmd_vel.max_rate) == (12001, "sensor_data", 20.0)
    assert cmd_vel.line == 16 and cmd_vel.lines["max_rate"] == 25
    assert scan.qos == 10
    assert map_.qos == {"reliability": "reliable", "durability": "transient_local", "depth": 1}
    assert (chatter_in.topic, chatter_in.direction, chatter_in.remote) == (
        "/chatter", "receive", "/robot2/chatter")

    assert config.services == [ServiceConfig(
        service="/mcu/ping", type="std_srvs/srv/Trigger", direction="transmit", remote="/mcu/ping",
        transport="tcp", codec="msgpack", cipher="none", port=20001, framing="rosgate", timeout=2.0,
        line=39, lines={"service": 39, "type": 40, "direction": 41, "port": 42, "timeout": 43})]

    assert config.lines["bridge"] == 1
    assert config.lines["bridge.server"] == 4
    assert config.lines["bridge.defaults.codec"] == 5
    assert config.lines["plugins.fernet.key_file"] == 10
    assert config.lines["topics[1]"] == 16
    assert config.lines["topics[1].codec"] == 21
    assert config.lines["topics[3].qos.depth"] == 33
    assert config.lines["services[0].port"] == 42


def test_error_is_located_at_the_key_or_its_nearest_parent(tmp_path: Path) -> None:
    config = load(write(tmp_path, CLIENT))

    error = config.error("plugins.fernet.key_file", "cannot read secret.key", fix="create it")
    assert (error.file, error.line, error.key, error.fix) == (
        config.file, 10, "plugins.fernet.key_file", "create it")
    assert config.error("topics[0].port", "port in use").line == 13  # not written: the entry's line
    assert config.error("plugins.nacl.key_env", "unset").line == 11
    assert config.error("services", "x").line == 38
    assert config.error("nowhere.at.all", "x").line is None


def test_link_keys_default_and_explicit() -> None:
    config = loads(CLIENT_HEAD)
    assert (config.peer_timeout, config.session_timeout) == (3.0, 60.0)
    assert (config.reconnect_min, config.reconnect_max) == (0.1, 10.0)
    assert (config.queue_frames, config.queue_bytes) == (1000, 8 * 1024 * 1024)
    config = loads(CLIENT_HEAD + "  heartbeat: 0.5\n  session_timeout: 5\n"
                   "  reconnect: {min: 0.5}\n  queue: {frames: 0, bytes: 100}\n")
    assert (config.peer_timeout, config.session_timeout) == (1.5, 5.0)  # three heartbeats
    assert (config.reconnect_min, config.reconnect_max) == (0.5, 10.0)
    assert (config.queue_frames, config.queue_bytes) == (0, 100)
    config = loads(CLIENT_HEAD + "  reconnect: {min: 20}\n")
    assert (config.reconnect_min, config.reconnect_max) == (20.0, 20.0)  # max follows a big min


def test_limits_default_and_explicit() -> None:
    from rosgate.config import Limits

    config = loads(CLIENT_HEAD)
    assert config.limits == Limits(connections=256, connections_per_source=16,
                                   handshake_timeout=5.0, max_frame_before_auth=65536,
                                   idle_timeout=2.0, sessions=256)
    config = loads(CLIENT_HEAD + "  limits: {connections: 10, connections_per_source: 2, "
                   "handshake_timeout: 1, idle_timeout: 0.5, max_frame_before_auth: 4096, "
                   "sessions: 3}\n")
    assert config.limits == Limits(10, 2, 1.0, 4096, 0.5, 3)


def test_server_file(tmp_path: Path) -> None:
    config = load(write(tmp_path, """
        bridge:
          name: hub
          role: server
          server: 0.0.0.0:12000
        plugins:
          fernet: {key_env: ROSGATE_KEY}
        """))

    assert (config.name, config.role, config.server, config.main_line) == (
        "hub", "server", "0.0.0.0:12000", "tcp")
    assert (config.peer, config.listen) == (None, None)
    assert config.defaults == DEFAULTS
    assert (config.stale_after, config.stale_warnings, config.heartbeat) == (15.0, 5, 1.0)
    assert config.plugins == {"fernet": {"key_env": "ROSGATE_KEY"}}
    assert (config.topics, config.services) == ([], [])


def test_peer_file(tmp_path: Path) -> None:
    # the CVRA microcontroller profile
    config = load(write(tmp_path, """
        bridge:
          name: cvra
          role: peer
          peer: 192.168.0.20
          defaults: {codec: msgpack}
        topics:
          - topic: /position
            type: geometry_msgs/msg/Point
            direction: receive
            remote: position
            port: 20000
            framing: none
        services:
          - service: /mcu/ping
            type: std_srvs/srv/Trigger
            direction: transmit
            remote: ping
            transport: tcp
            port: 20001
            framing: serial_datagram
        """))

    assert (config.role, config.peer, config.listen, config.server) == (
        "peer", "192.168.0.20", "0.0.0.0", None)
    assert config.defaults == {"transport": "udp", "codec": "msgpack", "cipher": "none"}
    (position,) = config.topics
    # bare framing: the name as written
    assert (position.remote, position.transport, position.codec, position.port,
            position.framing) == ("position", "udp", "msgpack", 20000, "none")
    (ping,) = config.services
    assert (ping.remote, ping.transport, ping.port, ping.framing, ping.timeout,
            ping.max_request) == ("ping", "tcp", 20001, "serial_datagram", 5.0, 65536)


def test_bare_framing_keeps_remote_as_written_and_defaults_to_the_name_without_slash() -> None:
    config = loads("""
bridge: {name: cvra, role: peer, peer: 127.0.0.1}
topics:
  - {topic: /cmd_vel, type: geometry_msgs/msg/Twist, direction: transmit, port: 20000,
     framing: none}
  - {topic: /pose, type: geometry_msgs/msg/Pose2D, direction: receive, port: 20000, framing: none,
     remote: Robot/Pose-2D}
  - {topic: /chatter, type: std_msgs/msg/String, direction: receive, port: 20002, remote: chatter}
services:
  - {service: /mcu/ping, type: std_srvs/srv/Trigger, direction: transmit, port: 20001,
     transport: tcp, framing: serial_datagram, max_request: 100}
""")
    assert [t.remote for t in config.topics] == ["cmd_vel", "Robot/Pose-2D", "/chatter"]
    assert (config.services[0].remote, config.services[0].max_request) == ("mcu/ping", 100)


def test_peer_listen_and_scalars_yaml_would_not_read_as_strings(tmp_path: Path) -> None:
    # 10:11:22:33:44:55 is a base-60 integer to YAML 1.1 and `yes` a boolean: keep the text as
    # written
    config = load(write(tmp_path, """
        bridge:
          name: yes
          role: peer
          peer: 10:11:22:33:44:55
          listen: 127.0.0.1
        """))
    assert (config.name, config.peer, config.listen) == ("yes", "10:11:22:33:44:55", "127.0.0.1")


def test_merge_keys_share_settings_between_entries(tmp_path: Path) -> None:
    config = load(write(tmp_path, """
        bridge: {name: robot1, role: peer, peer: 10.0.0.2}
        topics:
          - &scan
            topic: /scan
            type: sensor_msgs/msg/LaserScan
            direction: transmit
            codec: msgpack
            port: 12001
          - <<: *scan
            topic: /scan2
            port: 12002
        """))
    second = config.topics[1]
    assert (second.topic, second.type, second.codec, second.port) == (
        "/scan2", "sensor_msgs/msg/LaserScan", "msgpack", 12002)
    assert (second.line, second.lines["topic"], second.lines["port"]) == (9, 10, 11)


def test_loads_uses_the_given_name_and_folder(tmp_path: Path) -> None:
    config = loads("bridge: {name: a, role: server, server: ':12000'}\n", file="inline.yaml",
                   base_dir=tmp_path)
    assert (config.file, config.base_dir, config.server) == ("inline.yaml", tmp_path, ":12000")


# --- one located error per mistake ---------------------------------------------------------------

CLIENT_HEAD = """\
bridge:
  name: robot1
  role: client
  server: 127.0.0.1:12000
"""
PEER_HEAD = """\
bridge:
  name: robot1
  role: peer
  peer: 127.0.0.2
"""
SERVER_HEAD = """\
bridge:
  name: hub
  role: server
  server: 0.0.0.0:12000
"""
# a valid first topic entry (lines 5-8 after a head); cases append keys or entries to it
TOPIC = """\
topics:
  - topic: /chatter
    type: std_msgs/msg/String
    direction: transmit
"""
# the rest of an entry after its name
ENTRY = "    type: std_msgs/msg/String\n    direction: transmit\n"
SERVICE = """\
services:
  - service: /ping
    type: std_srvs/srv/Trigger
    direction: receive
"""

# id: (file text, line, key, part of the message)
ERRORS = {
    # YAML itself
    "yaml_syntax": (
        "bridge:\n  name: a: b\n",
        2, None, "YAML syntax error at column 10: mapping values are not allowed here"),
    "yaml_tab": (
        "bridge:\n\tname: robot1\n",
        2, None, "YAML syntax error"),
    "control_character": (
        "bridge:\n  name: a\x07\n",
        2, None, "unacceptable character #x0007"),
    "yaml_duplicate_key": (
        "bridge:\n  name: a\n  name: b\n",
        3, "bridge.name", "duplicate key 'name' (first on line 2)"),
    "recursive_alias": (
        "bridge: &b\n  name: robot1\n  role: *b\n",
        3, "bridge.role", "alias refers to the mapping"),
    "alias_bomb": (  # nine lists of nine, seven deep: 4.8 million values from 400 bytes
        "bridge:\n  a0: &a0 [x, x, x, x, x, x, x, x, x]\n" + "".join(
            f"  a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * 9)}]\n" for i in range(1, 8)),
        2, "bridge.a5[1][7][8][6][5][7]", "more than 200000 values once its aliases are expanded"),
    "key_not_a_name": (
        "? [a, b]\n: 1\n",
        1, None, "a key must be a plain name"),
    # the file's shape
    "empty": (
        "",
        None, None, "the file is empty"),
    "only_comments": (
        "# nothing yet\n",
        None, None, "the file is empty"),
    "top_is_a_list": (
        "- bridge\n",
        1, None, "expected a mapping with bridge: at the top"),
    # unknown keys, with the closest valid one
    "unknown_top_key": (
        CLIENT_HEAD + "topic:\n  - topic: /a\n",
        5, "topic", "unknown key 'topic' (did you mean 'topics'?)"),
    "unknown_bridge_key": (
        "bridge:\n  name: robot1\n  rol: client\n",
        3, "bridge.rol", "unknown key 'rol' (did you mean 'role'?)"),
    "unknown_defaults_key": (
        CLIENT_HEAD + "  defaults: {transport: udp, codek: cdr}\n",
        5, "bridge.defaults.codek", "unknown key 'codek' (did you mean 'codec'?)"),
    "unknown_service_key": (
        CLIENT_HEAD + SERVICE + "    qos: 10\n",
        9, "services[0].qos", "unknown key 'qos'"),
    "unknown_qos_key": (
        CLIENT_HEAD + TOPIC + "    qos: {reliability: reliable, deph: 5}\n",
        9, "topics[0].qos.deph", "unknown key 'deph' (did you mean 'depth'?)"),
    # missing keys: located at the parent
    "missing_bridge": (
        "plugins: {}\n",
        1, "bridge", "missing required key 'bridge'"),
    "missing_name": (
        "bridge:\n  role: client\n  server: x:1\n",
        1, "bridge.name", "missing required key 'name'"),
    "missing_role": (
        "bridge:\n  name: robot1\n  server: x:1\n",
        1, "bridge.role", "missing required key 'role'"),
    "missing_topic_type": (
        CLIENT_HEAD + "topics:\n  - topic: /a\n    direction: transmit\n",
        6, "topics[0].type", "missing required key 'type'"),
    "missing_service_direction": (
        CLIENT_HEAD + "services:\n  - service: /a\n    type: std_srvs/srv/Empty\n",
        6, "services[0].direction", "missing required key 'direction'"),
    # wrong types and ranges
    "bridge_not_a_mapping": (
        "bridge: robot1\n",
        1, "bridge", "expected a mapping, got 'robot1'"),
    "name_empty": (
        "bridge:\n  name:\n  role: client\n",
        2, "bridge.name", "expected a non-empty string, got nothing"),
    "name_invalid": (
        "bridge:\n  name: robot 1\n  role: client\n",
        2, "bridge.name", "'robot 1' is not a valid bridge name"),
    "stale_after_negative": (
        CLIENT_HEAD + "  stale_after: -1\n",
        5, "bridge.stale_after", "expected a number > 0, got -1"),
    "stale_warnings_fraction": (
        CLIENT_HEAD + "  stale_warnings: 1.5\n",
        5, "bridge.stale_warnings", "expected an integer >= 0, got 1.5"),
    "heartbeat_zero": (
        CLIENT_HEAD + "  heartbeat: 0\n",
        5, "bridge.heartbeat", "expected a number > 0, got 0"),
    "peer_timeout_not_over_heartbeat": (
        CLIENT_HEAD + "  heartbeat: 2\n  peer_timeout: 2\n",
        6, "bridge.peer_timeout", "2 s is not longer than the heartbeat (2 s)"),
    "session_timeout_zero": (
        CLIENT_HEAD + "  session_timeout: 0\n",
        5, "bridge.session_timeout", "expected a number of seconds > 0, got 0"),
    "reconnect_not_a_mapping": (
        CLIENT_HEAD + "  reconnect: 5\n",
        5, "bridge.reconnect", "expected a mapping, got 5"),
    "reconnect_max_below_min": (
        CLIENT_HEAD + "  reconnect:\n    min: 2\n    max: 1\n",
        7, "bridge.reconnect.max", "max (1 s) is below min (2 s)"),
    "reconnect_unknown_key": (
        CLIENT_HEAD + "  reconnect: {min: 1, cap: 5}\n",
        5, "bridge.reconnect.cap", "unknown key 'cap'"),
    "queue_frames_negative": (
        CLIENT_HEAD + "  queue:\n    frames: -1\n",
        6, "bridge.queue.frames", "expected an integer >= 0, got -1"),
    "queue_bytes_text": (
        CLIENT_HEAD + "  queue: {bytes: 8 MiB}\n",
        5, "bridge.queue.bytes", "expected an integer >= 0, got '8 MiB'"),
    "defaults_not_a_mapping": (
        CLIENT_HEAD + "  defaults: udp\n",
        5, "bridge.defaults", "expected a mapping"),
    "plugins_a_list": (
        CLIENT_HEAD + "plugins: [fernet]\n",
        5, "plugins", "expected a mapping, got a list"),
    "plugin_options_not_a_mapping": (
        CLIENT_HEAD + "plugins:\n  fernet: secret.key\n",
        6, "plugins.fernet", "expected a mapping, got 'secret.key'"),
    "topics_not_a_list": (
        CLIENT_HEAD + "topics: /chatter\n",
        5, "topics", "expected a list of entries"),
    "topic_entry_not_a_mapping": (
        CLIENT_HEAD + "topics:\n  - /chatter\n",
        6, "topics[0]", "expected a mapping (topic:"),
    "port_text": (
        CLIENT_HEAD + TOPIC + "    port: abc\n",
        9, "topics[0].port", "expected an integer 1..65535, got 'abc'"),
    "port_too_big": (
        CLIENT_HEAD + TOPIC + "    port: 70000\n",
        9, "topics[0].port", "got 70000"),
    "port_boolean": (
        CLIENT_HEAD + TOPIC + "    port: true\n",
        9, "topics[0].port", "got true (a boolean)"),
    "codec_a_list": (
        CLIENT_HEAD + TOPIC + "    codec: [cdr]\n",
        9, "topics[0].codec", "expected a non-empty string, got a list"),
    "max_rate_zero": (
        CLIENT_HEAD + TOPIC + "    max_rate: 0\n",
        9, "topics[0].max_rate", "expected a number of Hz 1e-06..1e+06, got 0"),
    "timeout_zero": (
        CLIENT_HEAD + SERVICE + "    timeout: 0\n",
        9, "services[0].timeout", "expected a number of seconds > 0"),
    # enums
    "role_typo": (
        "bridge:\n  name: robot1\n  role: clinet\n",
        3, "bridge.role", "'clinet' is not one of client, server, peer (did you mean 'client'?)"),
    "direction": (
        CLIENT_HEAD + "topics:\n  - topic: /a\n    type: std_msgs/msg/Empty\n    direction: send\n",
        8, "topics[0].direction", "'send' is not one of transmit, receive"),
    "framing": (
        CLIENT_HEAD + TOPIC + "    framing: slip\n",
        9, "topics[0].framing", "'slip' is not one of rosgate, none, serial_datagram"),
    "qos_list": (
        CLIENT_HEAD + TOPIC + "    qos: [1, 2]\n",
        9, "topics[0].qos", "expected a depth (integer >= 1), a profile name or a mapping"),
    "qos_zero": (
        CLIENT_HEAD + TOPIC + "    qos: '0'\n",
        9, "topics[0].qos", "expected a number of messages 1..100000, got 0"),
    "qos_profile": (
        CLIENT_HEAD + TOPIC + "    qos: sensor\n",
        9, "topics[0].qos", "unknown QoS profile 'sensor' (did you mean 'sensor_data'?)"),
    "qos_reliability": (
        CLIENT_HEAD + TOPIC + "    qos:\n      reliability: lossy\n",
        10, "topics[0].qos.reliability", "'lossy' is not one of reliable, best_effort"),
    "rule_durability": (
        SERVER_HEAD + "clients:\n  robot1:\n    key: AAECAwQFBgcICQoLDA0ODxAREhMUFRYXGBkaGxwdHh8=\n"
        "    topics:\n      - {name: /robot1/**, direction: both, durability: [transient_locl]}\n",
        9, "clients.robot1.topics[0].durability",
        "'transient_locl' is not one of volatile, transient_local "
        "(did you mean 'transient_local'?)"),
    "qos_depth": (
        CLIENT_HEAD + TOPIC + "    qos: {history: keep_last, depth: 0}\n",
        9, "topics[0].qos.depth", "expected a number of messages 1..100000, got 0"),
    # roles (peer: and port: in role peer are needed by point-to-point entries only, which only
    # the resolver knows: tests/test_bus_config.py)
    "client_without_server": (
        "bridge:\n  name: robot1\n  role: client\n",
        1, "bridge.server", "missing required key 'server'"),
    "server_without_server": (
        "bridge:\n  name: hub\n  role: server\n",
        1, "bridge.server", "missing required key 'server'"),
    "server_with_topics": (
        SERVER_HEAD + TOPIC,
        5, "topics", "a server gets its topics from its clients"),
    "server_with_services": (
        SERVER_HEAD + SERVICE,
        5, "services", "a server gets its services from its clients"),
    "client_with_listen": (
        CLIENT_HEAD + "  listen: 0.0.0.0\n",
        5, "bridge.listen", "listen: is for role peer only"),
    "peer_with_server": (
        PEER_HEAD + "  server: 127.0.0.1:12000\n",
        5, "bridge.server", "role peer has no main line"),
    "peer_with_main_line": (
        PEER_HEAD + "  main_line: tcp\n",
        5, "bridge.main_line", "role peer has no main line"),
    # names and types
    "topic_double_slash": (
        CLIENT_HEAD + "topics:\n  - topic: /a//b\n" + ENTRY,
        6, "topics[0].topic", "'/a//b' is not a valid ROS name"),
    "topic_digit": (
        CLIENT_HEAD + "topics:\n  - topic: /robot1/2d\n" + ENTRY,
        6, "topics[0].topic", "not a valid ROS name"),
    "topic_private": (
        CLIENT_HEAD + "topics:\n  - topic: ~/odom\n" + ENTRY,
        6, "topics[0].topic", "private names (~) are not supported"),
    "remote_trailing_slash": (
        CLIENT_HEAD + TOPIC + "    remote: /a/\n",
        9, "topics[0].remote", "'/a/' is not a valid ROS name"),
    "service_name": (
        CLIENT_HEAD + "services:\n  - service: mcu ping\n    type: std_srvs/srv/Empty\n"
                      "    direction: receive\n",
        6, "services[0].service", "not a valid ROS name"),
    "type_without_package": (
        CLIENT_HEAD + "topics:\n  - topic: /a\n    type: String\n    direction: transmit\n",
        7, "topics[0].type", "'String' is not an interface type name"),
    "topic_with_service_type": (
        CLIENT_HEAD + "topics:\n  - topic: /a\n    type: std_srvs/srv/Trigger\n"
                      "    direction: transmit\n",
        7, "topics[0].type",
        "'std_srvs/srv/Trigger' is a 'srv' type, but a topic needs package/msg/Type"),
    "service_with_message_type": (
        CLIENT_HEAD + "services:\n  - service: /a\n    type: std_msgs/msg/Empty\n"
                      "    direction: transmit\n",
        7, "services[0].type", "a service needs package/srv/Type"),
    # duplicates: at the second entry, naming the first
    "duplicate_topic": (
        CLIENT_HEAD + TOPIC + "  - topic: chatter\n    type: std_msgs/msg/String\n"
                              "    direction: transmit\n",
        9, "topics[1].topic", "/chatter (transmit) is already listed as topics[0] on line 6"),
    "duplicate_receive_remote": (
        CLIENT_HEAD + "topics:\n"
                      "  - {topic: /a, type: std_msgs/msg/Empty, direction: receive, remote: /x}\n"
                      "  - topic: /b\n    type: std_msgs/msg/Empty\n    direction: receive\n"
                      "    remote: x\n",
        10, "topics[1].remote", "remote /x is already received by topics[0] on line 6"),
    "duplicate_service": (
        CLIENT_HEAD + SERVICE + "  - service: /ping\n    type: std_srvs/srv/Trigger\n"
                                "    direction: receive\n",
        9, "services[1].service", "/ping (receive) is already listed as services[0] on line 6"),
    "duplicate_service_remote": (
        CLIENT_HEAD + SERVICE + "  - service: /other\n    type: std_srvs/srv/Trigger\n"
                                "    direction: receive\n    remote: /ping\n",
        12, "services[1].remote", "remote /ping is already received by services[0] on line 6"),
    # framing
    "framing_none_with_cipher": (
        CLIENT_HEAD + TOPIC + "    cipher: fernet\n    framing: none\n",
        10, "topics[0].framing", "no envelope to authenticate; cipher must be none, not 'fernet'"),
    "framing_none_with_default_cipher": (
        CLIENT_HEAD + "  defaults: {cipher: fernet}\n" + TOPIC + "    framing: none\n",
        10, "topics[0].framing", "cipher must be none, not 'fernet'"),
    "framing_none_on_service": (
        CLIENT_HEAD + "services:\n  - service: /s\n    type: std_srvs/srv/Trigger\n"
                      "    direction: receive\n    framing: none\n",
        9, "services[0].framing", "framing none is for topics"),
    "max_request_too_small": (
        CLIENT_HEAD + "services:\n  - service: /s\n    type: std_srvs/srv/Trigger\n"
                      "    direction: receive\n    max_request: 8\n",
        9, "services[0].max_request", "expected a number of bytes 16..67108864, got 8"),
    "limits_unknown_key": (
        CLIENT_HEAD + "  limits: {connexions: 5}\n",
        5, "bridge.limits.connexions", "unknown key 'connexions' (did you mean 'connections'?)"),
    "limits_per_source_over_total": (
        CLIENT_HEAD + "  limits:\n    connections: 4\n    connections_per_source: 8\n",
        7, "bridge.limits.connections_per_source", "8 per source is more than the 4 connections"),
    "limits_small_frame": (
        CLIENT_HEAD + "  limits: {max_frame_before_auth: 10}\n",
        5, "bridge.limits.max_frame_before_auth", "expected a number of bytes >= 1024, got 10"),
    "limits_handshake_infinite": (
        CLIENT_HEAD + "  limits: {handshake_timeout: .inf}\n",
        5, "bridge.limits.handshake_timeout", "expected a number of seconds > 0, got inf"),
    "qos_depth_huge": (
        CLIENT_HEAD + TOPIC + f"    qos: {2**64}\n",
        9, "topics[0].qos", "expected a number of messages 1..100000, got 18446744073709551616"),
    "qos_mapping_depth_huge": (
        CLIENT_HEAD + TOPIC + "    qos: {depth: 1000000}\n",
        9, "topics[0].qos.depth", "expected a number of messages 1..100000, got 1000000"),
    "max_rate_tiny": (
        CLIENT_HEAD + TOPIC + "    max_rate: 1.0e-320\n",
        9, "topics[0].max_rate", "expected a number of Hz 1e-06..1e+06, got 1e-320"),
    "timeout_not_finite": (
        CLIENT_HEAD + "services:\n  - service: /s\n    type: std_srvs/srv/Trigger\n"
                      "    direction: receive\n    timeout: .inf\n",
        9, "services[0].timeout", "at most 3600, got inf"),
    "topic_name_too_long": (
        CLIENT_HEAD + "topics:\n  - topic: /" + "a" * 300 + "\n    type: std_msgs/msg/String\n"
                      "    direction: transmit\n",
        6, "topics[0].topic", "a name of 301 characters is longer than ROS takes (200)"),
    "serial_datagram_on_topic": (
        CLIENT_HEAD + TOPIC + "    framing: serial_datagram\n",
        9, "topics[0].framing", "framing serial_datagram is for services"),
}


@pytest.mark.parametrize("text, line, key, message", ERRORS.values(), ids=ERRORS.keys())
def test_error(tmp_path: Path, text: str, line: int | None, key: str | None, message: str) -> None:
    error, path = load_error(tmp_path, text)
    assert (error.file, error.line, error.key) == (str(path), line, key)
    assert message in error.message
    assert error.fix  # every error says how to fix it


def test_error_reads_file_line_key_and_fix(tmp_path: Path) -> None:
    error, path = load_error(tmp_path, CLIENT_HEAD + TOPIC + """\
  - topic: /odom
    type: nav_msgs/msg/Odometry
    direction: transmit
    codek: msgpack
""")
    assert str(error) == (
        f"{path}:12: topics[1].codek: unknown key 'codek' (did you mean 'codec'?)\n"
        "  fix: valid keys are topic, type, direction, remote, transport, codec, cipher, port, "
        "framing, qos, max_rate, priority, latest_only, max_delay, batch, recovery, "
        "compression, typical_size, layout, args, floats, deny, max_routes")


def test_missing_key_fix_says_what_to_add(tmp_path: Path) -> None:
    error, _ = load_error(tmp_path, "bridge:\n  name: robot1\n  role: server\n")
    assert "where to listen" in error.fix
    error, _ = load_error(tmp_path, "bridge:\n  role: client\n")
    assert error.fix == "add name: robot1 under bridge:"


@pytest.mark.parametrize("path", LEGACY, ids=[p.name for p in LEGACY])
def test_legacy_file_is_named_as_such(path: Path) -> None:
    with pytest.raises(ConfigError) as info:
        load(path)
    error = info.value
    assert (error.file, error.line, error.key) == (str(path), 1, "client_node")
    assert "old ros2_socket_bridge format" in error.message
    assert "bridge:" in error.message and "topics:" in error.message
    assert "rosgate convert" in error.fix


def test_legacy_files_exist() -> None:
    # guards the parametrized test above against silently running zero cases
    assert len(LEGACY) >= 3


def test_unreadable_file(tmp_path: Path) -> None:
    for path in (tmp_path / "missing.yaml", tmp_path):
        with pytest.raises(ConfigError) as info:
            load(path)
        assert (info.value.file, info.value.line) == (str(path), None)
        assert "cannot read the file" in info.value.message


def test_not_utf8(tmp_path: Path) -> None:
    path = tmp_path / "bringup.yaml"
    path.write_bytes(b"bridge:\n  name: r\xe9bot\n")
    with pytest.raises(ConfigError) as info:
        load(path)
    assert (info.value.file, info.value.message) == (
        str(path), "not UTF-8 text (byte 17: invalid continuation byte)")


# --- entries over the network --------------------------------------------------------------------

def test_entries_round_trip_through_plain_mappings(tmp_path: Path) -> None:
    config = load(write(tmp_path, CLIENT))
    for topic in config.topics:
        mapping = topic_to_mapping(topic)
        assert json.loads(json.dumps(mapping)) == mapping
        expected = dataclasses.replace(topic, line=0, lines={})
        assert topic_from_mapping(mapping, DEFAULTS, "client robot1") == expected
    for service in config.services:
        mapping = service_to_mapping(service)
        expected = dataclasses.replace(service, line=0, lines={})
        assert service_from_mapping(mapping, DEFAULTS, "client robot1") == expected


def test_topic_to_mapping_leaves_unset_keys_out() -> None:
    topic = TopicConfig(topic="/a", type="std_msgs/msg/Empty", direction="transmit", remote="/b")
    assert topic_to_mapping(topic) == {
        "topic": "/a", "type": "std_msgs/msg/Empty", "direction": "transmit", "remote": "/b",
        "transport": "udp", "codec": "cdr", "cipher": "none", "framing": "rosgate", "qos": 10}


def test_entry_from_mapping_fills_defaults_and_normalises() -> None:
    topic = topic_from_mapping({"topic": "odom", "type": "nav_msgs/Odometry",
                                "direction": "receive"},
                               {"transport": "tcp", "codec": "msgpack", "cipher": "fernet"},
                               "client robot1")
    assert (topic.topic, topic.remote, topic.type) == ("/odom", "/odom", "nav_msgs/msg/Odometry")
    assert (topic.transport, topic.codec, topic.cipher, topic.line, topic.lines) == (
        "tcp", "msgpack", "fernet", 0, {})
    service = service_from_mapping({"service": "/s", "type": "std_srvs/Empty",
                                    "direction": "transmit"}, {}, "x")
    assert (service.type, service.transport, service.timeout) == ("std_srvs/srv/Empty", "udp", 5.0)


@pytest.mark.parametrize("data, key, message", [
    ({"topic": "/a", "type": "std_msgs/msg/Empty", "direction": "transmit", "codec": 5},
     "topics[3].codec", "expected a non-empty string, got 5"),
    ({"topic": "/a", "type": "std_msgs/msg/Empty", "direction": "transmit", "codek": "cdr"},
     "topics[3].codek", "did you mean 'codec'"),
    ({"topic": "/a", "direction": "transmit"}, "topics[3].type", "missing required key 'type'"),
    (["/a"], "topics[3]", "expected a mapping"),
])
def test_topic_from_mapping_errors(data: object, key: str, message: str) -> None:
    with pytest.raises(ConfigError) as info:
        topic_from_mapping(data, DEFAULTS, "client robot1", index=3)  # type: ignore[arg-type]
    assert (info.value.file, info.value.line, info.value.key) == ("client robot1", None, key)
    assert message in info.value.message


def test_service_from_mapping_errors() -> None:
    with pytest.raises(ConfigError) as info:
        service_from_mapping({"service": "/a", "type": "std_srvs/srv/Empty",
                              "direction": "transmit", "timeout": -2},
                             DEFAULTS, "client robot1", index=1)
    assert (info.value.file, info.value.line, info.value.key) == (
        "client robot1", None, "services[1].timeout")
    with pytest.raises(ConfigError) as info:
        service_from_mapping({"service": "/a"}, DEFAULTS, "client robot1")
    assert info.value.key == "services[?].type"


def test_bridge_config_error_without_lines() -> None:
    config = BridgeConfig(file="f.yaml", name="a", role="server", server=":1")
    assert (config.error("bridge.server", "in use").line, config.defaults) == (None, DEFAULTS)
