"""What a message costs in the bridges, counted in what does not depend on the machine's load:
system calls, thread switches and Python function calls per message, beside the CPU µs/msg.

    .venv/bin/python bench/cpu_counts.py [--size 2.5kB] [--path 'default file, reliable' ...]
                                         [--rate 2000] [--seconds 3] [--calls] [--top 25]

For each path (default: the default file reliable and best effort, and the udp floor) it starts
the case as bench.py does (fresh publisher, bridges A and B, subscriber) and runs, at ``--rate``:

1. a trial as bench.py's CPU trial: CPU µs/msg of A and B (load-dependent);
2. a trial under ``perf trace -s`` on A and on B: system calls per message by name, and context
   switches per message (from ``/proc/<pid>/task/*/status``), per side;
3. with ``--calls``, fresh bridges under bench/callcount.py (cProfile in every Python thread):
   Python function calls per message per side and thread, and the functions called most.

Each count is divided by the messages the subscriber received in that trial.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import processes
from processes import ROSGATE, Route

import bench
from bench import SIZES, Case, normalize

HERE = Path(__file__).resolve().parent
CALLCOUNT = HERE / "callcount.py"
PATHS = {route.path: route for route in
         [*bench.DEFAULTS, *bench.ROUTES, bench.SESSION, *bench.FLOORS]}
DEFAULT_PATHS = ["default file, reliable", "default file, best effort", "udp floor (no rosgate)"]


def switches(pid: int) -> Counter:
    """Context switches so far per thread name (voluntary: a wait; involuntary: preempted)."""
    out: Counter = Counter()
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            status = (task / "status").read_text()
        except OSError:
            continue
        name = re.search(r"^Name:\s*(.*)$", status, re.M).group(1)
        for kind in ("voluntary", "nonvoluntary"):
            found = re.search(rf"^{kind}_ctxt_switches:\s*(\d+)$", status, re.M)
            out[(name, kind)] += int(found.group(1))
    return out


def perf_trace(pid: int, out: Path) -> subprocess.Popen:
    return subprocess.Popen(["perf", "trace", "-s", "-p", str(pid), "-o", str(out)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def parse_perf(text: str) -> dict[str, Counter]:
    """perf trace -s's summary: thread ("name (tid)") -> syscall name -> calls."""
    threads: dict[str, Counter] = {}
    calls: Counter = Counter()
    for line in text.splitlines():
        thread = re.match(r"^ (\S.*\(\d+\)), \d+ events", line)
        if thread:
            calls = threads.setdefault(thread.group(1), Counter())
            continue
        found = re.match(r"^\s+([a-z_0-9]+)\s+(\d+)\s+\d+\s+[\d.]+", line)
        if found:
            calls[found.group(1)] += int(found.group(2))
    return threads


def syscall_trial(case: Case, rate: float, seconds: float, folder: Path) -> dict:
    sides = {"A": case.a, "B": case.b}
    before = {side: switches(p.pid) for side, p in sides.items()}
    tracers = {side: perf_trace(p.pid, folder / f"perf-{side}.txt") for side, p in sides.items()}
    time.sleep(1.0)  # perf attaches
    trial = case.trial(rate, seconds)
    for tracer in tracers.values():
        tracer.send_signal(signal.SIGINT)
        tracer.wait(30)
    after = {side: switches(p.pid) for side, p in sides.items()}
    n = max(trial.received, 1)
    out = {"messages": trial.received}
    for side in sides:
        threads = parse_perf((folder / f"perf-{side}.txt").read_text())
        calls = sum(threads.values(), Counter())
        moved = after[side] - before[side]
        out[side] = {
            "syscalls": sum(calls.values()) / n,
            "by_name": {k: v / n for k, v in calls.most_common(12)},
            "by_thread": {thread: {k: v / n for k, v in c.most_common(6) if v / n >= 0.01}
                          for thread, c in sorted(threads.items(), key=lambda t: -sum(
                              t[1].values())) if sum(c.values()) / n >= 0.05},
            "switches": {f"{name} {kind}": v / n for (name, kind), v in moved.most_common(10)},
            "switches_total": sum(moved.values()) / n,
        }
    return out


class CountedBridge(processes.Bridge):
    """``rosgate run FILE`` under bench/callcount.py."""

    def __init__(self, config: Path, domain: int, checkout=processes.HERE_CHECKOUT):
        self.name = config.stem
        self.config = config
        self.fifo = config.with_suffix(".fifo")
        os.mkfifo(self.fifo)
        self.proc = subprocess.Popen(
            [sys.executable, str(CALLCOUNT), str(self.fifo), ROSGATE, "run", str(config)],
            env=processes.ros_env(domain, checkout.root), stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE, text=True)
        self.lines = processes.Lines(self.proc.stderr, f"bridge {self.name}")


class CountedFloor(processes.Floor):
    def __init__(self, side, route, msg_type, port, depth, reliability, folder, domain):
        self.name = f"floor_{side}"
        self.config = folder / f"{self.name}.yaml"
        self.fifo = folder / f"{self.name}.fifo"
        os.mkfifo(self.fifo)
        self.proc = subprocess.Popen(
            [sys.executable, str(CALLCOUNT), str(self.fifo), str(processes.FLOOR), side,
             route.transport, msg_type, str(port), str(depth), reliability],
            env=processes.ros_env(domain), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
            text=True)
        self.lines = processes.Lines(self.proc.stderr, self.name)


def snapshot(process, path: Path) -> dict:
    with open(process.fifo, "w") as fifo:
        fifo.write(f"{path}\n")
    deadline = time.monotonic() + 30
    while not path.exists():
        if time.monotonic() > deadline:
            raise RuntimeError(f"{process.name}: no call counts")
        time.sleep(0.05)
    return json.loads(path.read_text())


def calls_trial(case: Case, rate: float, seconds: float, folder: Path) -> dict:
    sides = {"A": case.a, "B": case.b}
    before = {side: snapshot(p, folder / f"calls-{side}-0.json") for side, p in sides.items()}
    trial = case.trial(rate, seconds)
    after = {side: snapshot(p, folder / f"calls-{side}-1.json") for side, p in sides.items()}
    n = max(trial.received, 1)
    out: dict = {"messages": trial.received}
    for side in sides:
        per_thread, per_function = Counter(), Counter()
        for thread, counts in after[side].items():
            old = before[side].get(thread, {})
            for function, calls in counts.items():
                moved = calls - old.get(function, 0)
                if moved:
                    per_thread[thread.split("#")[0]] += moved
                    per_function[function] += moved
        out[side] = {"calls": sum(per_thread.values()) / n,
                     "threads": {k: v / n for k, v in per_thread.most_common()},
                     "functions": {k: v / n for k, v in per_function.most_common(200)}}
    return out


def perf_trial(case: Case, rate: float, seconds: float, folder: Path) -> dict:
    """``perf record`` on A and B during a trial: the share of samples per library (the
    interpreter, libc, the kernel, Fast DDS, the cipher ...) and CPU µs/msg each stands for."""
    sides = {"A": case.a, "B": case.b}
    records = {side: subprocess.Popen(
        ["perf", "record", "-F", "997", "-p", str(p.pid), "-o", str(folder / f"perf-{side}.data")],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL) for side, p in sides.items()}
    time.sleep(1.0)
    cpu0 = {side: p.cpu() for side, p in sides.items()}
    trial = case.trial(rate, seconds)
    cpu1 = {side: p.cpu() for side, p in sides.items()}
    for record in records.values():
        record.send_signal(signal.SIGINT)
        record.wait(60)
    n = max(trial.received, 1)
    out: dict = {}
    for side in sides:
        report = subprocess.run(
            ["perf", "report", "-i", str(folder / f"perf-{side}.data"), "--sort", "dso",
             "--stdio", "--percent-limit", "1"], capture_output=True, text=True).stdout
        us = (cpu1[side] - cpu0[side]) / n * 1e6
        shares = {}
        for line in report.splitlines():
            found = re.match(r"^\s+([\d.]+)%\s+(\S.*)$", line)
            if found:
                shares[found.group(2).strip()] = float(found.group(1))
        out[side] = {"us": us, "dso": {k: (v, v / 100 * us) for k, v in shares.items()}}
    return out


def run_path(route: Route, size, rate: float, seconds: float, calls: bool, folder: Path,
             perf: bool = False) -> dict:
    result: dict = {"path": route.path, "size": size.name, "rate": rate}
    with Case(size, route, folder / "plain") as case:
        case.warm_up()
        trial = case.trial(rate, seconds)
        result["cpu"] = {side: trial.us_per_msg(side) for side in ("pub", "A", "B", "sub")}
        result["delivered"] = trial.in_time / max(trial.sent, 1)
        n = max(trial.received, 1)
        result["threads"] = {side: {f"{name} {tid}": (user + system) / n * 1e6
                                    for tid, (name, user, system) in threads.items()
                                    if (user + system) / n * 1e6 >= 1}
                             for side, threads in trial.threads.items()}
        result["sys"] = syscall_trial(case, rate, seconds, folder)
        if perf:
            result["perf"] = perf_trial(case, rate, seconds, folder)
    if calls:
        saved = bench.Bridge, bench.Floor
        bench.Bridge, bench.Floor = CountedBridge, CountedFloor
        try:
            with Case(size, route, folder / "calls") as case:
                case.warm_up()
                result["calls"] = calls_trial(case, rate, seconds, folder)
        finally:
            bench.Bridge, bench.Floor = saved
    return result


def report(result: dict, top: int) -> str:
    lines = [f"## {result['size']} {result['path']} at {result['rate']:,.0f} msg/s "
             f"({result['delivered']:.1%} delivered)"]
    cpu = result["cpu"]
    lines.append("CPU µs/msg: " + ", ".join(f"{k} {v:.1f}" for k, v in cpu.items() if v))
    for side in ("A", "B"):
        lines.append(f"{side}: CPU µs/msg per thread: " + ", ".join(
            f"{k} {v:.0f}" for k, v in sorted(result["threads"][side].items(),
                                              key=lambda kv: -kv[1])))
        sys_ = result["sys"][side]
        lines.append(f"{side}: syscalls/msg {sys_['syscalls']:.2f} ("
                     + ", ".join(f"{k} {v:.2f}" for k, v in sys_["by_name"].items()) + ")")
        for thread, calls in sys_["by_thread"].items():
            lines.append(f"    {thread}: " + ", ".join(f"{k} {v:.2f}" for k, v in calls.items()))
        lines.append(f"{side}: context switches/msg {sys_['switches_total']:.2f} ("
                     + ", ".join(f"{k} {v:.2f}" for k, v in sys_["switches"].items() if v >= 0.01)
                     + ")")
        if "perf" in result:
            perf = result["perf"][side]
            lines.append(f"{side}: perf, {perf['us']:.1f} µs/msg in the trial: " + ", ".join(
                f"{k} {share:.0f}% ({us:.1f})" for k, (share, us) in perf["dso"].items()))
        if "calls" in result:
            calls = result["calls"][side]
            lines.append(f"{side}: Python calls/msg {calls['calls']:.1f} ("
                         + ", ".join(f"{k} {v:.1f}" for k, v in calls["threads"].items()
                                     if v >= 0.1) + ")")
            for function, per in list(calls["functions"].items())[:top]:
                lines.append(f"    {per:7.2f}  {function}")
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", action="append", help="100B, 2.5kB, 10kB (repeatable)")
    parser.add_argument("--path", action="append", help="a bench.py path label (repeatable)")
    parser.add_argument("--rate", type=float, default=bench.CPU_RATE)
    parser.add_argument("--seconds", type=float, default=3.0)
    parser.add_argument("--calls", action="store_true", help="count Python calls (cProfile)")
    parser.add_argument("--perf", action="store_true",
                        help="perf record: samples per library (interpreter, kernel, DDS...)")
    parser.add_argument("--top", type=int, default=25, help="functions listed per side")
    parser.add_argument("--json", type=Path, help="also write every number here")
    args = parser.parse_args()
    sizes = [s for s in SIZES if s.key in {normalize(k) for k in args.size or ["2.5kB"]}]
    results = []
    with tempfile.TemporaryDirectory(prefix="rosgate-cpu-counts-") as tmp:
        for size in sizes:
            for label in args.path or DEFAULT_PATHS:
                route = PATHS[label]
                folder = Path(tmp) / f"{size.key}-{len(results)}"
                folder.mkdir()
                result = run_path(route, size, args.rate, args.seconds, args.calls, folder,
                                  args.perf)
                results.append(result)
                print(report(result, args.top), flush=True)
                print(flush=True)
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
