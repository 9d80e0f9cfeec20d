"""rosgate_message_tree on its own: parsed trees (plain Python values, as any format's parser
returns them) to messages, strictly; a toy format for the writing side. The msgpack and cbor
codecs test the mapping byte for byte in their own formats."""

from __future__ import annotations

import struct

import numpy
import pytest
from geometry_msgs.msg import PoseWithCovariance, Twist
from rosgate_message_tree import TreeCodec, TreeError, WireFormat, message_tree, type_name
from sensor_msgs.msg import JointState
from std_msgs.msg import Float32

from rosgate import CodecError, OptionError

# A format that writes every part as a tagged, length-prefixed piece: enough to see the order
# and kind of what the mapping writes, without depending on a real format.
TOY = WireFormat(
    name="Toy", pack=lambda v: b"v" + repr(v).encode() + b";", float32_tag=ord("f"),
    float64_tag=ord("d"), array_header=lambda n: b"A%d;" % n, map_header=lambda n: b"M%d;" % n,
    bytes_header=lambda n: b"B%d;" % n, bytes_word="blob", str_word="text", nil_word="null")


def test_writing_follows_the_msg_field_order_and_float_widths():
    assert message_tree(Float32, TOY).encode(Float32(data=0.5)) == \
        b"M1;v'data';" + b"f" + struct.pack(">f", 0.5)
    data = message_tree(Twist, TOY).encode(Twist())
    assert data.startswith(b"M2;v'linear';M3;v'x';d") and data.count(b"d" + bytes(8)) == 6


def test_decoding_a_tree():
    state = message_tree(JointState, TOY).decode(
        {"name": ["a", "b"], "position": [1, 2.5], "header": {"frame_id": "f"}})
    expected = JointState(name=["a", "b"], position=[1.0, 2.5])
    expected.header.frame_id = "f"
    assert state == expected and type(state.position[0]) is float
    pose = message_tree(PoseWithCovariance, TOY).decode({"covariance": [0.5] * 36})
    assert isinstance(pose.covariance, numpy.ndarray) and pose.covariance[35] == 0.5


@pytest.mark.parametrize("tree, where, reason", [
    ({"name": ["a", 1]}, "name[1]", "expected string, got 1"),
    ({"header": {"stamp": {"sec": True}}}, "header.stamp.sec", "expected int32"),
    ({"position": [10**400]}, "position[0]", "expected double (a number)"),
    ({"bogus": 1}, "bogus", "unknown field of sensor_msgs/JointState"),
    ({"name": b"ab"}, "name", "got blob of 2 bytes"),
    ({"header": {"frame_id": None}}, "header.frame_id", "got null"),
])
def test_a_tree_that_does_not_fit_names_the_field(tree, where, reason):
    with pytest.raises(TreeError) as info:
        message_tree(JointState, TOY).decode(tree)
    assert info.value.where() == where
    assert reason in info.value.reason


def test_one_tree_per_message_class_and_format():
    assert message_tree(Twist, TOY) is message_tree(Twist, TOY)


def test_type_names_are_spelled_as_rosidl_does():
    assert [type_name(t) for t in PoseWithCovariance.SLOT_TYPES] == \
        ["geometry_msgs/Pose", "double[36]"]


class ToyCodec(TreeCodec):
    name = "toy"
    wire = TOY

    def parse(self, data: bytes):
        return {"data": float(data)}


def test_the_codec_base_checks_types_options_and_names_the_field():
    codec = ToyCodec(Float32, {})
    assert codec.decode(b"0.25") == Float32(data=0.25)
    with pytest.raises(CodecError, match=r"std_msgs/Float32: data: expected float \(within"):
        codec.decode(b"1e39")
    with pytest.raises(CodecError, match="expected a std_msgs/Float32 message, got Twist"):
        codec.encode(Twist())
    with pytest.raises(OptionError) as info:
        ToyCodec(Float32, {"fast": True})
    assert (info.value.key, info.value.message, info.value.fix) == (
        "fast", "unknown key 'fast'", "toy takes no options: remove it")
