"""The floor: the least a bridge written in Python on rclpy can do, with no rosgate in it.

Two processes stand where bridge A and bridge B stand in a bridged case, and do only what no
bridge can skip:

    a: a raw subscription (the same QoS as the bridges'), spun by a loop of
       ``EventsExecutor.spin_once`` as rosgate spins it; its callback sends the serialized
       message as it came: one UDP datagram (no header), or over TCP a 4-byte length and the
       bytes in one ``sendmsg``.
    b: a thread blocked in ``recv`` (UDP: one datagram is one message) or reading length and
       bytes (TCP, into a buffer of the message's size), publishing each with ``publish_raw``.

No envelope, no sequence numbers, no checks, no queues, no drops counted, nothing a real bridge
needs: its numbers say what rclpy, Fast DDS and the kernel cost on this machine before any
bridge does anything, so the rosgate rows can be read against them.

``python floor.py a|b udp|tcp TYPE PORT DEPTH [RELIABILITY]`` (``ROS_DOMAIN_ID`` from the
environment); writes ``running as floor`` to stderr when ready, exits on SIGINT.
"""

from __future__ import annotations

import importlib
import os
import signal
import socket
import struct
import sys
import time

from endpoints import TOPIC, node, qos  # the publisher's and subscriber's own: the same QoS

LENGTH = struct.Struct("<I")
CONNECT_TIMEOUT = 30.0


def message_type(name: str) -> type:
    package, _, kind = name.split("/")
    return getattr(importlib.import_module(f"{package}.msg"), kind)


def connect(port: int) -> socket.socket:
    deadline = time.monotonic() + CONNECT_TIMEOUT
    while True:
        try:
            sock = socket.create_connection(("127.0.0.1", port))
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            return sock
        except ConnectionRefusedError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.05)


def transmit(transport: str, msg_type: type, port: int, depth: int, reliability: str) -> None:
    from rclpy.experimental import EventsExecutor

    if transport == "udp":
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.connect(("127.0.0.1", port))
        send_datagram = sock.send

        def send(data: bytes) -> None:  # rclpy inspects the callback: a builtin will not do
            send_datagram(data)
    else:
        sock = connect(port)
        sendmsg, pack = sock.sendmsg, LENGTH.pack

        def send(data: bytes) -> None:
            parts = [pack(len(data)), data]
            total = 4 + len(data)
            sent = sendmsg(parts)
            if sent < total:  # rare: the rest, however the first call cut it
                sock.sendall((parts[0] + data)[sent:])

    floor = node("floor_a")
    floor.create_subscription(msg_type, TOPIC, send, qos(depth, reliability), raw=True)
    executor = EventsExecutor()
    executor.add_node(floor)
    print("running as floor a", file=sys.stderr, flush=True)
    while True:
        executor.spin_once(timeout_sec=0.1)


def receive(transport: str, msg_type: type, port: int, depth: int, reliability: str) -> None:
    publisher = node("floor_b").create_publisher(msg_type, TOPIC, qos(depth, reliability))
    publish_raw = publisher.handle.publish_raw
    if transport == "udp":
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)  # as rosgate's default
        sock.bind(("127.0.0.1", port))
        print("running as floor b", file=sys.stderr, flush=True)
        recv = sock.recv
        while True:
            publish_raw(recv(65536))
    listener = socket.create_server(("127.0.0.1", port))
    print("running as floor b", file=sys.stderr, flush=True)
    sock, _ = listener.accept()
    stream = sock.makefile("rb", buffering=1 << 16)
    read, readinto, unpack = stream.read, stream.readinto, LENGTH.unpack
    while True:
        head = read(4)
        if len(head) < 4:
            return
        data = bytearray(unpack(head)[0])
        if readinto(data) < len(data):
            return
        publish_raw(data)


def main() -> None:
    side, transport, type_name, port, depth = sys.argv[1:6]
    reliability = sys.argv[6] if len(sys.argv) > 6 else "reliable"
    signal.signal(signal.SIGINT, lambda *_: os._exit(0))
    run = {"a": transmit, "b": receive}[side]
    run(transport, message_type(type_name), int(port), int(depth), reliability)


if __name__ == "__main__":
    main()
