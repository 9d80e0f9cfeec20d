"""``python -m rosgate_emulator udp|tcp ...``: a relay as a process of its own, which prints its
address, runs until SIGINT/SIGTERM, then prints its counters as JSON."""

from __future__ import annotations

import argparse
import dataclasses
import json
import signal
import threading
from collections.abc import Sequence

from .shaping import PRESETS, Profile
from .tcp import TcpRelay
from .udp import UdpRelay


def _host_port(text: str) -> tuple[str, int]:
    host, _, port = text.rpartition(":")
    return host.strip("[]") or "127.0.0.1", int(port)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m rosgate_emulator",
        description="Relay UDP datagrams or TCP connections through an emulated link until "
                    "SIGINT/SIGTERM, then print the counters as JSON.")
    parser.add_argument("kind", choices=("udp", "tcp"))
    parser.add_argument("--target", type=_host_port, required=True, help="HOST:PORT")
    parser.add_argument("--listen", type=_host_port, default=("127.0.0.1", 0), help="HOST:PORT")
    parser.add_argument("--preset", choices=sorted(PRESETS), help="start from a named profile")
    for field in dataclasses.fields(Profile):
        kind = {"reorder": int, "seed": str}.get(field.name, float)
        parser.add_argument(f"--{field.name}", type=kind, help=f"override {field.name}")
    args = parser.parse_args(argv)
    profile = PRESETS[args.preset] if args.preset else Profile()
    changes = {f.name: getattr(args, f.name) for f in dataclasses.fields(Profile)
               if getattr(args, f.name) is not None}
    for name in ("burst", "mtu", "queue"):
        if name in changes:
            changes[name] = int(changes[name])
    if "reorder" in changes:
        changes["reorder"] = bool(changes["reorder"])
    profile = dataclasses.replace(profile, **changes)
    relay_class = UdpRelay if args.kind == "udp" else TcpRelay
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    with relay_class(profile, args.target, args.listen) as relay:
        host, port = relay.address
        print(f"{args.kind} {host}:{port} -> {args.target[0]}:{args.target[1]} "
              f"{dataclasses.asdict(profile)}", flush=True)
        stop.wait()
    counters = {"up": dataclasses.asdict(relay.up), "down": dataclasses.asdict(relay.down)}
    print(json.dumps(counters), flush=True)
    return 0
