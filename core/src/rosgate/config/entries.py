"""The keys of an entry — a topic, a service, an action — each declared once (type, default,
bounds or choices, one line of doc, an example for an error's fix); the keys the three share
are declared once for all.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

from ..batch import window
from ..options import option
from . import kinds
from .patterns import deny_list, is_pattern, name_or_pattern


class Direction(StrEnum):
    """Which way an entry carries its topic (or its service's calls)."""

    TRANSMIT = "transmit"  # this side -> the far side
    RECEIVE = "receive"    # the far side -> this side

    @property
    def flipped(self) -> Direction:
        return Direction.RECEIVE if self is Direction.TRANSMIT else Direction.TRANSMIT


class Framing(StrEnum):
    """What an entry's frames look like on the link (its ``framing:`` key)."""

    ROSGATE = "rosgate"                  # the envelope, sealed by the entry's cipher
    NONE = "none"                        # the bare payload on a datagram link (topics)
    SERIAL_DATAGRAM = "serial_datagram"  # SLIP-style + CRC-32, one call per connection (services)

    @property
    def bare(self) -> bool:
        """No envelope: the entry's name on the wire is ``remote`` exactly as written (a
        microcontroller's names are bare strings such as "cmd_vel"), not a ROS name."""
        return self is not Framing.ROSGATE


TRANSPORT_DEFAULT, CODEC_DEFAULT, CIPHER_DEFAULT = "udp", "cdr", "none"
TIMEOUT_MAX = 3600.0  # seconds: a service call's, an action goal's acceptance; a result's wait
#: recovery: and compression: without a plugin (a topic's own fragments, its payload as it is)
NO_PLUGIN = "none"
# microcontroller entries (framing none or serial_datagram): how what this side sends is laid out
LAYOUTS = ("array", "pair")       # [name, args] (CVRA's firmware) | name then args (its README)
ARGS = ("map", "array", "value")  # the arguments: fields by name | in .msg order | first alone
FLOATS = ("float32", "float64")   # the width of every float field on the wire
NO_ANSWERS = ("fail", "nil")      # a call's connection closed without a byte: a failure | nil
MCU_KEYS = ("layout", "args", "floats")
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
                                     unset="best effort: 25 ms (or its period) in the "
                                           "bridge's own queues once one stands behind for "
                                           "100 ms, the link's "
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

