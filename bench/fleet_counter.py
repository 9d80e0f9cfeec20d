"""The base's ROS side for bench/fleet.py: counts what the base publishes for every robot.

    python fleet_counter.py COUNT      (ROS_DOMAIN_ID: the base's domain)

Subscribes ``/robotNN/{scan,odom,status}`` for robots 00..COUNT-1 (scan best effort, the others
reliable, depth 100) and counts arrivals per topic and phase (the frame_id, or a String's first
letter). Commands on stdin: ``counts`` -> {"/robot00/scan": {"w": n, "m": n}, ...}; ``quit``.
"""

from __future__ import annotations

import json
import sys
import threading
from collections import Counter, defaultdict

from nav_msgs.msg import Odometry
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import LaserScan
from std_msgs.msg import String

from rosgate.ros import RosNode


def main() -> None:
    count = int(sys.argv[1])
    node = RosNode("fleet_counter")
    counts: dict[str, Counter] = defaultdict(Counter)
    lock = threading.Lock()

    def counter(topic: str, phase_of):
        def arrived(message) -> None:
            with lock:
                counts[topic][phase_of(message)] += 1
        return arrived

    best_effort = QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT)
    for n in range(count):
        robot = f"/robot{n:02d}"
        node.subscribe(LaserScan, f"{robot}/scan", best_effort,
                       counter(f"{robot}/scan", lambda m: m.header.frame_id), raw=False)
        node.subscribe(Odometry, f"{robot}/odom", 100,
                       counter(f"{robot}/odom", lambda m: m.header.frame_id), raw=False)
        node.subscribe(String, f"{robot}/status", 100,
                       counter(f"{robot}/status", lambda m: m.data[:1]), raw=False)
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
