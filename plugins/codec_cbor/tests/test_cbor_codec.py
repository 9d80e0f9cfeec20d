"""The cbor codec: the kit's conformance suite, exact CBOR bytes, strict reading of what
cbor2 would accept but a ROS message cannot hold, and the same trees as msgpack."""

from __future__ import annotations

import struct
import time

import cbor2
import msgpack
import pytest
from geometry_msgs.msg import Point32, Twist, Vector3
from rosgate_codec_cbor import CborCodec
from rosgate_codec_msgpack import MsgpackCodec
from rosgate_testing import CodecConformance, sample, samples
from sensor_msgs.msg import Image
from std_msgs.msg import Float32, Float32MultiArray, String, UInt64

import rosgate


class TestCborConformance(CodecConformance):
    codec = CborCodec


def codec(msg_type: type) -> CborCodec:
    return CborCodec(msg_type, {})


def test_string_is_exactly_a_cbor_map():
    assert codec(String).encode(String(data="hi")) == b"\xa1\x64data\x62hi"
    assert codec(String).encode(String(data="hi")) == cbor2.dumps({"data": "hi"})


def test_float32_fields_are_single_precision_and_float64_double():
    assert codec(Float32).encode(Float32(data=0.5)) == b"\xa1\x64data\xfa" + struct.pack(">f", 0.5)
    assert codec(Point32).encode(Point32(x=1.5)) == (
        b"\xa3" + b"".join(cbor2.dumps(k) + b"\xfa" + struct.pack(">f", v)
                           for k, v in [("x", 1.5), ("y", 0.0), ("z", 0.0)]))
    twist = Twist(linear=Vector3(x=1.0))
    assert codec(Twist).encode(twist) == cbor2.dumps({"linear": {"x": 1.0, "y": 0.0, "z": 0.0},
                                                      "angular": {"x": 0.0, "y": 0.0, "z": 0.0}})
    data = codec(Float32MultiArray).encode(Float32MultiArray(data=[0.5, -2.0]))
    assert data.endswith(b"\x64data\x82\xfa" + struct.pack(">f", 0.5)
                         + b"\xfa" + struct.pack(">f", -2.0))


def test_integers_take_their_smallest_encoding():
    assert codec(UInt64).encode(UInt64(data=23)) == b"\xa1\x64data\x17"
    assert codec(UInt64).encode(UInt64(data=2**64 - 1)) == b"\xa1\x64data\x1b" + b"\xff" * 8


@pytest.mark.parametrize("size, head", [(0, b"\x40"), (23, b"\x57"), (24, b"\x58\x18"),
                                        (256, b"\x59\x01\x00"), (70_000, b"\x5a\x00\x01\x11\x70")])
def test_uint8_arrays_are_byte_strings(size, head):
    pixels = bytes(range(256)) * (size // 256) + bytes(size % 256)
    data = codec(Image).encode(Image(data=pixels))
    assert head + pixels in data
    assert cbor2.loads(data)["data"] == pixels


@pytest.mark.parametrize("name", ["Twist", "NavSatFix", "ParameterValue", "CameraInfo", "Image"])
def test_the_same_tree_as_msgpack(name):
    message = sample(name)
    as_cbor = cbor2.loads(codec(type(message)).encode(message))
    as_msgpack = msgpack.unpackb(MsgpackCodec(type(message), {}).encode(message))
    assert as_cbor == as_msgpack


@pytest.mark.parametrize("data, match", [
    (cbor2.dumps({"data": "hi"}) + b"\x00", "1 bytes after it"),
    (b"\xa1\x01\x02", "not one CBOR data item"),                                  # an int key
    (b"\xa2\x64data\x61a\x64data\x61b", "Duplicate map key"),
    (b"\xa1\x64data\xc1\x1a\x00\x00\x00\x00", "tag 1: a tag"),  # a date: no tag is read
    (b"\xa1\x64data\x43abc", "data: expected string, got a byte string of 3 bytes"),
    (b"\xa1\x64data\xf6", "data: expected string, got null"),
    (b"\xa1\x64data\x7a\xff\xff\xff\xff", "not one CBOR data item"),              # forged length
    (b"\x81" * 100 + b"\x00", "not one CBOR data item"),                          # too deep
])
def test_what_a_string_cannot_be(data, match):
    with pytest.raises(rosgate.CodecError, match=match):
        codec(String).decode(data)


def test_a_bignum_where_a_double_belongs_is_refused():
    bignum = b"\xc2\x58\x80" + b"\xff" * 128  # tag 2: a 1024-bit integer
    with pytest.raises(rosgate.CodecError, match="semantic tag 2: a tag"):
        codec(Twist).decode(b"\xa1\x66linear\xa1\x61x" + bignum)


def test_half_precision_and_integers_are_taken_for_floats():
    twist = codec(Twist).decode(b"\xa1\x66linear\xa2\x61x\xf9\x3e\x00\x61y\x02")
    assert (twist.linear.x, twist.linear.y) == (1.5, 2.0)


def test_unknown_option_is_an_option_error():
    with pytest.raises(rosgate.OptionError) as info:
        CborCodec(String, {"canonical": True})
    assert (info.value.key, info.value.message, info.value.fix) == (
        "canonical", "unknown key 'canonical'", "cbor takes no options: remove it")


def test_samples_cover_the_field_kinds():
    assert {"NavSatFix", "CameraInfo", "ParameterValue", "NodeEntitiesInfo"} <= set(samples())


# -- decoder bombs (issue 10, attack 7) -----------------------------------------------------------

def test_no_tag_is_decoded_whatever_its_number():
    refused = []
    for tag in [*range(70_000), 2**32, 2**63, 2**64 - 1]:
        with pytest.raises(rosgate.CodecError, match="tag"):
            codec(String).decode(cbor2.dumps(cbor2.CBORTag(tag, "x")))
        refused.append(tag)
    assert len(refused) == 70_003


def test_shared_references_are_refused_at_once():
    """Before: these 24,027 bytes (one LaserEcho of 6,000 numbers, shared with tag 28 and
    referenced 6,000 times with tag 29) decoded into 36 million floats: 2.65 s, +136 MB."""
    from sensor_msgs.msg import MultiEchoLaserScan

    bomb = cbor2.dumps({"ranges": [{"echoes": [0] * 6000}] * 6000}, value_sharing=True)
    assert len(bomb) == 24_027
    start = time.thread_time()
    with pytest.raises(rosgate.CodecError, match="tag"):
        codec(MultiEchoLaserScan).decode(bomb)
    assert time.thread_time() - start < 0.1


@pytest.mark.parametrize("item", [b"\x80", b"\xa0", b"\x81\x80"])
def test_many_empty_containers_are_over_budget(item):
    count = 4_000_000 // len(item)
    data = b"\x9a" + count.to_bytes(4, "big") + item * count
    start = time.thread_time()
    with pytest.raises(rosgate.CodecError, match="arrays and maps in"):
        codec(String).decode(data)
    assert time.thread_time() - start < 1.0


def test_big_messages_within_budget_still_decode():
    from sensor_msgs.msg import LaserScan, PointCloud2, PointField

    scan = LaserScan(ranges=[float(i) for i in range(100_000)], intensities=[1.0] * 100_000)
    assert codec(LaserScan).decode(codec(LaserScan).encode(scan)).ranges[99_999] == 99_999.0
    cloud = PointCloud2(fields=[PointField(name=c, offset=4 * i, datatype=7, count=1)
                                for i, c in enumerate("xyz")] * 300, data=bytes(1 << 20))
    again = codec(PointCloud2).decode(codec(PointCloud2).encode(cloud))
    assert len(again.fields) == 900 and len(again.data) == 1 << 20


@pytest.mark.parametrize("data", [
    b"\x9b" + (2**63).to_bytes(8, "big") + b"\x00",   # an array longer than the input
    b"\x5b" + (2**63).to_bytes(8, "big") + b"\x00" * 2000,  # a byte string likewise
    b"\x9f" + b"\x00" * 2000 + b"\xff",               # indefinite length
    b"\x82" + b"\x00" * 2000,                          # trailing bytes after a whole item
])
def test_the_walk_refuses_what_the_decoder_would(data):
    with pytest.raises(rosgate.CodecError):
        codec(String).decode(data)
