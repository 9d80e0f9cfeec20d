"""The serial-line benchmark: the goodput of the ``serial`` link against the line's capacity.

    publisher --DDS--> bridge A --serial--> pty relay (rosgate_emulator.serial) --serial-->
    bridge B --DDS--> subscriber

Two bridges (peers, in this process) at either end of a pseudo-terminal pair whose relay
imposes the baud rate (10 bits a byte: start, 8 data, stop). A publisher offers 200-byte
Strings at 1.5 times what the line can carry; the subscriber counts what arrives over the
last ``--seconds`` (after as long again to settle). Goodput is the messages' serialized
bytes (CDR) delivered per second, in bits, against the line's capacity (``baud * 8 / 10``):
what is left is the envelope (28 B), the cipher's tag, the compact piece's head, the serial
framing (ports, CRC-32, delimiter: 9 B) and escapes.

    python bench/serial_link.py [--seconds 10] [--baud 57600 --baud 115200]

DDS domains: ``ROSGATE_BENCH_DOMAINS=FIRST-LAST`` (default 180-189).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import threading
import time
from pathlib import Path

os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")

from rosgate_crypto_aead import AeadCipher
from rosgate_emulator.serial import LineProfile, PtyRelay

from rosgate.config import loads
from rosgate.engine import Engine
from rosgate.ros import RosNode

SIZE = 200
_FIRST, _LAST = (int(n) for n in os.environ.get("ROSGATE_BENCH_DOMAINS", "180-189").split("-"))


def side(name: str, device: str, baud: int, key: Path | None, sends: bool) -> str:
    cipher = f"\n  aead: {{key_file: {key}}}" if key else ""
    return f"""
bridge: {{name: {name}, role: peer, peer: line, listen: line, insecure: true}}
plugins:
  serial: {{device: {device}, baud: {baud}}}{cipher}
topics:
  - {{topic: /bulk, type: std_msgs/msg/String, direction: {"transmit" if sends else "receive"},
     port: 1, transport: serial, cipher: {"aead" if key else "none"}, qos: 1000}}
"""


def run(baud: int, key: Path | None, seconds: float, domains: tuple[int, int]) -> dict:
    from rclpy.serialization import serialize_message
    from std_msgs.msg import String

    message = String(data="x" * SIZE)
    cdr = len(serialize_message(message))
    capacity = baud * 8 / 10
    with tempfile.TemporaryDirectory() as folder, \
            PtyRelay(folder, LineProfile(baud=baud)) as relay:
        a = Engine(loads(side("a", relay.a, baud, key, True), file="a.yaml"),
                   domain_id=domains[0]).prepare().start()
        b = Engine(loads(side("b", relay.b, baud, key, False), file="b.yaml"),
                   domain_id=domains[1]).prepare().start()
        talker, listener = RosNode("bench_pub", domains[0]), RosNode("bench_sub", domains[1])
        arrivals: list[float] = []
        listener.subscribe(String, "/bulk", 1000, lambda m: arrivals.append(time.monotonic()),
                           raw=False)
        publisher = talker.publisher(String, "/bulk", 1000)
        stop = threading.Event()
        rate = 1.5 * capacity / 8 / (cdr + 28)

        def offer() -> None:
            start, sent = time.monotonic(), 0
            while not stop.wait(max(0.0, start + sent / rate - time.monotonic())):
                publisher.publish(message)
                sent += 1

        thread = threading.Thread(target=offer, daemon=True)
        thread.start()
        try:
            time.sleep(seconds)  # settling: discovery, the queue fills
            window_start = time.monotonic()
            time.sleep(seconds)
            window_end = time.monotonic()
        finally:
            stop.set()
            thread.join()
            a.stop()
            b.stop()
            talker.close()
            listener.close()
    drops = {**a.link_drops, **{k: v for r in a.routes() for k, v in r.counters.drops.items()}}
    far = {**b.link_drops, **{k: v for r in b.routes() for k, v in r.counters.drops.items()}}
    delivered = sum(window_start <= t < window_end for t in arrivals)
    goodput = delivered * cdr * 8 / (window_end - window_start)
    return {"baud": baud, "cipher": "aead" if key else "none", "capacity": capacity,
            "msgs": delivered / (window_end - window_start), "goodput": goodput,
            "share": goodput / capacity, "drops": drops, "far": far}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--baud", type=int, action="append")
    args = parser.parse_args()
    bauds = args.baud or [57_600, 115_200]
    with tempfile.TemporaryDirectory() as keys:
        key = Path(keys) / "aead.key"
        key.write_bytes(AeadCipher.generate_key() + b"\n")
        key.chmod(0o600)
        print(f"serial link, {SIZE}-byte Strings offered at 1.5x the line, "
              f"{args.seconds:g} s measured")
        print(f"{'baud':>8} {'cipher':>6} {'capacity':>12} {'msg/s':>7} {'goodput':>12} "
              f"{'of line':>7}  drops")
        domains = iter(range(_FIRST, _LAST + 1))
        for baud in bauds:
            for cipher_key in (None, key):
                r = run(baud, cipher_key, args.seconds, (next(domains), next(domains)))
                print(f"{r['baud']:>8} {r['cipher']:>6} {r['capacity'] / 1e3:>7.1f} kbit "
                      f"{r['msgs']:>7.1f} {r['goodput'] / 1e3:>7.1f} kbit {r['share']:>7.0%}  "
                      f"sender {r['drops'] or '-'}, receiver {r['far'] or '-'}")


if __name__ == "__main__":
    main()
