"""Overload on a shaped link: the default file's best-effort topic and a real_time Twist
across two network namespaces joined by a veth pair that the kernel's token bucket (``tbf``)
caps at 10 Mbit/s each way, offered twice what the link carries.

    .venv/bin/python bench/shaped.py [--rate 10mbit] [--size 2500] [--seconds 4] [--out FILE]

    namespace rgshaped-a (10.201.0.1)                    namespace rgshaped-b (10.201.0.2)
    publisher --DDS--> bridge A (client) ==veth, tbf==> bridge B (server) --DDS--> subscriber
    Twist 20 Hz --DDS-->                                                  --DDS--> Twist's

Each namespace has its own loopback, so DDS stays inside it (and its own DDS domain, from
ROSGATE_BENCH_DOMAINS). The files are the default file (client/server, identities, udp with the
max_frame it takes from the path, cdr, aead); the measured topic best effort
(``{reliability: best_effort, history: keep_last, depth: 1000}``), the Twist ``priority:
real_time``, reliable, as a teleoperation node publishes it.

First a trial offered far more than 10 Mbit/s says what the link carries (messages delivered
per second); then a trial at twice that, with the Twist at 20 Hz beside it: the share
delivered, p50/p99 age (receive time minus the publisher's stamp) of what arrived, of what
arrived during the last quarter the share sent in it (the newest), the Twist's arrivals and
p99 age, the bridges' drops by reason and what tbf dropped. Targets (the issue's): the
best-effort topic's p99 <= 50 ms and the newest delivered, the Twist's p99 <= 20 ms.

Needs root (``ip netns``, ``tc``); without it, it says so and exits 0. Sends only between the
two namespaces it makes, and deletes them at the end, and any left by an earlier run at the
start. Writes bench/shaped_results.md (``--out -``: stdout only).
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from processes import (  # noqa: E402
    TWIST_TOPIC,
    Bridge,
    Endpoint,
    Route,
    StampedEnds,
    bringup_files,
    free_port,
    next_domains,
)

from bench import (  # noqa: E402
    NEWEST,
    OVERLOAD,
    OVERLOAD_P99_MS,
    TWIST_P99_MS,
    TWIST_RATE,
    Load,
    percentile,
    revision,
)

NAMESPACES = ("rgshaped-a", "rgshaped-b")
VETH = ("rgsh-a", "rgsh-b")
ADDRESSES = ("10.201.0.1", "10.201.0.2")
DEFAULT_BE = Route("udp", cipher="aead", roles="session", max_frame=None,
                   reliability="best_effort")
DEPTH = 1000
BUDGET = 0.9  # the budgeted case's bandwidth: this share of tbf's rate
DRAIN_QUIET, DRAIN_MAX = 0.5, 15.0


def log(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, check=check)


def in_ns(name: str) -> tuple[str, ...]:
    return ("ip", "netns", "exec", name)


def remove_namespaces() -> None:
    """This script's namespaces, if there (deleting one deletes its end of the veth pair, and
    with it the other end)."""
    listed = ip("netns", "list", check=False).stdout
    for name in NAMESPACES:
        if any(line.split()[:1] == [name] for line in listed.splitlines()):
            ip("netns", "del", name, check=False)


def make_link(rate: str) -> None:
    """Two namespaces, a veth pair between them, tbf on both ends (one per direction)."""
    for name in NAMESPACES:
        ip("netns", "add", name)
        ip("-n", name, "link", "set", "lo", "up")
    ip("link", "add", VETH[0], "netns", NAMESPACES[0], "type", "veth", "peer", "name", VETH[1],
       "netns", NAMESPACES[1])
    for name, dev, address in zip(NAMESPACES, VETH, ADDRESSES, strict=True):
        ip("-n", name, "addr", "add", f"{address}/24", "dev", dev)
        ip("-n", name, "link", "set", dev, "up")
        subprocess.run([*in_ns(name), "tc", "qdisc", "add", "dev", dev, "root", "tbf", "rate",
                        rate, "burst", "32kbit", "latency", "50ms"], check=True,
                       capture_output=True, text=True)


def tbf_drops() -> int:
    """Packets tbf dropped on both ends so far."""
    total = 0
    for name, dev in zip(NAMESPACES, VETH, strict=True):
        shown = subprocess.run([*in_ns(name), "tc", "-s", "qdisc", "show", "dev", dev],
                               capture_output=True, text=True).stdout
        words = shown.replace(",", " ").replace("(", " ").split()
        if "dropped" in words:
            total += int(words[words.index("dropped") + 1])
    return total


class Shaped:
    """The six processes, started in the two namespaces."""

    def __init__(self, folder: Path, size: int, stack: ExitStack, budget: str | None):
        def started(process):
            stack.callback(process.stop)
            return process

        self.folder = folder
        pub_domain, sub_domain = next_domains()
        ns_a, ns_b = (in_ns(name) for name in NAMESPACES)
        port = free_port()
        a, b = bringup_files(DEFAULT_BE, "std_msgs/msg/String", DEPTH, folder, "best_effort",
                             port=port, twist=True, host=(ADDRESSES[1], ADDRESSES[1]))
        if budget:  # both sides, as docs/real-links.md says: each budgets what it sends
            for path in (a, b):
                path.write_text(path.read_text().replace(
                    "bridge: {", f"bridge: {{links: {{udp: {{bandwidth: {budget}}}}}, ", 1))
        spec = [{"topic": TWIST_TOPIC, "kind": "twist", "rate": TWIST_RATE, "size": 48,
                 "reliable": True}]
        self.sub = started(Endpoint("sub", "string", size, DEPTH, sub_domain,
                                    folder / "sub.log", "best_effort", ns_b))
        self.twist_sub = started(StampedEnds("sub", spec, sub_domain, folder / "twist_sub.log",
                                             ns_b))
        self.b = started(Bridge(b, sub_domain, prefix=ns_b))
        self.a = started(Bridge(a, pub_domain, prefix=ns_a))
        self.twist_pub = started(StampedEnds("pub", spec, pub_domain, folder / "twist_pub.log",
                                             ns_a))
        self.pub = started(Endpoint("pub", "string", size, DEPTH, pub_domain,
                                    folder / "pub.log", "best_effort", ns_a))
        for process in (self.sub, self.twist_sub, self.b, self.a, self.twist_pub, self.pub):
            process.ready()
        self.trials = 0

    def warm_up(self) -> None:
        deadline = time.monotonic() + 60
        while not self.sub.ask("stats 0")["received"]:
            if time.monotonic() > deadline:
                raise RuntimeError("nothing crossed in 60 s")
            self.pub.ask("run 0 20 0.5", timeout=30)
        while not self.twist_sub.ask("count")[TWIST_TOPIC]:
            if time.monotonic() > deadline:
                raise RuntimeError("no Twist crossed in 60 s")
            self.twist_pub.ask("once", timeout=30)
            time.sleep(0.1)
        self.drain()

    def drain(self) -> None:
        deadline, last = time.monotonic() + DRAIN_MAX, -1
        while time.monotonic() < deadline:
            total = self.sub.ask("total")["received"]
            if total == last:
                return
            last = total
            time.sleep(DRAIN_QUIET)

    def trial(self, rate: float, seconds: float) -> dict:
        self.trials += 1
        since = time.time_ns()
        before = self.twist_sub.ask("count")[TWIST_TOPIC]
        self.twist_pub.send(f"run {seconds}")
        sent = self.pub.ask(f"run {self.trials} {rate} {seconds}", timeout=seconds * 3 + 30)
        twists = self.twist_pub.reply(30)["sent"][TWIST_TOPIC]
        self.drain()
        self.twist_sub.settle(TWIST_TOPIC, before + twists)
        got = self.sub.ask(f"stats {self.trials} {sent['end_ns'] + 100_000_000} "
                           f"{sent['tail_ns']} {sent['end_ns']}")
        ages = self.twist_sub.ages_ms(self.folder, since, TWIST_TOPIC)
        return {"offered": sent["sent"] / sent["seconds"], "sent": sent["sent"],
                "seconds": sent["seconds"], **got, "twist_sent": twists, "twist_ages": ages}


def describe(t: dict) -> str:
    ms = lambda us: "-" if us is None else f"{us / 1000:.1f}"
    ages = t["twist_ages"]
    twist = (f"Twist {len(ages)} of {t['twist_sent']}, p99 {percentile(ages, 0.99):.1f} ms"
             if ages else f"Twist 0 of {t['twist_sent']}")
    newest = f"{t['tail_fresh'] / t['tail']:.0%}" if t["tail"] else "-"
    return (f"offered {t['offered']:,.0f}/s, delivered {t['in_time'] / t['seconds']:,.0f}/s in "
            f"time, {t['received'] / max(t['sent'], 1):.1%} at all, age p50 {ms(t['p50_us'])} "
            f"ms p99 {ms(t['p99_us'])} ms, newest {newest}; {twist}")


def drops(bridge: Bridge) -> dict[str, int]:
    found: dict[str, int] = {}
    for line in bridge.lines.seen:
        if "drops: " in line:
            for item in line.rsplit("drops: ", 1)[1].split(", "):
                reason, _, count = item.partition("=")
                if count.isdigit():
                    found[reason] = found.get(reason, 0) + int(count)
    return found


@dataclass
class Result:
    name: str
    calibration: dict
    trial: dict
    drops: dict[str, int]
    tbf: int

    def row(self) -> str:
        t, ages = self.trial, self.trial["twist_ages"]
        ms = lambda us: "-" if us is None else f"{us / 1000:.1f}"
        newest = f"{t['tail_fresh'] / t['tail']:.0%}" if t["tail"] else "-"
        said = ", ".join(f"{k}={v}" for k, v in sorted(self.drops.items())) or "none"
        carried = self.calibration["in_time"] / self.calibration["seconds"]
        return (f"| {self.name} | {carried:,.0f} | {t['offered']:,.0f} | "
                f"{t['received'] / max(t['sent'], 1):.1%} | {ms(t['p50_us'])} | "
                f"{ms(t['p99_us'])} | {newest} | {len(ages)} of {t['twist_sent']} | "
                f"{f'{percentile(ages, 0.5):.1f}' if ages else '-'} | "
                f"{f'{percentile(ages, 0.99):.1f}' if ages else '-'} | {said} | {self.tbf} |")

    def verdicts(self) -> list[str]:
        t, ages = self.trial, self.trial["twist_ages"]
        newest = t["tail_fresh"] / t["tail"] if t["tail"] else None
        fresh = (t["p99_us"] is not None and t["p99_us"] <= OVERLOAD_P99_MS * 1000
                 and newest is not None and newest >= NEWEST)
        twist_p99 = percentile(ages, 0.99) if ages else None
        twist = (twist_p99 is not None and twist_p99 <= TWIST_P99_MS
                 and len(ages) >= t["twist_sent"])
        return [f"**{self.name}: best effort at {OVERLOAD:g}x what the link carries, age p99 <= "
                f"{OVERLOAD_P99_MS} ms and the newest delivered (>= {NEWEST:.0%} of the last "
                f"quarter's arrivals sent in it): {'MET' if fresh else 'NOT MET'}; the real_time "
                f"Twist beside it, every one and p99 <= {TWIST_P99_MS} ms: "
                f"{'MET' if twist else 'NOT MET'}**"]


def report(rate: str, size: int, results: list[Result], others: float) -> str:
    return "\n".join([
        "# Overload on a shaped link", "",
        f"{time.strftime('%Y-%m-%d %H:%M')}, rosgate {revision()}; two network namespaces, a "
        f"veth pair, tbf {rate} (burst 32kbit, latency 50ms) each way; the default file "
        f"(client/server, identities, udp, aead), and the same with a budget a little below "
        f"the link (`links: {{udp: {{bandwidth: ...}}}}` on both sides); {size:,} B best "
        f"effort, depth {DEPTH}, and a real_time Twist at {TWIST_RATE} Hz; other processes "
        f"used {others:.0%} of the CPU meanwhile. Carried: msg/s delivered in a trial offered "
        f"3x the link's rate; the trial offers {OVERLOAD:g}x that. Age: receive time minus the "
        "publisher's stamp. Newest: of what arrived during the trial's last quarter, the "
        "share sent in it.", "",
        "| file | carried msg/s | offered msg/s | delivered | age p50 ms | age p99 ms | newest | "
        "Twist arrived | Twist p50 ms | Twist p99 ms | bridges' drops (whole run) | "
        "tbf dropped packets |",
        "|---|--:|--:|--:|--:|--:|--:|--:|--:|--:|---|--:|",
        *[r.row() for r in results], "",
        *[line for r in results for line in r.verdicts()], ""])


def run_case(name: str, budget: str | None, args: argparse.Namespace, folder: Path) -> Result:
    """Fresh namespaces and processes: a trial at 3x the link's rate says what it carries,
    then one at OVERLOAD x that, the Twist beside it."""
    remove_namespaces()
    with ExitStack() as stack:
        stack.callback(remove_namespaces)  # last: after every process has stopped
        make_link(args.rate)
        folder.mkdir()
        shaped = Shaped(folder, args.size, stack, budget)
        shaped.warm_up()
        nominal = rate_bits(args.rate) / (args.size * 8)
        calibration = shaped.trial(3 * nominal, args.seconds)
        log(f"shaped [{name}]: offered 3x the link: {describe(calibration)}")
        carried = calibration["in_time"] / calibration["seconds"]
        tbf0 = tbf_drops()
        trial = shaped.trial(OVERLOAD * carried, args.seconds)
        log(f"shaped [{name}]: offered {OVERLOAD:g}x what it carried: {describe(trial)}")
        tbf = tbf_drops() - tbf0
        stack.close()  # the bridges log their counters when they stop
    counted = drops(shaped.a)
    for reason, n in drops(shaped.b).items():
        counted[reason] = counted.get(reason, 0) + n
    return Result(name, calibration, trial, counted, tbf)


def rate_bits(rate: str) -> float:
    """tc's "10mbit" (or kbit, gbit) in bits per second."""
    for unit, factor in (("gbit", 1e9), ("mbit", 1e6), ("kbit", 1e3), ("bit", 1.0)):
        if rate.endswith(unit):
            return float(rate.removesuffix(unit)) * factor
    sys.exit(f"shaped: --rate {rate}: write it as tc does, e.g. 10mbit")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rate", default="10mbit", help="tbf's rate each way (default 10mbit)")
    parser.add_argument("--size", type=int, default=2500, help="String bytes (default 2500)")
    parser.add_argument("--seconds", type=float, default=4.0, help="each trial (default 4)")
    parser.add_argument("--out", default=str(HERE / "shaped_results.md"))
    args = parser.parse_args()
    if os.geteuid() != 0 or not shutil.which("ip") or not shutil.which("tc"):
        log("shaped: needs root, ip and tc (network namespaces, tbf): skipped")
        return 0
    budget = f"{BUDGET * rate_bits(args.rate) / 1e6:g}mbit"
    load = Load()
    results = []
    with tempfile.TemporaryDirectory(prefix="rosgate-shaped-") as tmp:
        for i, (name, extra) in enumerate([("default file", None),
                                           (f"default file, bandwidth {budget}", budget)]):
            try:
                results.append(run_case(name, extra, args, Path(tmp) / f"case{i}"))
            except RuntimeError as exc:
                log(f"shaped [{name}]: FAILED: {exc}")
    text = report(args.rate, args.size, results, load.others())
    print(text)
    if args.out != "-":
        Path(args.out).write_text(text)
        log(f"shaped: wrote {args.out}")
    return 0 if len(results) == 2 else 1


if __name__ == "__main__":
    sys.exit(main())
