"""udp's segmentation and receive offload, on and off: CPU per frame of two rosgate links.

    .venv/bin/python bench/offload.py [--frames N] [--max-frame BYTES]

Two datagram links in this process, on loopback, with Ethernet's frame size (max_frame 1472:
a 10 kB frame is 7 datagrams, a 1 MB one 716); each frame is sent and waited for before the
next, so what is measured is the CPU time (this process: both links' threads) per frame, with
``offload: true`` (a frame's datagrams in one system call each way, where the kernel can) and
``offload: false`` (one call per datagram). A 10 kB frame leaves from the sending thread, a
1 MB one from the link's send thread. Loopback's own max_frame would be 65,000 (see udp's
docstring): this is what a real network's frame size costs.
"""

from __future__ import annotations

import argparse
import os
import threading
import time

from rosgate_transport_udp import UdpTransport

from rosgate.links.datagram import DatagramLink
from rosgate.wire import envelope


class Topic:
    topic_id = 1
    reliable = True

    def drop(self, reason: str, detail: str = "") -> None:
        raise RuntimeError(f"dropped: {reason} {detail}")


def measure(offload: bool, size: int, frames: int, max_frame: int) -> tuple[float, float]:
    """CPU µs and wall µs per frame."""
    transport = UdpTransport({"max_frame": max_frame, "offload": offload})
    arrived = threading.Semaphore(0)
    lost: list[str] = []
    b_end = transport.bind(("127.0.0.1", 0))
    b = DatagramLink(transport, b_end, "b", lambda frame, link, source: arrived.release(),
                     lambda topic, reason: lost.append(reason))
    a = DatagramLink(transport, transport.bind(("127.0.0.1", 0)), "a", lambda *_: None,
                     lambda topic, reason: lost.append(reason))
    to = b_end.sock.getsockname()[:2]
    frame = envelope.pack(0, 1, 1, 1, 0) + os.urandom(size)
    topic = Topic()
    try:
        for _ in range(min(20, frames)):  # warm up
            a.send(frame, topic, to)
            assert arrived.acquire(timeout=5), f"lost: {lost}"
        cpu, wall = time.process_time(), time.perf_counter()
        for _ in range(frames):
            a.send(frame, topic, to)
            assert arrived.acquire(timeout=5), f"lost: {lost}"
        return ((time.process_time() - cpu) / frames * 1e6,
                (time.perf_counter() - wall) / frames * 1e6)
    finally:
        a.close()
        b.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--max-frame", type=int, default=1472)
    args = parser.parse_args()
    print(f"max_frame {args.max_frame}, {args.frames} frames each, CPU of both links per frame")
    print("| frame | offload: CPU µs | wall µs | one call per datagram: CPU µs | wall µs | "
          "CPU ratio |")
    print("|---|--:|--:|--:|--:|--:|")
    for size, frames in ((10_000, args.frames), (1_000_000, max(20, args.frames // 10))):
        on = measure(True, size, frames, args.max_frame)
        off = measure(False, size, frames, args.max_frame)
        print(f"| {size:,} B | {on[0]:,.0f} | {on[1]:,.0f} | {off[0]:,.0f} | {off[1]:,.0f} | "
              f"{on[0] / off[0]:.2f} |", flush=True)


if __name__ == "__main__":
    main()
