"""rmw_zenoh's conventions, as ``rmw_zenoh_cpp`` writes them (ros2/rmw_zenoh,
``rmw_zenoh_cpp/src/detail/``): the key of a topic's data, the attachment on every sample and
the graph's liveliness tokens. Text and bytes only: no session here.

Followed: rmw_zenoh 0.2.4 and later on Jazzy, up to 0.2.10 (the zenoh 1.x line; the attachment
format of ``attachment_helpers.cpp`` since its "Change serialization format" of 0.2.4; volatile
as the default durability since 0.2.3's "Switch default durability to volatile"), which
rolling shares. Read from the source: ``liveliness_utils.cpp`` (keys, tokens, mangling, QoS),
``qos.cpp`` (the defaults a token leaves out), ``attachment_helpers.cpp`` and
``rmw_publisher_data.cpp`` (attachment, sequence numbers from 1), ``rmw_service_data.cpp``
(answers), ``type_support_common.cpp`` (type names).

Data key::

    <domain id>/<ROS name without its leading and trailing '/'>/<type>/<type hash>
    0/robot1/cmd_vel/geometry_msgs::msg::dds_::Twist_/RIHS01_9c45...

``<type>`` is the DDS name of the type (``pkg::msg::dds_::Name_``), ``<type hash>`` the RIHS01
hash ROS gives it. The payload is the message's CDR with its 4-byte encapsulation header.

Attachment (33 bytes, zenoh-ext's serialization): the sequence number (int64, little endian,
1 for a publisher's first sample), the source timestamp (int64, nanoseconds since the epoch),
then the publisher's 16-byte GID as a sequence (its length, 16, as one LEB128 byte, then the
bytes). rmw_zenoh 0.2.0 to 0.2.3 wrote each of the three after its name as a string
(``sequence_number``, ...); :func:`read_attachment` takes both.

Tokens (every ``/`` inside a part written ``%``; an empty namespace is ``/``, so ``%``)::

    @ros2_lv/<domain>/<zid>/<nid>/<nid>/NN/<enclave>/<namespace>/<node>
    @ros2_lv/<domain>/<zid>/<nid>/<id>/MP|MS|SS|SC/<enclave>/<namespace>/<node>/<name>/<type>/<hash>/<qos>

``<zid>`` is the session's zenoh id as zenoh writes it; ``<nid>`` the node's and ``<id>`` the
entity's number in their process. ``<qos>`` is, in rmw's numbers::

    <reliability>:<durability>:<history>,<depth>:<deadline s>,<ns>:<lifespan s>,<ns>:
    <liveliness>,<lease s>,<ns>                                      (one part, no line break)

each field left empty where it is rmw_zenoh's default (reliable, volatile, keep last 42, no
deadline, no lifespan, automatic liveliness with no lease): a volatile, reliable, keep-last-10
publisher is ``::,10:,:,:,,``, a transient local one ``:1:,10:,:,:,,``. (rmw_zenoh 0.2.0 to
0.2.2 took transient local as the default, so an empty durability meant transient local there;
the token does not say which release wrote it, and this module reads it as 0.2.3 and later do.)

An entity's GID is the XXH3-128 hash (seed 0) of its token, its low 64 bits then its high 64
bits, each little endian (``Entity::Entity`` in ``liveliness_utils.cpp``): the GID rmw_zenoh's
graph computes for rosgate's entities is the one rosgate's attachments carry.

Services use the same key and attachment: a client's query carries one (its own numbers and
GID); the server answers with the call's sequence number, a timestamp and the caller's GID.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

import xxhash

ADMIN = "@ros2_lv"
SLASH = "%"
GID_SIZE = 16
#: a duration left at rmw_zenoh's default (infinite), as rmw writes it: seconds, nanoseconds
INFINITE = (9223372036, 854775807)
_OLD_KEYS = (b"sequence_number", b"source_timestamp", b"source_gid")


class Kind(StrEnum):
    NODE = "NN"
    PUBLISHER = "MP"       # data comes out on the key
    SUBSCRIBER = "MS"      # data is taken from the key
    SERVER = "SS"
    CLIENT = "SC"

    @property
    def words(self) -> str:
        return {"NN": "node", "MP": "publisher", "MS": "subscriber", "SS": "service server",
                "SC": "service client"}[self.value]


def mangle(name: str) -> str:
    return name.replace("/", SLASH)


def demangle(part: str) -> str:
    return part.replace(SLASH, "/")


def dds_type(ros_type: str) -> str:
    """``std_msgs/msg/String`` -> ``std_msgs::msg::dds_::String_``."""
    package, kind, name = ros_type.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def ros_type(dds: str) -> str:
    """``std_msgs::msg::dds_::String_`` -> ``std_msgs/msg/String``; ``ValueError`` if it is not
    such a name."""
    parts = dds.split("::")
    if len(parts) != 4 or parts[2] != "dds_" or not parts[3].endswith("_") or len(parts[3]) < 2:
        raise ValueError(f"{dds!r} is not a DDS type name")
    return f"{parts[0]}/{parts[1]}/{parts[3][:-1]}"


def topic_key(domain: int, name: str, ros_type_name: str, type_hash: str) -> str:
    """The key a topic's data is put on."""
    return f"{domain}/{name.strip('/')}/{dds_type(ros_type_name)}/{type_hash}"


# -- QoS ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Qos:
    """A profile in rmw's numbers (``rmw/types.h``): reliability 1 reliable, 2 best effort;
    durability 1 transient local, 2 volatile; history 1 keep last, 2 keep all; liveliness 1
    automatic, 3 manual by topic. The defaults are rmw_zenoh's (``qos.cpp``)."""

    reliability: int = 1
    durability: int = 2
    history: int = 1
    depth: int = 42
    deadline: tuple[int, int] = INFINITE
    lifespan: tuple[int, int] = INFINITE
    liveliness: int = 1
    lease: tuple[int, int] = INFINITE

    @property
    def reliable(self) -> bool:
        return self.reliability == 1

    @property
    def transient_local(self) -> bool:
        return self.durability == 1

    @property
    def keep_all(self) -> bool:
        return self.history == 2

    def chunk(self) -> str:
        """The token's QoS part."""
        d = Qos()

        def one(value: Any, default: Any) -> str:
            return "" if value == default else str(value)

        def pair(value: tuple[int, int], default: tuple[int, int]) -> str:
            return f"{one(value[0], default[0])},{one(value[1], default[1])}"

        return ":".join([one(self.reliability, d.reliability), one(self.durability, d.durability),
                         f"{one(self.history, d.history)},{one(self.depth, d.depth)}",
                         pair(self.deadline, d.deadline), pair(self.lifespan, d.lifespan),
                         f"{one(self.liveliness, d.liveliness)},{pair(self.lease, d.lease)}"])

    @classmethod
    def parse(cls, chunk: str) -> Qos:
        """``ValueError`` when it is not one."""
        parts = chunk.split(":")
        if len(parts) < 6:
            raise ValueError(f"QoS {chunk!r} has {len(parts)} of 6 fields")
        history, deadline, lifespan, liveliness = (p.split(",") for p in parts[2:6])
        if min(len(history), len(deadline), len(lifespan)) < 2 or len(liveliness) < 3:
            raise ValueError(f"QoS {chunk!r}: a field has too few parts")
        d = Qos()

        def number(text: str, default: int) -> int:
            if not text:
                return default
            if not text.isdigit():
                raise ValueError(f"QoS {chunk!r}: {text!r} is not a number")
            return int(text)

        def pair(texts: list[str], default: tuple[int, int]) -> tuple[int, int]:
            return number(texts[0], default[0]), number(texts[1], default[1])

        return cls(reliability=number(parts[0], d.reliability),
                   durability=number(parts[1], d.durability),
                   history=number(history[0], d.history), depth=number(history[1], d.depth),
                   deadline=pair(deadline, d.deadline), lifespan=pair(lifespan, d.lifespan),
                   liveliness=number(liveliness[0], d.liveliness),
                   lease=pair(liveliness[1:], d.lease))

    @classmethod
    def of(cls, profile: Any) -> Qos:
        """From an rclpy QoSProfile, with what rmw_zenoh puts in place of "system default",
        "unknown", depth 0 and default durations (``QoS::best_available_qos``)."""
        d = cls()

        def policy(value: Any, default: int, unset: tuple[int, ...]) -> int:
            number = int(getattr(value, "value", value))
            return default if number in unset else number

        def duration(value: Any, default: tuple[int, int]) -> tuple[int, int]:
            nanoseconds = int(value.nanoseconds)
            return default if nanoseconds == 0 else divmod(nanoseconds, 1_000_000_000)

        return cls(reliability=policy(profile.reliability, d.reliability, (0, 3)),
                   durability=policy(profile.durability, d.durability, (0, 3)),
                   history=policy(profile.history, d.history, (0, 3)),
                   depth=int(profile.depth) or d.depth,
                   deadline=duration(profile.deadline, d.deadline),
                   lifespan=duration(profile.lifespan, d.lifespan),
                   liveliness=policy(profile.liveliness, d.liveliness, (0, 4)),
                   lease=duration(profile.liveliness_lease_duration, d.lease))


# -- tokens ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Node:
    """A node as the graph knows it."""

    domain: int
    zid: str
    nid: str
    name: str
    namespace: str = "/"
    enclave: str = "/"

    def parts(self, entity_id: str, kind: Kind) -> list[str]:
        return [ADMIN, str(self.domain), self.zid, self.nid, entity_id, kind.value,
                mangle(self.enclave), mangle(self.namespace), mangle(self.name)]

    def token(self) -> str:
        return "/".join(self.parts(self.nid, Kind.NODE))


@dataclass(frozen=True)
class Entity:
    """A publisher, subscriber, service server or client of a node."""

    node: Node
    id: str
    kind: Kind
    name: str  # the ROS name: /robot1/cmd_vel
    type: str  # the ROS type: geometry_msgs/msg/Twist
    hash: str  # RIHS01_...
    qos: Qos = field(default_factory=Qos)

    def token(self) -> str:
        return "/".join([*self.node.parts(self.id, self.kind), mangle(self.name),
                         dds_type(self.type), mangle(self.hash), self.qos.chunk()])

    def key(self) -> str:
        """The key of its data."""
        return topic_key(self.node.domain, self.name, self.type, self.hash)

    def gid(self) -> bytes:
        return gid(self.token())


def gid(token: str) -> bytes:
    """An entity's 16-byte GID, as rmw_zenoh derives it from its token (module documentation)."""
    return xxhash.xxh3_128_intdigest(token.encode()).to_bytes(GID_SIZE, "little")


def everything(domain: int) -> str:
    """The key expression of every token of a domain, for a liveliness watch."""
    return f"{ADMIN}/{domain}/**"


def parse(token: str) -> Node | Entity | None:
    """What a token announces; None for one that is not of this convention (a malformed token
    from the network is ignored, never an error)."""
    parts = token.split("/")
    if len(parts) not in (9, 13) or parts[0] != ADMIN or not all(parts):
        return None
    try:
        kind = Kind(parts[5])
        domain = int(parts[1])
    except ValueError:
        return None
    node = Node(domain, parts[2], parts[3], demangle(parts[8]), demangle(parts[7]),
                demangle(parts[6]))
    if kind is Kind.NODE:
        return node if len(parts) == 9 else None
    if len(parts) != 13:
        return None
    try:
        return Entity(node, parts[4], kind, demangle(parts[9]), ros_type(parts[10]),
                      demangle(parts[11]), Qos.parse(parts[12]))
    except ValueError:
        return None


# -- attachment -----------------------------------------------------------------------------------
@dataclass(frozen=True)
class Attachment:
    sequence_number: int
    source_timestamp: int  # nanoseconds since the epoch
    source_gid: bytes


def attachment(sequence_number: int, source_timestamp: int, source_gid: bytes) -> bytes:
    """The attachment of one sample."""
    if len(source_gid) != GID_SIZE:
        raise ValueError(f"a GID is {GID_SIZE} bytes, not {len(source_gid)}")
    return struct.pack("<qqB", sequence_number, source_timestamp, GID_SIZE) + source_gid


def read_attachment(data: bytes | None) -> Attachment:
    """A sample's attachment, in either format (module documentation); ``ValueError`` saying
    what is wrong with it."""
    if not data:
        raise ValueError("no attachment")
    if data.startswith(b"\x0f" + _OLD_KEYS[0]):
        return _read_keyed(data)
    if len(data) != 33 or data[16] != GID_SIZE:
        raise ValueError(f"an attachment of {len(data)} bytes is not (int64, int64, 16 bytes)")
    seq, stamp = struct.unpack_from("<qq", data)
    return Attachment(seq, stamp, bytes(data[17:]))


def _read_keyed(data: bytes) -> Attachment:
    values: list[Any] = []
    at = 0
    for index, key in enumerate(_OLD_KEYS):
        if data[at:at + 1 + len(key)] != bytes([len(key)]) + key:
            raise ValueError(f"the attachment has no {key.decode()} where it belongs")
        at += 1 + len(key)
        if index < 2:
            if len(data) < at + 8:
                raise ValueError("the attachment ends inside a number")
            values.append(struct.unpack_from("<q", data, at)[0])
            at += 8
        elif data[at:at + 1] != bytes([GID_SIZE]) or len(data) != at + 1 + GID_SIZE:
            raise ValueError("the attachment's source_gid is not 16 bytes")
        else:
            values.append(bytes(data[at + 1:]))
    return Attachment(*values)
