"""The base's ROS side for bench/fleet.py: counts what the base publishes for every robot.

    python fleet_counter.py COUNT      (ROS_DOMAIN_ID: the base's domain)

Subscribes ``/robotNN/{scan,odom,status}`` for robots 00..COUNT-1 (scan best effort, the others
reliable, depth 100) and counts arrivals per topic and phase (the frame_id, or a String's first
letter). Each arrival is compared, field by field, with the message the simulated robots send in
that phase (``fleet_robots.message``); one that differs counts under ``"?"``, not its phase.
(Not byte for byte: the CDR that DDS delivers has alignment padding of unspecified content.)
Commands on stdin: ``counts`` -> {"/robot00/scan": {"w": n, "m": n}, ...}; ``quit``.
"""

from __future__ import annotations

import json
import string
import sys
import threading
from collections import Counter, defaultdict

from fleet_robots import TOPICS, message, robot_name
from nav_msgs.msg import Odometry
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import LaserScan
from std_msgs.msg import String

from rosgate.ros import RosNode

CHANGED = "?"  # counted instead of its phase: an arrival unlike the message the robots sent


def main() -> None:
    count = int(sys.argv[1])
    node = RosNode("fleet_counter")
    counts: dict[str, Counter] = defaultdict(Counter)
    lock = threading.Lock()
    # every phase a robot may be told (one lowercase letter): its three messages, as sent
    types = {"scan": LaserScan, "odom": Odometry, "status": String}
    sent = {t: {p: deserialize_message(message(t, p), types[t]) for p in string.ascii_lowercase}
            for t in TOPICS}

    def counter(topic: str, kind: str, phase_of):
        expected = sent[kind]

        def arrived(msg) -> None:
            phase = phase_of(msg)
            if expected.get(phase) != msg:
                phase = CHANGED
            with lock:
                counts[topic][phase] += 1
                if phase == CHANGED and counts[topic][phase] == 1:  # the first, to the log
                    print(f"{topic}: differs from every message sent: {msg}"[:300],
                          file=sys.stderr, flush=True)
        return arrived

    best_effort = QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT)
    qos = {"scan": best_effort, "odom": 100, "status": 100}
    phases = {"scan": lambda m: m.header.frame_id, "odom": lambda m: m.header.frame_id,
              "status": lambda m: m.data[:1]}
    for n in range(count):
        for kind in TOPICS:
            topic = f"/{robot_name(n)}/{kind}"
            node.subscribe(types[kind], topic, qos[kind], counter(topic, kind, phases[kind]),
                           raw=False)
    print(json.dumps("ready"), flush=True)
    for line in sys.stdin:
        if line.strip() == "counts":
            with lock:
                print(json.dumps({t: dict(c) for t, c in counts.items()}), flush=True)
        elif line.strip() == "quit":
            break
    node.close()


if __name__ == "__main__":
    main()
