"""Large best-effort messages across Fast DDS alone, no rosgate: how many of them arrive.

    .venv/bin/python bench/large_best_effort.py [--size BYTES] [--count N] [--rate HZ]

A publisher process and a subscriber process on this machine, std_msgs/UInt8MultiArray of
``--size`` bytes at ``--rate`` per second, once best effort and once reliable (depth 10 both
sides). It prints how many of ``--count`` arrived. The default file's "1 MB, best effort" row of
bench.py crosses two such DDS hops (publisher -> bridge A, bridge B -> subscriber), so what one
hop loses here, that row loses twice, whatever the bridges do.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time

DOMAIN = 232  # bench.py's cases use 150 and up; tests 20-149


def side(role: str, reliability: str, size: int, count: int, rate: float) -> None:
    import rclpy
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from std_msgs.msg import UInt8MultiArray

    qos = QoSProfile(depth=10, history=HistoryPolicy.KEEP_LAST,
                     reliability=getattr(ReliabilityPolicy, reliability.upper()))
    rclpy.init()
    node = rclpy.create_node(f"large_{role}")
    if role == "sub":
        got = []
        node.create_subscription(UInt8MultiArray, "/large",
                                 lambda m: got.append(len(m.data) == size), qos)
        print("ready", flush=True)
        end = time.monotonic() + count / rate + 15
        while time.monotonic() < end and len(got) < count:
            rclpy.spin_once(node, timeout_sec=0.1)
        print(sum(got), flush=True)
        return
    publisher = node.create_publisher(UInt8MultiArray, "/large", qos)
    message = UInt8MultiArray(data=bytes(size))
    while publisher.get_subscription_count() == 0:
        time.sleep(0.05)
    time.sleep(1.0)  # discovery both ways
    for _ in range(count):
        publisher.publish(message)
        time.sleep(1 / rate)
    time.sleep(2.0)  # let the last ones leave before the publisher goes


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", type=int, default=1_000_000)
    parser.add_argument("--count", type=int, default=100)
    parser.add_argument("--rate", type=float, default=20.0)
    parser.add_argument("--side", nargs=2, metavar=("ROLE", "RELIABILITY"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.side:
        side(*args.side, args.size, args.count, args.rate)
        return 0
    env = dict(os.environ, ROS_DOMAIN_ID=str(DOMAIN), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    common = ["--size", str(args.size), "--count", str(args.count), "--rate", str(args.rate)]
    for reliability in ("best_effort", "reliable"):
        sub = subprocess.Popen([sys.executable, __file__, *common, "--side", "sub", reliability],
                               stdout=subprocess.PIPE, text=True, env=env)
        assert sub.stdout is not None
        sub.stdout.readline()  # ready
        subprocess.run([sys.executable, __file__, *common, "--side", "pub", reliability],
                       check=True, env=env)
        arrived = int(sub.stdout.readline() or 0)
        sub.wait()
        print(f"{args.size:,} B at {args.rate:g}/s, {reliability.replace('_', ' ')}: "
              f"{arrived} of {args.count} arrived")
    return 0


if __name__ == "__main__":
    sys.exit(main())
