"""The conformance suite of codecs, and the sample messages that hold every field kind."""

from __future__ import annotations

import functools
import itertools
import random
from collections.abc import Callable, Mapping
from typing import Any, ClassVar

import pytest

from rosgate import Codec, CodecError
from rosgate.options import parse

from .helpers import assert_registered, mutations


@functools.cache
def samples() -> dict[str, Callable[[], Any]]:
    """Name -> a function making a fresh sample message. Together they hold every field kind of
    the installed std_msgs, geometry_msgs, sensor_msgs, builtin_interfaces, rcl_interfaces and
    rmw_dds_common: all integer widths, float32/64, bool, byte, char, string, bounded string,
    fixed arrays (float64[N], uint8[N]), bounded sequences (of messages), unbounded sequences of
    every basic type, of strings and of messages, nested messages, uint8[], time and duration.
    Kinds that no installed message declares are not covered: wstring, and fixed arrays or
    bounded sequences of other element types (rosidl's test_msgs has them; it is not packaged
    here). Values are extremes of their type and exactly representable (float32 fields hold
    float32 values), so equality after a round trip is exact.

    Built on first call: importing the kit imports no ROS package."""
    import math

    import numpy
    from builtin_interfaces.msg import Duration, Time
    from geometry_msgs.msg import PoseWithCovariance, Twist, Vector3
    from rcl_interfaces.msg import FloatingPointRange, ParameterDescriptor, ParameterValue
    from rmw_dds_common.msg import Gid, NodeEntitiesInfo
    from sensor_msgs.msg import (
        CameraInfo,
        Image,
        JointState,
        NavSatFix,
        NavSatStatus,
        RegionOfInterest,
    )
    from std_msgs import msg as std

    def layout() -> Any:
        return std.MultiArrayLayout(data_offset=1, dim=[
            std.MultiArrayDimension(label="rows", size=2, stride=6),
            std.MultiArrayDimension(label="cols", size=3, stride=3)])

    stamp = Time(sec=-(2**31), nanosec=999_999_999)
    return {
        "Int8": lambda: std.Int8(data=-128), "UInt8": lambda: std.UInt8(data=255),
        "Int16": lambda: std.Int16(data=-(2**15)), "UInt16": lambda: std.UInt16(data=2**16 - 1),
        "Int32": lambda: std.Int32(data=-(2**31)), "UInt32": lambda: std.UInt32(data=2**32 - 1),
        "Int64": lambda: std.Int64(data=-(2**63)), "UInt64": lambda: std.UInt64(data=2**64 - 1),
        "Float32": lambda: std.Float32(data=-(2.0**100)),
        "Float64": lambda: std.Float64(data=math.pi),
        "Float64-inf": lambda: std.Float64(data=-math.inf),
        "Bool": lambda: std.Bool(data=True),
        "Byte": lambda: std.Byte(data=b"\xff"),
        "Char": lambda: std.Char(data=255),
        "String": lambda: std.String(data="héllo, wörld ✓ 日本"),
        "String-empty": lambda: std.String(data=""),
        "Empty": lambda: std.Empty(),
        "Time": lambda: stamp,
        "Duration": lambda: Duration(sec=2**31 - 1, nanosec=1),
        "ByteMultiArray": lambda: std.ByteMultiArray(layout=layout(),
                                                     data=[b"\x00", b"\xff", b"\x7f"]),
        "UInt8MultiArray": lambda: std.UInt8MultiArray(data=bytes(range(256))),
        "Int8MultiArray": lambda: std.Int8MultiArray(data=[-128, 0, 127]),
        "UInt16MultiArray": lambda: std.UInt16MultiArray(data=[0, 65535]),
        "Int32MultiArray": lambda: std.Int32MultiArray(layout=layout(), data=[-(2**31), 2**31 - 1]),
        "UInt64MultiArray": lambda: std.UInt64MultiArray(data=[0, 2**64 - 1]),
        "Float32MultiArray": lambda: std.Float32MultiArray(layout=layout(),
                                                           data=[0.5, -1.25, 3e38, -math.inf]),
        "Float64MultiArray": lambda: std.Float64MultiArray(data=[1e-300, -1e300, 0.1]),
        "Twist": lambda: Twist(linear=Vector3(x=1.0, y=-2.5, z=1e-9), angular=Vector3(z=0.25)),
        "PoseWithCovariance": lambda: PoseWithCovariance(
            covariance=numpy.arange(36, dtype=numpy.float64) / 7),
        "Image": lambda: Image(header=std.Header(stamp=stamp, frame_id="camera"), height=64,
                               width=256, encoding="mono8", is_bigendian=1, step=256,
                               data=random.Random(1).randbytes(64 * 256)),
        "JointState": lambda: JointState(name=["shoulder", "elbow", ""], position=[0.1, -0.2, 0.0],
                                         velocity=[1.0, 2.0, 3.0], effort=[]),
        "NavSatFix": lambda: NavSatFix(
            status=NavSatStatus(status=-1, service=NavSatStatus.SERVICE_GALILEO),
            latitude=48.8584, longitude=2.2945, altitude=-35.5,
            position_covariance=numpy.linspace(0.0, 8.0, 9), position_covariance_type=2),
        "CameraInfo": lambda: CameraInfo(
            height=480, width=640, distortion_model="plumb_bob", d=[0.1, -0.2, 0.0, 0.0, 0.05],
            k=numpy.linspace(1.0, 9.0, 9), r=numpy.eye(3).ravel(), p=numpy.linspace(0.0, 1.1, 12),
            binning_x=2, roi=RegionOfInterest(x_offset=1, width=10, do_rectify=True)),
        "ParameterValue": lambda: ParameterValue(
            type=9, bool_value=True, integer_value=-(2**63), double_value=0.5, string_value="v",
            byte_array_value=[b"\x01", b"\x00"], bool_array_value=[True, False, True],
            integer_array_value=[2**63 - 1, -1], double_array_value=[1.5],
            string_array_value=["a", "", "ü"]),
        "ParameterDescriptor": lambda: ParameterDescriptor(
            name="gain", floating_point_range=[FloatingPointRange(from_value=-1.0, step=0.5)]),
        "NodeEntitiesInfo": lambda: NodeEntitiesInfo(
            node_namespace="/", node_name="n" * 256,
            reader_gid_seq=[Gid(data=numpy.arange(16, dtype=numpy.uint8))]),
    }


def sample(name: str) -> Any:
    """A fresh sample message of :func:`samples`."""
    return samples()[name]()


class CodecConformance:
    """The conformance suite of a codec. Set :attr:`codec` (and :attr:`options`)."""

    #: the Codec subclass under test
    codec: ClassVar[type[Codec]]
    options: ClassVar[Mapping[str, Any]] = {}
    #: garbage inputs tried per sample message type (random bytes and damaged encodings)
    fuzz_inputs: ClassVar[int] = 400

    def make(self, msg_type: type) -> Codec:
        """An instance for ``msg_type``, made from :attr:`options` as the core makes it."""
        return self.codec(msg_type, parse(self.codec, self.options))

    def wire(self, message: Any) -> Any:
        """What ``encode`` takes: the message, or its serialized CDR for a raw codec."""
        if not self.codec.raw:
            return message
        from rclpy.serialization import serialize_message

        return serialize_message(message)

    def test_found_through_its_entry_point(self) -> None:
        assert_registered("codec", self.codec)

    def pytest_generate_tests(self, metafunc: pytest.Metafunc) -> None:
        if "sample_name" in metafunc.fixturenames:
            metafunc.parametrize("sample_name", list(samples()))

    def test_round_trip(self, sample_name: str) -> None:
        message = sample(sample_name)
        codec = self.make(type(message))
        given = self.wire(message)
        data = codec.encode(given)
        assert isinstance(data, bytes)
        decoded = codec.decode(data)
        if self.codec.raw:
            from rclpy.serialization import deserialize_message

            # byte for byte what was given (serializing twice may differ in padding bytes)
            assert decoded == given
            assert deserialize_message(decoded, type(message)) == message
            return
        assert type(decoded) is type(message)
        assert decoded == message
        assert codec.encode(decoded) == data  # the same message, the same bytes

    @pytest.mark.parametrize("field, value", [("x", "fast"), ("y", None), ("z", [1.0])])
    def test_a_field_holding_the_wrong_kind_of_value_is_a_codec_error(self, field: str,
                                                                        value: Any) -> None:
        """rclpy checks what is assigned to a field only with ROS_PYTHON_CHECK_FIELDS=1: without
        it a float64 field can hold a string, and encode must refuse it with CodecError, never
        write it. (A raw codec takes CDR, which rclpy wrote: it cannot be given one.)"""
        if self.codec.raw:
            pytest.skip("a raw codec is given serialized CDR, not a message")
        message = sample("Twist")
        setattr(message.linear, f"_{field}", value)  # past rclpy's field check, as unchecked
        with pytest.raises(CodecError):
            self.make(type(message)).encode(message)

    def test_empty_input_is_a_codec_error(self) -> None:
        with pytest.raises(CodecError):
            self.make(type(sample("Twist"))).decode(b"")

    def test_garbage_is_a_codec_error_and_nothing_else(self) -> None:
        """Seeded: random bytes and damaged valid encodings. Each either decodes to a value of
        the right kind, which encodes again, or raises CodecError; any other exception fails,
        showing the input."""
        rng = random.Random(20240601)
        for name in ("Twist", "JointState", "NavSatFix", "ParameterValue", "NodeEntitiesInfo",
                     "Float32MultiArray", "String"):
            message = sample(name)
            codec = self.make(type(message))
            valid = codec.encode(self.wire(message))
            inputs = itertools.chain(
                (rng.randbytes(rng.randrange(64)) for _ in range(self.fuzz_inputs // 2)),
                mutations(valid, rng, self.fuzz_inputs // 2))
            for data in inputs:
                try:
                    result = codec.decode(data)
                except CodecError:
                    continue
                except Exception as exc:  # the point of the test: report, do not propagate
                    pytest.fail(f"{name}: decode({data!r}) raised {type(exc).__name__}: {exc}")
                expected = bytes if self.codec.raw else type(message)
                assert isinstance(result, expected), f"{name}: decode({data!r}) -> {result!r}"
                codec.encode(result)  # what decode accepts is a message the codec can send on
