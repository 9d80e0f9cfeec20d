#!/usr/bin/env python3
"""A microcontroller that speaks as CVRA's robot firmware does, to try rosgate without hardware.

It uses only the standard library and ``msgpack`` (nothing from rosgate, so it checks rosgate's
side independently), and lays out its bytes as CVRA's firmware (``lib/simplerpc``,
``lib/serial-datagram``) and its Python package ``cvra_rpc`` do:

  topics    UDP, one message per datagram, no framing: ONE MessagePack array of two elements,
            ``[name, args]``, floats as float 32 (``packb([name, args], use_single_float=True)``).
            ``args`` is any value: the firmware streams bare floats, arrays, booleans, nil.
            A datagram that is not such an array is ignored, as the firmware ignores it.
  services  TCP, one connection per call. The caller writes ``[name, args]`` (as above) inside one
            serial datagram: escape(payload + CRC-32 of the payload, big-endian) + 0xC0, where
            0xC0 -> DB DC and 0xDB -> DB DD in both. The server answers with one plain
            MessagePack value (whatever the handler returns: "pong", an array, nil) or with no
            byte at all when the handler returns None, then closes the connection; the caller
            reads until it is closed.

What it does:
  * every 1/rate s sends ``position`` as ``[x, y, theta]`` (the fields of a geometry_msgs/Pose2D
    in order) and ``base/distance/measured`` as a bare float;
  * prints every message it receives (e.g. ``cmd_vel``) as one JSON line;
  * serves ``ping`` -> "pong" and ``set_led`` (args: a bool) -> ``[true, "led on|off"]``
    (the fields of a std_srvs/SetBool response in order), ``silent`` -> no byte at all;
  * with --call NAME, calls NAME on the bridge with --call-data (JSON: any value, default null)
    as its args, once or every --call-every seconds, and prints each answer.

Every line it prints is JSON with a "kind" key (bytes as hex under "hex"), so a program can read it.

  python examples/mcu_simulator.py --bridge 127.0.0.1 --rate 10
"""

from __future__ import annotations

import argparse
import json
import socket
import sys
import threading
import time
import zlib
from typing import Any

import msgpack

END, ESC, ESC_END, ESC_ESC = 0xC0, 0xDB, 0xDC, 0xDD


def pack(name: str, args: Any) -> bytes:
    """A message or a call as the firmware lays it out: [name, args], floats 32 bits wide."""
    return msgpack.packb([name, args], use_single_float=True)


def unpack(data: bytes) -> tuple[str, Any] | None:
    """(name, args) of a [name, args] array; None for anything else (the firmware ignores it)."""
    try:
        value = msgpack.unpackb(data, raw=False)
    except Exception:
        return None
    if type(value) is not list or len(value) != 2 or type(value[0]) is not str:
        return None
    return value[0], value[1]


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
    while not data.endswith(bytes((END,))):
        chunk = conn.recv(1024)
        if not chunk:
            return None
        data += chunk
    body = bytearray()
    escaped = False
    for byte in data[:-1]:
        if escaped:
            if byte not in (ESC_END, ESC_ESC):
                return None
            body.append(END if byte == ESC_END else ESC)
            escaped = False
        elif byte == ESC:
            escaped = True
        else:
            body.append(byte)
    if escaped or len(body) < 4:
        return None
    payload, crc = bytes(body[:-4]), int.from_bytes(body[-4:], "big")
    return payload if zlib.crc32(payload) == crc else None


def say(kind: str, **fields: object) -> None:
    # one write per line: two threads printing at once must not run their lines together
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
        self.handlers = {"ping": self.ping, "set_led": self.set_led, "silent": lambda args: None}

    def run(self) -> None:
        for target in (self.stream, self.receive_topics, self.serve):
            threading.Thread(target=target, daemon=True).start()
        say("ready", topic_port=self.udp.getsockname()[1], service_port=self.tcp.getsockname()[1])
        if self.args.call:
            threading.Thread(target=self.call_loop, daemon=True).start()
        start = time.monotonic()
        try:
            while not self.stop.wait(0.2):
                if self.args.duration and time.monotonic() - start > self.args.duration:
                    break
        except KeyboardInterrupt:
            pass
        self.stop.set()

    # -- topics ----------------------------------------------------------------------------------

    def stream(self) -> None:
        if not self.args.rate:
            return
        n = 0
        target = (self.args.bridge, self.args.bridge_topic_port)
        while not self.stop.wait(1 / self.args.rate):
            self.udp.sendto(pack("position", [float(n), 0.5, 0.25]), target)
            self.udp.sendto(pack("base/distance/measured", 0.125 * n), target)
            n += 1

    def receive_topics(self) -> None:
        while not self.stop.is_set():
            try:
                datagram, _ = self.udp.recvfrom(65535)
            except TimeoutError:
                continue
            message = unpack(datagram)
            if message is None:
                say("ignored", hex=datagram.hex())
                continue
            say("topic", name=message[0], args=message[1], hex=datagram.hex())

    # -- services --------------------------------------------------------------------------------

    def ping(self, args: Any) -> Any:
        return "pong"

    def set_led(self, args: Any) -> Any:
        self.led = bool(args)
        return [True, f"led {'on' if self.led else 'off'}"]

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
            call = unpack(payload) if payload is not None else None
            if call is None or call[0] not in self.handlers:
                say("bad_request", hex=payload.hex() if payload else "")
                return  # closed without an answer
            name, args = call
            answer = self.handlers[name](args)
            say("served", name=name, args=args, hex=payload.hex())
            if answer is not None:  # a handler that returns None answers nothing at all
                conn.sendall(msgpack.packb(answer))

    def call_loop(self) -> None:
        args = json.loads(self.args.call_data)
        while True:
            try:
                self.call(self.args.call, args)
            except OSError as exc:
                say("call_failed", name=self.args.call, error=str(exc))
            if not self.args.call_every or self.stop.wait(self.args.call_every):
                return

    def call(self, name: str, args: Any) -> None:
        address = (self.args.bridge, self.args.bridge_service_port)
        with socket.create_connection(address, 5) as c:
            c.sendall(serial_datagram(pack(name, args)))
            answer = b""
            while chunk := c.recv(1024):  # the server closes after answering
                answer += chunk
        say("answer", name=name, answer=msgpack.unpackb(answer, raw=False) if answer else None,
            hex=answer.hex())


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--bridge", default="127.0.0.1", help="the bridge's address")
    parser.add_argument("--listen", default="127.0.0.1", help="address this simulator binds")
    parser.add_argument("--topic-port", type=int, default=20000,
                        help="UDP port messages arrive on here (default 20000)")
    parser.add_argument("--service-port", type=int, default=20001,
                        help="TCP port this simulator serves calls on (default 20001)")
    parser.add_argument("--bridge-topic-port", type=int, default=20000,
                        help="the bridge's UDP port for messages (default 20000)")
    parser.add_argument("--bridge-service-port", type=int, default=20001,
                        help="the bridge's TCP port for calls (default 20001)")
    parser.add_argument("--rate", type=float, default=10.0,
                        help="position and distance messages per second (0: none)")
    parser.add_argument("--call", metavar="NAME", help="call this service on the bridge")
    parser.add_argument("--call-data", default="null", metavar="JSON",
                        help="the call's args, any JSON value (default null)")
    parser.add_argument("--call-every", type=float, default=0, metavar="SECONDS",
                        help="repeat the call this often (0: once)")
    parser.add_argument("--duration", type=float, default=0, help="seconds to run (0: until ^C)")
    Simulator(parser.parse_args(argv)).run()
    return 0


if __name__ == "__main__":
    sys.exit(main())
