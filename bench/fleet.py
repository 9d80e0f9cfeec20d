"""rosgate fleet benchmark: one base bridge with fleet entries, 50 robots through a zenoh router.

    .venv/bin/python bench/fleet.py [--robots 50] [--seconds 10] [--tls both|on|off] [--full]
                                    [--skip-throughput]

1. **Fleet**, twice by default: with zenoh's mutual TLS and the router's access control (the
   default deployment), then without TLS (``--tls on|off``: one of them). A ``rosgate router``
   (with TLS: ``--tls DIR --base fleet_base --robot robotNN ...``, certificates from
   ``rosgate certs``); a base (``rosgate run``, ``tls: DIR`` in its zenoh options) whose three
   fleet entries
   (``/{robot}/scan``, ``/{robot}/odom``, ``/{robot}/status``) make a ROS publisher for each
   robot the first time it sends; ``--robots`` simulated robots in two processes (one below
   10 robots; ``fleet_robots.py``: a zenoh session each, with TLS presenting the robot's own
   certificate, a liveliness token, three topics at 10 Hz in rosgate envelopes: LaserScan
   ~2.5 kB best effort, Odometry and a 100 B String reliable); a ROS process on the base's domain
   (``fleet_counter.py``) counting what the base publishes, compared field by field.
   A warm-up phase lets every route and DDS match form; then a measured phase of ``--seconds``.
   Reported: how many of the robots' topics the base published, the delivered ratio (messages
   of the measured phase that reached the base's ROS side unchanged / sent), the base's CPU
   (share of one core, and per message) and RSS (now and peak), the router's CPU, and the
   machine's load (``/proc/loadavg``, and other processes' share of the CPU meanwhile).
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
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fleet_counter import CHANGED
from fleet_robots import PREFIX, TOPICS, robot_name
from processes import ROSGATE, Lines, Route, free_port, next_domains, ros_env

import bench

HERE = Path(__file__).resolve().parent
DELIVERED_TARGET = 0.998
WARM_UP_ROUNDS = 6
SETTLE = 15.0  # s: at most this long after the measured phase for its last messages
BASE = "fleet_base"  # its certificate's name too; not "base", which other bridges here may use


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

    def quit(self) -> None:
        try:
            self.send("quit")
        except OSError:
            pass

    def stop(self) -> None:
        try:
            self.quit()
            self.proc.wait(15)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self.log.close()


class Router:
    """``rosgate router`` on a loopback port; with ``tls`` (a folder ``rosgate certs`` filled)
    mutual TLS and access control: ``base`` may do anything, each robot only its own keys."""

    def __init__(self, tls: Path | None = None, robots: Sequence[str] = ()):
        self.endpoint = f"{'tls' if tls else 'tcp'}/127.0.0.1:{free_port()}"
        argv = [ROSGATE, "router", "--listen", self.endpoint]
        if tls is not None:
            argv += ["--tls", str(tls), "--prefix", PREFIX, "--base", BASE]
            for robot in robots:
                argv += ["--robot", robot]
        self.proc = subprocess.Popen(argv, stderr=subprocess.PIPE, text=True)
        self.lines = Lines(self.proc.stderr, "router")  # type: ignore[arg-type]
        self.lines.wait_for("router running", 30)

    def stop(self) -> None:
        self.proc.terminate()
        self.proc.wait(10)


@dataclass
class FleetResult:
    tls: bool  # mutual TLS, each robot presenting its own certificate, and access control
    robots: int
    seconds: float
    topics_published: int
    sent: dict[str, int]
    delivered: dict[str, int]
    changed: int  # arrivals that differ, field by field, from the message the robots sent
    base_cpu: float  # share of one core during the measured phase
    base_rss: tuple[float, float]
    router_cpu: float
    robots_cpu: float
    robot_processes: int
    warm_up_rounds: int
    settle: float  # s from the measured phase's end until its last message was counted (0.2 s
    # steps)
    load: tuple[float, float]  # /proc/loadavg's 1-minute load, before and after the phase
    others: float  # the share of the machine's CPU other processes used during the phase
    problems: list[str]

    @property
    def ratio(self) -> float:
        return sum(self.delivered.values()) / max(1, sum(self.sent.values()))

    @property
    def met(self) -> bool:
        return self.ratio >= DELIVERED_TARGET and self.changed == 0 and \
            self.topics_published == self.robots * len(TOPICS)

    @property
    def label(self) -> str:
        return "TLS + access control" if self.tls else "no TLS"


def certificates(folder: Path, robots: list[str]) -> Path:
    """A fleet CA and a certificate each for the router, the base and every robot."""
    tls = folder / "certs"
    subprocess.run([ROSGATE, "certs", "--out", str(tls), "router", BASE, *robots], check=True,
                   capture_output=True, timeout=120)
    return tls


def base_file(folder: Path, endpoint: str, tls: Path | None) -> Path:
    path = folder / "base.yaml"
    entry = ("  - {{topic: '/{{robot}}/{t}', type: {type}, direction: receive, "
             "remote: '{prefix}/{{robot}}/{t}', qos: {qos}}}\n")
    types = {"scan": ("sensor_msgs/msg/LaserScan", "sensor_data"),
             "odom": ("nav_msgs/msg/Odometry", 100), "status": ("std_msgs/msg/String", 100)}
    # without TLS the base says it accepts frames from anyone who reaches the router: the
    # benchmark measures what TLS costs
    tls_, open_ = (f", tls: {tls}", "") if tls is not None else ("", ", insecure: true")
    path.write_text(
        f"bridge: {{name: {BASE}, role: peer, defaults: {{transport: zenoh}}, stale_after: 600"
        f"{open_}}}\n"
        f"plugins: {{zenoh: {{mode: client, connect: [{endpoint}], prefix: {PREFIX}{tls_}}}}}\n"
        "topics:\n"
        + "".join(entry.format(t=t, type=types[t][0], qos=types[t][1], prefix=PREFIX)
                  for t in TOPICS))
    return path


def loadavg() -> float:
    with open("/proc/loadavg") as f:
        return float(f.read().split()[0])


def measured(counts: dict[str, dict[str, int]]) -> int:
    return sum(c.get("m", 0) for c in counts.values())


def settled(counts: Callable[[], dict[str, dict[str, int]]], sent: int,
            timeout: float = SETTLE) -> tuple[dict[str, dict[str, int]], float]:
    """The counts once the measured phase's last messages have arrived (all it sent did, or a
    second passed without one more: a loaded machine's base may lag behind), and when the last
    one was counted (``time.monotonic()``)."""
    deadline = time.monotonic() + timeout
    last = counts()
    changed = time.monotonic()
    while measured(last) < sent and time.monotonic() < deadline \
            and time.monotonic() - changed < 1.0:
        time.sleep(0.2)
        now = counts()
        if measured(now) != measured(last):
            changed = time.monotonic()
        last = now
    return last, changed


def fleet(robots: int, seconds: float, folder: Path, tls: bool, domain: int | None = None,
          warm_up: float = 2.0) -> FleetResult:
    """One fleet run; ``domain``: the base's DDS domain (default: the benchmark's next)."""
    folder.mkdir(parents=True, exist_ok=True)
    names = [robot_name(n) for n in range(robots)]
    domain = next_domains()[0] if domain is None else domain
    # the processes start as early as they can (their imports take seconds): the counter needs
    # nothing, the robots only the router; the warm-up waits for every route to form
    counter = Child("counter", [sys.executable, str(HERE / "fleet_counter.py"), str(robots)],
                    ros_env(domain), folder / "counter.log")
    children: list[Child] = [counter]
    router: Router | None = None
    base: subprocess.Popen | None = None
    try:
        certs = certificates(folder, names) if tls else None
        router = Router(certs, names)
        base = subprocess.Popen([ROSGATE, "run", str(base_file(folder, router.endpoint, certs))],
                                env=ros_env(domain), stderr=subprocess.PIPE, text=True)
        base_lines = Lines(base.stderr, "base")  # type: ignore[arg-type]
        groups = 2 if robots >= 10 else 1
        for i in range(groups):  # the robots have no ROS node: their domain does not matter
            first, last = robots * i // groups, robots * (i + 1) // groups
            children.append(Child(f"robots{first}", [
                sys.executable, str(HERE / "fleet_robots.py"), router.endpoint, str(first),
                str(last - first), *(["--tls", str(certs)] if certs else [])],
                ros_env(domain), folder / f"robots{first}.log"))
        base_lines.wait_for("running as", 60)
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
            phase("w", warm_up)
            time.sleep(0.5)
            now = counts()
            seen = sum(1 for c in now.values() if c.get("w"))
            changed = sum(c.get(CHANGED, 0) for c in now.values())
            log(f"fleet ({'TLS' if tls else 'no TLS'}): warm-up {rounds}: {seen} of {expected} "
                f"robot topics on the base" + (f", {changed} messages changed" if changed else ""))
            if seen == expected:
                break
        before = counts()
        ours = [base.pid, router.proc.pid] + [c.proc.pid for c in children]
        cpu0 = {pid: cpu_seconds(pid) for pid in ours}
        busy0, load0 = bench.system_busy(), loadavg()
        started = time.monotonic()
        results = phase("m", seconds)
        wall = time.monotonic() - started
        cpu1 = {pid: cpu_seconds(pid) for pid in ours}
        busy1, load1 = bench.system_busy(), loadavg()
        rss = memory_mb(base.pid)
        sent = {t: sum(r["sent"][t] for r in results) for t in TOPICS}
        ended = time.monotonic()
        after, last_counted = settled(counts, sum(sent.values()))
        settle = max(0.0, last_counted - ended)
        delivered = {t: sum(c.get("m", 0) - before.get(topic, {}).get("m", 0)
                            for topic, c in after.items() if topic.endswith("/" + t))
                     for t in TOPICS}
        changed = sum(c.get(CHANGED, 0) for c in after.values())
        published = sum(1 for c in after.values() if c.get("m"))
        robots_cpu = sum(r["cpu_s"] for r in results) / wall
        used = {pid: cpu1[pid] - cpu0[pid] for pid in ours}
        others = max(0.0, busy1 - busy0 - sum(used.values())) / (wall * (os.cpu_count() or 1))
    finally:
        if base is not None:
            base.send_signal(2)  # first, so that robots leaving is not what it logs last
            base.wait(20)
            base_lines.ended.wait(5)
        for child in children:
            child.quit()
        for child in reversed(children):
            child.stop()
        if router is not None:
            router.stop()
            router.lines.ended.wait(5)
    (folder / "base.log").write_text("\n".join(base_lines.seen) + "\n")
    (folder / "router.log").write_text("\n".join(router.lines.seen) + "\n")
    problems = [f"{who}: {line}" for who, lines in (("base", base_lines), ("router", router.lines))
                for line in lines.seen
                if " ERROR " in line or "Traceback" in line or (
                    " WARNING " in line and "without TLS" not in line and "INSECURE" not in line)
                or ("drops:" in line and not line.endswith("drops: none"))]
    return FleetResult(tls, robots, wall, published, sent, delivered, changed,
                       used[base.pid] / wall, rss, used[router.proc.pid] / wall, robots_cpu,
                       len(children) - 1, rounds, settle, (load0, load1), others, problems)


def throughput(settings: bench.Settings, folder: Path) -> list[bench.Result]:
    """2.5 kB over udp and over zenoh (both bridges clients of one router), through bench.py's
    cases: bench.bringup_files is wrapped to write the zenoh pair."""
    router = Router()
    plain = bench.bringup_files

    def bringup_files(route: Route, msg_type: str, depth: int, where: Path,
                      reliability: str = "reliable", *rest: Any, **kwargs: Any):
        if route.transport != "zenoh":  # bench.py's own, with whatever else it passes
            return plain(route, msg_type, depth, where, reliability, *rest, **kwargs)
        topic = (f"{{topic: /bench, type: {msg_type}, transport: zenoh, codec: {route.codec}, "
                 f"cipher: {route.cipher}, remote: bench/2k5, "
                 f"qos: {{reliability: {reliability}, history: keep_last, depth: {depth}}}")
        plugin = f"plugins: {{zenoh: {{mode: client, connect: [{router.endpoint}]}}}}\n"
        paths = where / "bench_a.yaml", where / "bench_b.yaml"
        for path, name, direction in zip(paths, ("bench_a", "bench_b"), ("transmit", "receive"),
                                         strict=True):
            # loopback, no TLS: the file says it takes frames from anyone who reaches the router
            path.write_text(f"bridge: {{name: {name}, role: peer, insecure: true}}\n{plugin}"
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


def report(fleets: list[FleetResult], rates: list[bench.Result], elapsed: float) -> str:
    parts = ["# rosgate fleet benchmark", "",
             f"{time.strftime('%Y-%m-%d %H:%M')}, rosgate {bench.revision()}, {os.cpu_count()} "
             f"cores, {elapsed / 60:.1f} min.", ""]
    if fleets:
        first = fleets[0]
        offered = sum(first.sent.values()) / first.seconds
        expected = first.robots * len(TOPICS)

        def row(label: str, cell) -> str:
            return f"| {label} | " + " | ".join(cell(r) for r in fleets) + " |"

        def share(part: int, whole: int) -> str:
            return f"{part:,} of {whole:,} ({part / max(1, whole):.2%})"

        parts += [
            f"## Fleet: {first.robots} robots x {len(TOPICS)} topics at 10 Hz "
            f"({offered:,.0f} msg/s) through one zenoh router into one base with fleet entries",
            "", "With TLS, the router is `rosgate router --tls DIR --base fleet_base --robot "
            "robot00 ...` (certificates from `rosgate certs`), the base says `tls: DIR`, and each "
            "simulated robot's zenoh session presents its own certificate; the router's access "
            "control lets each robot put only on its own keys. Without TLS, the same files say "
            "`insecure: true` instead.", "",
            "| | " + " | ".join(r.label for r in fleets) + " |",
            "|---|" + "--:|" * len(fleets),
            row("robot topics published on the base's ROS side",
                lambda r: f"{r.topics_published} of {expected}"),
            row("measured phase", lambda r: f"{r.seconds:.1f} s"),
            *[row(f"delivered {t}", lambda r, t=t: share(r.delivered[t], r.sent[t]))
              for t in TOPICS],
            row("**delivered, all**",
                lambda r: f"**{share(sum(r.delivered.values()), sum(r.sent.values()))}**"),
            row("arrived differing from the message sent (field by field)",
                lambda r: f"{r.changed}"),
            row("base CPU", lambda r: f"{r.base_cpu:.1%} of one core "
                f"({1e6 * r.base_cpu * r.seconds / max(1, sum(r.delivered.values())):.0f} "
                "µs/msg)"),
            row("base RSS", lambda r: f"{r.base_rss[0]:.0f} MB (peak {r.base_rss[1]:.0f} MB)"),
            row("router CPU", lambda r: f"{r.router_cpu:.1%} of one core"),
            row("simulated robots' CPU", lambda r: f"{r.robots_cpu:.1%} of one core "
                f"({r.robot_processes} processes)"),
            row("warm-up rounds", lambda r: f"{r.warm_up_rounds}"),
            row("counts settled after the phase's end (a lagging base shows here)",
                lambda r: f"{r.settle:.1f} s"),
            row("machine load (1-min loadavg, before / after)",
                lambda r: f"{r.load[0]:.2f} / {r.load[1]:.2f}"),
            row("other processes' share of the CPU meanwhile", lambda r: f"{r.others:.0%}"),
            "", f"**target: every robot's topics published on the base, nothing changed, "
            f"delivered >= {DELIVERED_TARGET:.1%}:** " + ", ".join(
                f"{r.label}: **{'MET' if r.met else 'NOT MET'}** ({r.ratio:.2%})"
                for r in fleets)]
        for r in fleets:
            if r.problems:
                parts += ["", f"{r.label}: the base's and the router's warnings and drop "
                          "counters:", "", *[f"- {line}" for line in r.problems[:10]]]
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
    parser.add_argument("--tls", choices=("both", "on", "off"), default="both",
                        help="the fleet with TLS and access control, without, or both (default)")
    parser.add_argument("--full", action="store_true", help="bench.py's full throughput trials")
    parser.add_argument("--skip-fleet", action="store_true")
    parser.add_argument("--skip-throughput", action="store_true")
    parser.add_argument("--out", type=Path, default=HERE / "fleet_results.md")
    args = parser.parse_args()
    start = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="rosgate-fleet-") as tmp:
        folder = Path(tmp)
        modes = [] if args.skip_fleet else {"both": [True, False], "on": [True],
                                            "off": [False]}[args.tls]
        fleets = [fleet(args.robots, args.seconds, folder / ("tls" if tls else "plain"), tls)
                  for tls in modes]
        rates = [] if args.skip_throughput else throughput(
            bench.FULL if args.full else bench.QUICK, folder)
    text = report(fleets, rates, time.monotonic() - start)
    print(text)
    args.out.write_text(text)
    failed = any(not r.met for r in fleets) or any(r.error for r in rates)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
