#!/usr/bin/env python3
"""A microcontroller that speaks the CVRA MessagePack profile, to try rosgate without hardware.

It uses only the standard library and ``msgpack`` (nothing from rosgate: the serial datagram
framing below is written from the wire description, so it checks rosgate's independently).

Wire format:
  topics    UDP, one message per datagram: a MessagePack str (the topic's name) followed by a
            MessagePack map of its fields (nested messages as maps).
  services  TCP, one connection per call: the caller writes one serial datagram
            (escape(payload) + escape(CRC-32 of payload, big-endian) + 0xC0; 0xC0 -> DB DC,
            0xDB -> DB DD) whose payload is the service's name (str) + the request (map); the
            server answers with the response as a plain MessagePack map and closes.

What it does:
  * sends ``position`` {x, y, theta} (geometry_msgs/Pose2D style) to the bridge every 1/rate s;
  * prints every topic message it receives (e.g. ``cmd_vel``, a Twist) as one JSON line;
  * serves ``ping`` -> {success: true, message: "pong"} and ``set_led`` (SetBool style)
    -> {success: true, message: "led on|off"} on its service port;
  * with --call NAME, calls NAME on the bridge (with --call-data as the request, JSON), once
    or every --call-every seconds, and prints each answer as one JSON line.

Every line it prints is JSON with a "kind" key, so a program can read it.

  python examples/mcu_simulator.py --bridge 127.0.0.1 --rate 10
"""

from __future__ import annotations

import argparse
import json
import math
import socket
import sys
import threading
import time
import zlib

import msgpack

END, ESC, ESC_END, ESC_ESC = 0xC0, 0xDB, 0xDC, 0xDD


def serial_datagram(payload: bytes) -> bytes:
    """escape(payload + crc32 big-endian) + END."""
    out = bytearray()
    for byte in payload + zlib.crc32(payload).to_bytes(4, "big"):
        if byte == END:
            out += bytes((ESC, ESC_END))
        elif byte == ESC:
            out += bytes((ESC, ESC_ESC))
        else:
            out.append(byte)
    out.append(END)
    return bytes(out)


def read_serial_datagram(conn: socket.socket) -> bytes | None:
    """One datagram from a connection; None when it is malformed or the peer closes first."""
    data = bytearray()
    escaped = False
    while True:
        chunk = conn.recv(1)
        if not chunk:
            return None
        byte = chunk[0]
        if byte == END:
            break
        if escaped:
            if byte not in (ESC_END, ESC_ESC):
                return None
            data.append(END if byte == ESC_END else ESC)
            escaped = False
        elif byte == ESC:
            escaped = True
        else:
            data.append(byte)
    if escaped or len(data) < 4:
        return None
    payload, crc = bytes(data[:-4]), int.from_bytes(data[-4:], "big")
    return payload if zlib.crc32(payload) == crc else None


def say(kind: str, **fields: object) -> None:
    # one write per line: print() writes the text and the newline separately, so two threads
    # printing at once could run their lines together
    sys.stdout.write(json.dumps({"kind": kind, **fields}, default=repr) + "\n")
    sys.stdout.flush()


class Simulator:
    def __init__(self, args: argparse.Namespace):
        self.args = args
        self.stop = threading.Event()
        self.udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.udp.bind((args.listen, args.topic_port))
        self.udp.settimeout(0.2)
        self.tcp = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.tcp.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.tcp.bind((args.listen, args.service_port))
        self.tcp.listen(16)
        self.tcp.settimeout(0.2)
        self.led = False

    def run(self) -> None:
        threads = [threading.Thread(target=t, daemon=True)
                   for t in (self.send_position, self.receive_topics, self.serve)]
        for thread in threads:
            thread.start()
        say("ready", topic_port=self.udp.getsockname()[1], service_port=self.tcp.getsockname()[1])
        if self.args.call:
            threading.Thread(target=self.call_loop, daemon=True).start()
        try:
            while not self.stop.wait(0.2):
                if self.args.duration and time.monotonic() - START > self.args.duration:
                    break
        except KeyboardInterrupt:
            pass
        self.stop.set()

    def send_position(self) -> None:
        if not self.args.rate:
            return
        n = 0
        while not self.stop.wait(1 / self.args.rate):
            position = {"x": float(n), "y": 0.5, "theta": math.pi / 4}
            datagram = msgpack.packb("position") + msgpack.packb(position)
            self.udp.sendto(datagram, (self.args.bridge, self.args.bridge_topic_port))
            n += 1

    def receive_topics(self) -> None:
        while not self.stop.is_set():
            try:
                datagram, _ = self.udp.recvfrom(65535)
            except TimeoutError:
                continue
            unpacker = msgpack.Unpacker(raw=False)
            unpacker.feed(datagram)
            try:
                name, fields = unpacker.unpack(), unpacker.unpack()
            except Exception as exc:
                say("bad_datagram", error=str(exc))
                continue
            say("topic", name=name, fields=fields)

    def serve(self) -> None:
        while not self.stop.is_set():
            try:
                conn, _ = self.tcp.accept()
            except TimeoutError:
                continue
            threading.Thread(target=self.serve_one, args=(conn,), daemon=True).start()

    def serve_one(self, conn: socket.socket) -> None:
        with conn:
            conn.settimeout(5)
            payload = read_serial_datagram(conn)
            if payload is None:
                say("bad_request")
                return
            unpacker = msgpack.Unpacker(raw=False)
            unpacker.feed(payload)
            name, request = unpacker.unpack(), unpacker.unpack()
            if name == "ping":
                answer = {"success": True, "message": "pong"}
            elif name == "set_led":
                self.led = bool(request.get("data", False))
                answer = {"success": True, "message": f"led {'on' if self.led else 'off'}"}
            else:
                answer = {"success": False, "message": f"no service {name}"}
            say("served", name=name, request=request)
            conn.sendall(msgpack.packb(answer))

    def call_loop(self) -> None:
        request = json.loads(self.args.call_data)
        while True:
            try:
                self.call(self.args.call, request)
            except OSError as exc:
                say("call_failed", name=self.args.call, error=str(exc))
            if not self.args.call_every or self.stop.wait(self.args.call_every):
                return

    def call(self, name: str, request: dict) -> None:
        with socket.create_connection((self.args.bridge, self.args.bridge_service_port), 5) as c:
            c.sendall(serial_datagram(msgpack.packb(name) + msgpack.packb(request)))
            answer = b""
            while chunk := c.recv(4096):  # the server closes after answering
                answer += chunk
        say("answer", name=name, response=msgpack.unpackb(answer, raw=False) if answer else None)


START = time.monotonic()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--bridge", default="127.0.0.1", help="the bridge's address")
    parser.add_argument("--listen", default="127.0.0.1", help="address this simulator binds")
    parser.add_argument("--topic-port", type=int, default=20000,
                        help="UDP port topics arrive on here (default 20000)")
    parser.add_argument("--service-port", type=int, default=20001,
                        help="TCP port this simulator serves calls on (default 20001)")
    parser.add_argument("--bridge-topic-port", type=int, default=20000,
                        help="the bridge's UDP port for topics (default 20000)")
    parser.add_argument("--bridge-service-port", type=int, default=20001,
                        help="the bridge's TCP port for calls (default 20001)")
    parser.add_argument("--rate", type=float, default=10.0,
                        help="position messages per second (0: none)")
    parser.add_argument("--call", metavar="NAME", help="call this service on the bridge")
    parser.add_argument("--call-data", default="{}", metavar="JSON", help="the request's fields")
    parser.add_argument("--call-every", type=float, default=0, metavar="SECONDS",
                        help="repeat the call this often (0: once)")
    parser.add_argument("--duration", type=float, default=0, help="seconds to run (0: until ^C)")
    Simulator(parser.parse_args(argv)).run()
    return 0


if __name__ == "__main__":
    sys.exit(main())
