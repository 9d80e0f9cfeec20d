"""A ROS talker or listener run as a process of its own, inside a network namespace (a test's
"host"): rclpy's sockets must live in the namespace of the bridge they talk to, so these sides
cannot be nodes of the test's own process.

``python roam_side.py listen TOPIC``: prints ``ready``, then ``<data> <monotonic time>`` for
every std_msgs/String it receives (reliable, depth 1000).

``python roam_side.py talk TOPIC COUNT RATE``: publishes ``warm`` every 0.1 s until a line
``go`` comes on stdin, then ``0`` ... ``COUNT - 1`` at RATE Hz, printing ``sent <i>`` after
each; then ``done``, and stays until stdin closes.
"""

from __future__ import annotations

import sys
import threading
import time

import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

QOS = QoSProfile(depth=1000, history=HistoryPolicy.KEEP_LAST,
                 reliability=ReliabilityPolicy.RELIABLE)


def say(line: str) -> None:
    sys.stdout.write(line + "\n")
    sys.stdout.flush()


def listen(node: object, topic: str) -> None:
    node.create_subscription(  # type: ignore[attr-defined]
        String, topic, lambda m: say(f"{m.data} {time.monotonic():.6f}"), QOS)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    say("ready")
    while rclpy.ok():
        executor.spin_once(timeout_sec=0.1)


def talk(node: object, topic: str, count: int, rate: float) -> None:
    publisher = node.create_publisher(String, topic, QOS)  # type: ignore[attr-defined]
    go = threading.Event()

    def read() -> None:
        for line in sys.stdin:
            if line.strip() == "go":
                go.set()
        go.set()

    threading.Thread(target=read, daemon=True).start()
    say("ready")
    while not go.wait(0.1):
        publisher.publish(String(data="warm"))
    start = time.monotonic()
    for i in range(count):  # paced against the clock, not by sleeps that add up
        time.sleep(max(0.0, start + i / rate - time.monotonic()))
        publisher.publish(String(data=str(i)))
        say(f"sent {i}")
    say("done")
    sys.stdin.read()


def main() -> None:
    rclpy.init()
    node = rclpy.create_node(f"roam_{sys.argv[1]}")
    try:
        if sys.argv[1] == "listen":
            listen(node, sys.argv[2])
        else:
            talk(node, sys.argv[2], int(sys.argv[3]), float(sys.argv[4]))
    except KeyboardInterrupt:
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
