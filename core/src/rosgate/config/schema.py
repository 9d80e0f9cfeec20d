"""bringup.yaml's keys, each declared once: type, default, bounds or choices, one line of doc and
an example for an error's fix. The loader reads a file against them (and adds the rules that tie
keys together); docs/configuration.md's reference is generated from them (``tools/docgen``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import Any

from ..batch import window
from ..errors import ConfigError
from ..options import option, show
from . import kinds
from .kinds import Key, read
from .patterns import DENY_DEFAULT, deny_list, is_pattern, name_or_pattern
from .source import line_of


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
SESSION_CIPHER_DEFAULT = "aead"   # the default cipher inside an authenticated session
LISTEN_DEFAULT = "0.0.0.0"
PEER_TIMEOUT_HEARTBEATS = 3       # default bridge.peer_timeout, in heartbeats
RECONNECT_MAX_DEFAULT = 10.0
MAX_DELAY_DEFAULT = 1.0           # seconds a best-effort message may wait in a link's queue
TIMEOUT_MAX = 3600.0  # seconds: a service call's, an action goal's acceptance; a result's wait
#: recovery: and compression: without a plugin (a topic's own fragments, its payload as it is)
NO_PLUGIN = "none"
# microcontroller entries (framing none or serial_datagram): how what this side sends is laid out
LAYOUTS = ("array", "pair")       # [name, args] (CVRA's firmware) | name then args (its README)
ARGS = ("map", "array", "value")  # the arguments: fields by name | in .msg order | first alone
FLOATS = ("float32", "float64")   # the width of every float field on the wire
NO_ANSWERS = ("fail", "nil")      # a call's connection closed without a byte: a failure | nil
MCU_KEYS = ("layout", "args", "floats")
RULE_DIRECTIONS = ("transmit", "receive", "both")
MAX_ROUTES_DEFAULT = 300  # routes a pattern entry makes at most
TYPE_FROM_GRAPH = ("pattern entries: taken from the graph (the publishers, servers, action "
                   "servers found); else required")

# the keys topics, services and actions share, declared once for all
_ENTRY: dict[str, dict[str, Any]] = {
    "name": dict(doc="the ROS name on this side, or a pattern (`*` within a segment, `**` "
                 "across) for every name that appears under it", parse=name_or_pattern),
    "direction": dict(example="transmit (this side to the peer) or receive (the peer to this "
                              "side)"),
    "remote": dict(parse=kinds.text),  # a ROS name, a bus key or a bare name: see load
    "transport": dict(default=TRANSPORT_DEFAULT, doc="the link: `udp`, `tcp`, or any installed "
                      "transport plugin", unset="`bridge.defaults.transport` (`udp`)",
                      example="udp"),
    "codec": dict(default=CODEC_DEFAULT, doc="how messages are written: `cdr` (ROS's own, passed "
                  "through), `msgpack` (nested maps, for peers without ROS), ...",
                  unset="`bridge.defaults.codec` (`cdr`)", example="cdr"),
    "cipher": dict(default=CIPHER_DEFAULT, doc="`aead`, `nacl`, `fernet`, `none`, ...",
                   unset="`bridge.defaults.cipher`: `aead` in a client/server session, else "
                         "`none`", example="none"),
    "port": dict(default=None, doc="a port of its own; required in peer role (not on a bus)",
                 minimum=1, maximum=65535, unset="the main port", example="12001"),
    "layout": dict(default=LAYOUTS[0], doc="microcontroller entries: `[name, args]` (array) or "
                   "the name then the arguments (pair)", choices=LAYOUTS, example="array"),
    "args": dict(default=ARGS[0], doc="microcontroller entries: the arguments as fields by name, "
                 "in `.msg` order, or the first alone", choices=ARGS, example="map"),
    "floats": dict(default=FLOATS[0], doc="microcontroller entries: the width of every float "
                   "field on the wire", choices=FLOATS, example="float32"),
    "deny": dict(default=(), doc="pattern entries: names (or patterns) left out, besides "
                 "`bridge.deny`", unset="none", example="[/robot1/camera/**]", parse=deny_list),
    "max_routes": dict(default=MAX_ROUTES_DEFAULT, doc="pattern entries: the most routes it "
                       "makes; a name past them is refused, said in the log", minimum=1,
                       example="300"),
}


def _entry(key: str, **given: Any) -> Any:
    return option(**_ENTRY[key], **given)


@dataclass
class TopicConfig:
    """Per topic you choose:"""

    topic: str = _entry("name", example="/chatter")
    type: str = option(doc="the message type", example="std_msgs/msg/String",
                       unset=TYPE_FROM_GRAPH,
                       parse=kinds.interface("msg"))
    direction: Direction = _entry("direction", doc="`transmit`: to the far side (client to "
                                  "server, or to the peer); `receive`: from it")
    remote: str = _entry("remote", doc="the name on the far side (server, peer's link name, or a "
                         "bus key)", unset="the same as `topic`", example="/robot1/chatter")
    transport: str = _entry("transport")
    codec: str = _entry("codec")
    cipher: str = _entry("cipher")
    port: int | None = _entry("port")
    framing: Framing = option(Framing.ROSGATE, "`rosgate`: the envelope; `none`: the bare payload "
                              "on a datagram link (a microcontroller's)", example="rosgate")
    qos: int | str | dict = option(10, "the QoS of this side's publisher or subscription",
                                   example="sensor_data", parse=kinds.qos,
                                   unset="found from the publishers the sending side discovers "
                                         "(durability, reliability); depth 10")
    #: False: the entry gives no qos, so its QoS is found from the publishers the sending side
    #: discovers (durability and reliability)
    qos_given: bool = field(default=True, compare=False)
    max_rate: float | None = option(None, "faster messages are dropped (`rate_limit`)",
                                    minimum=1e-6, maximum=1e6, unit="Hz", unset="unlimited",
                                    example="20")
    priority: int | None = option(None, "what leaves a link first (on a bus: zenoh's priority)",
                                  unset="`data` (5)", example="data", parse=kinds.priority)
    latest_only: bool | None = option(None, "a message still waiting to leave is replaced by a "
                                      "newer one (`superseded`); not on a bus",
                                      unset="`true` for best-effort QoS, else `false`",
                                      example="true")
    max_delay: float | None = option(None, "seconds a message may wait anywhere in the bridge "
                                     "before it is dropped (`too_late`), whatever its QoS",
                                     above=0, unit="seconds", example="0.05",
                                     unset="best effort: 25 ms in the bridge's own queues "
                                           "once one stands behind for 100 ms, the link's "
                                           "`max_delay` in its send queue; reliable: no limit")
    batch: float | None = option(None, "a window that opens with a message: what the topic "
                                 "publishes until it closes is taken at once and leaves together "
                                 "(one datagram or stream write as far as it fits); it bounds "
                                 "the latency it adds", unit="seconds", example="2ms",
                                 parse=window, unset="no window: each message leaves as it comes")
    recovery: str | None = option(None, "loss recovery by a packetizer plugin (`retransmit`, "
                                  "`fec`) or `none`, on datagram links of frames of 256 "
                                  "bytes or more with `framing: rosgate`; its options over "
                                  "its `plugins:` table as "
                                  "`{fec: {overhead: 0.25}}`",
                                  example="fec (or with options: {fec: {overhead: 0.25}})",
                                  unset="by the QoS: `retransmit` for a reliable topic on "
                                        "such a link (in order, once), else `none`",
                                  parse=kinds.plugin_choice)
    #: the topic's options for its recovery plugin, over its plugins: table
    recovery_options: dict[str, Any] = field(default_factory=dict)
    compression: str = option(NO_PLUGIN, "a payload transform plugin (`zstd`), with `framing: "
                              "rosgate`; the receiver needs no setting; its options as "
                              "`{zstd: {level: 19}}`",
                              example="zstd (or with options: {zstd: {level: 19}})",
                              parse=kinds.plugin_choice)
    compression_options: dict[str, Any] = field(default_factory=dict)
    typical_size: int | None = option(None, "bytes of a message, for `rosgate check`'s budget "
                                      "arithmetic", minimum=1, unit="bytes", example="921600",
                                      unset="a fixed-size type's own size; others are not counted")
    layout: str = _entry("layout")
    args: str = _entry("args")
    floats: str = _entry("floats")
    deny: tuple[str, ...] = _entry("deny")
    max_routes: int = _entry("max_routes")
    line: int = 0
    lines: dict[str, int] = field(default_factory=dict)

    @property
    def pattern(self) -> bool:
        """Whether the entry stands for every matching name that appears."""
        return is_pattern(self.topic)


@dataclass
class ServiceConfig:
    """`services:` entries carry ROS 2 services across the link; [services.md](services.md)
    says how calls, answers and failures behave. Between a client and its server, the service a
    bridge offers exists only while a real server of it runs on the far side."""

    service: str = _entry("name", example="/mcu/ping")
    type: str = option(doc="the service type", example="std_srvs/srv/Trigger",
                       unset=TYPE_FROM_GRAPH,
                       parse=kinds.interface("srv"))
    direction: Direction = _entry("direction", doc="`transmit`: calls made here are served on the "
                                  "far side; `receive`: the far side's calls are served here")
    remote: str = _entry("remote", doc="the name on the far side", unset="the same as `service`",
                         example="/ping")
    transport: str = _entry("transport")
    codec: str = _entry("codec")
    cipher: str = _entry("cipher")
    port: int | None = _entry("port")
    framing: Framing = option(Framing.ROSGATE, "`rosgate`: the envelope; `serial_datagram`: a "
                              "microcontroller's calls", example="rosgate")
    timeout: float = option(5.0, "the ROS caller is answered within this, whatever happens",
                            above=0, maximum=TIMEOUT_MAX, unit="seconds", example="5")
    max_request: int = option(64 * 1024, "a longer request is dropped and counted", minimum=16,
                              maximum=64 * 1024 * 1024, unit="bytes", example="65536")
    layout: str = _entry("layout")
    args: str = _entry("args")
    floats: str = _entry("floats")
    no_answer: str = option(NO_ANSWERS[0], "calls to a microcontroller: what a connection closed "
                            "without a byte means", choices=NO_ANSWERS, example="fail")
    deny: tuple[str, ...] = _entry("deny")
    max_routes: int = _entry("max_routes")
    line: int = 0
    lines: dict[str, int] = field(default_factory=dict)

    @property
    def pattern(self) -> bool:
        """Whether the entry stands for every matching name that appears."""
        return is_pattern(self.service)


@dataclass
class ActionConfig:
    """`actions:` entries carry ROS 2 actions: goals, cancels and results cross as the action's
    three services, feedback and status as its two topics; [actions.md](actions.md) says how."""

    action: str = _entry("name", example="/navigate_to_pose")
    type: str = option(doc="the action type", example="nav2_msgs/action/NavigateToPose",
                       unset=TYPE_FROM_GRAPH,
                       parse=kinds.interface("action"))
    direction: Direction = _entry("direction", doc="`transmit`: goals sent here are served on the "
                                  "far side; `receive`: the far side's goals are served here")
    remote: str = _entry("remote", doc="the name on the far side", unset="the same as `action`",
                         example="/robot1/navigate_to_pose")
    transport: str = _entry("transport")
    codec: str = _entry("codec")
    cipher: str = _entry("cipher")
    port: int | None = _entry("port")
    timeout: float = option(5.0, "a goal's acceptance and a cancel are answered within this; a "
                            "result waits as long as its goal runs", above=0, maximum=TIMEOUT_MAX,
                            unit="seconds", example="5")
    framing: Framing = Framing.ROSGATE
    deny: tuple[str, ...] = _entry("deny")
    max_routes: int = _entry("max_routes")
    line: int = 0
    lines: dict[str, int] = field(default_factory=dict)

    @property
    def pattern(self) -> bool:
        """Whether the entry stands for every matching name that appears."""
        return is_pattern(self.action)


@dataclass(frozen=True)
class LinkConfig:
    """``bridge.links.<transport>``: what this side may put on each link of that transport."""

    transport: str
    bandwidth: float | None = option(None, "bits per second this side sends at most to each "
                                     "destination, packet headers counted; not for a bus",
                                     unset="unlimited", example="20mbit", parse=kinds.bandwidth)
    max_delay: float = option(MAX_DELAY_DEFAULT, "seconds a best-effort message without a "
                              "`max_delay` of its own may wait in the send queue (`too_late`)",
                              above=0, unit="seconds", example="1.0")
    line: int = 0


@dataclass(frozen=True)
class Limits:
    """``bridge.limits``: what a peer may cost this bridge before it is trusted (a client before
    its handshake, a stranger on a port), so that strangers cannot exhaust it."""

    connections: int = option(256, "stream connections held at once, over every listening port "
                              "(each costs two threads); more are closed (`too_many_connections`)",
                              minimum=1, example="256")
    connections_per_source: int = option(16, "of those, from one source address "
                                         "(`too_many_per_source`): a client's main line, its "
                                         "ports and a reconnect fit", minimum=1, example="16")
    handshake_timeout: float = option(5.0, "seconds an accepted connection has to complete its "
                                      "handshake or introduce itself (`handshake_timeout`)",
                                      above=0, unit="seconds", example="5")
    max_frame_before_auth: int = option(64 * 1024, "bytes a frame may have on such a connection "
                                        "until then (`bad_length`)", minimum=1024, unit="bytes",
                                        example="65536")
    idle_timeout: float = option(2.0, "seconds a connection to a microcontroller service port "
                                 "may stay silent (`idle_timeout`)", above=0, unit="seconds",
                                 example="2")
    sessions: int = option(256, "server: client sessions kept at once (connected, or waiting out "
                           "`session_timeout`); a new client past it is refused", minimum=1,
                           example="256")


@dataclass(frozen=True)
class Rule:
    """One rule of a client's policy (``clients.NAME.topics[i]`` / ``services[i]``): what it
    allows. ``None`` means any; names and types are globs (``*`` within a segment, ``**``
    across segments)."""

    name: str = option(doc="a glob on the server-side name: `*` and `?` within a segment, `**` "
                           "across", example="/robot1/**")
    direction: str = option(doc="the client's: `transmit` (it publishes or calls on the "
                                "server), `receive`, `both`", choices=RULE_DIRECTIONS,
                            example="transmit, receive or both")
    types: tuple[str, ...] | None = option(None, "globs on `pkg/msg/Type`", unset="any",
                                           example="[geometry_msgs/msg/*]", parse=kinds.names)
    ports: tuple[tuple[int, int], ...] = option(
        (), "ports of their own it may ask for", unset="none: the main port only",
        example="[12001, 12010-12019]", parse=kinds.port_ranges)
    ciphers: tuple[str, ...] | None = option(None, "ciphers it may use (`none` only when listed)",
                                             unset="any cipher a session keys", example="[aead]",
                                             parse=kinds.names)
    depth: int = option(1000, "topics: the deepest queue (QoS depth) an entry may ask for",
                        minimum=1, maximum=kinds.QOS_DEPTH_MAX, example="100")
    keep_all: bool = option(False, "topics: whether an entry may ask for history `keep_all` (a "
                            "queue without bound)", example="true")
    durability: tuple[str, ...] | None = option(None, "topics: the durabilities an entry may ask "
                                                "for", unset="any: `volatile`, `transient_local`",
                                                example="[volatile]", parse=kinds.durabilities)
    shared: bool = option(False, "actions: whether the client sees and may cancel every goal of "
                          "the action, other clients' too (else only the goals it sent)",
                          example="true")
    line: int = 0


def _rules(key: Key, value: Any) -> tuple[Rule, ...]:
    """a list of rules: `- {name: /robot1/**, direction: both}`"""
    fix = "e.g. - {name: /robot1/**, direction: both}"
    if value is None:  # written empty
        return ()
    if not isinstance(value, list):
        raise key.error(f"expected a list of rules, got {show(value)}", fix=fix)
    return tuple(kinds.item(key.src, f"{key.path}[{i}]", rule, Rule,
                            "a rule (name:, direction: ...)", fix) for i, rule in enumerate(value))


@dataclass(frozen=True)
class ClientPolicy:
    """A client a server accepts: its public key and what it may ask for (default deny)."""

    name: str
    key: bytes = option(doc="the client's public key; `NAME` is its `bridge.name`",
                        example="<the client's public key>", parse=kinds.public_key)
    topics: tuple[Rule, ...] = option((), "rules: topics the client may bridge; an entry must "
                                      "match one", unset="none: every topic refused", parse=_rules)
    services: tuple[Rule, ...] = option((), "rules: services the client may bridge",
                                        unset="none", parse=_rules)
    actions: tuple[Rule, ...] = option((), "rules: actions the client may bridge", unset="none",
                                       parse=_rules)
    line: int = 0


@dataclass
class Defaults:
    """``bridge.defaults``: for entries that do not say."""

    transport: str = option(TRANSPORT_DEFAULT, "the transport of entries", example="udp")
    codec: str = option(CODEC_DEFAULT, "the codec of entries", example="cdr")
    cipher: str = option(CIPHER_DEFAULT, "the cipher of entries", example="none",
                         unset="`aead` in a client/server session, else `none`")


def _section(section: type, build: bool = True) -> Any:
    """The parse function of a key holding a fixed mapping (``bridge.limits``): the ``section``
    made of it, or (``build`` false) the keys given, for the loader to complete."""

    def parse(key: Key, value: Any) -> Any:
        given = read(key.src, kinds.mapping(key, value), key.path, section)
        return section(**given) if build else given

    parse.section = section  # type: ignore[attr-defined]  # the docs list its keys
    parse.__doc__ = "a mapping"
    return parse


def _links(key: Key, value: Any) -> dict[str, LinkConfig]:
    """per transport: `{udp: {bandwidth: 20mbit}}`"""
    return {name: kinds.item(key.src, f"{key.path}.{name}", given, LinkConfig, "a mapping",
                             f"write it as {name}: {{bandwidth: 20mbit}}", name)
            for name, given in kinds.mapping(key, value).items()}


_links.section = LinkConfig  # type: ignore[attr-defined]


@dataclass
class BridgeConfig:
    """The keys under `bridge:`, all optional but name and role; see [Links that
    fail](real-links.md#links-that-fail) and [Real links](real-links.md):"""

    file: str
    name: str = option(doc="this side's name; a server knows a client by it (`clients:`)",
                       example="robot1", parse=kinds.bridge_name)
    role: Role = option(doc="what this side is", example="client")
    server: str | None = option(None, "client: the server's main line, `host:port` or `[v6]:port` "
                                "(Bluetooth: `AA:BB:CC:DD:EE:FF/5`); server: where it listens",
                                unset="required for client and server", example="127.0.0.1:12000")
    main_line: str = option("tcp", "client, server: the stream transport of the main line and "
                            "handshake", example="tcp")
    peer: str | None = option(None, "peer: the far host, where topics are sent (not needed on a "
                              "bus)", unset="required for point-to-point links",
                              example="192.168.1.20")
    listen: str | None = option(None, "peer: the address this side binds",
                                unset=f"`{LISTEN_DEFAULT}`", example=LISTEN_DEFAULT)
    defaults: dict[str, str] = option({"transport": TRANSPORT_DEFAULT, "codec": CODEC_DEFAULT,
                                       "cipher": CIPHER_DEFAULT},
                                      "`{transport, codec, cipher}` for entries that do not say",
                                      example="{transport: udp, codec: cdr, cipher: none}",
                                      parse=_section(Defaults, build=False))
    stale_after: float = option(15.0, "seconds of silence on a received topic before a warning",
                                above=0, example="15")
    stale_warnings: int = option(5, "warnings per silence (0: none)", minimum=0, example="5")
    heartbeat: float = option(1.0, "seconds between pings on the main line", above=0, example="1.0")
    peer_timeout: float = option(3.0, "seconds of silence on the main line before the far side "
                                 "is declared down; must exceed `heartbeat`", above=0,
                                 unit="seconds", unset="3 × `heartbeat`", example="3.0")
    session_timeout: float = option(60.0, "server: seconds a client that lost its main line "
                                    "keeps its session (routes, ids, queued frames)", above=0,
                                    unit="seconds", example="60")
    reconnect_min: float = option(0.1, "seconds before the first reconnection attempt; then "
                                  "doubling, with jitter", key="reconnect.min", above=0,
                                  unit="seconds", example="0.1")
    reconnect_max: float = option(RECONNECT_MAX_DEFAULT, "seconds between attempts at most",
                                  key="reconnect.max", above=0, unit="seconds", example="10",
                                  unset="`10`, or `min` when larger")
    queue_frames: int = option(1000, "client: the messages reliable topics hold while the server "
                               "is out of reach (and a stream link, or a datagram link whose line "
                               "is gone, a serial device unplugged, while it is down)",
                               key="queue.frames", minimum=0, example="1000")
    queue_bytes: int = option(8 * 1024 * 1024, "and the bytes", key="queue.bytes", minimum=0,
                              example="8388608")
    limits: Limits = option(Limits(), "what a peer may cost before it is trusted",
                            example="{connections: 256, connections_per_source: 16, "
                                    "handshake_timeout: 5}", parse=_section(Limits))
    identity: bytes | None = option(None, "this side's private key file (relative to the file), "
                                    "mode 0600", example="robot1.key", parse=kinds.text,
                                    unset="client, server: required, unless `insecure: true`; "
                                          "peer: optional")
    server_key: bytes | None = option(None, "client: the server's public key (base64, 44 "
                                      "characters)", unset="required with `identity`",
                                      example="<the server's public key, from rosgate keygen "
                                              "identity>", parse=kinds.text)
    handshake_port: int | None = option(None, "peer with `identity`: the port of the "
                                        "handshake line (on `handshake_line`)", minimum=1,
                                        maximum=65535, unset="—",
                                        example="12100")
    handshake_line: str = option("tcp", "peer with `identity`: the transport of the handshake "
                                 "line: a stream (tcp), or the peers' datagram link when it "
                                 "is all they share (serial), which then carries it with "
                                 "repetitions", example="serial")
    insecure: bool = option(False, "`true` accepts links anyone can write to (no handshake, no "
                            "keyed cipher, a bus without mutual TLS on every link), named in a "
                            "warning on every `run` and `check`; the file's one such key",
                            example="true")
    rekey: float = option(120.0, "server (or responding peer): seconds a session key generation "
                          "lasts", minimum=1, unit="seconds", example="120")
    allow: tuple[Any, ...] = option((), "peer: the only addresses or networks frames and calls "
                                    "are taken from; others are counted `not_allowed`",
                                    unset="datagram and stream ports: `bridge.peer` only; "
                                          "microcontroller service ports: anyone",
                                    example="[192.168.0.20, 10.1.0.0/24]", parse=kinds.networks)
    peer_key: str | None = option(None, "peer with `identity`: the other peer's public key",
                                  unset="—", example="<the other peer's public key>",
                                  parse=kinds.text)
    clients: dict[str, ClientPolicy] = field(default_factory=dict)  # server: who may connect
    fleet_timeout: float = option(30.0, "seconds after a robot's liveliness token went before "
                                  "its fleet routes are dropped (see [Fleets](fleets.md))",
                                  above=0, unit="seconds", example="30")
    links: dict[str, LinkConfig] = option({}, "per transport, what this side may put on each link",
                                          example="{udp: {bandwidth: 20mbit}}", parse=_links)
    diagnostics: bool = option(True, "publish `diagnostic_msgs/DiagnosticArray` on `/diagnostics` "
                               "once a second (see [operators.md](operators.md))", example="false")
    metrics: str | None = option(None, "`host:port` of a Prometheus endpoint (the "
                                 "`rosgate-metrics-prometheus` monitor)", unset="none",
                                 example="127.0.0.1:9108", parse=kinds.text)
    metrics_public: bool = option(False, "let `metrics` bind an address that is not loopback",
                                  example="true")
    deny: tuple[str, ...] = option(DENY_DEFAULT, "names (or patterns) no pattern entry bridges; "
                                   "a name listed as an entry is bridged all the same",
                                   unset="`[" + ", ".join(DENY_DEFAULT) + "]`",
                                   example="[/rosout, /parameter_events, /robot1/debug/**]",
                                   parse=deny_list)
    pattern_grace: float = option(10.0, "seconds a name a pattern entry found keeps its route "
                                  "after its last publisher went; then the route is removed on "
                                  "both sides", above=0, unit="seconds", example="10")
    plugins: dict[str, dict] = field(default_factory=dict)
    topics: list[TopicConfig] = field(default_factory=list)
    services: list[ServiceConfig] = field(default_factory=list)
    actions: list[ActionConfig] = field(default_factory=list)
    lines: dict[str, int] = field(default_factory=dict)
    base_dir: Path = field(default_factory=Path.cwd)

    def error(self, key: str, message: str, fix: str | None = None) -> ConfigError:
        """A ConfigError at the line of dotted key `key` (or of its nearest parent)."""
        return ConfigError(message, file=self.file, line=line_of(self.lines, key), key=key,
                           fix=fix)

    @property
    def secure(self) -> bool:
        """With identities: every link of a session is authenticated."""
        return self.identity is not None


@dataclass
class File:
    """The file's top level; the loader reads each section."""

    bridge: dict = option(doc="this side: its name, role and links", example="{name: robot1, "
                          "role: client, server: 127.0.0.1:12000}")
    plugins: dict = option({}, "each plugin's options, by its name",
                           example="{fernet: {key_file: secret.key}}")
    topics: list = option([], "the topics to bridge", example="- topic: /chatter")
    services: list = option([], "the services to bridge", example="- service: /mcu/ping")
    actions: list = option([], "the actions to bridge", example="- action: /navigate_to_pose")
    clients: dict = option({}, "server: the clients it accepts",
                           example="{robot1: {key: <public key>, topics: [{name: /robot1/**, "
                                   "direction: both}]}}")
