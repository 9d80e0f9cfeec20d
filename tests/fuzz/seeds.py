"""Write the seed corpus of every fuzz target into tests/fuzz/corpus/<target>/ (committed):

    python tests/fuzz/seeds.py

Seeds are valid inputs (and a few near misses) of each decoder, so mutation starts from what a
real peer sends: envelopes of every flag, fragments of frames, length-prefixed streams, the
serial datagram vectors, a client's real hello, and each message type of the codec targets
encoded by its codec. Deterministic: running it again writes the same files.
"""

from __future__ import annotations

import hashlib
import json
import random
import shutil
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))

import targets

CORPUS = Path(__file__).parent / "corpus"
VECTORS = (Path(__file__).parents[2] / "plugins" / "mcu_cvra" / "tests" / "vectors"
           / "serial_datagram.txt")


def messages() -> list[tuple[int, object]]:
    """(index in targets.message_types(), a message) for every codec target's type."""
    import numpy
    from geometry_msgs.msg import Point32, PoseStamped, Twist, Vector3
    from nav_msgs.msg import OccupancyGrid, Odometry
    from nav_msgs.msg import Path as NavPath
    from rosgate_testing import sample
    from sensor_msgs.msg import LaserEcho, LaserScan, MultiEchoLaserScan, PointCloud2, PointField
    from std_msgs.msg import Header

    types = targets.message_types()
    made = [cls() for cls in types]  # every type with its defaults
    made += [sample(name) for name in ("Twist", "Image", "JointState", "NavSatFix", "CameraInfo",
                                       "ParameterValue", "String", "Float64MultiArray", "Time")]
    stamp = Header(frame_id="base_link")
    made += [
        Twist(linear=Vector3(x=1.5), angular=Vector3(z=-0.25)),
        PoseStamped(header=stamp),
        Odometry(header=stamp, child_frame_id="odom"),
        NavPath(header=stamp, poses=[PoseStamped(header=stamp) for _ in range(3)]),
        OccupancyGrid(data=[-1, 0, 100, 50] * 16),
        LaserScan(ranges=[float(i) for i in range(32)], intensities=[1.0] * 32),
        MultiEchoLaserScan(ranges=[LaserEcho(echoes=[1.0, 2.0])] * 3),
        PointCloud2(fields=[PointField(name=c, offset=4 * i, datatype=7, count=1)
                            for i, c in enumerate("xyz")], data=bytes(range(48)), width=4,
                    height=1, point_step=12, row_step=48),
    ]
    from geometry_msgs.msg import PolygonStamped
    polygon = PolygonStamped()
    polygon.polygon.points = [Point32(x=1.0, y=2.0, z=3.0)] * 4
    made.append(polygon)
    numpy.random.seed(0)
    return [(types.index(type(m)), m) for m in made]


def write(target: str, seeds: list[bytes]) -> None:
    directory = CORPUS / target
    shutil.rmtree(directory, ignore_errors=True)
    directory.mkdir(parents=True)
    for seed in seeds:
        name = hashlib.sha1(seed).hexdigest()[:16]
        (directory / name).write_bytes(seed)


def main() -> None:
    from rclpy.serialization import serialize_message
    from rosgate_codec_cbor import CborCodec
    from rosgate_codec_msgpack import MsgpackCodec
    from rosgate_mcu_cvra import serial_datagram

    from rosgate.builtin import fragment
    from rosgate.config import TopicConfig, topic_to_mapping
    from rosgate.roles.mainline import control
    from rosgate.streamlink.link import length_prefixed
    from rosgate.wire import envelope, names

    rng = random.Random(10)
    pack = envelope.pack

    # the envelope: headers of every flag, then (epoch, width, seq, flip) runs for the window
    windows = [bytes([0]) + b"".join(bytes([1, 2]) + i.to_bytes(2, "big") + b"\x00"
                                      for i in range(1, 40)),
               bytes([1, 3, 8]) + (2**63).to_bytes(8, "big") + b"\x00" + bytes([3, 1, 5, 0])]
    write("envelope", [pack(flags, 7, 1, 2, 3) for flags in (0, 1, 2, 4, 8, 24)] + windows)

    # fragments: a frame cut by the link (kind 0), and raw datagrams (kind 1)
    frame = pack(0, 7, 1, 1, 0) + rng.randbytes(300)
    cut = bytes([0, 1]) + len(frame).to_bytes(2, "big") + frame + bytes([64]) + \
        (7).to_bytes(4, "big") + (1).to_bytes(4, "big") + bytes(range(1, 40))
    pieces = fragment(frame, 100, 7, 9)
    raw = b"".join(bytes([1, 2, len(p) - 1]) + p for p in pieces)
    write("reassembly", [cut, raw, raw + cut])

    # streams: a limit, then length-prefixed frames cut into pieces
    stream = b"".join(length_prefixed(pack(0, 7, 1, i, 0) + b"x" * i)
                      for i in range(5))
    write("stream_framing", [b"\x01\x00" + bytes([len(stream) // 4]) + stream,
                             b"\x00\x10" + b"\x03" + b"\xff\xff\xff\xff" * 4])

    # serial datagrams: the shared vectors, and a CVRA request
    frames = []
    for line in VECTORS.read_text().splitlines():
        if "->" in line and not line.startswith("#"):
            frames.append(bytes.fromhex(line.split("->")[1].strip()))
    request = names.pack_name("ping") + MsgpackCodec(targets.message_types()[-2], {}).encode(
        targets.message_types()[-2](data=True))
    write("serial_datagram", [b"\x01\x00\x10" + f for f in frames] +
          [b"\x00\x80\x40" + serial_datagram.encode(request) * 3])

    # the main line: a real hello (topics and services as a client sends them), and the others
    topics = [topic_to_mapping(TopicConfig(topic=f"/t{i}", type="std_msgs/msg/String",
                                           direction="transmit", remote=f"/r{i}", port=12000 + i,
                                           qos=qos, max_rate=rate))
              for i, (qos, rate) in enumerate([(10, None), ("sensor_data", 20.0),
                                               ({"reliability": "best_effort", "depth": 5},
                                                None)])]
    services = [{"service": "/ping", "type": "std_srvs/srv/Trigger", "direction": "receive",
                 "timeout": 2.5}]
    hello = {"type": "hello", "protocol": 1, "name": "robot1", "topics": topics,
             "services": services}
    bodies = [json.dumps(m).encode() for m in (
        hello, {"type": "ping"}, {"type": "bye"},
        {"type": "welcome", "name": "base", "session": 1, "token": "00" * 16,
         "topic_ids": [1, 2, 3], "service_ids": [4]},
        {"type": "refused", "error": "no"})]
    write("control_message", bodies)
    write("control_depth", bodies + [b"[" * 31 + b"]" * 31, b'{"a": "[[[["}'])
    assert control(hello)[envelope.SIZE:] == bodies[0].replace(b" ", b"")  # same JSON, compact

    # codecs: each message type, encoded (first byte: its index in targets.message_types())
    msgpack_seeds, cbor_seeds, cdr_seeds, cvra_seeds = [], [], [], []
    for index, message in messages():
        kind = type(message)
        msgpack_seeds.append(bytes([index]) + MsgpackCodec(kind, {}).encode(message))
        cbor_seeds.append(bytes([index]) + CborCodec(kind, {}).encode(message))
        cdr_seeds.append(bytes([index]) + serialize_message(message))
        cvra_seeds.append(names.pack_name("x" * index)  # the name's length picks the type
                          + MsgpackCodec(kind, {}).encode(message))
    write("msgpack_codec", msgpack_seeds)
    write("cbor_codec", cbor_seeds)
    write("cdr_check", cdr_seeds)
    write("cvra_name_and_map", cvra_seeds)
    for name in targets.TARGETS:
        assert (CORPUS / name).is_dir(), f"no seeds for {name}"


if __name__ == "__main__":
    main()
