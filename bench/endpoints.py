"""The two ROS ends of a benchmark: a paced publisher and a counting subscriber.

Each runs as a process of its own (``python endpoints.py pub|sub KIND SIZE DEPTH [RELIABILITY]``),
in the DDS domain given by ``ROS_DOMAIN_ID``, and takes one command per line on stdin, answering
one JSON line on stdout:

    pub: ``run TRIAL RATE SECONDS``  -> {"sent": n, "seconds": s, "end_ns": t, "tail_ns": t}
                                        publish at a steady rate; end_ns: wall clock after the
                                        last one; tail_ns: where the trial's last quarter began
    sub: ``stats TRIAL [DEADLINE_NS [TAIL_NS END_NS]]`` -> {"received": n, "in_time": n,
                                          "p50_us": .., "p90_us": .., "p99_us": ..,
                                          "p99_settled_us": .., "tail": n, "tail_fresh": n}
                                        in_time: how many arrived by the deadline;
                                        settled: of those sent in the trial's second half;
                                        tail: how many arrived between TAIL_NS and END_NS,
                                        tail_fresh: ... of them sent since TAIL_NS
         ``total``                   -> {"received": n}   everything so far (for draining)
    both: ``quit``

Every message carries its send time (ns, wall clock) and its trial number, so the subscriber
sorts arrivals by trial and a late message of one trial never counts for the next. All
processes share one machine, so wall clocks agree.

Both ends work on serialized CDR only (pre-serialized ``publish(bytes)``, ``raw=True``
subscription) so that neither is the bottleneck of what is measured.
"""

from __future__ import annotations

import bisect
import json
import struct
import sys
import threading
import time
from array import array
from collections import defaultdict

TOPIC = "/bench"
KINDS = ("string", "image")


# -- payloads: a serialized template whose stamp and trial bytes are patched per message ------
class StringPayload:
    """std_msgs/String of ``size`` bytes of data: 16 hex digits of stamp, 8 of trial, padding.

    CDR: 4-byte encapsulation header, u32 length, then the characters (so the data starts at 8).
    """

    STAMP, TRIAL = 8, 24

    def __init__(self, size: int):
        from std_msgs.msg import String

        self.msg_type = String
        self.template = self._serialize(String(data="0" * 24 + "x" * (size - 24)))

    def stamp(self, buf: bytearray, ns: int) -> None:
        buf[self.STAMP:self.STAMP + 16] = b"%016x" % ns

    def trial(self, buf: bytearray, trial: int) -> None:
        buf[self.TRIAL:self.TRIAL + 8] = b"%08x" % trial

    def read(self, data: bytes) -> tuple[int, int]:
        return int(data[8:24], 16), int(data[24:32], 16)

    @staticmethod
    def _serialize(message) -> bytearray:
        from rclpy.serialization import serialize_message

        data = bytearray(serialize_message(message))
        assert data[:2] == b"\x00\x01", "expected little-endian CDR"
        return data


class ImagePayload(StringPayload):
    """sensor_msgs/Image, mono8, ``size`` bytes of pixels: the header stamp is the send time,
    the frame_id (8 hex digits) the trial.

    CDR: encapsulation (4), stamp.sec i32 (4..8), stamp.nanosec u32 (8..12), frame_id length
    (12..16), frame_id characters (16..24)."""

    STAMP_FIELDS = struct.Struct("<iI")

    def __init__(self, size: int):
        from sensor_msgs.msg import Image

        self.msg_type = Image
        side = int(size ** 0.5)
        image = Image(height=size // side, width=side, encoding="mono8", step=side)
        image.header.frame_id = "0" * 8
        image.data = (bytes(range(256)) * (image.height * side // 256)
                      + bytes(image.height * side % 256))
        self.template = self._serialize(image)

    def stamp(self, buf: bytearray, ns: int) -> None:
        self.STAMP_FIELDS.pack_into(buf, 4, ns // 1_000_000_000, ns % 1_000_000_000)

    def trial(self, buf: bytearray, trial: int) -> None:
        buf[16:24] = b"%08x" % trial

    def read(self, data: bytes) -> tuple[int, int]:
        sec, nsec = self.STAMP_FIELDS.unpack_from(data, 4)
        return sec * 1_000_000_000 + nsec, int(data[16:24], 16)


def payload(kind: str, size: int) -> StringPayload:
    return {"string": StringPayload, "image": ImagePayload}[kind](size)


def qos(depth: int, reliability: str = "reliable"):
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

    # deep: a shallow queue (e.g. sensor_data, depth 5) drops most of a burst; reliable unless
    # a best-effort trial asks otherwise (a reliable reader does not match a best-effort writer)
    return QoSProfile(depth=depth, history=HistoryPolicy.KEEP_LAST,
                      reliability=getattr(ReliabilityPolicy, reliability.upper()))


def node(name: str):
    import rclpy

    rclpy.init()
    return rclpy.create_node(name, start_parameter_services=False)


def answer(obj: dict) -> None:
    sys.stdout.write(json.dumps(obj) + "\n")
    sys.stdout.flush()


# -- publisher ------------------------------------------------------------------------------
def run_publisher(p: StringPayload, depth: int, reliability: str) -> None:
    publisher = node("bench_pub").create_publisher(p.msg_type, TOPIC, qos(depth, reliability))
    answer({"ready": True})
    for line in sys.stdin:
        words = line.split()
        if words[:1] == ["run"]:
            answer(publish_paced(publisher, p, int(words[1]), float(words[2]), float(words[3])))
        elif words[:1] == ["quit"]:
            return


TAIL = 0.25  # the trial's last quarter: whether what arrives of an overload is the newest


def publish_paced(publisher, p: StringPayload, trial: int, rate: float, seconds: float) -> dict:
    """Publish at a steady ``rate`` for ``seconds``.

    Sleeping once per message is too coarse above a few kHz, so the loop wakes about every
    half millisecond and sends whatever the schedule says is due by then: the offered load is
    steady at millisecond scale. When publishing itself cannot keep up, fewer are sent and the
    answer says so (the orchestrator then knows the publisher, not the path, was the limit)."""
    buf = bytearray(p.template)
    p.trial(buf, trial)
    publish, stamp, clock = publisher.publish, p.stamp, time.time_ns
    sent = 0
    start = time.perf_counter()
    end = start + seconds
    tail_ns = clock() + int((1 - TAIL) * seconds * 1e9)
    while True:
        now = time.perf_counter()
        if now >= end:
            break
        due = min(int((now - start) * rate) + 1, int(seconds * rate))
        while sent < due:
            stamp(buf, clock())
            publish(bytes(buf))
            sent += 1
        time.sleep(0.0005)
    return {"sent": sent, "seconds": time.perf_counter() - start, "end_ns": time.time_ns(),
            "tail_ns": tail_ns}


# -- subscriber -----------------------------------------------------------------------------
class Tally:
    """Arrivals per trial: when each came, and how long it took."""

    def __init__(self, p: StringPayload):
        self.read = p.read
        self.arrivals: dict[int, array] = defaultdict(lambda: array("q"))
        self.latencies: dict[int, array] = defaultdict(lambda: array("q"))
        self.total = 0

    def on_message(self, data: bytes) -> None:
        now = time.time_ns()
        stamp, trial = self.read(data)
        self.arrivals[trial].append(now)
        self.latencies[trial].append(now - stamp)
        self.total += 1

    def stats(self, trial: int, deadline_ns: int, tail_ns: int, end_ns: int) -> dict:
        arrivals = self.arrivals.get(trial, array("q"))
        waits = self.latencies.get(trial, array("q"))
        latencies = sorted(waits)
        pick = lambda q, of: of[min(len(of) - 1, int(q * len(of)))] / 1000 if of else None
        # what a path does once it has settled into an overload, its first reaction over:
        # the messages sent in the second half of the trial
        stamps = [at - wait for at, wait in zip(arrivals, waits, strict=True)]
        half = (min(stamps) + max(stamps)) / 2 if stamps else 0
        settled = sorted(w for stamp, w in zip(stamps, waits, strict=True) if stamp >= half)
        # arrivals are appended in time order, one callback after the other
        return {"received": len(arrivals), "in_time": bisect.bisect_right(arrivals, deadline_ns),
                "p50_us": pick(0.50, latencies), "p90_us": pick(0.90, latencies),
                "p99_us": pick(0.99, latencies), "p99_settled_us": pick(0.99, settled),
                # what arrived while the trial's last quarter was sent: how much of it was new
                **tail(arrivals, stamps, tail_ns, end_ns)}


def tail(arrivals, stamps, tail_ns: int, end_ns: int) -> dict:
    """How many arrived between ``tail_ns`` and ``end_ns``, and how many of those were sent
    since ``tail_ns``: a path that queues delivers older messages then, one that keeps its
    data fresh the newest."""
    late = [stamp for at, stamp in zip(arrivals, stamps, strict=True) if tail_ns <= at <= end_ns]
    return {"tail": len(late), "tail_fresh": sum(stamp >= tail_ns for stamp in late)}


def run_subscriber(p: StringPayload, depth: int, reliability: str) -> None:
    from rclpy.experimental import EventsExecutor

    tally = Tally(p)
    sub_node = node("bench_sub")
    sub_node.create_subscription(p.msg_type, TOPIC, tally.on_message, qos(depth, reliability),
                                 raw=True)
    executor = EventsExecutor()
    executor.add_node(sub_node)
    done = threading.Event()
    threading.Thread(target=serve_commands, args=(tally, done), daemon=True).start()
    answer({"ready": True})
    # a loop of spin_once: EventsExecutor.spin() was seen to deliver nothing and hang at shutdown
    while not done.is_set():
        executor.spin_once(timeout_sec=0.1)


def serve_commands(tally: Tally, done: threading.Event) -> None:
    for line in sys.stdin:
        words = line.split()
        if words[:1] == ["stats"]:
            deadline = int(words[2]) if len(words) > 2 else 2**63 - 1
            since, end = (int(words[3]), int(words[4])) if len(words) > 4 else (0, 0)
            answer(tally.stats(int(words[1]), deadline, since, end))
        elif words[:1] == ["total"]:
            answer({"received": tally.total})
        elif words[:1] == ["quit"]:
            break
    done.set()


def main() -> None:
    role, kind, size, depth = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
    reliability = sys.argv[5] if len(sys.argv) > 5 else "reliable"
    p = payload(kind, size)
    {"pub": run_publisher, "sub": run_subscriber}[role](p, depth, reliability)


if __name__ == "__main__":
    main()
