"""The soak: a client/server pair of ``rosgate run`` processes carrying 1,000 msg/s on four
topics for 30 minutes while strangers flood the server with garbage, connect and leave as
clients over and over, and hold idle connections open.

    python tests/soak/soak.py [--minutes 30] [--rate 1000] [--warmup 2]

Phases: warm-up (traffic only), then the attacks with the traffic, then a quiet end (attacks
stopped, the server's deadlines let run out). Pass, each checked and printed:

* every message published was delivered, per topic (sequence numbers, none missing or twice);
* RSS of each bridge at the end at most 5 % (``--rss-limit``) above what it was at the end of
  the warm-up, and over the attack phase its last fifth at most 5 % above its first fifth;
* file descriptors and threads of each bridge at the end as at the end of the warm-up.

Everything runs on 127.0.0.0/8 and stops by itself. The figures go to stdout as a Markdown
table and into --out (default tests/soak/last.md).
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import socket
import sys
import tempfile
import threading
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

HERE = Path(__file__).parent
sys.path.insert(0, str(HERE.parent))

os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")

from conftest import Bridge, RosSide, free_port  # noqa: E402
from resources import Resources, Snapshot  # noqa: E402

from rosgate.streamlink.link import length_prefixed  # noqa: E402
from rosgate.wire import envelope, framing  # noqa: E402

TOPICS = {  # name on the client -> (direction seen from the client, extra keys)
    "/soak/udp": ("transmit", ""),
    "/soak/udp_port": ("transmit", ", port: {udp_port}"),
    "/soak/tcp": ("transmit", ", transport: tcp, qos: 1000"),
    "/soak/down": ("receive", ""),
}
HANDSHAKE_TIMEOUT, SESSION_TIMEOUT = 2, 4


@dataclass
class Counts:
    sent: dict[str, int] = field(default_factory=lambda: defaultdict(int))
    got: dict[str, set[int]] = field(default_factory=lambda: defaultdict(set))
    twice: dict[str, int] = field(default_factory=lambda: defaultdict(int))
    lock: threading.Lock = field(default_factory=threading.Lock)

    def receive(self, topic: str, seq: int) -> None:
        with self.lock:
            if seq in self.got[topic]:
                self.twice[topic] += 1
            self.got[topic].add(seq)


def write_files(directory: Path, port: int, udp_port: int) -> tuple[Path, Path]:
    server = directory / "server.yaml"
    server.write_text(f"""
bridge:
  name: base
  role: server
  server: 127.0.0.1:{port}
  session_timeout: {SESSION_TIMEOUT}
  limits: {{handshake_timeout: {HANDSHAKE_TIMEOUT}}}
""")
    entries = "\n".join(
        f"  - {{topic: {name}, type: std_msgs/msg/String, direction: {way}"
        f"{extra.format(udp_port=udp_port)}}}" for name, (way, extra) in TOPICS.items())
    client = directory / "client.yaml"
    client.write_text(f"""
bridge: {{name: robot1, role: client, server: 127.0.0.1:{port}}}
topics:
{entries}
""")
    return server, client


# -- the attackers ---------------------------------------------------------------------------

class Attacks:
    """Garbage, reconnect churn and idle connections against the server, until stopped."""

    def __init__(self, port: int, udp_port: int):
        self.port, self.udp_port = port, udp_port
        self.stop = threading.Event()
        self.done: dict[str, int] = defaultdict(int)
        self.rng = random.Random(7)
        self.threads = [threading.Thread(target=f, daemon=True)
                        for f in (self._garbage, self._churn, self._idle)]

    def start(self) -> None:
        for thread in self.threads:
            thread.start()

    def close(self) -> None:
        self.stop.set()
        for thread in self.threads:
            thread.join(10)

    def _garbage(self) -> None:
        """~200 datagrams/s of junk, truncated envelopes and broken fragments to both UDP
        ports; a connection of junk to the main line every second."""
        rng = self.rng
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.bind(("127.0.0.4", 0))
            tick = 0
            while not self.stop.wait(0.005):
                kind = rng.randrange(4)
                if kind == 0:
                    junk = rng.randbytes(rng.randrange(1, 1500))
                elif kind == 1:
                    junk = envelope.pack(0, rng.getrandbits(32), 1, rng.getrandbits(64), 0)[
                        :rng.randrange(28)]
                elif kind == 2:
                    junk = framing.FRAGMENT.pack(b"RF", rng.randrange(9), rng.randrange(1, 9),
                                                 rng.getrandbits(32), rng.getrandbits(32)) + \
                        rng.randbytes(100)
                else:
                    junk = envelope.pack(0, rng.getrandbits(32), 1, 1, 0) + rng.randbytes(64)
                s.sendto(junk, ("127.0.0.1", rng.choice((self.port, self.udp_port))))
                self.done["garbage datagrams"] += 1
                tick += 1
                if tick % 200 == 0:
                    try:
                        with socket.create_connection(("127.0.0.1", self.port), 2) as c:
                            c.sendall(rng.randbytes(rng.randrange(1, 4000)))
                        self.done["garbage connections"] += 1
                    except OSError:
                        pass

    def _churn(self) -> None:
        """A client that comes and goes: hello with a topic of its own, then bye (or, one time
        in four, gone without a word: its session expires)."""
        from rosgate.roles.mainline import control

        n = 0
        while not self.stop.wait(1.0):
            n += 1
            hello = control({"type": "hello", "protocol": 1, "name": f"churn{n % 8}",
                             "topics": [{"topic": f"/churn{n % 8}", "type": "std_msgs/msg/String",
                                         "direction": "transmit"}], "services": []})
            try:
                with socket.create_connection(("127.0.0.1", self.port), 2) as c:
                    c.sendall(length_prefixed(hello))
                    c.settimeout(2)
                    c.recv(4096)  # the welcome
                    if n % 4:
                        c.sendall(length_prefixed(control({"type": "bye"})))
                        time.sleep(0.05)
                self.done["churn sessions"] += 1
            except OSError:
                self.done["churn failures"] += 1

    def _idle(self) -> None:
        """Every 5 s, 40 idle connections from another address; the server closes them."""
        held: list[socket.socket] = []
        while not self.stop.wait(5.0):
            for s in held:
                s.close()
            held = []
            for _ in range(40):
                s = socket.socket()
                s.bind(("127.0.0.3", 0))
                s.settimeout(0.5)
                try:
                    s.connect(("127.0.0.1", self.port))
                    held.append(s)
                except OSError:
                    s.close()
            self.done["idle connections"] += len(held)
        for s in held:
            s.close()


# -- the run ---------------------------------------------------------------------------------

def main() -> int:
    # SIGTERM ends the run through its finally: blocks, so the bridges it started stop with it
    # (an earlier run killed that way left its bridges running, in the DDS domains of the next)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=30, help="the attack phase")
    parser.add_argument("--warmup", type=float, default=2, help="minutes of traffic only first")
    parser.add_argument("--rate", type=float, default=1000, help="messages per second, all topics")
    parser.add_argument("--every", type=float, default=10, help="seconds between samples")
    parser.add_argument("--rss-limit", type=float, default=0.05,
                        help="RSS growth allowed (a fraction; a short smoke run needs more)")
    parser.add_argument("--out", default=str(HERE / "last.md"))
    args = parser.parse_args()

    # two DDS domains of its own (the benchmark uses 150 and up, tests 20-119 unless told)
    first, second = (int(d) for d in os.environ.get("ROSGATE_SOAK_DOMAINS", "140,141").split(","))
    port, udp_port = free_port(), free_port()
    counts = Counts()
    with tempfile.TemporaryDirectory(prefix="rosgate-soak-") as tmp:
        server_file, client_file = write_files(Path(tmp), port, udp_port)
        server = Bridge(server_file, first)
        client = Bridge(client_file, second)
        here, there = RosSide(second, "soak_client_side"), RosSide(first, "soak_server_side")
        try:
            return run(args, server, client, here, there, counts, port, udp_port)
        finally:
            here.close()
            there.close()
            codes = client.stop(), server.stop()
            if any(codes) or "Traceback" in server.log + client.log:
                print(f"bridges exited {codes}; server log tail:\n"
                      + "\n".join(server.lines[-30:]), file=sys.stderr)


def run(args, server: Bridge, client: Bridge, here: RosSide, there: RosSide, counts: Counts,
        port: int, udp_port: int) -> int:
    from std_msgs.msg import String

    assert client.wait_log("server 'base' up", 30), client.log
    publishers = {}
    probed: dict[str, threading.Event] = {name: threading.Event() for name in TOPICS}

    def received(name: str, message: String) -> None:
        if message.data == "probe":
            probed[name].set()
        else:
            counts.receive(name, int(message.data.split(":")[1]))

    for name, (way, _) in TOPICS.items():
        publish_side, listen_side = (here, there) if way == "transmit" else (there, here)
        publishers[name] = publish_side.publisher(name, String, 1000)
        listen_side.ros.subscribe(String, name, 1000, lambda m, n=name: received(n, m), raw=False)
    # discovery, both ROS sides and both bridges: probes until one has crossed on every topic
    deadline = time.monotonic() + 60
    for name, done in probed.items():
        while not done.wait(0.2):
            assert time.monotonic() < deadline, f"nothing crossed on {name}"
            publishers[name].publish(String(data="probe"))
    resources = {"server": Resources(server.proc.pid), "client": Resources(client.proc.pid)}
    samples: list[tuple[float, str, dict[str, Snapshot]]] = []
    stop_publishing = threading.Event()
    pad = "x" * 100

    def publish() -> None:
        interval, names = 1.0 / args.rate, list(TOPICS)
        next_at, n = time.monotonic(), 0
        while not stop_publishing.is_set():
            name = names[n % len(names)]
            seq = counts.sent[name]
            publishers[name].publish(String(data=f"{name}:{seq}:{pad}"))
            counts.sent[name] = seq + 1
            n += 1
            next_at += interval
            delay = next_at - time.monotonic()
            if delay > 0:
                time.sleep(delay)

    publisher = threading.Thread(target=publish, daemon=True)
    start = time.monotonic()
    publisher.start()

    def sample(phase: str) -> None:
        samples.append((time.monotonic() - start, phase,
                        {k: r.snapshot() for k, r in resources.items()}))

    def phase(name: str, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            time.sleep(min(args.every, max(0.0, end - time.monotonic())))
            sample(name)

    phase("warm-up", args.warmup * 60)
    base = samples[-1][2]
    attacks = Attacks(port, udp_port)
    attacks.start()
    phase("attacks", args.minutes * 60)
    attacks.close()
    stop_publishing.set()
    publisher.join(5)
    phase("quiet", max(HANDSHAKE_TIMEOUT, SESSION_TIMEOUT) + 6)
    return report(args, samples, base, counts, attacks.done, server, client)


def report(args, samples, base, counts: Counts, attacks: dict[str, int], server: Bridge,
           client: Bridge) -> int:
    end = samples[-1][2]
    attack = [s for s in samples if s[1] == "attacks"]
    fifth = max(1, len(attack) // 5)
    lines, failures = [], []
    lines.append(f"soak: {args.minutes:g} min of attacks after {args.warmup:g} min of warm-up, "
                 f"{args.rate:g} msg/s on {len(TOPICS)} topics; {time.strftime('%Y-%m-%d %H:%M')}")
    lines.append("")
    lines.append("| bridge | RSS MB warm-up end -> end | attack phase first -> last fifth | "
                 "fds warm-up end / max / end | threads warm-up end / max / end |")
    lines.append("|---|---|---|---|---|")
    for who in ("server", "client"):
        b, e = base[who], end[who]
        first = sum(s[2][who].rss_mb for s in attack[:fifth]) / fifth
        last = sum(s[2][who].rss_mb for s in attack[-fifth:]) / fifth
        growth, drift = (e.rss_mb - b.rss_mb) / b.rss_mb, (last - first) / first
        fds_max = max(s[2][who].fds for s in samples)
        threads_max = max(s[2][who].threads for s in samples)
        lines.append(f"| {who} | {b.rss_mb:.1f} -> {e.rss_mb:.1f} ({growth:+.1%}) | "
                     f"{first:.1f} -> {last:.1f} ({drift:+.1%}) | {b.fds} / {fds_max} / {e.fds} "
                     f"| {b.threads} / {threads_max} / {e.threads} |")
        if growth > args.rss_limit or drift > args.rss_limit:
            failures.append(f"{who}: RSS grew {growth:+.1%} (attack phase {drift:+.1%})")
        if e.fds != b.fds or e.threads != b.threads:
            failures.append(f"{who}: fds {b.fds} -> {e.fds}, threads {b.threads} -> {e.threads}")
    lines.append("")
    lines.append("| topic | published | delivered | missing | twice |")
    lines.append("|---|--:|--:|--:|--:|")
    for name in TOPICS:
        sent, got = counts.sent[name], counts.got[name]
        gone = sorted(set(range(sent)) - got)
        missing = len(gone)
        where = f" (seq {gone[0]}..{gone[-1]})" if gone else ""
        lines.append(f"| {name} | {sent:,} | {len(got):,} | {missing}{where} | "
                     f"{counts.twice[name]} |")
        if missing or counts.twice[name] or len(got) != sent:
            failures.append(f"{name}: {missing} missing, {counts.twice[name]} twice")
    lines.append("")
    lines.append("attacks: " + ", ".join(f"{v:,} {k}" for k, v in sorted(attacks.items())))
    lines.append("")
    if failures:  # where it went: what both bridges (still running) counted for those topics
        lines += counted([f.split(":")[0] for f in failures]) + [""]
    lines.append("PASS" if not failures else "FAIL: " + "; ".join(failures))
    text = "\n".join(lines)
    print(text)
    Path(args.out).write_text(text + "\n")
    (Path(args.out).with_suffix(".json")).write_text(json.dumps(
        [{"t": t, "phase": p, **{f"{k}_{f}": getattr(v, f) for k, v in snaps.items()
                                 for f in ("rss_mb", "fds", "threads")}}
         for t, p, snaps in samples], indent=0))
    return 0 if not failures else 1


def counted(names: list[str]) -> list[str]:
    """Each bridge's counters of the topics ``names`` (sent, received, lost, drops by reason)
    and what its links dropped, as its status socket says them."""
    from rosgate_top.client import StatusClient

    out = []
    for bridge in ("robot1", "base"):
        try:
            with StatusClient(bridge) as ask:
                status = ask.status()
        except Exception as exc:  # a bridge that no longer answers says so, in the report
            out.append(f"{bridge}: no status ({type(exc).__name__}: {exc})")
            continue
        out += [f"{bridge} {e['name']} ({e['direction']}): sent {e['sent']}, received "
                f"{e['received']}, lost {e.get('lost')}, drops {e['drops']}"
                for e in status["entries"] if e["name"] in names]
        out.append(f"{bridge} link drops: {status.get('link_drops')}")
    return out


if __name__ == "__main__":
    sys.exit(main())
