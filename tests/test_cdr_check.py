"""The CDR check of frames no cipher authenticated: the middleware's own deserializer, called
through ctypes, accepts exactly what rclpy's deserializer accepts, and says why it refuses."""

from __future__ import annotations

import random

import pytest
from rclpy.serialization import serialize_message
from sensor_msgs.msg import Image
from std_msgs.msg import String

from rosgate.errors import CodecError
from rosgate.ros import _RmwChecker, cdr_checker


def rclpy_check(msg_type: type):
    """The fallback: rclpy's deserializer."""
    from rclpy.serialization import deserialize_message

    def check(data: bytes) -> None:
        try:
            deserialize_message(data, msg_type)
        except Exception as exc:
            raise CodecError(str(exc)) from None
    return check


def verdict(check, data: bytes) -> bool:
    try:
        check(data)
    except CodecError:
        return False
    return True


def samples() -> list[tuple[type, bytes]]:
    rng = random.Random(1)
    image = Image(height=64, width=64, step=64, encoding="mono8", data=rng.randbytes(4096))
    good = [(String, serialize_message(String(data="x" * 2500))),
            (String, serialize_message(String(data=""))),
            (Image, serialize_message(image))]
    out = list(good)
    for msg_type, data in good:
        out += [(msg_type, data[:cut]) for cut in (0, 3, 4, 7, len(data) // 2, len(data) - 1)]
        out.append((msg_type, data[:8] + b"\xff" * (len(data) - 8)))
    out += [(Image, good[0][1]), (String, b"\x00\x01\x00\x00\xff\xff\xff\xff")]
    out += [(String, rng.randbytes(rng.randint(0, 64))) for _ in range(50)]
    return out


def test_the_slow_check_is_the_middlewares_deserializer():
    assert _RmwChecker.make(String) is not None
    # a type with fields the quick look (rosgate.cdr) does not judge goes to it directly
    from rcl_interfaces.msg import ParameterDescriptor

    assert isinstance(cdr_checker(ParameterDescriptor).__self__, _RmwChecker)


@pytest.mark.parametrize("msg_type, data", samples())
def test_the_fast_check_agrees_with_rclpy(msg_type, data):
    assert verdict(cdr_checker(msg_type), data) == verdict(rclpy_check(msg_type), data)


def test_valid_messages_pass_and_broken_ones_say_why(capfd):
    check = cdr_checker(String)
    data = serialize_message(String(data="hello"))
    check(data)
    for _ in range(3):
        with pytest.raises(CodecError, match="not a valid String"):
            check(data[:-3])
    check(data)  # a refusal leaves the checker usable
    # each refusal resets rcutils' error state: no "error state is being overwritten" on stderr
    assert "overwritten" not in capfd.readouterr().err
