"""Fuzz targets: every decoder that takes bytes from the network, as a function of one input.

Each target feeds its input to a decoder (or a sequence of them, read from the input) and lets
only the decoder's documented refusal through (``EnvelopeError``, ``FramingError``,
``CodecError`` ...); any other exception is a finding, and so are broken invariants (a duplicate
accepted twice, a reassembler holding more than its bound). ``fuzz.py`` runs a target under
atheris, ``test_fuzz.py`` replays the committed corpus and every past finding through it.

Targets need no atheris: they read their input with :class:`Reader`, so a finding replays as
a plain function call.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

Target = Callable[[bytes], None]
TARGETS: dict[str, Target] = {}
#: largest input per target (bytes); a datagram's worth unless said otherwise
MAX_LEN: dict[str, int] = {}


def target(max_len: int = 65536) -> Callable[[Target], Target]:
    def register(function: Target) -> Target:
        TARGETS[function.__name__] = function
        MAX_LEN[function.__name__] = max_len
        return function
    return register


class Reader:
    """Reads structure out of a fuzzer's bytes; past the end everything is zero or empty."""

    def __init__(self, data: bytes):
        self.data = data
        self.pos = 0

    @property
    def left(self) -> int:
        return len(self.data) - self.pos

    def byte(self) -> int:
        if self.pos >= len(self.data):
            return 0
        self.pos += 1
        return self.data[self.pos - 1]

    def integer(self, size: int) -> int:
        return int.from_bytes(self.take(size), "big")

    def take(self, size: int) -> bytes:
        chunk = self.data[self.pos:self.pos + size]
        self.pos += len(chunk)
        return chunk

    def rest(self) -> bytes:
        return self.take(self.left)

    def chunks(self) -> list[bytes]:
        """The rest, cut into pieces whose sizes the input chooses."""
        pieces = []
        while self.left:
            pieces.append(self.take(self.byte() * 4 + 1))
        return pieces


# -- message types the codec targets pick from (the first input byte chooses) ----------------

@functools.cache
def message_types() -> list[type]:
    from builtin_interfaces.msg import Time
    from geometry_msgs.msg import PolygonStamped, PoseStamped, Twist
    from nav_msgs.msg import OccupancyGrid, Odometry, Path
    from rcl_interfaces.msg import ParameterValue
    from sensor_msgs.msg import (
        CameraInfo,
        Image,
        JointState,
        LaserScan,
        MultiEchoLaserScan,
        NavSatFix,
        PointCloud2,
    )
    from std_msgs.msg import Empty, Float64MultiArray, Header, String
    from std_srvs.srv import SetBool

    return [Twist, PoseStamped, PolygonStamped, Odometry, Path, OccupancyGrid, LaserScan,
            MultiEchoLaserScan, PointCloud2, Image, CameraInfo, JointState, NavSatFix, String,
            Float64MultiArray, Header, Empty, Time, ParameterValue, SetBool.Request,
            SetBool.Response]


@functools.cache
def _codec(name: str, msg_type: type) -> Any:
    if name == "msgpack":
        from rosgate_codec_msgpack import MsgpackCodec
        return MsgpackCodec(msg_type, {})
    if name == "cbor":
        from rosgate_codec_cbor import CborCodec
        return CborCodec(msg_type, {})
    from rosgate.ros import cdr_checker
    return cdr_checker(msg_type)


def caches() -> tuple[int, ...]:
    """How much the targets' caches hold (message types, codecs, converter trees): an input
    during which they grew paid for building them, which a time limit must not count."""
    import sys

    from rosgate_message_tree import _TREES

    return (message_types.cache_info().misses, _codec.cache_info().misses, len(_TREES),
            len(sys.modules))


def warm(run: Target) -> None:
    """What a target builds once (codecs' converters, lazy imports), built before timing it."""
    for msg_type in message_types():
        for codec in ("msgpack", "cbor", "cdr"):
            _codec(codec, msg_type)
    from rosgate_message_tree import to_tree
    for msg_type in message_types():
        to_tree(msg_type())
    for seed in (b"", b"\x00" * 64):
        try:
            run(seed)
        except Exception:
            pass


def _pick_type(reader: Reader) -> type:
    types = message_types()
    return types[reader.byte() % len(types)]


# -- the envelope and the replay window -----------------------------------------------------

@target(max_len=4096)
def envelope(data: bytes) -> None:
    """The 28-byte header, then the replay window driven by (epoch, seq) pairs from the input."""
    from rosgate.wire import envelope as env

    try:
        env.unpack(data)
    except env.EnvelopeError:
        pass
    reader = Reader(data)
    window = env.ReplayWindow(authenticated=bool(reader.byte() & 1))
    while reader.left >= 2:
        epoch = reader.byte() % 12
        width = reader.byte() % 9
        seq = reader.integer(width)
        if reader.byte() & 1:
            seq = 2**64 - 1 - seq
        if window.accept(epoch, seq) is None:
            assert window.accept(epoch, seq) is not None, f"({epoch}, {seq}) accepted twice"
        assert len(window._windows) <= window.EPOCHS
        assert all(len(tracks) <= window.TRACKS for tracks in window._windows.values())


# -- fragments and compact pieces ----------------------------------------------------------

@target()
def reassembly(data: bytes) -> None:
    """Datagrams to a fragment reassembler and a compact one, from up to four sources: some as
    the input gives them, some cut from a frame by the link's own fragmenter and shuffled."""
    from rosgate_compact import CompactReassembler, compact_fragment

    from rosgate.builtin import Reassembler, fragment
    from rosgate.wire import framing

    lost: list[tuple[int | None, str]] = []
    bound = 1 << 16
    fragments = Reassembler(lambda *x: lost.append(x), max_message=bound,
                            max_pending_bytes=4 * bound)
    compact = CompactReassembler(lambda *x: lost.append(x), max_message=bound,
                                 max_pending_bytes=4 * bound)
    reader = Reader(data)
    while reader.left:
        kind, source = reader.byte(), reader.byte() % 4
        if kind % 3 == 0:  # a frame cut by the link, pieces in an order the input chooses
            frame = reader.take(reader.integer(2) % 4096)
            size = 16 + reader.byte()
            try:
                pieces = fragment(frame, size, reader.integer(4), reader.integer(4))
            except framing.FramingError:
                continue
            order = sorted(range(len(pieces)), key=lambda i: (reader.byte(), i))
            datagrams = [pieces[i] for i in order if reader.byte() % 8]
            datagrams += [bytes(p) for p in compact_fragment(frame, 8 + size % 56, reader.byte())]
        else:
            datagrams = [reader.take(reader.byte() + 1)]
        for datagram in datagrams:
            for reassembler in (fragments, compact):
                try:
                    whole = reassembler.add(source, bytes(datagram))
                except framing.FramingError:
                    continue
                assert whole is None or len(whole) <= bound
                assert reassembler.pending_bytes <= 4 * bound + 65536
        if kind % 7 == 0:
            fragments.expire(float("inf"))
            compact.expire(float("inf"))


# -- stream framing --------------------------------------------------------------------------

@target()
def stream_framing(data: bytes) -> None:
    """Length-prefixed frames, fed in pieces of sizes the input chooses, with a small limit."""
    from rosgate.streamlink.link import StreamReader
    from rosgate.wire import framing

    reader = Reader(data)
    limit = 64 + reader.integer(2)
    stream = StreamReader(limit)
    for piece in reader.chunks():
        try:
            for frame in stream.feed(piece):
                assert len(frame) <= limit
        except framing.FramingError:
            return  # a corrupt stream: the link closes the connection
        assert len(stream._buffer) <= limit + 4 + len(piece)


# -- serial datagrams (CVRA service calls) -------------------------------------------------

@target()
def serial_datagram(data: bytes) -> None:
    """SLIP-style frames with CRC-32: the decoder never raises, holds at most its limit, and
    what the encoder writes decodes to what it was given."""
    from rosgate_mcu_cvra import serial_datagram as sd

    errors: list[tuple[str, str]] = []
    reader = Reader(data)
    limit = 16 + reader.integer(2) % 4096
    decoder = sd.Decoder(lambda *error: errors.append(error), limit)
    for piece in reader.chunks():
        for payload in decoder.feed(piece):
            assert len(payload) <= limit
        assert decoder.pending <= limit + sd.CRC_SIZE
    payload = data[:limit]
    assert list(sd.Decoder(lambda *e: None, limit).feed(sd.encode(payload))) == [payload]


# -- the main line: control messages and the entries of a hello -----------------------------

@target()
def control_message(data: bytes) -> None:
    """A control message's JSON, then, for a hello, its topics, services and actions checked as a
    server checks them, and what the server builds from a valid one (QoS, rate)."""
    from rosgate.config import TopicConfig
    from rosgate.errors import ConfigError
    from rosgate.roles.mainline import client_entries, flipped
    from rosgate.rostypes import is_reliable, qos_profile
    from rosgate.wire import control

    try:
        message = control.parse(data)
    except control.ControlError:
        return
    defaults = {"transport": "udp", "codec": "cdr", "cipher": "none"}
    try:
        entries, _ = client_entries(message, defaults, "fuzz")
    except ConfigError:
        return
    for entry in entries:
        flipped(entry)
        _resolve_safely(entry.type)
        if isinstance(entry, TopicConfig):
            qos_profile(entry.qos).get_c_qos_profile()  # what rclpy would be handed
            is_reliable(entry.qos)
            if entry.max_rate:
                int(1e9 / entry.max_rate)  # a transmitting route's interval


def _resolve_safely(name: str) -> None:
    """A type name from a peer resolves, or is refused, without importing its package unless
    that is a ROS interface package (issue 10, attack 10: ``this/msg/Foo`` imported ``this``)."""
    import sys

    from rosgate.rostypes import TypeNotFound, is_interface_package, resolve_type

    package, _, rest = name.partition("/")
    known = package in sys.modules
    try:
        resolve_type(name)
    except TypeNotFound:
        pass
    if not known and package in sys.modules:
        assert is_interface_package(package, rest.partition("/")[0]), f"{name!r} imported it"


@target(max_len=4096)
def control_depth(data: bytes) -> None:
    """The depth check agrees with the JSON parser: what it lets through parses without
    recursing past the limit."""
    import json

    from rosgate.wire import control

    if control.too_deep(data):
        return
    try:
        value = json.loads(data)
    except (ValueError, RecursionError) as exc:
        assert not isinstance(exc, RecursionError), "recursed although not too deep"
        return

    def depth(node: Any) -> int:
        if isinstance(node, dict):
            return 1 + max(map(depth, node.values()), default=0)
        if isinstance(node, list):
            return 1 + max(map(depth, node), default=0)
        return 0
    assert depth(value) <= control.MAX_DEPTH


# -- microcontrollers: a name, then a map ---------------------------------------------------

@target()
def cvra_name_and_map(data: bytes) -> None:
    """A bare datagram (or a call's payload): the name as a MessagePack str, then the message
    as a MessagePack map, decoded for the type the name picks."""
    from rosgate.errors import CodecError
    from rosgate.wire.names import NameMissing, pack_name, split_name

    try:
        name, rest = split_name(data)
    except NameMissing:
        return
    assert split_name(pack_name(name) + rest) == (name, rest)
    types = message_types()
    try:
        _codec("msgpack", types[len(name) % len(types)]).decode(rest)
    except CodecError:
        pass


# -- codecs, through message_tree -------------------------------------------------------

@target()
def msgpack_codec(data: bytes) -> None:
    from rosgate.errors import CodecError

    reader = Reader(data)
    try:
        _codec("msgpack", _pick_type(reader)).decode(reader.rest())
    except CodecError:
        pass


@target()
def cbor_codec(data: bytes) -> None:
    from rosgate.errors import CodecError

    reader = Reader(data)
    try:
        _codec("cbor", _pick_type(reader)).decode(reader.rest())
    except CodecError:
        pass


@target()
def cdr_check(data: bytes) -> None:
    """Raw CDR that no cipher authenticated, checked by the quick look (rosgate.cdr) and, for
    what that is not sure of, by deserializing it (in C); what passes is a message every field
    of which can be read (walked as a tree: which also gives the fuzzer coverage to follow).
    A frame the quick look passes and rclpy cannot read is a finding."""
    from rclpy.serialization import deserialize_message
    from rosgate_message_tree import to_tree

    from rosgate.errors import CodecError

    reader = Reader(data)
    msg_type, payload = _pick_type(reader), reader.rest()
    try:
        _codec("cdr", msg_type)(payload)
    except CodecError:
        return
    to_tree(deserialize_message(payload, msg_type))
