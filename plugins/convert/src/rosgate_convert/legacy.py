"""A ros2_socket_bridge ``bringup.yaml`` (``<node>: ros__parameters:`` with parallel lists per
direction: ``*_topics``, ``*_msg_types``, ``*_ports``, ``*_protocols``, ``*_qos`` and, where
present, ``*_encryption``) as a rosgate client file and the server's part, with a note, at the
old file's line, for everything that does not carry over as it was."""

from __future__ import annotations

import importlib.util
import re
from dataclasses import dataclass, field
from typing import Any

import yaml

from rosgate import ConfigError

DIRECTIONS = ("receive", "transmit")
LISTS = ("topics", "msg_types", "ports", "protocols", "qos")
PROTOCOLS = {"UDP": "udp", "TCP": "tcp", "BLUETOOTH": "bt"}
# the short names the old bridge imported by hand, and where they live
KNOWN_TYPES = {
    "String": "std_msgs", "Bool": "std_msgs", "Int32": "std_msgs", "Int64": "std_msgs",
    "Float32": "std_msgs", "Float64": "std_msgs", "Empty": "std_msgs", "Header": "std_msgs",
    "Twist": "geometry_msgs", "TwistStamped": "geometry_msgs", "Pose": "geometry_msgs",
    "PoseStamped": "geometry_msgs", "PoseWithCovarianceStamped": "geometry_msgs",
    "Point": "geometry_msgs", "Transform": "geometry_msgs",
    "TransformStamped": "geometry_msgs",
    "LaserScan": "sensor_msgs", "Image": "sensor_msgs", "CompressedImage": "sensor_msgs",
    "Imu": "sensor_msgs", "PointCloud2": "sensor_msgs", "NavSatFix": "sensor_msgs",
    "JointState": "sensor_msgs", "BatteryState": "sensor_msgs", "CameraInfo": "sensor_msgs",
    "Odometry": "nav_msgs", "OccupancyGrid": "nav_msgs", "Path": "nav_msgs",
    "TFMessage": "tf2_msgs",
}
# other interface packages to look a short name up in, when it is installed
SEARCHED = ("std_msgs", "geometry_msgs", "sensor_msgs", "nav_msgs", "tf2_msgs",
            "visualization_msgs", "diagnostic_msgs", "trajectory_msgs", "shape_msgs",
            "stereo_msgs", "actionlib_msgs")
MAC = re.compile(r"[0-9A-Fa-f]{2}(:[0-9A-Fa-f]{2}){5}")
MAX_BYTES = 1_000_000  # of an old file: the real ones are a few kB
MAX_VALUES = 100_000  # values an old file holds once its aliases are expanded
#: characters of a pattern: an old bridge named topics and types one by one, never by a pattern,
#: and a pattern carried into the server's policy would allow every topic or type it matches
WILDCARD = re.compile(r"[*?\[\]{}]")


def read_yaml(text: str, file: str) -> Any:
    """The old file's values, read within bounds: at most :data:`MAX_BYTES`, and at most
    :data:`MAX_VALUES` values once aliases are expanded (a kilobyte of nested aliases stands
    for billions); :class:`ConfigError` past them."""
    if len(text) > MAX_BYTES:
        raise ConfigError(f"{len(text)} characters: not a ros2_socket_bridge file (those are a "
                          f"few kB; at most {MAX_BYTES} are read)", file=file,
                          fix="give the bringup.yaml of the old client node")
    root = yaml.compose(text, Loader=yaml.SafeLoader)
    if root is not None:
        _expanded_size(root, {}, set(), file)
    return yaml.safe_load(text)


def _expanded_size(node: yaml.Node, sizes: dict[int, int], open_: set[int], file: str) -> int:
    """How many values ``node`` holds once its aliases are expanded (each node counted once per
    place it appears); :class:`ConfigError` past :data:`MAX_VALUES` or for an alias to a node
    that contains it."""
    known = sizes.get(id(node))
    if known is not None:
        return known
    if id(node) in open_:
        raise ConfigError("an alias refers to the list or mapping that contains it",
                          file=file, line=node.start_mark.line + 1,
                          fix="remove the recursive alias (*name)")
    size = 1
    if isinstance(node, yaml.CollectionNode):
        open_.add(id(node))
        children = (node.value if isinstance(node, yaml.SequenceNode)
                    else [n for pair in node.value for n in pair])
        for child in children:
            size += _expanded_size(child, sizes, open_, file)
            if size > MAX_VALUES:
                raise ConfigError(f"its aliases expand to more than {MAX_VALUES} values: not a "
                                  "ros2_socket_bridge file", file=file,
                                  line=node.start_mark.line + 1,
                                  fix="write the lists out, without nested aliases (*name)")
        open_.discard(id(node))
    sizes[id(node)] = size
    return size


@dataclass
class Converted:
    client: dict[str, Any]
    server: dict[str, Any]
    notes: list[tuple[int, str]] = field(default_factory=list)  # (line of the old file, note)


def _lines(text: str) -> dict[str, int]:
    """The line of every key under ``ros__parameters`` (and of the node's key)."""
    lines: dict[str, int] = {}
    root = yaml.compose(text)
    if not isinstance(root, yaml.MappingNode):
        return lines
    for key, value in root.value:
        lines["node"] = key.start_mark.line + 1
        if isinstance(value, yaml.MappingNode):
            for k2, v2 in value.value:
                if k2.value == "ros__parameters" and isinstance(v2, yaml.MappingNode):
                    for k3, _ in v2.value:
                        lines[k3.value] = k3.start_mark.line + 1
    return lines


def full_type(short: str) -> tuple[str, str | None]:
    """``pkg/msg/Type`` for an old short name, and a note when it was a guess or unknown."""
    if short.count("/") == 2:
        return short, None
    if short.count("/") == 1:
        pkg, name = short.split("/")
        return f"{pkg}/msg/{name}", None
    known = KNOWN_TYPES.get(short)
    if known is not None:
        missing = None if importlib.util.find_spec(known) else (
            f"{known}/msg/{short}: the package {known} is not installed here (install "
            f"ros-<distro>-{known.replace('_', '-')} where this bridge runs)")
        return f"{known}/msg/{short}", missing
    for pkg in SEARCHED:
        if importlib.util.find_spec(pkg) is None:
            continue
        module = importlib.import_module(f"{pkg}.msg")
        if hasattr(module, short):
            return f"{pkg}/msg/{short}", f"{short}: found as {pkg}/msg/{short}; check it is meant"
    return f"unknown_msgs/msg/{short}", (f"{short}: no installed package has this message; "
                                         "write its pkg/msg/Type")


def convert(text: str, file: str, name: str = "robot1", server_name: str = "server",
            client_key: str = "robot1.key", server_key: str = "server.key",
            client_public: str = "", server_public: str = "") -> Converted:
    data = read_yaml(text, file)
    node = next((v for v in data.values() if isinstance(v, dict) and "ros__parameters" in v),
                None) if isinstance(data, dict) else None
    if node is None:
        raise ConfigError("not a ros2_socket_bridge file (no <node>: ros__parameters:)",
                          file=file, fix="give the bringup.yaml of the old client node")
    params: dict[str, Any] = node["ros__parameters"] or {}
    lines = _lines(text)
    out = Converted({}, {})

    def note(key: str, message: str) -> None:
        out.notes.append((lines.get(key, lines.get("node", 0)), f"{key}: {message}"))

    host, port = str(params.get("server_ip", "127.0.0.1")), int(params.get("server_port", 12000))
    bluetooth = bool(MAC.fullmatch(host))
    address = f"{host}/{port}" if bluetooth else f"{host}:{port}"
    if bluetooth:
        note("server_ip", "a Bluetooth address: the main line is bt (RFCOMM channel "
                          f"{port}); rosgate-transport-bt must be installed on both sides")
    bridge: dict[str, Any] = {"name": name, "role": "client", "server": address}
    if bluetooth:
        bridge["main_line"] = "bt"
    bridge |= {"identity": client_key, "server_key": server_public}
    note("server_port", "the main line now carries an authenticated handshake (identities "
                        f"{client_key} and {server_key}) instead of the old plain topic list")
    topics, rules = [], []
    for direction in DIRECTIONS:
        columns = {k: params.get(f"{direction}_{k}") or [] for k in LISTS}
        encryption = params.get(f"{direction}_encryption")
        count = len(columns["topics"])
        for k, values in columns.items():
            if len(values) != count:
                note(f"{direction}_{k}", f"{len(values)} values for {count} topics: the "
                                         "missing ones take rosgate's defaults")
        for i, topic in enumerate(columns["topics"]):
            for key in ("topics", "msg_types"):
                if i < len(columns[key]):
                    _refuse_patterns(file, lines.get(f"{direction}_{key}"), f"{direction}_{key}",
                                     i, columns[key][i])
            entry = _topic(topic, direction, i, columns, note)
            if encryption is not None and i < len(encryption) and not encryption[i]:
                note(f"{direction}_encryption", f"{entry['topic']} was not encrypted; rosgate "
                                                "encrypts and authenticates it like the others")
            topics.append(entry)
            rule: dict[str, Any] = {"name": entry["topic"], "direction": direction,
                                    "types": [entry["type"]]}
            if "port" in entry:
                rule["ports"] = [entry["port"]]
            rules.append(rule)
    if not any(f"{d}_encryption" in params for d in DIRECTIONS):
        note("node", "the old bridge's encryption key came from its launch file's command line; "
                     "rosgate encrypts every topic of a session with keys from the handshake "
                     f"(identity files {client_key} and {server_key}, mode 0600, never on a "
                     "command line)")
    note("node", "pickle on the wire becomes cdr (ROS's own serialization): no Python objects "
                 "are unpickled from the network any more")
    out.client = {"bridge": bridge, "topics": topics}
    server_bridge: dict[str, Any] = {"name": server_name, "role": "server", "server": address}
    if bluetooth:
        server_bridge["main_line"] = "bt"
    server_bridge["identity"] = server_key
    out.server = {"bridge": server_bridge,
                  "clients": {name: {"key": client_public, "topics": rules}}}
    return out


def _refuse_patterns(file: str, line: int | None, key: str, i: int, value: Any) -> None:
    """:class:`ConfigError` for an old topic or type that is no name: a pattern, or no text."""
    if not isinstance(value, str):
        raise ConfigError(f"{type(value).__name__} where a name belongs", file=file, line=line,
                          key=f"{key}[{i}]", fix="write each topic and type as a quoted name")
    if WILDCARD.search(value):
        raise ConfigError(f"{value!r} is a pattern, not a name: converted, it would let the "
                          "client ask for everything it matches", file=file, line=line,
                          key=f"{key}[{i}]", fix="write each topic and type it carries by its "
                                                 "name")


def _topic(topic: str, direction: str, i: int, columns: dict[str, list[Any]],
           note: Any) -> dict[str, Any]:
    name = topic if topic.startswith("/") else f"/{topic}"
    if name != topic:
        note(f"{direction}_topics", f"{topic!r} becomes {name!r} (the old nodes ran in the root "
                                    "namespace)")
    entry: dict[str, Any] = {"topic": name}
    types = columns["msg_types"]
    if i < len(types):
        entry["type"], why = full_type(str(types[i]))
        if why:
            note(f"{direction}_msg_types", why)
    entry["direction"] = direction
    protocols = columns["protocols"]
    if i < len(protocols):
        transport = PROTOCOLS.get(str(protocols[i]).upper())
        if transport is None:
            note(f"{direction}_protocols", f"{protocols[i]!r} is not UDP, TCP or BLUETOOTH; "
                                           "the topic takes bridge.defaults")
        else:
            entry["transport"] = transport
    ports = columns["ports"]
    if i < len(ports):
        entry["port"] = int(ports[i])
    qos = columns["qos"]
    if i < len(qos):
        value = str(qos[i]).strip()
        entry["qos"] = int(value) if value.isdigit() else value.removeprefix("qos_profile_")
    return entry
