"""The ROS ends of the constrained-link benchmark: a robot's publisher of several topics at
their own rates, and a base's subscriber that records every arrival.

``python constrained_ends.py pub SPEC`` / ``sub SPEC``, in the DDS domain of ``ROS_DOMAIN_ID``;
SPEC is JSON: ``[{"topic": "/camera", "kind": "image", "rate": 10, "size": 921600,
"reliable": false}, ...]``. Kinds: ``image`` (sensor_msgs/Image rgb8 of ``size`` bytes of
noise: what a camera's pixels are to a compressor), ``grid`` (nav_msgs/OccupancyGrid, a square
of ``size`` cells, 95 % unknown), ``twist`` (geometry_msgs/Twist), ``string``
(std_msgs/String of ``size`` bytes).

Each message carries its send time (wall clock, ns) and its number: images and grids in
``header.stamp`` and ``header.frame_id``, a Twist in ``angular.x`` (seconds) and ``angular.y``,
a String in its first 24 characters. One command per line on stdin, one JSON line back:

    pub: ``run SECONDS`` -> {"sent": {topic: n}}       publish every topic at its rate
         ``once``        -> {"sent": {topic: 1}}       one of each (a warm-up)
    sub: ``count``       -> {topic: n}                 arrivals so far
         ``dump FILE``   -> {"written": FILE}           every arrival: [arrival_ns, sent_ns, n]
    both: ``quit``
"""

from __future__ import annotations

import json
import os
import struct
import sys
import threading
import time
from array import array

from endpoints import answer, node  # bench/ is this script's folder, first on sys.path

STAMP = struct.Struct("<iI")  # header.stamp after the 4-byte CDR encapsulation


def qos(reliable: bool, depth: int = 10):
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(depth=depth, history=HistoryPolicy.KEEP_LAST,
                      reliability=ReliabilityPolicy.RELIABLE if reliable
                      else ReliabilityPolicy.BEST_EFFORT)


def msg_type(kind: str):
    if kind == "image":
        from sensor_msgs.msg import Image

        return Image
    if kind == "grid":
        from nav_msgs.msg import OccupancyGrid

        return OccupancyGrid
    if kind == "twist":
        from geometry_msgs.msg import Twist

        return Twist
    from std_msgs.msg import String

    return String


def read(kind: str, data: bytes) -> tuple[int, int]:
    """(send time in ns, number) of a message as it arrived (serialized)."""
    if kind in ("image", "grid"):
        sec, nsec = STAMP.unpack_from(data, 4)
        return sec * 1_000_000_000 + nsec, int(data[16:24], 16)
    if kind == "twist":
        seconds, n = struct.unpack_from("<dd", data, 28)
        return int(seconds * 1e9), int(n)
    return int(data[8:24], 16), int(data[24:32], 16)


class Stamped:
    """A topic's pre-serialized message, its stamp and number patched in per message (images
    and grids: a megabyte is not serialized again each time)."""

    def __init__(self, kind: str, size: int):
        from rclpy.serialization import serialize_message

        self.kind = kind
        self.msg_type = msg_type(kind)
        if kind == "image":
            Image = self.msg_type
            width = 640 if size == 921_600 else int((size / 3) ** 0.5)
            message = Image(height=size // (3 * width), width=width, encoding="rgb8",
                            step=3 * width, data=os.urandom(size))
        elif kind == "grid":
            message = self.msg_type()
            side = int(size ** 0.5)
            message.info.width = message.info.height = side
            message.info.resolution = 0.05
            cells = bytearray(b"\xff" * side * side)
            known = int((0.05 * side * side) ** 0.5)
            noise = os.urandom(known * known)
            for row in range(known):  # an explored room: free cells, a few walls
                start = (side // 3 + row) * side + side // 3
                cells[start:start + known] = bytes(100 if n < 8 else 0
                                                   for n in noise[row * known:(row + 1) * known])
            message.data = memoryview(cells).cast("b").tolist()
        elif kind == "twist":
            message = self.msg_type()
        else:
            message = self.msg_type(data="0" * 24 + "x" * max(0, size - 24))
        if kind in ("image", "grid"):
            message.header.frame_id = "00000000"
        self.template = bytearray(serialize_message(message))
        self.size = len(self.template)

    def make(self, n: int, ns: int) -> bytes:
        buf = self.template
        if self.kind in ("image", "grid"):
            STAMP.pack_into(buf, 4, ns // 1_000_000_000, ns % 1_000_000_000)
            buf[16:24] = b"%08x" % n
        elif self.kind == "twist":
            # linear (3 x f64) then angular: angular.x at 4 + 24, angular.y at 4 + 32
            struct.pack_into("<dd", buf, 28, ns / 1e9, float(n))
        else:
            buf[8:32] = b"%016x%08x" % (ns, n)
        return bytes(buf)


def run_publisher(spec: list[dict]) -> None:
    pub_node = node("constrained_pub")
    topics = [(t, Stamped(t["kind"], t["size"]),
               pub_node.create_publisher(msg_type(t["kind"]), t["topic"],
                                         qos(t["reliable"], 10 if t["reliable"] else 5)))
              for t in spec]
    answer({"ready": True})
    for line in sys.stdin:
        words = line.split()
        if words[:1] == ["run"]:
            answer({"sent": publish(topics, float(words[1]))})
        elif words[:1] == ["once"]:  # one message of every topic, numbered past any run's
            for _t, stamped, publisher in topics:
                publisher.publish(stamped.make(99_999_999, time.time_ns()))
            answer({"sent": {t["topic"]: 1 for t, _, _ in topics}})
        elif words[:1] == ["quit"]:
            return


def publish(topics, seconds: float) -> dict[str, int]:
    """Every topic at its rate for ``seconds``, on a common clock (a wake every millisecond
    sends what is due)."""
    sent = {t["topic"]: 0 for t, _, _ in topics}
    start = time.perf_counter()
    while True:
        now = time.perf_counter()
        if now - start >= seconds:
            break
        for t, stamped, publisher in topics:
            due = min(int((now - start) * t["rate"]) + 1, int(seconds * t["rate"]))
            while sent[t["topic"]] < due:
                publisher.publish(stamped.make(sent[t["topic"]], time.time_ns()))
                sent[t["topic"]] += 1
        time.sleep(0.001)
    return sent


def run_subscriber(spec: list[dict]) -> None:
    from rclpy.experimental import EventsExecutor

    sub_node = node("constrained_sub")
    arrivals: dict[str, array] = {}
    for t in spec:
        record = arrivals[t["topic"]] = array("q")

        def on_message(data: bytes, kind=t["kind"], record=record) -> None:
            now = time.time_ns()
            sent, n = read(kind, data)
            record.extend((now, sent, n))

        sub_node.create_subscription(msg_type(t["kind"]), t["topic"], on_message,
                                     qos(t["reliable"], 100), raw=True)
    executor = EventsExecutor()
    executor.add_node(sub_node)
    done = threading.Event()

    def serve() -> None:
        for line in sys.stdin:
            words = line.split()
            if words[:1] == ["count"]:
                answer({topic: len(record) // 3 for topic, record in arrivals.items()})
            elif words[:1] == ["dump"]:
                with open(words[1], "w") as out:
                    json.dump({topic: [list(record[i:i + 3]) for i in range(0, len(record), 3)]
                               for topic, record in arrivals.items()}, out)
                answer({"written": words[1]})
            elif words[:1] == ["quit"]:
                break
        done.set()

    threading.Thread(target=serve, daemon=True).start()
    answer({"ready": True})
    while not done.is_set():  # spin_once in a loop: EventsExecutor.spin() hangs (DESIGN.md)
        executor.spin_once(timeout_sec=0.1)


def main() -> None:
    role, spec = sys.argv[1], json.loads(sys.argv[2])
    {"pub": run_publisher, "sub": run_subscriber}[role](spec)


if __name__ == "__main__":
    main()
