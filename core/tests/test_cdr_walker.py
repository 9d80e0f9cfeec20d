"""The quick CDR look (rosgate.cdr) against the middleware's own deserializer, on random messages
of many types and on thousands of damaged copies of them.

What must hold: every message rclpy serializes is well-formed to the walker (else the quick
look never saves anything), and whatever the walker calls well-formed, ``rmw_deserialize``
accepts (else a damaged or forged frame would reach subscribers without the real check)."""

from __future__ import annotations

import importlib
import random
import struct
from typing import Any

import pytest
from rclpy.serialization import serialize_message
from rosidl_parser import definition as idl

from rosgate.cdr import walker
from rosgate.errors import CodecError
from rosgate.ros import _RmwChecker

TYPES = [
    "std_msgs/String", "std_msgs/Bool", "std_msgs/Header", "std_msgs/Float64MultiArray",
    "std_msgs/UInt8MultiArray", "std_msgs/Int8", "std_msgs/Empty", "builtin_interfaces/Time",
    "sensor_msgs/Image", "sensor_msgs/CompressedImage", "sensor_msgs/PointCloud2",
    "sensor_msgs/JointState", "sensor_msgs/Imu", "sensor_msgs/LaserScan", "sensor_msgs/NavSatFix",
    "sensor_msgs/BatteryState", "geometry_msgs/Twist", "geometry_msgs/PoseStamped",
    "geometry_msgs/PoseWithCovarianceStamped", "nav_msgs/Odometry", "nav_msgs/OccupancyGrid",
    "nav_msgs/Path", "rcl_interfaces/ParameterValue", "rcl_interfaces/Log",
]
# types with fields the walker leaves to the middleware (bounded sequences)
UNJUDGED = ["rcl_interfaces/ParameterDescriptor"]

_INTS = {"octet": (0, 255), "uint8": (0, 255), "int8": (-128, 127), "uint16": (0, 65535),
         "int16": (-32768, 32767), "uint32": (0, 2**32 - 1), "int32": (-2**31, 2**31 - 1),
         "uint64": (0, 2**64 - 1), "int64": (-2**63, 2**63 - 1)}


def load(name: str) -> type:
    package, kind = name.split("/")
    return getattr(importlib.import_module(f"{package}.msg"), kind)


def value(t: idl.AbstractType, rng: random.Random) -> Any:
    if isinstance(t, idl.BasicType):
        if t.typename == "boolean":
            return rng.random() < 0.5
        if t.typename in _INTS:
            low, high = _INTS[t.typename]
            return rng.choice([low, high, 0, rng.randint(low, high)])
        if t.typename in ("float", "double"):
            return rng.choice([0.0, -1.5, rng.uniform(-1e6, 1e6)])
        raise LookupError(t.typename)
    if isinstance(t, idl.UnboundedString):
        return "".join(rng.choice("abcxyz/_é") for _ in range(rng.choice([0, 1, 3, 7, 20])))
    if isinstance(t, idl.NamespacedType):
        return message(getattr(importlib.import_module(".".join(t.namespaces)), t.name), rng)
    if isinstance(t, idl.Array):
        return [value(t.value_type, rng) for _ in range(t.size)]
    if isinstance(t, idl.UnboundedSequence):
        n = rng.choice([0, 0, 1, 2, 5])
        vt = t.value_type
        if isinstance(vt, idl.BasicType) and vt.typename in ("uint8", "octet"):
            data = rng.randbytes(rng.choice([0, 1, 13, 64]))
            return list(data) if vt.typename == "uint8" else [bytes([b]) for b in data]
        return [value(vt, rng) for _ in range(n)]
    raise LookupError(type(t).__name__)


def message(msg_type: type, rng: random.Random) -> Any:
    msg = msg_type()
    for name, t in zip(msg_type.get_fields_and_field_types(), msg_type.SLOT_TYPES, strict=True):
        try:
            setattr(msg, name, value(t, rng))
        except LookupError:
            pass  # a kind this filler does not make (char, bounded): the default stays
    return msg


def accepted(checker: _RmwChecker, data: bytes) -> bool:
    try:
        checker.check(data)
    except CodecError:
        return False
    return True


def damaged(data: bytes, rng: random.Random) -> bytes:
    """One of the ways bytes go wrong on a link, or are made to."""
    b = bytearray(data)
    kind = rng.randrange(8)
    if kind == 0 and b:  # one byte changed
        b[rng.randrange(len(b))] = rng.randrange(256)
    elif kind == 1:  # cut short
        del b[rng.randrange(len(b) + 1):]
    elif kind == 2 and len(b) >= 8:  # a length or count replaced
        at = 4 + 4 * rng.randrange((len(b) - 4) // 4)
        old = struct.unpack_from("<I", b, at)[0]
        struct.pack_into("<I", b, at, rng.choice([0, 1, 2, 7, 255, 2**16, 2**31, 2**32 - 1,
                                                  (old + 1) % 2**32]))
    elif kind == 3:  # bytes inserted
        at = rng.randrange(len(b) + 1)
        b[at:at] = rng.randbytes(rng.choice([1, 3, 4, 8]))
    elif kind == 4 and len(b) > 4:  # bytes taken out
        at = rng.randrange(4, len(b))
        del b[at:at + rng.choice([1, 3, 4, 8])]
    elif kind == 5:  # the other byte order, or another encapsulation
        b[:2] = rng.choice([b"\x00\x00", b"\x00\x02", b"\x00\x03", b"\x01\x01", b"\x00\x06"])
    elif kind == 6 and b:  # a byte set to 2 (a bool that is neither)
        b[rng.randrange(len(b))] = 2
    else:  # garbage at the end
        b += rng.randbytes(rng.choice([1, 4, 9]))
    return bytes(b)


@pytest.mark.parametrize("name", TYPES)
def test_well_formed_to_the_walker_and_never_more_than_the_middleware(name):
    msg_type = load(name)
    quick = walker(msg_type)
    assert quick is not None, f"{name}: the walker should judge it"
    checker = _RmwChecker.make(msg_type)
    assert checker is not None
    rng = random.Random(name)
    said_yes_to_damage = 0
    for _ in range(40):
        data = serialize_message(message(msg_type, rng))
        assert accepted(checker, data)
        assert quick(data), f"{name}: a message rclpy serialized is not well-formed to the walker"
        assert quick(bytearray(data))
        for _ in range(60):
            bad = damaged(data, rng)
            if quick(bad):
                said_yes_to_damage += 1
                assert accepted(checker, bad), f"{name}: passed what rmw refuses: {bad!r}"
    # the damage is not all of a kind the walker cannot tell from a message
    assert said_yes_to_damage < 40 * 60


@pytest.mark.parametrize("name", UNJUDGED)
def test_what_it_does_not_judge_goes_to_the_middleware(name):
    assert walker(load(name)) is None


def test_big_endian_messages_are_read_in_their_order():
    from std_msgs.msg import UInt8MultiArray

    quick = walker(UInt8MultiArray)
    assert quick is not None
    # layout: dim[] (count 0), data_offset u32 = 0; data[] count 3 and three bytes; big endian
    data = b"\x00\x00\x00\x00" + b"\x00\x00\x00\x00" + b"\x00\x00\x00\x00" + b"\x00\x00\x00\x03abc"
    assert quick(data)
    assert not quick(data[:-1])
    assert not quick(b"\x00\x00\x00\x00" + b"\x00\x00\x00\x00" * 2 + b"\x03\x00\x00\x00abc")


def test_strings_need_their_terminating_nul_and_bools_are_zero_or_one():
    from std_msgs.msg import Bool, String

    string, boolean = walker(String), walker(Bool)
    assert string is not None and boolean is not None
    assert string(b"\x00\x01\x00\x00\x03\x00\x00\x00ab\x00")
    assert not string(b"\x00\x01\x00\x00\x03\x00\x00\x00abc")  # no NUL: rmw decides
    assert not string(b"\x00\x01\x00\x00\x00\x00\x00\x00")  # length 0: rmw decides
    assert boolean(b"\x00\x01\x00\x00\x01") and boolean(b"\x00\x01\x00\x00\x00")
    assert not boolean(b"\x00\x01\x00\x00\x02")
    assert not boolean(b"\x00\x01\x00\x00")
