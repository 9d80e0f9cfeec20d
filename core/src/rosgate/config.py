"""bringup.yaml: parse, validate, fill defaults. Every mistake becomes one ConfigError that names
the file, the line, the key and the fix, never a traceback.

The YAML is composed into nodes with the safe loader and turned into plain values here, so every
key path ("topics[1].codec", "plugins.fernet.key_file") keeps the line it was written on; other
modules locate their own errors through ``BridgeConfig.error``.

Topic and service entries also arrive over the network from clients (no file, no lines):
``topic_from_mapping`` / ``service_from_mapping`` run the same checks on them.
"""

from __future__ import annotations

import difflib
import math
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import Any, overload

import yaml

from .errors import ConfigError


class Role(StrEnum):
    CLIENT = "client"
    SERVER = "server"
    PEER = "peer"


class Direction(StrEnum):
    TRANSMIT = "transmit"  # this side -> the far side
    RECEIVE = "receive"    # the far side -> this side

    @property
    def flipped(self) -> Direction:
        return Direction.RECEIVE if self is Direction.TRANSMIT else Direction.TRANSMIT


class Framing(StrEnum):
    ROSGATE = "rosgate"                  # the envelope, sealed by the entry's cipher
    NONE = "none"                        # the bare payload on a datagram link (topics)
    SERIAL_DATAGRAM = "serial_datagram"  # SLIP-style + CRC-32, one call per connection (services)

    @property
    def bare(self) -> bool:
        """No envelope: the entry's name on the wire is ``remote`` exactly as written (a
        microcontroller's names are bare strings such as "cmd_vel"), not a ROS name."""
        return self is not Framing.ROSGATE


TRANSPORT_DEFAULT, CODEC_DEFAULT, CIPHER_DEFAULT = "udp", "cdr", "none"
MAIN_LINE_DEFAULT = "tcp"
LISTEN_DEFAULT = "0.0.0.0"
FRAMING_DEFAULT = Framing.ROSGATE
QOS_DEFAULT = 10
TIMEOUT_DEFAULT = 5.0
MAX_REQUEST_DEFAULT = 64 * 1024
STALE_AFTER_DEFAULT = 15.0
STALE_WARNINGS_DEFAULT = 5
HEARTBEAT_DEFAULT = 1.0
PEER_TIMEOUT_HEARTBEATS = 3       # default bridge.peer_timeout, in heartbeats
SESSION_TIMEOUT_DEFAULT = 60.0
RECONNECT_MIN_DEFAULT, RECONNECT_MAX_DEFAULT = 0.1, 10.0
QUEUE_FRAMES_DEFAULT, QUEUE_BYTES_DEFAULT = 1000, 8 * 1024 * 1024
QOS_DEPTH_MAX = 100_000  # far past any real queue; rclpy fails on depths past 64 bits
MAX_RATE_RANGE = (1e-6, 1e6)  # Hz: from once in eleven days to faster than any link
TIMEOUT_MAX = 3600.0  # seconds a service call may take
ROS_NAME_MAX = 200  # characters: rclpy refuses topic names past 247, service names sooner
MAX_REQUEST_MAX = 64 * 1024 * 1024  # bytes, the largest message a link carries
FLEET_TIMEOUT_DEFAULT = 30.0
#: a topic's priority (zenoh's numbering): 1 the most urgent, 7 the least; default data (5). On a
#: bus zenoh's own; on datagram and stream links the classes of the link's scheduler
PRIORITIES = {"real_time": 1, "interactive_high": 2, "interactive_low": 3, "data_high": 4,
              "data": 5, "data_low": 6, "background": 7}

#: recovery: and compression: without a plugin (a topic's own fragments, its payload as it is)
NO_PLUGIN = "none"
MAX_DELAY_DEFAULT = 1.0           # seconds a best-effort message may wait in a link's queue
# microcontroller entries (framing none or serial_datagram): how what this side sends is laid out
LAYOUTS = ("array", "pair")       # [name, args] (CVRA's firmware) | name then args (its README)
ARGS = ("map", "array", "value")  # the arguments: fields by name | in .msg order | first alone
FLOATS = ("float32", "float64")   # the width of every float field on the wire
NO_ANSWERS = ("fail", "nil")      # a call's connection closed without a byte: a failure | nil
MCU_KEYS = ("layout", "args", "floats")

ROLES = tuple(Role)
DIRECTIONS = tuple(Direction)
FRAMINGS = tuple(Framing)
# rclpy.qos.qos_profile_<name> for each
QOS_PROFILES = ("default", "system_default", "sensor_data", "services_default", "parameters",
                "best_available")
QOS_POLICIES = {
    "reliability": ("reliable", "best_effort"),
    "durability": ("volatile", "transient_local"),
    "history": ("keep_last", "keep_all"),
}

TOP_KEYS = ("bridge", "plugins", "topics", "services", "actions", "clients")
BRIDGE_KEYS = ("name", "role", "server", "main_line", "peer", "listen", "defaults", "stale_after",
               "stale_warnings", "heartbeat", "peer_timeout", "session_timeout", "reconnect",
               "queue", "identity", "server_key", "insecure", "rekey", "allow", "peer_key",
               "handshake_port", "fleet_timeout", "links", "limits")
LINK_KEYS = ("bandwidth", "max_delay")
CLIENT_KEYS = ("key", "topics", "services", "actions")
RULE_KEYS = ("name", "direction", "types", "ports", "ciphers")
RULE_DIRECTIONS = ("transmit", "receive", "both")
SESSION_CIPHER_DEFAULT = "aead"   # the default cipher inside an authenticated session
REKEY_DEFAULT = 120.0
DEFAULTS_KEYS = ("transport", "codec", "cipher")
RECONNECT_KEYS = ("min", "max")
QUEUE_KEYS = ("frames", "bytes")
LIMITS_KEYS = ("connections", "connections_per_source", "handshake_timeout",
               "max_frame_before_auth", "idle_timeout", "sessions")
TOPIC_KEYS = ("topic", "type", "direction", "remote", "transport", "codec", "cipher", "port",
              "framing", "qos", "max_rate", "priority", "latest_only", "max_delay", "recovery",
              "compression", "typical_size", *MCU_KEYS)
SERVICE_KEYS = ("service", "type", "direction", "remote", "transport", "codec", "cipher", "port",
                "framing", "timeout", "max_request", *MCU_KEYS, "no_answer")
ACTION_KEYS = ("action", "type", "direction", "remote", "transport", "codec", "cipher", "port",
               "timeout")
QOS_KEYS = ("reliability", "durability", "history", "depth")

# One example value per key for the fix of every error about it; "section.key" where it differs.
_EXAMPLES = {
    "bridge": "{name: robot1, role: client, server: 127.0.0.1:12000}",
    "plugins": "{fernet: {key_file: secret.key}}",
    "defaults": "{transport: udp, codec: cdr, cipher: none}",
    "name": "robot1", "role": "client", "server": "127.0.0.1:12000", "main_line": "tcp",
    "peer": "192.168.1.20", "listen": "0.0.0.0", "stale_after": "15", "stale_warnings": "5",
    "heartbeat": "1.0", "peer_timeout": "3.0", "session_timeout": "60",
    "reconnect": "{min: 0.1, max: 10}", "queue": "{frames: 1000, bytes: 8388608}",
    "limits": "{connections: 256, connections_per_source: 16, handshake_timeout: 5}",
    "bridge.limits.connections": "256", "bridge.limits.connections_per_source": "16",
    "bridge.limits.handshake_timeout": "5", "bridge.limits.max_frame_before_auth": "65536",
    "bridge.limits.idle_timeout": "2", "bridge.limits.sessions": "256",
    "bridge.reconnect.min": "0.1", "bridge.reconnect.max": "10", "bridge.queue.frames": "1000",
    "bridge.queue.bytes": "8388608", "transport": "udp", "codec": "cdr", "cipher": "none",
    "topic": "/chatter", "service": "/mcu/ping", "type": "std_msgs/msg/String",
    "services.type": "std_srvs/srv/Trigger", "services.remote": "/ping",
    "action": "/navigate_to_pose", "actions.type": "nav2_msgs/action/NavigateToPose",
    "actions.remote": "/robot1/navigate_to_pose",
    "direction": "transmit (this side to the peer) or receive (the peer to this side)",
    "remote": "/robot1/chatter", "port": "12001", "framing": "rosgate", "qos": "sensor_data",
    "max_rate": "20", "priority": "data", "latest_only": "true",
    "recovery": "fec (or with options: {fec: {overhead: 0.25}})",
    "compression": "zstd (or with options: {zstd: {level: 19}})",
    "typical_size": "921600", "links": "{udp: {bandwidth: 20mbit}}", "bandwidth": "20mbit",
    "max_delay": "1.0", "topics.max_delay": "0.05", "fleet_timeout": "30", "timeout": "5",
    "max_request": "65536", "reliability": "reliable", "durability": "volatile",
    "history": "keep_last", "depth": "10",
    "layout": "array", "args": "map", "floats": "float32", "no_answer": "fail",
    "identity": "robot1.key",
    "server_key": "<the server's public key, from rosgate keygen identity>",
    "insecure": "true", "rekey": "120", "peer_key": "<the other peer's public key>",
    "handshake_port": "12100", "allow": "[192.168.0.20, 10.1.0.0/24]",
    "key": "<the client's public key>",
    "clients": "{robot1: {key: <public key>, topics: [{name: /robot1/**, direction: both}]}}",
    "clients.name": "/robot1/**", "clients.direction": "transmit, receive or both",
    "clients.types": "[geometry_msgs/msg/*]", "clients.ports": "[12001, 12010-12019]",
    "clients.ciphers": "[aead]",
}

_BRIDGE_NAME = re.compile(r"[A-Za-z0-9_.-]+")
_NAME_TOKEN = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
# a part of a name that a bus fills in ({robot}): which ones there are is the bus's to say
_PLACEHOLDER = re.compile(r"\{[^{}/]*\}")
# a bus key as written for remote: chunks without wildcards or a leading slash (bus.py says more)
_KEY = re.compile(r"[^/*$?#\s]+(?:/[^/*$?#\s]+)*")
# pkg/Type or pkg/<kind>/Type; ROS package names are lower case, interface names CamelCase
_INTERFACE = re.compile(r"([a-z][a-z0-9_]*)/(?:([a-z]+)/)?([A-Z][A-Za-z0-9]*)")
_INDEX = re.compile(r"\[\d+\]$")
_MERGE_TAG = "tag:yaml.org,2002:merge"
_START_FIX = "start with a bridge: section, as in the README's bringup.yaml walk-through"


@dataclass
class TopicConfig:
    topic: str
    type: str
    direction: Direction
    remote: str
    transport: str = TRANSPORT_DEFAULT
    codec: str = CODEC_DEFAULT
    cipher: str = CIPHER_DEFAULT
    port: int | None = None
    framing: Framing = FRAMING_DEFAULT
    qos: int | str | dict = QOS_DEFAULT
    #: False: the entry gives no qos, so the QoS is found from the publishers the sending side
    #: discovers (durability and reliability)
    qos_given: bool = field(default=True, compare=False)
    max_rate: float | None = None
    priority: int | None = None  # 1 (real time) .. 7 (background); None: data (5)
    latest_only: bool | None = None  # None: as the QoS says (best effort: true)
    max_delay: float | None = None  # seconds a message may wait to start; None: the link's (best
    #                                 effort) or none (reliable)
    #: a packetizer by name (loss recovery: fec, retransmit); none: the link's own fragments
    recovery: str = NO_PLUGIN
    #: the topic's options for it, over its plugins: table (recovery: {fec: {overhead: 0.2}})
    recovery_options: dict[str, Any] = field(default_factory=dict)
    #: a payload transform by name (zstd); none: the payload as the codec wrote it
    compression: str = NO_PLUGIN
    compression_options: dict[str, Any] = field(default_factory=dict)
    typical_size: int | None = None  # bytes, for rosgate check's budget arithmetic
    layout: str = LAYOUTS[0]  # microcontroller entries: see LAYOUTS, ARGS and FLOATS
    args: str = ARGS[0]
    floats: str = FLOATS[0]
    line: int = 0
    lines: dict[str, int] = field(default_factory=dict)


@dataclass
class ActionConfig:
    """An action: its goals, cancels and results cross as three services, its feedback and
    status as two topics (rosgate.actions)."""

    action: str
    type: str
    direction: Direction
    remote: str
    transport: str = TRANSPORT_DEFAULT
    codec: str = CODEC_DEFAULT
    cipher: str = CIPHER_DEFAULT
    port: int | None = None
    framing: Framing = FRAMING_DEFAULT
    timeout: float = TIMEOUT_DEFAULT  # for a goal's acceptance and a cancel; a result waits
    line: int = 0
    lines: dict[str, int] = field(default_factory=dict)


@dataclass
class ServiceConfig:
    service: str
    type: str
    direction: Direction
    remote: str
    transport: str = TRANSPORT_DEFAULT
    codec: str = CODEC_DEFAULT
    cipher: str = CIPHER_DEFAULT
    port: int | None = None
    framing: Framing = FRAMING_DEFAULT
    timeout: float = TIMEOUT_DEFAULT
    max_request: int = MAX_REQUEST_DEFAULT  # bytes; a longer request is dropped and counted
    layout: str = LAYOUTS[0]  # microcontroller entries: see LAYOUTS, ARGS, FLOATS, NO_ANSWERS
    args: str = ARGS[0]
    floats: str = FLOATS[0]
    no_answer: str = NO_ANSWERS[0]
    line: int = 0
    lines: dict[str, int] = field(default_factory=dict)


@dataclass(frozen=True)
class LinkConfig:
    """``bridge.links.<transport>``: what this side may put on each link of that transport."""

    transport: str
    bandwidth: float | None = None  # bit/s, per peer; None: as fast as the link takes
    max_delay: float = MAX_DELAY_DEFAULT  # seconds a best-effort message may wait to start
    line: int = 0


@dataclass(frozen=True)
class Limits:
    """``bridge.limits``: what a peer may cost this bridge before it is trusted (a client before
    its handshake, a stranger on a port), so that strangers cannot exhaust it."""

    #: stream connections accepted at once, over every listening port of the bridge
    connections: int = 256
    #: of those, from one source address
    connections_per_source: int = 16
    #: seconds an accepted connection has to complete its handshake (main line) or introduce
    #: itself (a dedicated stream port) before it is closed
    handshake_timeout: float = 5.0
    #: bytes a frame may have on such a connection until then
    max_frame_before_auth: int = 64 * 1024
    #: seconds a connection to a microcontroller service port may stay silent
    idle_timeout: float = 2.0
    #: server: client sessions kept at once (connected, or waiting out session_timeout)
    sessions: int = 256


@dataclass(frozen=True)
class Rule:
    """One rule of a client's policy (``clients.NAME.topics[i]`` / ``services[i]``): what it
    allows. ``None`` means any; names and types are globs (``*`` within a segment, ``**``
    across segments)."""

    name: str
    direction: str                               # the client's: transmit, receive or both
    types: tuple[str, ...] | None = None
    ports: tuple[tuple[int, int], ...] = ()      # ranges; none: the main port only
    ciphers: tuple[str, ...] | None = None       # None: any cipher a session can key
    line: int = 0


@dataclass(frozen=True)
class ClientPolicy:
    """A client a server accepts: its public key and what it may ask for (default deny)."""

    name: str
    key: bytes
    topics: tuple[Rule, ...] = ()
    services: tuple[Rule, ...] = ()
    line: int = 0
    actions: tuple[Rule, ...] = ()


@dataclass
class BridgeConfig:
    file: str
    name: str
    role: Role
    server: str | None = None
    main_line: str = MAIN_LINE_DEFAULT
    peer: str | None = None
    listen: str | None = None
    defaults: dict[str, str] = field(default_factory=lambda: {
        "transport": TRANSPORT_DEFAULT, "codec": CODEC_DEFAULT, "cipher": CIPHER_DEFAULT})
    stale_after: float = STALE_AFTER_DEFAULT
    stale_warnings: int = STALE_WARNINGS_DEFAULT
    heartbeat: float = HEARTBEAT_DEFAULT
    peer_timeout: float = HEARTBEAT_DEFAULT * PEER_TIMEOUT_HEARTBEATS
    session_timeout: float = SESSION_TIMEOUT_DEFAULT
    reconnect_min: float = RECONNECT_MIN_DEFAULT
    reconnect_max: float = RECONNECT_MAX_DEFAULT
    queue_frames: int = QUEUE_FRAMES_DEFAULT
    queue_bytes: int = QUEUE_BYTES_DEFAULT
    limits: Limits = field(default_factory=Limits)
    identity: bytes | None = None      # this side's private key (read from bridge.identity)
    server_key: bytes | None = None    # client: the server's public key; peer: the peer's
    handshake_port: int | None = None  # peer with identities: where the handshake line runs
    insecure: bool = False             # client/server without a handshake (loudly)
    rekey: float = REKEY_DEFAULT       # seconds between key generations in a session
    allow: tuple[Any, ...] = ()        # peer: the only addresses frames are taken from (if any)
    clients: dict[str, ClientPolicy] = field(default_factory=dict)  # server: who may connect
    fleet_timeout: float = FLEET_TIMEOUT_DEFAULT
    links: dict[str, LinkConfig] = field(default_factory=dict)  # by transport name
    plugins: dict[str, dict] = field(default_factory=dict)
    topics: list[TopicConfig] = field(default_factory=list)
    services: list[ServiceConfig] = field(default_factory=list)
    actions: list[ActionConfig] = field(default_factory=list)
    lines: dict[str, int] = field(default_factory=dict)
    base_dir: Path = field(default_factory=Path.cwd)

    def error(self, key: str, message: str, fix: str | None = None) -> ConfigError:
        """A ConfigError located at the line of dotted key `key` (falls back to the nearest
        parent key's line)."""
        return ConfigError(message, file=self.file, line=_line_of(self.lines, key), key=key,
                           fix=fix)

    @property
    def secure(self) -> bool:
        """With identities: every link of a session is authenticated (client, server, and a
        peer that names its peer's key)."""
        return self.identity is not None


def load(path: str | Path) -> BridgeConfig:
    file = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"not UTF-8 text (byte {exc.start}: {exc.reason})", file=file,
                          fix="save the file as UTF-8") from None
    except OSError as exc:
        raise ConfigError(f"cannot read the file: {exc.strerror or exc}", file=file,
                          fix="check the path and its permissions") from None
    return loads(text, file=file, base_dir=Path(path).absolute().parent)


def loads(text: str, file: str = "<string>", base_dir: Path | None = None) -> BridgeConfig:
    data, src = _parse(text, file)
    return _bridge_config(data, src, base_dir if base_dir is not None else Path.cwd())


def topic_from_mapping(data: dict, defaults: dict[str, str], where: str, *,
                       index: int | None = None) -> TopicConfig:
    """Validate one topic entry received from a client; `where` becomes the error's file and
    `index` its position in the client's list (error keys read "topics[3].codec")."""
    return _topic(_Source(where), data, _entry_path("topics", index), defaults)


def service_from_mapping(data: dict, defaults: dict[str, str], where: str, *,
                         index: int | None = None) -> ServiceConfig:
    """Like topic_from_mapping, for a service entry."""
    return _service(_Source(where), data, _entry_path("services", index), defaults)


def topic_to_mapping(t: TopicConfig) -> dict:
    """As the user would write it: the keys of real links only when they are not the defaults
    (so a server that predates them still reads a client's hello that does not use them)."""
    mapping = _to_mapping(t, TOPIC_KEYS)
    if not t.qos_given:  # the far side finds it from the publishers too
        del mapping["qos"]
    for key, options in (("recovery", t.recovery_options), ("compression", t.compression_options)):
        if mapping[key] == NO_PLUGIN:
            del mapping[key]
        elif options:
            mapping[key] = {mapping[key]: dict(options)}
    return _without_microcontroller_keys(t, mapping)


def service_to_mapping(s: ServiceConfig) -> dict:
    mapping = _without_microcontroller_keys(s, _to_mapping(s, SERVICE_KEYS))
    if s.framing is not Framing.SERIAL_DATAGRAM or s.direction is not Direction.TRANSMIT:
        del mapping["no_answer"]
    return mapping


def _without_microcontroller_keys(entry: TopicConfig | ServiceConfig, mapping: dict) -> dict:
    """Only microcontroller entries take them (an entry with an envelope refuses them)."""
    if not entry.framing.bare:
        for key in MCU_KEYS:
            del mapping[key]
    return mapping


# --- parsing -------------------------------------------------------------------------------------

@dataclass
class _Source:
    """Where values came from: the file name, each key path's line, and the source text of
    scalars YAML did not read as strings (for keys that want text, see _text)."""

    file: str
    lines: dict[str, int] = field(default_factory=dict)
    texts: dict[str, str] = field(default_factory=dict)
    root_line: int | None = None

    def error(self, key: str, message: str, fix: str | None = None) -> ConfigError:
        line = _line_of(self.lines, key) or self.root_line
        return ConfigError(message, file=self.file, line=line, key=key or None, fix=fix)


def _parse(text: str, file: str) -> tuple[Any, _Source]:
    src = _Source(file)
    loader = None
    try:
        loader = yaml.SafeLoader(text)
        root = loader.get_single_node()
        if root is None:
            raise ConfigError("the file is empty", file=file, fix=_START_FIX)
        src.root_line = root.start_mark.line + 1
        data = _Builder(loader, src).build(root, "")
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        problem = exc.problem or exc.context or "invalid YAML"
        column = f" at column {mark.column + 1}" if mark is not None else ""
        raise ConfigError(f"YAML syntax error{column}: {problem}", file=file,
                          line=mark.line + 1 if mark is not None else None,
                          fix="check the indentation (spaces, not tabs) and quote values that "
                              "contain ': ' or ' #' or start with a special character") from None
    except yaml.reader.ReaderError as exc:
        raise ConfigError(f"unacceptable character #x{exc.character:04x} (YAML allows no control "
                          "characters)", file=file, line=text.count("\n", 0, exc.position) + 1,
                          fix="remove the control character") from None
    finally:
        if loader is not None:
            loader.dispose()
    return data, src


class _Builder:
    """Turns the node tree into plain values, recording each key path's line in the _Source."""

    def __init__(self, loader: yaml.SafeLoader, src: _Source):
        self.loader = loader
        self.src = src
        self.open: set[int] = set()  # collections being built: an alias to one is a cycle

    def build(self, node: yaml.Node, path: str) -> Any:
        if isinstance(node, yaml.ScalarNode):
            value = self.loader.construct_object(node)
            if value is not None and not isinstance(value, str):
                self.src.texts[path] = node.value
            return value
        if id(node) in self.open:
            raise self.src.error(path, "an alias refers to the mapping or list that contains it",
                                 fix="remove the recursive alias (*name)")
        self.open.add(id(node))
        try:
            if isinstance(node, yaml.SequenceNode):
                items = []
                for i, item in enumerate(node.value):
                    self.src.lines[f"{path}[{i}]"] = item.start_mark.line + 1
                    items.append(self.build(item, f"{path}[{i}]"))
                return items
            assert isinstance(node, yaml.MappingNode)  # the third kind of node
            return self._mapping(node, path)
        finally:
            self.open.discard(id(node))

    def _mapping(self, node: yaml.MappingNode, path: str) -> dict[str, Any]:
        result: dict[str, Any] = {}
        # "<<: *anchor" merges go in first so that the mapping's own keys override them; of several
        # merged mappings the earlier wins
        for key_node, value_node in node.value:
            if key_node.tag == _MERGE_TAG:
                merged = (value_node.value if isinstance(value_node, yaml.SequenceNode)
                          else [value_node])
                for source in reversed(merged):
                    if not isinstance(source, yaml.MappingNode):
                        raise self.src.error(path, "'<<' must be followed by a mapping or a list "
                                                   "of mappings",
                                             fix="merge anchored mappings: <<: *name")
                    result.update(self.build(source, path))
        own: set[str] = set()
        for key_node, value_node in node.value:
            if key_node.tag == _MERGE_TAG:
                continue
            if not isinstance(key_node, yaml.ScalarNode):
                raise ConfigError("a key must be a plain name, not a list or mapping",
                                  file=self.src.file, line=key_node.start_mark.line + 1,
                                  key=path or None, fix="write the key as a name followed by ': '")
            key = key_node.value  # the text as written: "yes:" stays "yes", not True
            key_path = _join(path, key)
            if key in own:
                raise ConfigError(f"duplicate key '{key}' "
                                  f"(first on line {self.src.lines[key_path]})",
                                  file=self.src.file, line=key_node.start_mark.line + 1,
                                  key=key_path, fix="keep only one of the two")
            own.add(key)
            self.src.lines[key_path] = key_node.start_mark.line + 1
            result[key] = self.build(value_node, key_path)
        return result


# --- the file ------------------------------------------------------------------------------------

def _bridge_config(data: Any, src: _Source, base_dir: Path) -> BridgeConfig:
    if not isinstance(data, dict):
        raise src.error("", f"expected a mapping with bridge: at the top, got {_show(data)}",
                        fix=_START_FIX)
    _reject_legacy(src, data)
    _check_keys(src, data, "", TOP_KEYS)
    _require(src, data, "", ("bridge",))
    bridge = _section(src, data, "", "bridge")
    _check_keys(src, bridge, "bridge", BRIDGE_KEYS)
    _require(src, bridge, "bridge", ("name", "role"))
    name = _required(src, bridge, "bridge", "name")
    if not _BRIDGE_NAME.fullmatch(name):
        raise src.error("bridge.name", f"'{name}' is not a valid bridge name",
                        fix="use only letters, digits, '_', '.' and '-', e.g. name: robot1")
    role = Role(_required(src, bridge, "bridge", "role", ROLES))
    _check_role(src, data, bridge, role)
    insecure = _flag(src, bridge, "bridge", "insecure")
    identity, server_key = _identity(src, bridge, role, insecure, base_dir)
    secure = identity is not None
    defaults = _defaults(src, bridge, SESSION_CIPHER_DEFAULT if secure else CIPHER_DEFAULT)
    heartbeat = _number(src, bridge, "bridge", "heartbeat", HEARTBEAT_DEFAULT, "a number > 0",
                        _positive)
    peer_timeout = _number(src, bridge, "bridge", "peer_timeout",
                           heartbeat * PEER_TIMEOUT_HEARTBEATS, "a number of seconds > 0",
                           _positive)
    if peer_timeout <= heartbeat:
        raise src.error("bridge.peer_timeout", f"{peer_timeout:g} s is not longer than the "
                        f"heartbeat ({heartbeat:g} s): every peer would be declared down between "
                        "two pings",
                        fix=f"e.g. peer_timeout: {heartbeat * PEER_TIMEOUT_HEARTBEATS:g} "
                            "(three heartbeats)")
    reconnect_min, reconnect_max = _reconnect(src, bridge)
    queue_frames, queue_bytes = _queue(src, bridge)
    return BridgeConfig(
        file=src.file,
        name=name,
        role=role,
        server=_text(src, bridge, "bridge", "server"),
        main_line=_text(src, bridge, "bridge", "main_line", MAIN_LINE_DEFAULT),
        peer=_text(src, bridge, "bridge", "peer"),
        listen=_text(src, bridge, "bridge", "listen",
                     LISTEN_DEFAULT if role is Role.PEER else None),
        defaults=defaults,
        stale_after=_number(src, bridge, "bridge", "stale_after", STALE_AFTER_DEFAULT,
                            "a number > 0", _positive),
        stale_warnings=_number(src, bridge, "bridge", "stale_warnings", STALE_WARNINGS_DEFAULT,
                               "an integer >= 0", lambda v: v >= 0, integer=True),
        heartbeat=heartbeat,
        peer_timeout=peer_timeout,
        session_timeout=_number(src, bridge, "bridge", "session_timeout", SESSION_TIMEOUT_DEFAULT,
                                "a number of seconds > 0", _positive),
        reconnect_min=reconnect_min,
        reconnect_max=reconnect_max,
        queue_frames=queue_frames,
        queue_bytes=queue_bytes,
        limits=_limits(src, bridge),
        identity=identity,
        server_key=server_key,
        handshake_port=_number(src, bridge, "bridge", "handshake_port", None,
                               "an integer 1..65535", lambda v: 1 <= v <= 65535, integer=True),
        insecure=insecure,
        rekey=_number(src, bridge, "bridge", "rekey", REKEY_DEFAULT, "a number of seconds >= 1",
                      lambda v: v >= 1),
        clients=_clients(src, data, role),
        allow=_allow(src, bridge, role),
        fleet_timeout=_number(src, bridge, "bridge", "fleet_timeout", FLEET_TIMEOUT_DEFAULT,
                              "a number of seconds > 0", _positive),
        links=_links(src, bridge),
        plugins=_plugins(src, data),
        topics=_entries(src, data, "topics", role, defaults),
        services=_entries(src, data, "services", role, defaults),
        actions=_entries(src, data, "actions", role, defaults),
        lines=src.lines,
        base_dir=base_dir,
    )


def _reject_legacy(src: _Source, data: dict) -> None:
    for key, value in data.items():
        if isinstance(value, dict) and "ros__parameters" in value:
            raise src.error(key, f"this is the old ros2_socket_bridge format "
                                 f"({key}: ros__parameters:); rosgate uses bridge: + topics: "
                                 "instead",
                            fix="rewrite it as in the README's bringup.yaml walk-through: a "
                                "bridge: section (name, role: client, server: host:port) and one "
                                "topics: entry per topic (topic, type: pkg/msg/Type, direction, "
                                "port)")


def _check_role(src: _Source, data: dict, bridge: dict, role: Role) -> None:
    if role is Role.PEER:
        for key in ("server", "main_line"):
            if key in bridge:
                raise src.error(f"bridge.{key}",
                                f"role peer has no main line, so {key}: does not apply",
                                fix="remove it; a peer sends to peer: (the far host) and binds "
                                    "listen:")
        # peer: is needed by entries on point-to-point links, not by those on a bus: the
        # resolver, which knows which transport is which, requires it
        return
    for key in ("peer", "listen"):
        if key in bridge:
            raise src.error(f"bridge.{key}", f"{key}: is for role peer only",
                            fix=f"remove it; a {role} uses server: only")
    if role is Role.CLIENT:
        _require(src, bridge, "bridge", ("server",),
                 fix="add server: host:port, the server's main line")
        return
    _require(src, bridge, "bridge", ("server",),
             fix="add server: address:port, where to listen for clients")
    for key in ("topics", "services"):
        if data.get(key):
            raise src.error(key, f"a server gets its {key} from its clients, so its file has "
                                 f"no {key}:",
                            fix=f"remove {key}: here and list them in each client's file")


def _defaults(src: _Source, bridge: dict, cipher: str) -> dict[str, str]:
    given = _section(src, bridge, "bridge", "defaults")
    _check_keys(src, given, "bridge.defaults", DEFAULTS_KEYS)
    return {
        "transport": _text(src, given, "bridge.defaults", "transport", TRANSPORT_DEFAULT),
        "codec": _text(src, given, "bridge.defaults", "codec", CODEC_DEFAULT),
        "cipher": _text(src, given, "bridge.defaults", "cipher", cipher),
    }


def _flag(src: _Source, data: dict, path: str, key: str) -> bool:
    value = data.get(key, False)
    if not isinstance(value, bool):
        raise src.error(_join(path, key), f"expected true or false, got {_show(value)}",
                        fix=f"e.g. {key}: {_example(path, key)}")
    return value


def _identity(src: _Source, bridge: dict, role: Role, insecure: bool,
              base_dir: Path) -> tuple[bytes | None, bytes | None]:
    """This side's private key and (client) the server's public key. Client and server refuse
    to go without them unless ``insecure: true`` says so."""
    from .identity import IdentityError, decode_public, load_private

    if role is Role.PEER:
        for key in ("server_key", "insecure"):
            if key in bridge:
                raise src.error(f"bridge.{key}", f"role peer has no {key}:",
                                fix="a peer authenticates with identity:, peer_key: and "
                                    "handshake_port: (README, Security), or not at all")
        given = [k for k in ("identity", "peer_key", "handshake_port") if k in bridge]
        if not given:
            for key in ("rekey",):
                if key in bridge:
                    raise src.error(f"bridge.{key}", f"{key}: is for peers with identities",
                                    fix="add identity:, peer_key: and handshake_port:, or "
                                        "remove it")
            return None, None
        for key in ("identity", "peer_key", "handshake_port"):
            if key not in bridge:
                raise src.error(f"bridge.{given[0]}", "a peer with a handshake needs "
                                "identity:, peer_key: and handshake_port:",
                                fix=f"add {key}: {_example('bridge', key)}")
        try:
            identity = load_private(base_dir / _required(src, bridge, "bridge", "identity"))
        except IdentityError as exc:
            raise src.error("bridge.identity", str(exc), fix=exc.fix) from None
        try:
            peer_key = decode_public(_required(src, bridge, "bridge", "peer_key"))
        except IdentityError as exc:
            raise src.error("bridge.peer_key", f"the peer_key {exc}", fix=exc.fix) from None
        return identity, peer_key
    if "peer_key" in bridge or "handshake_port" in bridge:
        key = "peer_key" if "peer_key" in bridge else "handshake_port"
        raise src.error(f"bridge.{key}", f"{key}: is for role peer",
                        fix="a client names server_key:, a server its clients:")
    wanted = ("identity", "server_key") if role is Role.CLIENT else ("identity",)
    if role is Role.SERVER and "server_key" in bridge:
        raise src.error("bridge.server_key", "a server has no server_key: it names its clients' "
                        "keys under clients:", fix="remove it")
    if insecure:
        for key in wanted:
            if key in bridge:
                raise src.error(f"bridge.{key}", f"insecure: true and {key}: contradict each "
                                "other", fix="remove insecure: true to authenticate (or the key "
                                             "to run without)")
        return None, None
    if "identity" not in bridge:
        # a client or server without identities is refused when it is planned (Resolver.plan),
        # so that this module still reads any file for what else it may say
        return None, None
    if role is Role.CLIENT and "server_key" not in bridge:
        raise src.error("bridge.identity", "a client with an identity needs the server's "
                        "public key too", fix="add server_key: <the server's public key>")
    path = base_dir / _required(src, bridge, "bridge", "identity")
    try:
        identity = load_private(path)
    except IdentityError as exc:
        raise src.error("bridge.identity", str(exc), fix=exc.fix) from None
    server_key = None
    if role is Role.CLIENT:
        try:
            server_key = decode_public(_required(src, bridge, "bridge", "server_key"))
        except IdentityError as exc:
            raise src.error("bridge.server_key", f"the server_key {exc}", fix=exc.fix) from None
    return identity, server_key


def _allow(src: _Source, bridge: dict, role: Role) -> tuple[Any, ...]:
    """Peer role: the addresses (or networks) frames and connections are taken from — for links
    without keys, such as a microcontroller's (the CVRA profile)."""
    import ipaddress

    if "allow" not in bridge:
        return ()
    if role is not Role.PEER:
        raise src.error("bridge.allow", "allow: is for role peer (a client or server "
                        "authenticates its peers by their keys)", fix="remove it")
    value = bridge["allow"]
    items = value if isinstance(value, list) else [value]
    networks = []
    for item in items:
        try:
            networks.append(ipaddress.ip_network(str(item), strict=False))
        except ValueError:
            raise src.error("bridge.allow", f"{item!r} is not an IP address or network",
                            fix="e.g. allow: [192.168.0.20, 10.1.0.0/24]") from None
    return tuple(networks)


def _clients(src: _Source, data: dict, role: Role) -> dict[str, ClientPolicy]:
    """A server's ``clients:``: each client's public key and its policy (default deny)."""
    from .identity import IdentityError, decode_public

    given = _section(src, data, "", "clients")
    if given and role is not Role.SERVER:
        raise src.error("clients", "only a server lists clients", fix="remove clients: here")
    policies: dict[str, ClientPolicy] = {}
    seen: dict[bytes, str] = {}
    for name, entry in given.items():
        path = f"clients.{name}"
        if not _BRIDGE_NAME.fullmatch(name):
            raise src.error(path, f"'{name}' is not a valid client name",
                            fix="use the client's bridge.name: letters, digits, '_', '.', '-'")
        entry = _section(src, given, "clients", name)
        _check_keys(src, entry, path, CLIENT_KEYS)
        _require(src, entry, path, ("key",))
        try:
            key = decode_public(entry["key"])
        except IdentityError as exc:
            raise src.error(f"{path}.key", f"the key {exc}", fix=exc.fix) from None
        if key in seen:
            raise src.error(f"{path}.key", f"the same key as clients.{seen[key]}",
                            fix="give every client an identity of its own")
        seen[key] = name
        policies[name] = ClientPolicy(name, key, _rules(src, entry, f"{path}.topics"),
                                      _rules(src, entry, f"{path}.services"),
                                      src.lines.get(path, 0),
                                      _rules(src, entry, f"{path}.actions"))
    return policies


def _rules(src: _Source, entry: dict, path: str) -> tuple[Rule, ...]:
    key = path.rpartition(".")[2]
    items = entry.get(key)
    if items is None:
        return ()
    if not isinstance(items, list):
        raise src.error(path, f"expected a list of rules, got {_show(items)}",
                        fix="e.g. - {name: /robot1/**, direction: both}")
    rules = []
    for i, item in enumerate(items):
        rule_path = f"{path}[{i}]"
        if not isinstance(item, dict):
            raise src.error(rule_path,
                            f"expected a rule (name:, direction: ...), got {_show(item)}",
                            fix="e.g. - {name: /robot1/**, direction: both}")
        _check_keys(src, item, rule_path, RULE_KEYS)
        _require(src, item, rule_path, ("name", "direction"))
        rules.append(Rule(
            name=_required(src, item, rule_path, "name"),
            direction=_required(src, item, rule_path, "direction", RULE_DIRECTIONS),
            types=_words(src, item, rule_path, "types"),
            ports=_port_ranges(src, item, rule_path),
            ciphers=_words(src, item, rule_path, "ciphers"),
            line=src.lines.get(rule_path, 0)))
    return tuple(rules)


def _words(src: _Source, data: dict, path: str, key: str) -> tuple[str, ...] | None:
    if key not in data:
        return None
    value = data[key]
    if isinstance(value, str):
        value = [value]
    if not isinstance(value, list) or not all(isinstance(v, str) and v for v in value):
        raise src.error(_join(path, key), f"expected a list of names, got {_show(value)}",
                        fix=f"e.g. {key}: {_example('clients', key)}")
    return tuple(value)


def _port_ranges(src: _Source, data: dict, path: str) -> tuple[tuple[int, int], ...]:
    value = data.get("ports", [])
    items = value if isinstance(value, list) else [value]
    ranges = []
    for item in items:
        low, _, high = str(item).partition("-")
        try:
            first, last = int(low), int(high or low)
        except ValueError:
            first, last = 0, -1
        if isinstance(item, bool) or not 1 <= first <= last <= 65535:
            raise src.error(_join(path, "ports"), f"{item!r} is not a port or a range of ports",
                            fix="e.g. ports: [12001, 12010-12019]")
        ranges.append((first, last))
    return tuple(ranges)


def _reconnect(src: _Source, bridge: dict) -> tuple[float, float]:
    """Backoff between reconnection attempts: from min, doubling, capped at max (seconds)."""
    given = _section(src, bridge, "bridge", "reconnect")
    _check_keys(src, given, "bridge.reconnect", RECONNECT_KEYS)
    low = _number(src, given, "bridge.reconnect", "min", RECONNECT_MIN_DEFAULT,
                  "a number of seconds > 0", _positive)
    high = _number(src, given, "bridge.reconnect", "max", max(low, RECONNECT_MAX_DEFAULT),
                   "a number of seconds > 0", _positive)
    if high < low:
        raise src.error("bridge.reconnect.max", f"max ({high:g} s) is below min ({low:g} s)",
                        fix="make max at least min, e.g. reconnect: {min: 0.1, max: 10}")
    return low, high


def _queue(src: _Source, bridge: dict) -> tuple[int, int]:
    """What reliable topics on a stream link may hold while the link is down."""
    given = _section(src, bridge, "bridge", "queue")
    _check_keys(src, given, "bridge.queue", QUEUE_KEYS)
    return (_number(src, given, "bridge.queue", "frames", QUEUE_FRAMES_DEFAULT, "an integer >= 0",
                    lambda v: v >= 0, integer=True),
            _number(src, given, "bridge.queue", "bytes", QUEUE_BYTES_DEFAULT, "an integer >= 0",
                    lambda v: v >= 0, integer=True))


_BANDWIDTH = re.compile(r"(\d+(?:\.\d*)?|\.\d+)\s*([kmg]?)(?:bit)?(?:/s)?", re.IGNORECASE)
_BANDWIDTH_UNITS = {"": 1, "k": 1e3, "m": 1e6, "g": 1e9}


def parse_bandwidth(value: Any) -> float:
    """Bits per second from ``20mbit``, ``20 Mbit/s``, ``500kbit``, ``1.5gbit``, ``20M`` or a plain
    number; ValueError for anything else. Bytes are refused, and so is ``mbps``, which tc reads
    as megabytes and most people as megabits."""
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        bits = float(value)
    else:
        match = _BANDWIDTH.fullmatch(value.strip()) if isinstance(value, str) else None
        if match is None:
            raise ValueError(f"expected a bandwidth in bits per second, got {_show(value)}")
        bits = float(match.group(1)) * _BANDWIDTH_UNITS[match.group(2).lower()]
    if not bits > 0:
        raise ValueError(f"a bandwidth must be > 0, got {_show(value)}")
    return bits


def _links(src: _Source, bridge: dict) -> dict[str, LinkConfig]:
    """``bridge.links``: per transport, the budget and queueing of each of its links."""
    given = _section(src, bridge, "bridge", "links")
    links = {}
    for name in given:
        path = f"bridge.links.{name}"
        entry = _section(src, given, "bridge.links", name,
                         fix=f"write it as {name}: {{bandwidth: 20mbit}}")
        _check_keys(src, entry, path, LINK_KEYS)
        bandwidth = None
        if "bandwidth" in entry:
            try:
                bandwidth = parse_bandwidth(entry["bandwidth"])
            except ValueError as exc:
                raise src.error(f"{path}.bandwidth", str(exc),
                                fix="bits per second: 20mbit, 500kbit, 1.5gbit or 20000000 "
                                    "(2.5 megabytes per second is 20mbit)") from None
        links[name] = LinkConfig(
            transport=name, bandwidth=bandwidth,
            max_delay=_number(src, entry, path, "max_delay", MAX_DELAY_DEFAULT,
                              "a number of seconds > 0", _positive),
            line=src.lines.get(path, 0))
    return links


def _limits(src: _Source, bridge: dict) -> Limits:
    """What a peer may cost before it is trusted (see :class:`Limits`)."""
    given = _section(src, bridge, "bridge", "limits")
    path = "bridge.limits"
    _check_keys(src, given, path, LIMITS_KEYS)
    default = Limits()
    limits = Limits(
        connections=_number(src, given, path, "connections", default.connections,
                            "an integer >= 1", lambda v: v >= 1, integer=True),
        connections_per_source=_number(src, given, path, "connections_per_source",
                                       default.connections_per_source, "an integer >= 1",
                                       lambda v: v >= 1, integer=True),
        handshake_timeout=_number(src, given, path, "handshake_timeout",
                                  default.handshake_timeout, "a number of seconds > 0", _positive),
        max_frame_before_auth=_number(src, given, path, "max_frame_before_auth",
                                      default.max_frame_before_auth,
                                      "a number of bytes >= 1024", lambda v: v >= 1024,
                                      integer=True),
        idle_timeout=_number(src, given, path, "idle_timeout", default.idle_timeout,
                             "a number of seconds > 0", _positive),
        sessions=_number(src, given, path, "sessions", default.sessions, "an integer >= 1",
                         lambda v: v >= 1, integer=True),
    )
    if limits.connections_per_source > limits.connections:
        raise src.error(f"{path}.connections_per_source",
                        f"{limits.connections_per_source} per source is more than the "
                        f"{limits.connections} connections allowed in total",
                        fix="make connections at least connections_per_source")
    return limits


def _plugins(src: _Source, data: dict) -> dict[str, dict]:
    given = _section(src, data, "", "plugins")
    return {name: _section(src, given, "plugins", name,
                           fix=f"write its options as {name}: {{option: value}}")
            for name in given}


def _entries(src: _Source, data: dict, key: str, role: Role, defaults: dict[str, str]) -> list:
    items = data.get(key)
    if items is None:
        return []
    if not isinstance(items, list):
        raise src.error(key, f"expected a list of entries, got {_show(items)}",
                        fix=f"start each entry with '- {key[:-1]}: ' on its own line under {key}:")
    build = {"topics": _topic, "services": _service, "actions": _action}[key]
    entries = []
    for i, item in enumerate(items):
        # a peer's port: is checked by the resolver: entries on a bus have none
        entries.append(build(src, item, f"{key}[{i}]", defaults))
    _check_duplicates(src, key, entries)
    return entries


def _check_duplicates(src: _Source, key: str, entries: list) -> None:
    name_key = key[:-1]  # "topic" | "service"
    by_name: dict[tuple[str, str], int] = {}
    by_remote: dict[str, int] = {}
    for j, entry in enumerate(entries):
        name = getattr(entry, name_key)
        first = by_name.setdefault((name, entry.direction), j)
        if first != j:
            raise src.error(f"{key}[{j}].{name_key}",
                            f"{name} ({entry.direction}) is already listed as {key}[{first}] "
                            f"on line {entries[first].line}", fix="remove one of the two entries")
        if entry.direction is Direction.RECEIVE:
            # incoming frames are routed by remote name: two receivers of one name are ambiguous
            first = by_remote.setdefault(entry.remote, j)
            if first != j:
                raise src.error(f"{key}[{j}].remote",
                                f"remote {entry.remote} is already received by {key}[{first}] "
                                f"on line {entries[first].line}",
                                fix=f"give each receive {name_key} its own remote")


# --- entries (file or network) -------------------------------------------------------------------

def _topic(src: _Source, data: Any, path: str, defaults: dict[str, str]) -> TopicConfig:
    _expect_entry(src, data, path, "topic")
    _check_keys(src, data, path, TOPIC_KEYS)
    _require(src, data, path, ("topic", "type", "direction"))
    common = _common(src, data, path, "topic", "msg", defaults)
    if common["framing"] is Framing.SERIAL_DATAGRAM:
        raise src.error(_join(path, "framing"), "framing serial_datagram is for services (request "
                                                "and answer to a microcontroller), not topics",
                        fix="use framing: none for bare payloads on a datagram link, "
                            "or leave framing: out")
    return TopicConfig(
        **common,
        qos=_qos(src, data, path),
        qos_given="qos" in data,
        max_rate=_number(src, data, path, "max_rate", None,
                         f"a number of Hz > 0 ({MAX_RATE_RANGE[0]:g}..{MAX_RATE_RANGE[1]:g})",
                         lambda v: MAX_RATE_RANGE[0] <= v <= MAX_RATE_RANGE[1]),
        priority=_priority(src, data, path),
        **_real_link(src, data, path, common["framing"]),
        **_microcontroller(src, data, path, common["framing"]),
        **_entry_lines(src, path),
    )


def _action(src: _Source, data: Any, path: str, defaults: dict[str, str]) -> ActionConfig:
    _expect_entry(src, data, path, "action")
    _check_keys(src, data, path, ACTION_KEYS)
    _require(src, data, path, ("action", "type", "direction"))
    return ActionConfig(
        **_common(src, data, path, "action", "action", defaults),
        timeout=_number(src, data, path, "timeout", TIMEOUT_DEFAULT,
                        f"a number of seconds > 0, at most {TIMEOUT_MAX:g}",
                        lambda v: 0 < v <= TIMEOUT_MAX),
        **_entry_lines(src, path),
    )


def action_from_mapping(data: dict, defaults: dict[str, str], where: str, *,
                        index: int | None = None) -> ActionConfig:
    """Like topic_from_mapping, for an action entry."""
    return _action(_Source(where), data, _entry_path("actions", index), defaults)


def action_to_mapping(a: ActionConfig) -> dict:
    return _to_mapping(a, ACTION_KEYS)


def _service(src: _Source, data: Any, path: str, defaults: dict[str, str]) -> ServiceConfig:
    _expect_entry(src, data, path, "service")
    _check_keys(src, data, path, SERVICE_KEYS)
    _require(src, data, path, ("service", "type", "direction"))
    common = _common(src, data, path, "service", "srv", defaults)
    if common["framing"] is Framing.NONE:
        raise src.error(_join(path, "framing"), "framing none is for topics: a service call needs "
                                                "its answer matched to it",
                        fix="leave framing: out (rosgate), or use framing: serial_datagram with a "
                            "microcontroller")
    return ServiceConfig(
        **common,
        timeout=_number(src, data, path, "timeout", TIMEOUT_DEFAULT,
                        f"a number of seconds > 0, at most {TIMEOUT_MAX:g}",
                        lambda v: 0 < v <= TIMEOUT_MAX),
        max_request=_number(src, data, path, "max_request", MAX_REQUEST_DEFAULT,
                            f"a number of bytes >= 16 (at most {MAX_REQUEST_MAX})",
                            lambda v: 16 <= v <= MAX_REQUEST_MAX, integer=True),
        **_microcontroller(src, data, path, common["framing"]),
        **_no_answer(src, data, path, common["framing"], common["direction"]),
        **_entry_lines(src, path),
    )


def _common(src: _Source, data: dict, path: str, name_key: str, kind: str,
            defaults: dict[str, str]) -> dict[str, Any]:
    """The keys topics and services share."""
    name = _ros_name(src, data, path, name_key, placeholders=True)
    framing = Framing(_choice(src, data, path, "framing", FRAMINGS, FRAMING_DEFAULT))
    if framing.bare:
        remote = _text(src, data, path, "remote", name.removeprefix("/"))
    else:
        remote = _remote(src, data, path) if "remote" in data else name
    fields = {
        name_key: name,
        "type": _interface(src, data, path, kind),
        "direction": Direction(_required(src, data, path, "direction", DIRECTIONS)),
        "remote": remote,
        "transport": _text(src, data, path, "transport",
                           defaults.get("transport", TRANSPORT_DEFAULT)),
        "codec": _text(src, data, path, "codec", defaults.get("codec", CODEC_DEFAULT)),
        "cipher": _text(src, data, path, "cipher", defaults.get("cipher", CIPHER_DEFAULT)),
        "port": _number(src, data, path, "port", None, "an integer 1..65535",
                        lambda v: 1 <= v <= 65535, integer=True),
        "framing": framing,
    }
    if framing.bare and fields["cipher"] != "none":
        raise src.error(_join(path, "framing"),
                        f"framing {framing} sends the bare payload, so there is no envelope to "
                        "authenticate; "
                        f"cipher must be none, not '{fields['cipher']}'",
                        fix="set cipher: none on this entry, or use framing: rosgate to keep "
                            "the cipher")
    return fields


def _microcontroller(src: _Source, data: dict, path: str, framing: Framing) -> dict[str, Any]:
    """``layout``, ``args`` and ``floats``: how a microcontroller entry writes what it sends."""
    for key in MCU_KEYS:
        if key in data and not framing.bare:
            raise src.error(_join(path, key), f"{key} is for microcontroller entries (framing none "
                            "or serial_datagram); this entry has an envelope",
                            fix=f"remove {key}:, or set framing: none (topics) or "
                                "serial_datagram (services)")
    return {"layout": _choice(src, data, path, "layout", LAYOUTS, LAYOUTS[0]),
            "args": _choice(src, data, path, "args", ARGS, ARGS[0]),
            "floats": _choice(src, data, path, "floats", FLOATS, FLOATS[0])}


def _no_answer(src: _Source, data: dict, path: str, framing: Framing,
               direction: Direction) -> dict[str, Any]:
    if "no_answer" in data and (framing is not Framing.SERIAL_DATAGRAM
                                or direction is not Direction.TRANSMIT):
        raise src.error(_join(path, "no_answer"), "no_answer is for calls this bridge makes to a "
                        "microcontroller (direction: transmit, framing: serial_datagram)",
                        fix="remove no_answer: from this entry")
    return {"no_answer": _choice(src, data, path, "no_answer", NO_ANSWERS, NO_ANSWERS[0])}


def _qos(src: _Source, data: dict, path: str) -> int | str | dict:
    if "qos" not in data:
        return QOS_DEFAULT
    value = data["qos"]
    qos_path = _join(path, "qos")
    expected = ("expected a depth (integer >= 1), a profile name or a mapping "
                f"{{{', '.join(QOS_KEYS)}}}, got {_show(value)}")
    fix = ("e.g. qos: 10, qos: sensor_data or qos: {reliability: reliable, depth: 10}; "
           f"profiles: {', '.join(QOS_PROFILES)}")
    if isinstance(value, str):
        if value.isascii() and value.isdigit():  # legacy files wrote depths as strings: '10'
            value = int(value)
        else:
            name = value.removeprefix("qos_profile_")  # legacy rclpy spelling
            if name in QOS_PROFILES:
                return name
            hint = _did_you_mean(_closest(name, QOS_PROFILES))
            raise src.error(qos_path, f"unknown QoS profile '{value}'{hint}", fix=fix)
    if isinstance(value, int) and not isinstance(value, bool):
        if value < 1:
            raise src.error(qos_path, f"a QoS depth must be >= 1, got {value}", fix=fix)
        return _depth_bound(src, qos_path, value)
    if not isinstance(value, dict):
        raise src.error(qos_path, expected, fix=fix)
    _check_keys(src, value, qos_path, QOS_KEYS)
    policies: dict[str, Any] = {key: _choice(src, value, qos_path, key, choices)
                                for key, choices in QOS_POLICIES.items() if key in value}
    if "depth" in value:
        policies["depth"] = _depth_bound(src, _join(qos_path, "depth"), _number(
            src, value, qos_path, "depth", None, "an integer >= 1", lambda v: v >= 1, integer=True))
    return policies


def _depth_bound(src: _Source, key: str, depth: int) -> int:
    if depth > QOS_DEPTH_MAX:
        raise src.error(key, f"a QoS depth must be at most {QOS_DEPTH_MAX}, got {depth}",
                        fix="a depth a subscriber can hold, e.g. qos: 1000")
    return depth


def _ros_name(src: _Source, data: dict, path: str, key: str, placeholders: bool = False) -> str:
    text = _required(src, data, path, key)
    if text.startswith("~"):
        raise src.error(_join(path, key), f"private names (~) are not supported: '{text}'",
                        fix=f"write the full name, e.g. {key}: {_example(path, key)}")
    if len(text) > ROS_NAME_MAX:
        raise src.error(_join(path, key), f"a name of {len(text)} characters is longer than ROS "
                                          f"takes ({ROS_NAME_MAX})",
                        fix=f"use a shorter name, e.g. {key}: {_example(path, key)}")
    tokens = text.removeprefix("/").split("/")
    if not all(_NAME_TOKEN.fullmatch(token) or placeholders and _PLACEHOLDER.fullmatch(token)
               for token in tokens):
        raise src.error(_join(path, key), f"'{text}' is not a valid ROS name",
                        fix="use letters, digits and '_' in parts separated by single '/', no part "
                            f"starting with a digit, e.g. {key}: {_example(path, key)}")
    return "/" + "/".join(tokens)  # relative names are taken from the root namespace


def _remote(src: _Source, data: dict, path: str) -> str:
    """A ROS name ("/robot1/scan", normalised), or else a bus key as written ("fleet/robot-1/scan",
    no leading slash): only the resolver knows which transport the entry is on, and says so when
    a key is given to a point-to-point link."""
    text = _required(src, data, path, "remote")
    tokens = text.removeprefix("/").split("/")
    if all(_NAME_TOKEN.fullmatch(t) or _PLACEHOLDER.fullmatch(t) for t in tokens):
        return "/" + "/".join(tokens)
    if _KEY.fullmatch(text):
        return text
    return _ros_name(src, data, path, "remote", placeholders=True)  # raises, saying why


def _priority(src: _Source, data: dict, path: str) -> int | None:
    if "priority" not in data:
        return None
    value = data["priority"]
    if isinstance(value, str) and value in PRIORITIES:
        return PRIORITIES[value]
    if isinstance(value, int) and not isinstance(value, bool) and 1 <= value <= 7:
        return value
    close = _closest(str(value), tuple(PRIORITIES))
    raise src.error(_join(path, "priority"), f"expected a priority, 1 (real_time) to 7 "
                    f"(background), got {_show(value)}{_did_you_mean(close)}",
                    fix=f"one of {', '.join(PRIORITIES)} (or 1..7)")


def _real_link(src: _Source, data: dict, path: str, framing: Framing) -> dict[str, Any]:
    """The keys of a topic on a constrained link: latest_only, recovery, compression (each a
    plugin: the resolver finds it and checks its options)."""
    recovery, recovery_options = _plugin_choice(src, data, path, "recovery")
    compression, compression_options = _plugin_choice(src, data, path, "compression")
    if framing is not Framing.ROSGATE:
        for key in ("recovery", "compression"):
            if key in data and data[key] != NO_PLUGIN:
                raise src.error(_join(path, key), f"{key} needs the envelope (framing: rosgate): "
                                f"with framing {framing} a datagram is the bare payload",
                                fix=f"remove {key}:, or use framing: rosgate")
    latest_only = None
    if "latest_only" in data:
        latest_only = _flag(src, data, path, "latest_only")
    return {
        "latest_only": latest_only,
        "max_delay": _number(src, data, path, "max_delay", None, "a number of seconds > 0",
                             _positive),
        "recovery": recovery,
        "recovery_options": recovery_options,
        "compression": compression,
        "compression_options": compression_options,
        "typical_size": _number(src, data, path, "typical_size", None, "a number of bytes >= 1",
                                lambda v: v >= 1, integer=True),
    }


def _plugin_choice(src: _Source, data: dict, path: str, key: str) -> tuple[str, dict[str, Any]]:
    """A plugin picked per topic: ``key: NAME``, or ``key: {NAME: {option: value}}`` with the
    topic's own options over the plugin's ``plugins:`` table (the resolver checks them)."""
    value = data.get(key, NO_PLUGIN)
    fix = f"write it as {key}: {_example(path, key)}"
    if isinstance(value, dict):
        if len(value) != 1:
            raise src.error(_join(path, key), f"expected one {key} plugin with its options, got "
                            f"{len(value)} names", fix=fix)
        ((name, options),) = value.items()
        if options is None:
            options = {}
        if not isinstance(name, str) or not isinstance(options, dict):
            raise src.error(_join(path, key), f"expected a name and a mapping of its options, got "
                            f"{_show(name)}: {_show(options)}", fix=fix)
        return name, options
    if not isinstance(value, str) or not _NAME_TOKEN.fullmatch(value):
        raise src.error(_join(path, key), f"expected a plugin's name, got {_show(value)}", fix=fix)
    return value, {}


def _interface(src: _Source, data: dict, path: str, kind: str) -> str:
    text = _required(src, data, path, "type")
    example = _example(path, "type")
    what = {"msg": "a topic", "srv": "a service", "action": "an action"}[kind]
    match = _INTERFACE.fullmatch(text)
    if match is None:
        raise src.error(_join(path, "type"), f"'{text}' is not an interface type name",
                        fix=f"write it as package/{kind}/Type, e.g. type: {example}")
    package, middle, name = match.groups()
    if middle not in (None, kind):
        raise src.error(_join(path, "type"),
                        f"'{text}' is a '{middle}' type, but {what} needs package/{kind}/Type",
                        fix=f"e.g. type: {example}")
    return f"{package}/{kind}/{name}"


# --- typed getters: each returns the value or raises a located ConfigError ------------------------

def _join(path: str, key: str) -> str:
    return f"{path}.{key}" if path else key


def _entry_path(key: str, index: int | None) -> str:
    return f"{key}[{index if index is not None else '?'}]"


def _parent(key: str) -> str:
    match = _INDEX.search(key)
    return key[:match.start()] if match else key.rpartition(".")[0]


def _line_of(lines: dict[str, int], key: str) -> int | None:
    while key:
        if key in lines:
            return lines[key]
        key = _parent(key)
    return None


def _entry_lines(src: _Source, path: str) -> dict[str, Any]:
    prefix = path + "."
    lines = {key[len(prefix):]: line for key, line in src.lines.items() if key.startswith(prefix)}
    return {"line": src.lines.get(path, 0), "lines": lines}


def _show(value: Any) -> str:
    if value is None:
        return "nothing"
    if isinstance(value, bool):
        return f"{str(value).lower()} (a boolean)"
    if isinstance(value, dict):
        return "a mapping"
    if isinstance(value, list):
        return "a list"
    return repr(value)


def _closest(word: str, choices: tuple[str, ...]) -> str | None:
    close = difflib.get_close_matches(word, choices, n=1)
    return close[0] if close else None


def _did_you_mean(close: str | None) -> str:
    return f" (did you mean '{close}'?)" if close else ""


def _example(path: str, key: str) -> str:
    section = path.partition("[")[0]  # "services[2]" -> "services"
    return _EXAMPLES.get(f"{section}.{key}", _EXAMPLES.get(key, "<value>"))


def _positive(value: float) -> bool:
    return value > 0


def _check_keys(src: _Source, data: dict, path: str, valid: tuple[str, ...]) -> None:
    for key in data:
        if key not in valid:
            hint = _did_you_mean(_closest(key, valid))
            raise src.error(_join(path, key), f"unknown key '{key}'{hint}",
                            fix=f"valid keys are {', '.join(valid)}")


def _require(src: _Source, data: dict, path: str, keys: tuple[str, ...],
             fix: str | None = None) -> None:
    for key in keys:
        if key not in data:
            where = f" under {path}:" if path else ""
            raise src.error(_join(path, key), f"missing required key '{key}'",
                            fix=fix or f"add {key}: {_example(path, key)}{where}")


def _expect_entry(src: _Source, data: Any, path: str, name_key: str) -> None:
    if not isinstance(data, dict):
        raise src.error(path, f"expected a mapping ({name_key}:, type:, direction: ...), "
                              f"got {_show(data)}",
                        fix=f"write the entry as '- {name_key}: {_example(path, name_key)}' "
                            "with its other keys indented under it")


def _section(src: _Source, data: dict, path: str, key: str, fix: str | None = None) -> dict:
    value = data.get(key)
    if value is None:  # absent or written empty
        return {}
    if not isinstance(value, dict):
        raise src.error(_join(path, key), f"expected a mapping, got {_show(value)}",
                        fix=fix or f"write it as {key}: {_example(path, key)}")
    return value


@overload
def _text(src: _Source, data: dict, path: str, key: str, default: str) -> str: ...
@overload
def _text(src: _Source, data: dict, path: str, key: str, default: None = None) -> str | None: ...


def _text(src: _Source, data: dict, path: str, key: str, default: str | None = None) -> str | None:
    if key not in data:
        return default
    key_path = _join(path, key)
    value = data[key]
    if value is not None and not isinstance(value, str) and key_path in src.texts:
        # keep what was written: YAML 1.1 reads 10:11:22:33:44:55 (a Bluetooth address) as a number
        value = src.texts[key_path]
    if not isinstance(value, str) or not value.strip():
        raise src.error(key_path, f"expected a non-empty string, got {_show(value)}",
                        fix=f"e.g. {key}: {_example(path, key)}")
    return value


def _required(src: _Source, data: dict, path: str, key: str,
              choices: tuple[str, ...] | None = None) -> str:
    """A key _require has checked is there (of ``choices``, when given)."""
    value = _text(src, data, path, key) if choices is None else _choice(src, data, path, key,
                                                                         choices)
    if value is None:
        raise src.error(_join(path, key), f"missing required key '{key}'",
                        fix=f"add {key}: {_example(path, key)}")
    return value


@overload
def _choice(src: _Source, data: dict, path: str, key: str, choices: tuple[str, ...],
            default: str) -> str: ...
@overload
def _choice(src: _Source, data: dict, path: str, key: str, choices: tuple[str, ...],
            default: None = None) -> str | None: ...


def _choice(src: _Source, data: dict, path: str, key: str, choices: tuple[str, ...],
            default: str | None = None) -> str | None:
    value = _text(src, data, path, key, default)
    if value is not None and value not in choices:
        close = _closest(value, choices)
        raise src.error(_join(path, key),
                        f"'{value}' is not one of {', '.join(choices)}{_did_you_mean(close)}",
                        fix=f"e.g. {key}: {close or _example(path, key)}")
    return value


def _number(src: _Source, data: dict, path: str, key: str, default: Any, expected: str,
            ok: Callable[[Any], bool], integer: bool = False) -> Any:
    if key not in data:
        return default
    value = data[key]
    kinds = int if integer else (int, float)
    if (isinstance(value, bool) or not isinstance(value, kinds)
            or isinstance(value, float) and not math.isfinite(value) or not ok(value)):
        raise src.error(_join(path, key), f"expected {expected}, got {_show(value)}",
                        fix=f"e.g. {key}: {_example(path, key)}")
    return value if integer else float(value)


def _to_mapping(entry: TopicConfig | ServiceConfig | ActionConfig, keys: tuple[str, ...]) -> dict:
    mapping = {}
    for key in keys:
        value = getattr(entry, key)
        if value is not None:  # unset optional keys are left out, as a user would
            mapping[key] = dict(value) if isinstance(value, dict) else value
    return mapping
