"""rosgate fleet benchmark: one base bridge with fleet entries, 50 robots through a zenoh router.

    .venv/bin/python bench/fleet.py [--robots 50] [--seconds 10] [--full] [--skip-throughput]

1. **Fleet.** A ``rosgate router``; a base (``rosgate run``) whose three fleet entries
   (``/{robot}/scan``, ``/{robot}/odom``, ``/{robot}/status``) make a ROS publisher for each
   robot the first time it sends; ``--robots`` simulated robots in two processes
   (``fleet_robots.py``: a zenoh session each, a liveliness token, three topics at 10 Hz in
   rosgate envelopes: LaserScan ~2.5 kB best effort, Odometry and a 100 B String reliable); a
   ROS process on the base's domain (``fleet_counter.py``) counting what the base publishes.
   A warm-up phase lets every route and DDS match form; then a measured phase of ``--seconds``.
   Reported: how many of the robots' topics the base published, the delivered ratio (messages
   of the measured phase that reached the base's ROS side / sent), the base's CPU (share of one
   core, and per message) and RSS (now and peak), the router's CPU.
2. **Throughput**: 2.5 kB Strings over zenoh (through a router) against udp, with bench.py's
   own cases and sustained-rate search (``--full``: its full trials; else its quick ones).

Progress goes to stderr, the report to stdout and ``bench/fleet_results.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from processes import ROSGATE, Lines, Route, free_port, next_domains, ros_env

import bench

HERE = Path(__file__).resolve().parent
DELIVERED_TARGET = 0.99
WARM_UP_ROUNDS = 6
TOPICS = ("scan", "odom", "status")


def log(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def cpu_seconds(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def memory_mb(pid: int) -> tuple[float, float]:
    """(RSS now, peak RSS) in MB."""
    values = {}
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith(("VmRSS:", "VmHWM:")):
                key, kb, _ = line.split()
                values[key] = int(kb) / 1024
    return values["VmRSS:"], values["VmHWM:"]


class Child:
    """A process answering one JSON line per command line."""

    def __init__(self, name: str, argv: list[str], env: dict[str, str], log_path: Path):
        self.name = name
        self.log = log_path.open("w")
        self.proc = subprocess.Popen(argv, env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     stderr=self.log, text=True, bufsize=1)
        self.lines = Lines(self.proc.stdout, name)  # type: ignore[arg-type]

    def ready(self, timeout: float = 60) -> None:
        assert json.loads(self.lines.next(timeout)) == "ready"

    def send(self, command: str) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(command + "\n")
        self.proc.stdin.flush()

    def answer(self, timeout: float) -> object:
        return json.loads(self.lines.next(timeout))

    def stop(self) -> None:
        try:
            self.send("quit")
            self.proc.wait(15)
        except (OSError, subprocess.TimeoutExpired):
            self.proc.kill()
            self.proc.wait()
        self.log.close()


class Router:
    def __init__(self, log_path: Path):
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.log = log_path.open("w")
        self.proc = subprocess.Popen([ROSGATE, "router", "--listen", self.endpoint],
                                     stderr=subprocess.PIPE, text=True)
        self.lines = Lines(self.proc.stderr, "router")  # type: ignore[arg-type]
        self.lines.wait_for("router running", 30)

    def stop(self) -> None:
        self.proc.terminate()
        self.proc.wait(10)


@dataclass
class FleetResult:
    robots: int
    seconds: float
    topics_published: int
    sent: dict[str, int]
    delivered: dict[str, int]
    base_cpu: float  # share of one core during the measured phase
    base_rss: tuple[float, float]
    router_cpu: float
    robots_cpu: float
    warm_up_rounds: int
    base_problems: list[str]

    @property
    def ratio(self) -> float:
        return sum(self.delivered.values()) / max(1, sum(self.sent.values()))


def base_file(folder: Path, endpoint: str) -> Path:
    path = folder / "base.yaml"
    entry = ("  - {{topic: '/{{robot}}/{t}', type: {type}, direction: receive, "
             "remote: 'fleet/{{robot}}/{t}', qos: {qos}}}\n")
    types = {"scan": ("sensor_msgs/msg/LaserScan", "sensor_data"),
             "odom": ("nav_msgs/msg/Odometry", 100), "status": ("std_msgs/msg/String", 100)}
    path.write_text(
        "bridge: {name: base, role: peer, defaults: {transport: zenoh}, stale_after: 600}\n"
        f"plugins: {{zenoh: {{mode: client, connect: [{endpoint}], insecure: true}}}}\ntopics:\n"
        + "".join(entry.format(t=t, type=types[t][0], qos=types[t][1]) for t in TOPICS))
    return path


def fleet(robots: int, seconds: float, folder: Path) -> FleetResult:
    router = Router(folder / "router.log")
    domain = next_domains()[0]
    base = subprocess.Popen([ROSGATE, "run", str(base_file(folder, router.endpoint))],
                            env=ros_env(domain), stderr=subprocess.PIPE, text=True)
    base_lines = Lines(base.stderr, "base")  # type: ignore[arg-type]
    children: list[Child] = []
    try:
        base_lines.wait_for("running as", 60)
        counter = Child("counter", [sys.executable, str(HERE / "fleet_counter.py"), str(robots)],
                        ros_env(domain), folder / "counter.log")
        children.append(counter)
        half = robots // 2
        for first, count in ((0, half), (half, robots - half)):
            children.append(Child(f"robots{first}", [sys.executable,
                                                     str(HERE / "fleet_robots.py"),
                                                     router.endpoint, str(first), str(count)],
                                  ros_env(domain + 1), folder / f"robots{first}.log"))
        for child in children:
            child.ready()
        fleet_processes = children[1:]

        def phase(name: str, length: float) -> list[dict]:
            for child in fleet_processes:
                child.send(f"run {name} {length}")
            return [child.answer(length * 3 + 60) for child in fleet_processes]  # type: ignore

        def counts() -> dict[str, dict[str, int]]:
            counter.send("counts")
            return counter.answer(30)  # type: ignore[return-value]

        expected = robots * len(TOPICS)
        rounds = 0
        for rounds in range(1, WARM_UP_ROUNDS + 1):  # until every route and DDS match formed
            phase("w", 2.0)
            time.sleep(0.5)
            seen = sum(1 for c in counts().values() if c.get("w"))
            log(f"fleet: warm-up {rounds}: {seen} of {expected} robot topics on the base")
            if seen == expected:
                break
        before = counts()
        base0, router0 = cpu_seconds(base.pid), cpu_seconds(router.proc.pid)
        started = time.monotonic()
        results = phase("m", seconds)
        wall = time.monotonic() - started
        base1, router1 = cpu_seconds(base.pid), cpu_seconds(router.proc.pid)
        rss = memory_mb(base.pid)
        time.sleep(1.0)  # the last messages on their way
        after = counts()
        sent = {t: sum(r["sent"][t] for r in results) for t in TOPICS}
        delivered = {t: sum(c.get("m", 0) - before.get(topic, {}).get("m", 0)
                            for topic, c in after.items() if topic.endswith("/" + t))
                     for t in TOPICS}
        published = sum(1 for c in after.values() if c.get("m"))
        robots_cpu = sum(r["cpu_s"] for r in results) / wall
    finally:
        base.send_signal(2)  # first, so that robots leaving is not what it logs last
        base.wait(20)
        base_lines.ended.wait(5)
        for child in reversed(children):
            child.stop()
        router.stop()
    (folder / "base.log").write_text("\n".join(base_lines.seen) + "\n")
    problems = [line for line in base_lines.seen
                if " WARNING " in line or " ERROR " in line or "Traceback" in line
                or ("drops:" in line and not line.endswith("drops: none"))]
    return FleetResult(robots, wall, published, sent, delivered, (base1 - base0) / wall, rss,
                       (router1 - router0) / wall, robots_cpu, rounds, problems)


def throughput(settings: bench.Settings, folder: Path) -> list[bench.Result]:
    """2.5 kB over udp and over zenoh (both bridges clients of one router), through bench.py's
    cases: bench.bringup_files is wrapped to write the zenoh pair."""
    router = Router(folder / "router-throughput.log")
    plain = bench.bringup_files

    def bringup_files(route: Route, msg_type: str, depth: int, where: Path,
                      reliability: str = "reliable", root: Path = bench.ROOT):
        if route.transport != "zenoh":
            return plain(route, msg_type, depth, where, reliability, root)
        topic = (f"{{topic: /bench, type: {msg_type}, transport: zenoh, codec: {route.codec}, "
                 f"cipher: {route.cipher}, remote: bench/2k5, "
                 f"qos: {{reliability: {reliability}, history: keep_last, depth: {depth}}}")
        plugin = f"plugins: {{zenoh: {{mode: client, connect: [{router.endpoint}]}}}}\n"
        paths = where / "bench_a.yaml", where / "bench_b.yaml"
        for path, name, direction in zip(paths, ("bench_a", "bench_b"), ("transmit", "receive"),
                                         strict=True):
            path.write_text(f"bridge: {{name: {name}, role: peer}}\n{plugin}"
                            f"topics:\n  - {topic}, direction: {direction}}}\n")
        return paths

    bench.bringup_files = bringup_files  # type: ignore[assignment]
    size = next(s for s in bench.SIZES if s.name == "2.5 kB")
    options = bench.Options(best_effort=frozenset())  # bench.py's reliable trials only
    results = []
    try:
        for i, route in enumerate([Route("udp"), Route("zenoh")]):
            case = folder / f"throughput{i}"
            case.mkdir()
            results.append(bench.measure(size, route, settings, case, options))
    finally:
        bench.bringup_files = plain  # type: ignore[assignment]
        router.stop()
    return results


def report(result: FleetResult | None, rates: list[bench.Result], elapsed: float) -> str:
    parts = ["# rosgate fleet benchmark", "",
             f"{time.strftime('%Y-%m-%d %H:%M')}, rosgate {bench.revision()}, {os.cpu_count()} "
             f"cores, {elapsed / 60:.1f} min.", ""]
    if result is not None:
        r = result
        offered = sum(r.sent.values()) / r.seconds
        total = sum(r.delivered.values())
        verdict = "MET" if r.ratio >= DELIVERED_TARGET and \
            r.topics_published == r.robots * len(TOPICS) else "NOT MET"
        parts += [
            f"## Fleet: {r.robots} robots x {len(TOPICS)} topics at 10 Hz through one zenoh "
            "router into one base with fleet entries", "",
            "| | |", "|---|--:|",
            f"| robot topics published on the base's ROS side | {r.topics_published} of "
            f"{r.robots * len(TOPICS)} |",
            f"| measured phase | {r.seconds:.1f} s, {offered:,.0f} msg/s offered |",
            *[f"| delivered {t} | {r.delivered[t]:,} of {r.sent[t]:,} "
              f"({r.delivered[t] / max(1, r.sent[t]):.2%}) |" for t in TOPICS],
            f"| delivered, all | {total:,} of {sum(r.sent.values()):,} ({r.ratio:.2%}) |",
            f"| base CPU | {r.base_cpu:.1%} of one core "
            f"({1e6 * r.base_cpu * r.seconds / max(1, total):.0f} µs per message) |",
            f"| base RSS | {r.base_rss[0]:.0f} MB (peak {r.base_rss[1]:.0f} MB) |",
            f"| router CPU | {r.router_cpu:.1%} of one core |",
            f"| simulated robots' CPU (2 processes) | {r.robots_cpu:.1%} of one core |",
            "", f"**target: every robot's topics published on the base, delivered >= "
            f"{DELIVERED_TARGET:.0%}: {verdict} ({r.ratio:.2%})**"]
        if r.base_problems:
            parts += ["", "The base's warnings and drop counters:", "",
                      *[f"- {line}" for line in r.base_problems[:10]]]
    if rates:
        parts += ["", "## 2.5 kB throughput: zenoh (through a router) vs udp, same run", "",
                  bench.table(rates)]
        notes = [f"- {x.path}: {line}" for x in rates for line in x.problems[:6]]
        if notes:
            parts += ["", *notes]
    return "\n".join(parts) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--robots", type=int, default=50)
    parser.add_argument("--seconds", type=float, default=10.0, help="the measured phase")
    parser.add_argument("--full", action="store_true", help="bench.py's full throughput trials")
    parser.add_argument("--skip-fleet", action="store_true")
    parser.add_argument("--skip-throughput", action="store_true")
    parser.add_argument("--out", type=Path, default=HERE / "fleet_results.md")
    args = parser.parse_args()
    start = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="rosgate-fleet-") as tmp:
        folder = Path(tmp)
        result = None if args.skip_fleet else fleet(args.robots, args.seconds, folder)
        rates = [] if args.skip_throughput else throughput(
            bench.FULL if args.full else bench.QUICK, folder)
    text = report(result, rates, time.monotonic() - start)
    print(text)
    args.out.write_text(text)
    failed = result is not None and result.ratio < DELIVERED_TARGET or any(r.error for r in rates)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
