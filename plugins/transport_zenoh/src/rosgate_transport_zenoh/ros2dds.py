"""zenoh-bridge-ros2dds's convention, as its sources write it: the liveliness tokens it declares
for every route and reads to learn the others' (``liveliness_mgt.rs``), and the request header
its service calls carry (``ros2_utils.rs``). Text and bytes only: no session here.

Tokens::

    @/<zenoh id>/@ros2_lv                                   a bridge (its session) is there
    @/<zenoh id>/@ros2_lv/MP/<key>/<type>/<qos>             a publisher: data comes out on <key>
    @/<zenoh id>/@ros2_lv/MS/<key>/<type>/<qos>             a subscriber: data is taken from <key>
    @/<zenoh id>/@ros2_lv/SS/<key>/<type>                   a service served on <key>
    @/<zenoh id>/@ros2_lv/SC/<key>/<type>                   a service called on <key>
    @/<zenoh id>/@ros2_lv/AS/<key>/<type>                   an action served on <key>/_action/
    @/<zenoh id>/@ros2_lv/AC/<key>/<type>                   an action called on <key>/_action/

``<key>`` and ``<type>`` (``geometry_msgs/msg/Twist``) with every ``/`` written ``§``;
``<qos>`` is ``[K]:<reliability>:<durability>:<history>,<depth>[:<user data>]`` in Cyclone DDS's
numbers (best effort 0, reliable 1; volatile 0, transient local 1; keep last 0, keep all 1),
``K`` only for keyed types (no ROS message is keyed), an empty field for a policy left unset.

Actions (``route_action_srv.rs``, ``route_action_cli.rs``, ``ros2_utils.rs``): an action keyed
``<key>`` with type ``pkg/action/Name`` is three services and two topics under
``<key>/_action/``: ``send_goal`` (``pkg/action/Name_SendGoal``), ``cancel_goal``
(``action_msgs/srv/CancelGoal``), ``get_result`` (``pkg/action/Name_GetResult``), called as any
service, and ``feedback`` (``pkg/action/Name_FeedbackMessage``, reliable, volatile) and
``status`` (``action_msgs/msg/GoalStatusArray``, reliable, transient_local: cached and queried
as any transient_local topic). The five parts hold no token of their own: the action holds one,
``AS`` or ``AC``, on ``<key>`` with the action's type.

Service calls: the query's payload is the request's CDR (with its 4-byte encapsulation header),
the answer the response's CDR; a bridge's query carries the attachment ``b"rqh"`` + the 16-byte
request id (the client's 8-byte GUID, then the call's 8-byte sequence number, in the CDR's byte
order) + 1 byte (1: little endian).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from typing import Any

SLASH = "§"
ROOT = "@ros2_lv"
#: every token of every bridge, for a liveliness watch
ALL = f"@/*/{ROOT}/**"
REQUEST_HEADER = b"rqh"


class Kind(StrEnum):
    PUBLISHER = "MP"       # data comes out on the key (a route from a ROS publisher)
    SUBSCRIBER = "MS"      # data is taken from the key (a route to a ROS subscriber)
    SERVER = "SS"          # calls on the key are served (a ROS service server behind it)
    CLIENT = "SC"          # calls go out on the key (a ROS client behind it)
    ACTION_SERVER = "AS"
    ACTION_CLIENT = "AC"

    @property
    def words(self) -> str:
        return {"MP": "publisher", "MS": "subscriber", "SS": "service server",
                "SC": "service client", "AS": "action server", "AC": "action client"}[self.value]


@dataclass(frozen=True)
class Qos:
    reliable: bool = True
    transient_local: bool = False
    keep_all: bool = False
    depth: int = 10

    def chunk(self) -> str:
        """The token's QoS chunk of a keyless type."""
        return (f":{int(self.reliable)}:{int(self.transient_local)}:"
                f"{int(self.keep_all)},{self.depth}")

    @classmethod
    def of(cls, profile: Any) -> Qos:
        """From an rclpy QoSProfile."""
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, ReliabilityPolicy

        return cls(reliable=profile.reliability != ReliabilityPolicy.BEST_EFFORT,
                   transient_local=profile.durability == DurabilityPolicy.TRANSIENT_LOCAL,
                   keep_all=profile.history == HistoryPolicy.KEEP_ALL,
                   depth=max(1, int(profile.depth)))

    @classmethod
    def parse(cls, chunk: str) -> Qos:
        """``ValueError`` when it is not one."""
        parts = chunk.split(":")
        if len(parts) < 4:
            raise ValueError(f"QoS chunk {chunk!r} has fewer than 4 fields")
        history = parts[3].split(",") if parts[3] else ["0", "10"]
        if len(history) != 2:
            raise ValueError(f"QoS chunk {chunk!r}: history is not <kind>,<depth>")
        return cls(reliable=parts[1] != "0", transient_local=parts[2] == "1",
                   keep_all=history[0] == "1", depth=int(history[1]))


#: the parts of an action, each under ``<key>/_action/``
ACTION_PARTS = ("send_goal", "cancel_goal", "get_result", "feedback", "status")
_ACTION = "/_action/"


def action_part(name: str) -> str | None:
    """Which part of an action a ROS name or a key is (``/fib/_action/send_goal``:
    ``send_goal``), as that bridge tells them apart (by the name's end); None: no part."""
    head, found, part = name.rpartition(_ACTION)
    return part if found and head and part in ACTION_PARTS else None


def action_of(key: str, part_type: str) -> tuple[str, str]:
    """The key and the type of the action whose ``send_goal`` part is ``key`` with
    ``part_type`` (``bot1/fib/_action/send_goal``, ``pkg/action/Fib_SendGoal``)."""
    return (key.removesuffix(f"{_ACTION}send_goal"), part_type.removesuffix("_SendGoal"))


def escape(text: str) -> str:
    return text.replace("/", SLASH)


def unescape(text: str) -> str:
    return text.replace(SLASH, "/")


def bridge_token(zid: str) -> str:
    """The token a bridge declares for itself."""
    return f"@/{zid}/{ROOT}"


def token(zid: str, kind: Kind, key: str, ros_type: str, qos: Qos | None = None) -> str:
    """The token of one route; ``qos`` for publishers and subscribers."""
    base = f"@/{zid}/{ROOT}/{kind.value}/{escape(key)}/{escape(ros_type)}"
    return f"{base}/{qos.chunk()}" if qos is not None else base


@dataclass(frozen=True)
class Announced:
    """A route another bridge announced."""

    zid: str
    kind: Kind
    key: str
    type: str
    qos: Qos | None = None


def parse(token_key: str) -> Announced | None:
    """The route a token announces; None for a bridge's own token or one that is not of this
    convention (a malformed token from the network is ignored, never an error)."""
    parts = token_key.split("/")
    if len(parts) < 6 or parts[0] != "@" or parts[2] != ROOT:
        return None
    try:
        kind = Kind(parts[3])
    except ValueError:
        return None
    topic = kind in (Kind.PUBLISHER, Kind.SUBSCRIBER)
    if len(parts) != (7 if topic else 6):
        return None
    try:
        qos = Qos.parse(parts[6]) if topic else None
    except ValueError:
        return None
    return Announced(parts[1], kind, unescape(parts[4]), unescape(parts[5]), qos)


def request_header(client: int, seq: int) -> bytes:
    """The attachment of a call: the caller's id and the call's number (little endian)."""
    return (REQUEST_HEADER + client.to_bytes(8, "little") + seq.to_bytes(8, "little", signed=True)
            + b"\x01")

