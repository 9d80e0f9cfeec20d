"""Simulated robots for bench/fleet.py: plain zenoh sessions that speak as rosgate robots do.

    python fleet_robots.py ENDPOINT FIRST COUNT [--tls DIR]

Each robot is a zenoh client session of its own with a liveliness token
``fleet/robotNN/@alive`` and three publishers, ``fleet/robotNN/{scan,odom,status}``: a
LaserScan of ~2.5 kB (best effort: CongestionControl.DROP), an Odometry (~0.7 kB) and a 100 B
String (reliable: BLOCK), each in a rosgate envelope (cipher none) around its CDR. With
``--tls DIR`` (a folder ``rosgate certs`` filled) every session is zenoh's mutual TLS, presenting
``DIR/robotNN.pem`` as a rosgate bridge named robotNN does (``plugins: {zenoh: {tls: DIR}}``), so
a router with access control lets each robot on its own keys only. Commands, one per line on
stdin, one JSON line back on stdout:

    run PHASE SECONDS  -> {"sent": {"scan": n, ...}, "cpu_s": s, "wall_s": s}
                          every robot publishes its three topics at 10 Hz; PHASE (one letter)
                          is the messages' frame_id (String: first letter), so the counter on the
                          base's ROS side tells phases apart
    quit
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time

import zenoh
from nav_msgs.msg import Odometry
from rclpy.serialization import serialize_message
from rosgate_transport_zenoh.tls import zenoh_tls
from sensor_msgs.msg import LaserScan
from std_msgs.msg import String

from rosgate.wire import envelope
from rosgate.wire.envelope import topic_id_for

RATE = 10.0  # Hz, every topic
TOPICS = ("scan", "odom", "status")
PREFIX = "fleet"  # the robots' keys, their tokens', and the router's --prefix


def robot_name(n: int) -> str:
    return f"robot{n:02d}"


def message(topic: str, phase: str) -> bytes:
    if topic == "scan":
        scan = LaserScan(angle_min=-3.14, angle_max=3.14, range_max=30.0, ranges=[1.5] * 600)
        scan.header.frame_id = phase
        return serialize_message(scan)
    if topic == "odom":
        odom = Odometry(child_frame_id="base_link")
        odom.header.frame_id = phase
        return serialize_message(odom)
    return serialize_message(String(data=phase + "x" * 99))


class Robot:
    def __init__(self, endpoint: str, name: str, tls: str | None):
        config: dict = {"mode": "client", "connect": {"endpoints": [endpoint]},
                        "scouting": {"multicast": {"enabled": False}}}
        if tls is not None:  # the transport.link.tls a rosgate bridge with `tls: DIR` uses
            config["transport"] = {"link": {"tls": zenoh_tls(tls, name)}}
        self.session = zenoh.open(zenoh.Config.from_json5(json.dumps(config)))
        self.token = self.session.liveliness().declare_token(f"{PREFIX}/{name}/@alive")
        self.keys = {t: f"{PREFIX}/{name}/{t}" for t in TOPICS}
        block, drop = zenoh.CongestionControl.BLOCK, zenoh.CongestionControl.DROP
        self.publishers = {t: self.session.declare_publisher(
            key, congestion_control=drop if t == "scan" else block) for t, key in self.keys.items()}
        self.epoch = int.from_bytes(os.urandom(4), "big")
        self.seq = 0

    def put(self, topic: str, payload: bytes) -> None:
        self.seq += 1
        header = envelope.pack(0, topic_id_for(self.keys[topic]), self.epoch, self.seq,
                               time.time_ns())
        self.publishers[topic].put(header + payload)


def run(robots: list[Robot], phase: str, seconds: float) -> dict:
    payloads = {t: message(t, phase) for t in TOPICS}
    sent = dict.fromkeys(TOPICS, 0)
    r0, t0 = resource.getrusage(resource.RUSAGE_SELF), time.monotonic()
    tick = 0
    while tick / RATE < seconds:
        due = t0 + tick / RATE
        now = time.monotonic()
        if due > now:
            time.sleep(due - now)
        for robot in robots:
            for topic in TOPICS:
                robot.put(topic, payloads[topic])
                sent[topic] += 1
        tick += 1
    r1 = resource.getrusage(resource.RUSAGE_SELF)
    return {"sent": sent, "cpu_s": r1.ru_utime - r0.ru_utime + r1.ru_stime - r0.ru_stime,
            "wall_s": time.monotonic() - t0}


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("endpoint")
    parser.add_argument("first", type=int)
    parser.add_argument("count", type=int)
    parser.add_argument("--tls", metavar="DIR")
    args = parser.parse_args()
    robots = [Robot(args.endpoint, robot_name(n), args.tls)
              for n in range(args.first, args.first + args.count)]
    print(json.dumps("ready"), flush=True)
    try:
        for line in sys.stdin:
            words = line.split()
            if not words or words[0] == "quit":
                break
            print(json.dumps(run(robots, words[1], float(words[2]))), flush=True)
    finally:
        for robot in robots:
            robot.session.close()


if __name__ == "__main__":
    main()
