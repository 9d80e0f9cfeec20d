"""The constrained-link benchmark: two bridges through the link emulator set to issue 12's
Wi-Fi (20 Mbit/s, 10 ms, 2 ms jitter, 1 % loss per IP packet, MTU 1500), everything in one run.

    publisher --DDS--> bridge A --udp--> relay (python -m rosgate_emulator) --udp-->
    bridge B --DDS--> subscriber          (and back: NACKs and ACKs)

Sections, each a few cases of fresh processes:

1. **mixed**: a 640x480 rgb8 camera (921,600 B of noise) at 10 Hz, a Twist at 50 Hz and a
   100-byte String at 100 Hz, for ``--seconds``. Per topic: delivered Hz, latency (for the
   camera: age) p50/p99/max, over time and in all; the camera's queue in bridge A. Cases:
   ``main`` (the rosgate of ``--base``, today's defaults: 65,000-byte datagrams, one queue),
   ``defaults`` (this checkout, the same file: what the new defaults alone do) and ``tuned``
   (a budget, priorities, latest-only, FEC).
2. **1 MB over 1 % loss**: 1024x1024 mono8 images, one every 0.5 s, with recovery none, fec
   and retransmit (and ``main``): the share delivered.
3. **compression**: a 4000x4000 OccupancyGrid, 95 % unknown, with and without zstd: bytes on
   the wire per map (bridge A's counters and the emulator's), and how long one takes.

Writes ``bench/constrained_results.md`` and ``bench/plots/constrained-*.png`` (delivered rate and
latency per topic over time, per case of section 1). ``--quick``: 8 s cases, no ``main``.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from processes import (  # noqa: E402
    HERE_CHECKOUT,
    ROOT,
    Bridge,
    Checkout,
    Endpoint,
    Lines,
    Process,
    free_port,
    ros_env,
)

from bench import Load, base_checkout, revision  # noqa: E402

ENDS = HERE / "constrained_ends.py"
PRESET = "wifi"
WIFI = "20 Mbit/s, 10 ms delay, 2 ms jitter, 1 % loss per IP packet, MTU 1500, 250 kB queue"

# The camera is reliable between the ROS ends and the bridges: Fast DDS loses most best-effort
# samples of 921,600 bytes on this machine before any bridge sees them (bare pub -> sub at
# 10 Hz: 17 of 50 arrived), which would measure DDS, not the link.
MIXED = [
    {"topic": "/camera", "kind": "image", "rate": 10, "size": 921_600, "reliable": True,
     "qos": "{reliability: reliable, depth: 5}"},
    {"topic": "/cmd_vel", "kind": "twist", "rate": 50, "size": 48, "reliable": True},
    {"topic": "/status", "kind": "string", "rate": 100, "size": 100, "reliable": True},
]
BIG = [{"topic": "/big", "kind": "image", "rate": 2, "size": 1 << 20, "reliable": True}]
GRID = [{"topic": "/map", "kind": "grid", "rate": 0.5, "size": 4000 * 4000, "reliable": True}]
TYPES = {"image": "sensor_msgs/msg/Image", "twist": "geometry_msgs/msg/Twist",
         "string": "std_msgs/msg/String", "grid": "nav_msgs/msg/OccupancyGrid"}

#: what the tuned case adds to each topic, and to bridge A
TUNED = {"/camera": "priority: data_low, latest_only: true, max_delay: 0.05, "
                   "recovery: {fec: {overhead: 0.05}}",
         "/cmd_vel": "priority: interactive_high", "/status": "priority: data"}
BUDGET = "links: {udp: {bandwidth: 20mbit}}"
#: the tuned case knows its network: Ethernet's MTU, so datagrams of 1,472 bytes
TUNED_PLUGINS = "plugins: {udp: {max_frame: 1472}}"


def log(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


_FIRST, _LAST = (int(n) for n in os.environ.get("ROSGATE_BENCH_DOMAINS", "170-179").split("-"))
_pairs = itertools.cycle(range(_FIRST, _LAST, 2))


def domains() -> tuple[int, int]:
    """A pair of DDS domains: from ROSGATE_BENCH_DOMAINS=FIRST-LAST, else 170-179 (bench.py
    uses 150-169, the tests 20-119)."""
    first = next(_pairs)
    return first, first + 1


class Ends(Endpoint):
    """The publisher or the subscriber (constrained_ends.py), driven as bench's endpoints are."""

    def __init__(self, role: str, spec: list[dict], domain: int, log_file: Path):
        self.name = role
        self.log = log_file.open("w")
        self.proc = subprocess.Popen([sys.executable, str(ENDS), role, json.dumps(spec)],
                                     env=ros_env(domain), stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, stderr=self.log, text=True,
                                     bufsize=1)
        self.lines = Lines(self.proc.stdout, role)
        self.lines.wait_for('"ready"', 60)

    def ask(self, command: str, timeout: float = 30.0) -> dict[str, Any]:
        return super().ask(command, timeout)


class Relay(Process):
    """``python -m rosgate_emulator udp --preset wifi``, a process of its own."""

    def __init__(self, listen: int, target: int, **overrides: Any):
        extra = [a for k, v in overrides.items() for a in (f"--{k}", str(v))]
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "rosgate_emulator", "udp", "--preset", PRESET,
             "--listen", f"127.0.0.1:{listen}", "--target", f"127.0.0.1:{target}", *extra],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
            env=dict(os.environ, PYTHONPATH=str(ROOT / "tools" / "emulator" / "src")))
        self.lines = Lines(self.proc.stdout, "relay")
        self.lines.wait_for("->", 20)
        self.counters: dict[str, Any] = {}

    def stop(self) -> None:
        super().stop()
        self.lines.ended.wait(5)
        for line in reversed(self.lines.seen):
            if line.startswith("{"):
                self.counters = json.loads(line)
                break


@dataclass
class Case:
    section: str
    name: str
    spec: list[dict]
    checkout: Checkout = HERE_CHECKOUT
    topic_keys: dict[str, str] = field(default_factory=dict)
    bridge_a: str = ""
    plugins_a: str = ""
    seconds: float = 20.0
    drain: float = 3.0
    #: seconds between warm-up messages: longer than one takes on the link, or the warm-up
    #: leaves a backlog the measured messages wait behind (a raw map takes 6.4 s)
    probe_every: float = 1.0
    # results
    arrivals: dict[str, list[list[int]]] = field(default_factory=dict)
    sent: dict[str, int] = field(default_factory=dict)
    start_ns: int = 0
    counters_a: dict[str, dict[str, Any]] = field(default_factory=dict)
    relay: dict[str, Any] = field(default_factory=dict)
    problems: list[str] = field(default_factory=list)
    error: str = ""
    note: str = ""  # said beside its results


def files(case: Case, folder: Path, relay_port: int, port_b: int) -> tuple[Path, Path]:
    entries_a, entries_b = [], []
    for t in case.spec:
        qos = "qos: " + t.get("qos", "100" if t["reliable"] else "sensor_data")
        common = f"topic: {t['topic']}, type: {TYPES[t['kind']]}, {qos}"
        extra = case.topic_keys.get(t["topic"], "")
        entries_a.append(f"  - {{{common}, direction: transmit, port: {relay_port}"
                         f"{', ' + extra if extra else ''}}}")
        entries_b.append(f"  - {{{common}, direction: receive, port: {port_b}}}")
    bridge = "{{name: {}, role: peer, peer: 127.0.0.1, listen: 127.0.0.1{}}}"
    a, b = folder / "bridge_a.yaml", folder / "bridge_b.yaml"
    a.write_text(f"bridge: {bridge.format('robot', ', ' + case.bridge_a if case.bridge_a else '')}"
                 f"\n{case.plugins_a}\ntopics:\n" + "\n".join(entries_a) + "\n")
    b.write_text(f"bridge: {bridge.format('base', '')}\ntopics:\n" + "\n".join(entries_b) + "\n")
    return a, b


COUNTER_LINE = re.compile(
    r"INFO (?P<topic>/\S+): sent (?P<sent>\d+) \((?P<bytes>\d+) B\)(?P<rest>.*)")


def bridge_counters(lines: list[str]) -> dict[str, dict[str, Any]]:
    """What bridge A logged when it stopped, per topic."""
    out: dict[str, dict[str, Any]] = {}
    for line in lines:
        match = COUNTER_LINE.search(line)
        if match is None:
            continue
        rest = match["rest"]
        wire = re.search(r"on the wire (\d+) B", rest)
        drops = rest.partition("drops: ")[2]
        out[match["topic"]] = {
            "sent": int(match["sent"]), "bytes": int(match["bytes"]),
            "wire": int(wire[1]) if wire else int(match["bytes"]),
            "drops": dict((k, int(v)) for k, v in re.findall(r"(\w+)=(\d+)", drops)),
            "retransmitted": int(m[1]) if (m := re.search(r"retransmitted (\d+)", rest)) else 0,
        }
    return out


def run(case: Case, folder: Path) -> Case:
    folder.mkdir(parents=True, exist_ok=True)
    pub_domain, sub_domain = domains()
    port_b, relay_port = free_port(), free_port()
    a_file, b_file = files(case, folder, relay_port, port_b)
    log(f"[{case.section}/{case.name}] {case.seconds:g} s ...")
    with ExitStack() as stack:
        def started(process):
            stack.callback(process.stop)
            return process

        sub = started(Ends("sub", case.spec, sub_domain, folder / "sub.log"))
        b = started(Bridge(b_file, sub_domain, case.checkout))
        relay = started(Relay(relay_port, port_b))
        a = started(Bridge(a_file, pub_domain, case.checkout))
        try:
            for bridge in (a, b):
                bridge.ready()
            pub = started(Ends("pub", case.spec, pub_domain, folder / "pub.log"))
            # warm-up: one message of each topic until one crosses (discovery, first frames)
            deadline, probes = time.monotonic() + 60, 0
            while not any(sub.ask("count").values()):
                if time.monotonic() > deadline:
                    if case.section != "big":
                        raise RuntimeError("nothing crossed in 60 s")
                    # a 1 MB message without recovery over 1 % loss crosses 0.02 % of the time:
                    # that is the result; measure the run all the same
                    case.note = f"none of {probes} warm-up messages crossed either"
                    break
                pub.ask("once", timeout=30)
                probes += 1
                time.sleep(case.probe_every)
            time.sleep(case.drain)
            sub.ask(f"dump {folder / 'warmup.json'}")
            case.start_ns = time.time_ns()
            case.sent = pub.ask(f"run {case.seconds}", timeout=case.seconds + 60)["sent"]
            time.sleep(case.drain)
            sub.ask(f"dump {folder / 'arrivals.json'}")
            arrivals = json.loads((folder / "arrivals.json").read_text())
            case.arrivals = {topic: [a for a in items if a[1] >= case.start_ns]
                             for topic, items in arrivals.items()}
        except Exception as exc:  # a case that fails is reported, the run goes on
            case.error = f"{type(exc).__name__}: {exc}"
            log(f"  failed: {case.error}")
        finally:
            a.stop()  # first: its counters, and the relay's, are read below
            relay.stop()
        case.counters_a = bridge_counters(a.lines.seen)
        case.relay = relay.counters
        case.problems = [line for line in a.lines.seen + b.lines.seen
                         if " WARNING " in line or "Traceback" in line][:8]
    return case


# -- figures ----------------------------------------------------------------------------------
def percentile(values: list[float], q: float) -> float | None:
    if not values:
        return None
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))]


@dataclass
class TopicResult:
    topic: str
    offered_hz: float
    delivered_hz: float
    delivered: int
    sent: int
    p50_ms: float | None
    p99_ms: float | None
    max_ms: float | None
    first_half_p50: float | None
    second_half_p50: float | None


def topic_results(case: Case) -> list[TopicResult]:
    out = []
    for t in case.spec:
        topic = t["topic"]
        items = case.arrivals.get(topic, [])
        latencies = [(arrival - sent) / 1e6 for arrival, sent, _ in items]
        middle = case.start_ns + case.seconds * 5e8
        first = [(a - s) / 1e6 for a, s, _ in items if s < middle]
        second = [(a - s) / 1e6 for a, s, _ in items if s >= middle]
        out.append(TopicResult(topic, t["rate"], len(items) / case.seconds, len(items),
                               case.sent.get(topic, 0), percentile(latencies, 0.5),
                               percentile(latencies, 0.99), max(latencies, default=None),
                               percentile(first, 0.5), percentile(second, 0.5)))
    return out


def fmt(value: float | None, digits: int = 0) -> str:
    return "—" if value is None else f"{value:,.{digits}f}"


def plot(cases: list[Case], folder: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for case in cases:
        if not case.arrivals:
            continue
        fig, (rate_ax, lat_ax) = plt.subplots(2, 1, figsize=(9, 7), sharex=True)
        for color, t in zip(("tab:red", "tab:blue", "tab:green"), case.spec, strict=False):
            items = case.arrivals.get(t["topic"], [])
            seconds = [(a - case.start_ns) / 1e9 for a, _, _ in items]
            bins = [0] * (int(case.seconds + case.drain) + 1)
            for s in seconds:
                if 0 <= s < len(bins):
                    bins[int(s)] += 1
            rate_ax.step(range(len(bins)), bins, where="post", color=color,
                         label=f"{t['topic']} (offered {t['rate']:g} Hz)")
            lat_ax.plot([(s - case.start_ns) / 1e9 for _, s, _ in items],
                        [(a - s) / 1e6 for a, s, _ in items], ".", color=color, markersize=3,
                        label=t["topic"])
        rate_ax.set_ylabel("delivered per second")
        rate_ax.set_yscale("symlog", linthresh=10)
        rate_ax.legend(loc="upper right", fontsize=8)
        rate_ax.grid(alpha=0.3)
        lat_ax.set_yscale("log")
        lat_ax.set_ylabel("latency (camera: age) ms")
        lat_ax.set_xlabel("seconds (by send time)")
        lat_ax.axhline(50, color="gray", linestyle=":", linewidth=0.8)
        lat_ax.axhline(500, color="gray", linestyle="--", linewidth=0.8)
        lat_ax.grid(alpha=0.3)
        fig.suptitle(f"constrained link ({WIFI}): {case.name}", fontsize=10)
        fig.tight_layout()
        path = folder / f"constrained-{case.name.split(' ')[0].replace('@', '-')}.png"
        fig.savefig(path, dpi=100)
        plt.close(fig)
        written.append(path)
    return written


# -- the report -------------------------------------------------------------------------------
def report(mixed: list[Case], big: list[Case], grids: list[Case], plots: list[Path],
           minutes: float, others: float) -> str:
    lines = [
        "# Constrained link",
        "",
        f"`bench/constrained.py` on rosgate {revision()}, {time.strftime('%Y-%m-%d %H:%M')}, "
        f"{os.cpu_count()} cores, {minutes:.1f} min; other processes used {100 * others:.0f} % "
        f"of the CPU meanwhile. The link: the emulator's `{PRESET}` preset ({WIFI}), a relay "
        "process of its own between bridge A and bridge B.",
        "",
        "Bridge A's topics in the **tuned** case (both bridges' files are otherwise the same in "
        f"every case): `bridge: {{{BUDGET}}}`, `{TUNED_PLUGINS}`, and",
        "",
        *[f"- `{topic}`: `{keys}`" for topic, keys in TUNED.items()],
        "",
        "## Camera, Twist and status together",
        "",
        "Offered: a 640x480 rgb8 camera (921,600 B of noise) at 10 Hz = 74 Mbit/s, "
        "a Twist (reliable) at 50 Hz, a 100 B String (reliable) at 100 Hz. The link carries "
        "at most ~2.6 camera frames a second. Latency is publisher to subscriber (the camera's "
        "is its age when it arrives); 'p50 1st/2nd half': p50 of the messages sent in each half "
        "of the run (a backlog that grows shows as a second half slower than the first).",
        "",
        "| case | topic | offered Hz | published | delivered | delivered Hz | p50 ms | p99 ms "
        "| max ms | p50 1st/2nd half |",
        "|---|---|--:|--:|--:|--:|--:|--:|--:|--:|",
    ]
    for case in mixed:
        if case.error:
            lines.append(f"| {case.name} | — | | | | | | | | {case.error} |")
            continue
        for r in topic_results(case):
            lines.append(f"| {case.name} | {r.topic} | {r.offered_hz:g} | {r.sent} | "
                         f"{r.delivered} | {r.delivered_hz:.2f} | "
                         f"{fmt(r.p50_ms)} | {fmt(r.p99_ms)} | {fmt(r.max_ms)} | "
                         f"{fmt(r.first_half_p50)} / {fmt(r.second_half_p50)} |")
    lines += ["", "What each case's bridge A did, and the emulated link:", ""]
    for case in mixed:
        lines.append(f"- **{case.name}**: " + case_notes(case))
    lines += ["", "## 1 MB over 1 % loss", "",
              "1024x1024 mono8 images (1 MiB of pixels, reliable), one every 0.5 s (8.4 Mbit/s "
              "of the 20). Without recovery a 1 MB message in 1,200-byte datagrams is 874 IP "
              "packets, all of which must arrive (0.99^874 = 0.02 %); in today's 65,000-byte "
              "datagrams it is 17 datagrams of 44 IP fragments, the same odds.", "",
              "| case | sent | delivered | share | p50 ms | p99 ms | A: on the wire per message | "
              "retransmitted |", "|---|--:|--:|--:|--:|--:|--:|--:|"]
    for case in big:
        r = topic_results(case)[0] if not case.error else None
        c = case.counters_a.get("/big", {})
        per = c.get("wire", 0) / max(1, c.get("sent", 0))
        lines.append(f"| {case.name} | {r.sent if r else '—'} | {r.delivered if r else '—'} | "
                     f"{100 * r.delivered / max(1, r.sent):.0f} % | " if r else
                     f"| {case.name} | — | — | — | ")
        if r:
            lines[-1] += (f"{fmt(r.p50_ms)} | {fmt(r.p99_ms)} | {per:,.0f} B | "
                          f"{c.get('retransmitted', 0)} |")
            if case.note:
                lines[-1] += f" {case.note}"
        else:
            lines[-1] += f"— | — | — | {case.error} |"
    lines += ["", "## A 4000x4000 map, 95 % unknown", "",
              "nav_msgs/OccupancyGrid, 16,000,000 cells (-1 but a 894x894 explored square), "
              "reliable, `recovery: retransmit`, one every 2 s.", "",
              "| case | maps delivered | A: bytes per map (frame) | A: on the wire per map | "
              "emulator: wire bytes per map | p50 ms |", "|---|--:|--:|--:|--:|--:|"]
    for case in grids:
        c = case.counters_a.get("/map", {})
        sent = max(1, c.get("sent", 0))
        up = case.relay.get("up", {})
        wire = (up.get("bytes_in", 0) + 28 * up.get("datagrams_in", 0)) / sent
        r = topic_results(case)[0] if not case.error else None
        lines.append(f"| {case.name} | {r.delivered if r else '—'} of {r.sent if r else '—'} | "
                     f"{c.get('bytes', 0) / sent:,.0f} | {c.get('wire', 0) / sent:,.0f} | "
                     f"{wire:,.0f} | {fmt(r.p50_ms if r else None)} |")
    if len(grids) == 2 and all(g.counters_a.get("/map") for g in grids):
        raw, packed = (g.counters_a["/map"]["wire"] / max(1, g.counters_a["/map"]["sent"])
                       for g in grids)
        lines += ["", f"zstd: {raw / max(1, packed):.0f}x fewer bytes on the wire per map."]
    if plots:
        lines += ["", "Plots: " + ", ".join(f"[{p.stem}](plots/{p.name})" for p in plots)]
    return "\n".join(lines) + "\n"


def case_notes(case: Case) -> str:
    parts = []
    for topic, c in case.counters_a.items():
        drops = ", ".join(f"{k} {v}" for k, v in sorted(c["drops"].items())) or "no drops"
        parts.append(f"{topic} sent {c['sent']} ({drops})")
    up = case.relay.get("up", {})
    dropped = up.get("dropped", {})
    parts.append(f"emulator: {up.get('datagrams_in', 0):,} datagrams in, lost "
                 f"{dropped.get('loss', 0):,}, queue full {dropped.get('queue_full', 0):,}, "
                 f"queue at most {up.get('queue_max', 0):,} B")
    if case.problems:
        parts.append(f"{len(case.problems)}+ warnings, e.g. `{case.problems[0][-120:]}`")
    return "; ".join(parts)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="8 s cases, no --base")
    parser.add_argument("--seconds", type=float, default=20.0, help="length of a mixed case")
    parser.add_argument("--base", default="main", metavar="REV",
                        help="today's rosgate for the 'main' cases (default main; 'none': skip)")
    parser.add_argument("--only", choices=("mixed", "big", "grid"), action="append")
    parser.add_argument("--out", default=str(HERE / "constrained_results.md"))
    parser.add_argument("--keep", action="store_true", help="keep the files and logs")
    args = parser.parse_args()
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    seconds = 8.0 if args.quick else args.seconds
    start, load = time.monotonic(), Load()
    sections = set(args.only or ("mixed", "big", "grid"))
    with ExitStack() as stack:
        base = None
        if args.base != "none" and not args.quick:
            base = base_checkout(args.base, stack)
        tmp = Path(tempfile.mkdtemp(prefix="rosgate-constrained-")) if args.keep else Path(
            stack.enter_context(tempfile.TemporaryDirectory(prefix="rosgate-constrained-")))
        if args.keep:
            log(f"constrained: keeping files and logs in {tmp}")
        tuned_keys = dict(TUNED)
        mixed, big, grids = [], [], []
        if "mixed" in sections:
            if base:
                mixed.append(Case("mixed", f"main@{base.rev} (today's defaults)", MIXED, base,
                                  seconds=seconds))
            mixed.append(Case("mixed", "defaults (this checkout, the same file)", MIXED,
                              seconds=seconds))
            mixed.append(Case("mixed", "tuned", MIXED, topic_keys=tuned_keys, bridge_a=BUDGET,
                              plugins_a=TUNED_PLUGINS, seconds=seconds))
        if "big" in sections:
            big_seconds = 8.0 if args.quick else 15.0
            if base:
                big.append(Case("big", f"main@{base.rev}", BIG, base, seconds=big_seconds))
            for recovery in ("none", "fec", "retransmit"):
                big.append(Case("big", f"recovery: {recovery}", BIG,
                                topic_keys={"/big": f"recovery: {recovery}"}, bridge_a=BUDGET,
                                seconds=big_seconds))
        if "grid" in sections:
            for name, keys in (("raw", "recovery: retransmit"),
                               ("zstd", "recovery: retransmit, compression: zstd")):
                grids.append(Case("grid", name, GRID, topic_keys={"/map": keys},
                                  bridge_a=BUDGET, seconds=4.0, drain=14.0, probe_every=8.0))
        for i, case in enumerate([*mixed, *big, *grids]):
            run(case, tmp / f"case{i:02d}")
    plots = plot(mixed, HERE / "plots")
    text = report(mixed, big, grids, plots, (time.monotonic() - start) / 60, load.others())
    print(text)
    Path(args.out).write_text(text)
    log(f"constrained: wrote {args.out} in {(time.monotonic() - start) / 60:.1f} min")
    return 1 if any(c.error for c in [*mixed, *big, *grids]) else 0


if __name__ == "__main__":
    sys.exit(main())
