"""rosgate benchmark: bare rclpy pub->sub against pub->bridge A->link->bridge B->sub, in one run.

    .venv/bin/python bench/bench.py [--quick] [--only SIZE ...] [--path PATH ...] [--keep]

For every message size and path (bare, or a bridge with a given transport/codec/cipher) it
measures latency (p50/p99) at a moderate fixed rate, then finds the *sustained* rate — the
highest steady offered rate of which >= 95 % arrives by the end of the trial (plus 0.1 s) —
by a short search of few-second trials. Progress goes to stderr; the table to stdout and to bench/results.md.
See bench/README.md for how to read it.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import subprocess
import sys
import tempfile
import time
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path

from processes import Bridge, Endpoint, Route, bringup_files, next_domains

HERE = Path(__file__).resolve().parent
DELIVERED = 0.95  # a trial passes when this share of what was offered arrives on time
WARM_UP_TIMEOUT = 30.0
GRACE = 0.1  # seconds after the last send (plus a few message intervals) a message may still arrive
DRAIN_MAX = 10.0  # seconds to let a backlog clear between trials
DRAIN_QUIET = 0.5  # ... and how long nothing must arrive to call it cleared

BUSY = 0.10  # warn when other processes took more than this share of the CPU during a case

TARGET_SIZE, TARGET_ROUTE, TARGET_RATE = "2.5 kB", Route("udp"), 10_000
REPLACED_RATE = 3_300  # ros2_socket_bridge at 2.5 kB, the system rosgate replaces


@dataclass(frozen=True)
class Size:
    name: str
    kind: str            # endpoints.KINDS: the message type
    bytes: int           # String data length, or Image pixel bytes
    start_rate: float    # the search's first offered rate
    ceiling: float       # never offer more than this
    latency_rate: float  # the fixed rate latency is measured at

    @property
    def key(self) -> str:
        """What --only matches: "100", "2.5k", "10k", "1m"."""
        return normalize(self.name)

    @property
    def msg_type(self) -> str:
        return {"string": "std_msgs/msg/String", "image": "sensor_msgs/msg/Image"}[self.kind]

    @property
    def depth(self) -> int:
        # deep queues everywhere on the measuring path; 1 MB samples would make 1000 of them 1 GB
        return 1000 if self.kind == "string" else 100


SIZES = [
    Size("100 B", "string", 100, 4_000, 200_000, 1_000),
    Size("2.5 kB", "string", 2_500, 4_000, 200_000, 1_000),
    Size("10 kB", "string", 10_000, 2_000, 100_000, 1_000),
    Size("1 MB", "image", 1024 * 1024, 20, 2_000, 20),
]
ROUTES = [Route("udp"), Route("udp", codec="msgpack"), Route("udp", cipher="fernet"), Route("tcp")]
QUICK_ROUTES = [Route("udp"), Route("tcp")]
CLIENT_SERVER = Route("udp", roles="client/server")  # shown at 2.5 kB only


@dataclass(frozen=True)
class Settings:
    quick: bool
    trial_seconds: float
    latency_seconds: float
    max_trials: int


FULL = Settings(False, trial_seconds=2.0, latency_seconds=3.0, max_trials=7)
QUICK = Settings(True, trial_seconds=1.0, latency_seconds=1.5, max_trials=6)


def normalize(size: str) -> str:
    return size.lower().replace(" ", "").removesuffix("b")


def log(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


# -- one trial: a steady rate for a few seconds ---------------------------------------------------
@dataclass
class Trial:
    rate: float      # asked of the publisher
    sent: int
    seconds: float
    received: int
    in_time: int     # received by the end of the trial plus a short grace
    p50_us: float | None
    p99_us: float | None

    @property
    def offered(self) -> float:
        return self.sent / self.seconds

    @property
    def delivered(self) -> float:
        return self.in_time / self.seconds

    @property
    def ok(self) -> bool:
        return self.sent > 0 and self.in_time >= DELIVERED * self.sent

    @property
    def publisher_bound(self) -> bool:
        """The publisher could not offer what was asked (short of CPU, or DDS pushed back)."""
        return self.sent < 0.9 * self.rate * self.seconds


def grace(rate: float) -> float:
    """How long after the last send arrivals still count for the trial. Short on purpose: a
    path slower than the offered rate builds a backlog, and what is still queued at the end
    was not delivered at that rate (a lenient bound would let short trials hide it)."""
    return GRACE + 5 / rate


class Case:
    """The processes of one (size, path) and the trials run through them."""

    def __init__(self, size: Size, route: Route | None, folder: Path):
        self.size = size
        self.route = route
        self.folder = folder
        self.trials = 0
        self.bridges: list[Bridge] = []
        self._stack = ExitStack()

    @property
    def label(self) -> str:
        return f"{self.size.name} {self.route.label if self.route else 'bare rclpy'}"

    def __enter__(self) -> "Case":
        with ExitStack() as stack:
            self._start(stack)
            self._stack = stack.pop_all()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stack.close()

    def _start(self, stack: ExitStack) -> None:
        """Start everything at once (imports and DDS start-up overlap), then wait for each."""
        size, pub_domain = self.size, next_domains()[0]
        sub_domain = pub_domain + 1 if self.route else pub_domain

        def started(process):
            stack.callback(process.stop)  # stopped in reverse order: the publisher first
            return process

        self.sub = started(Endpoint("sub", size.kind, size.bytes, size.depth, sub_domain,
                                    self.folder / "sub.log"))
        if self.route:
            a, b = bringup_files(self.route, size.msg_type, size.depth, self.folder)
            self.bridges = [started(Bridge(b, sub_domain)), started(Bridge(a, pub_domain))]
        self.pub = started(Endpoint("pub", size.kind, size.bytes, size.depth, pub_domain,
                                    self.folder / "pub.log"))
        for process in [self.sub, *self.bridges, self.pub]:
            process.ready()

    def warm_up(self) -> None:
        """Publish slowly until a message crosses: DDS discovery (and a client's handshake)
        take a moment, and nothing may be measured before."""
        deadline = time.monotonic() + WARM_UP_TIMEOUT
        rate = min(50.0, self.size.latency_rate)
        while time.monotonic() < deadline:
            self.pub.ask(f"run 0 {rate} 0.5", timeout=30)
            if self.sub.ask("stats 0")["received"]:
                self._drain()
                return
        raise RuntimeError(f"{self.label}: nothing arrived within {WARM_UP_TIMEOUT:.0f} s")

    def trial(self, rate: float, seconds: float) -> Trial:
        self.trials += 1
        sent = self.pub.ask(f"run {self.trials} {rate} {seconds}", timeout=seconds * 3 + 30)
        self._drain()
        deadline = sent["end_ns"] + int(grace(rate) * 1e9)
        got = self.sub.ask(f"stats {self.trials} {deadline}")
        return Trial(rate, sent["sent"], sent["seconds"], got["received"], got["in_time"],
                     got["p50_us"], got["p99_us"])

    def _drain(self) -> None:
        """Wait until arrivals stop, so a backlog does not load the next trial's path."""
        deadline = time.monotonic() + DRAIN_MAX
        last = -1
        while time.monotonic() < deadline:
            total = self.sub.ask("total")["received"]
            if total == last:
                return
            last = total
            time.sleep(DRAIN_QUIET)

    def problems(self) -> list[str]:
        return [f"{b.name}: {line}" for b in self.bridges for line in b.problems()]


# -- the search for the sustained rate ------------------------------------------------------------
def find_sustained(case: Case, settings: Settings) -> tuple[Trial | None, list[Trial]]:
    """The highest passing trial, and every trial run.

    Rates go up fourfold until a trial fails, then the failing trial's delivered rate (what the
    path managed under overload, close to its capacity) or else the geometric midpoint between
    the best pass and the lowest failure is tried, until the two are within 25 %."""
    size = case.size
    good: Trial | None = None
    bad: Trial | None = None
    trials: list[Trial] = []
    rate = size.start_rate
    for _ in range(settings.max_trials):
        t = case.trial(rate, settings.trial_seconds)
        trials.append(t)
        log(f"  [{case.label}] {describe(t)}")
        if t.ok:
            good = t if good is None or t.offered > good.offered else good
            if t.publisher_bound or rate >= size.ceiling:
                break  # nothing higher can be offered
        else:
            bad = t if bad is None or t.rate < bad.rate else bad
        if good and bad and bad.rate <= 1.25 * good.rate:
            break
        rate = next_rate(good, bad, size)
        if rate is None:
            break
    return good, trials


def next_rate(good: Trial | None, bad: Trial | None, size: Size) -> float | None:
    if bad is None:
        assert good is not None
        return min(good.rate * 4, size.ceiling)
    guess = 0.95 * bad.delivered
    if good is None:
        rate = max(bad.rate / 8, min(guess, bad.rate / 2))
        return rate if rate >= 1 else None
    low, high = good.rate * 1.1, bad.rate / 1.1
    return guess if low < guess < high else math.sqrt(good.rate * bad.rate)


def describe(t: Trial) -> str:
    verdict = "ok" if t.ok else "FAIL"
    bound = " (publisher-bound)" if t.publisher_bound else ""
    late = f", {t.received - t.in_time} later" if t.received > t.in_time else ""
    return (f"asked {t.rate:,.0f}/s: offered {t.offered:,.0f}/s{bound}, delivered "
            f"{t.delivered:,.0f}/s ({t.in_time / max(t.sent, 1):.1%}{late}), "
            f"p50 {ms(t.p50_us)} ms p99 {ms(t.p99_us)} ms -> {verdict}")


def ms(us: float | None) -> str:
    return "-" if us is None else f"{us / 1000:.2f}"


# -- other work on the machine ----------------------------------------------------------------------
class Load:
    """The share of the machine's CPU that processes outside this benchmark used since
    creation: other work (a test run, a build) takes cores from the paths measured."""

    def __init__(self) -> None:
        self.start = time.monotonic(), system_busy(), own_cpu()

    def others(self) -> float:
        t0, busy0, own0 = self.start
        elapsed = (time.monotonic() - t0) * (os.cpu_count() or 1)
        return max(0.0, (system_busy() - busy0) - (own_cpu() - own0)) / elapsed if elapsed else 0.0


def system_busy() -> float:
    """CPU seconds the whole machine spent busy since boot (/proc/stat)."""
    with open("/proc/stat") as stat:
        user, nice, system, idle, iowait, irq, softirq, steal = map(int, stat.readline().split()[1:9])
    return (user + nice + system + irq + softirq + steal) / os.sysconf("SC_CLK_TCK")


def own_cpu() -> float:
    """CPU seconds of this process and its children that have ended (every case's processes
    have ended by the time this is read)."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


# -- one case from start to finish ----------------------------------------------------------------
@dataclass
class Result:
    size: Size
    route: Route | None
    sustained: Trial | None = None
    peak: float = 0.0            # the most delivered per second in any trial
    latency: Trial | None = None
    error: str | None = None
    problems: list[str] = field(default_factory=list)
    others: float = 0.0          # share of the CPU other processes used meanwhile

    @property
    def path(self) -> str:
        return self.route.label if self.route else "bare rclpy"


def measure(size: Size, route: Route | None, settings: Settings, folder: Path) -> Result:
    result = Result(size, route)
    case = Case(size, route, folder)
    log(f"[{case.label}] starting")
    start, load = time.monotonic(), Load()
    try:
        with case:
            case.warm_up()
            # latency first, on a quiet path: after an overload trial, queues deep in DDS can
            # take a while to settle, and their wait would be charged to this measurement
            seconds = max(settings.latency_seconds, 100 / size.latency_rate)  # >= 100 samples
            result.latency = case.trial(size.latency_rate, seconds)
            log(f"  [{case.label}] latency: {describe(result.latency)}")
            result.sustained, trials = find_sustained(case, settings)
            result.peak = max(t.delivered for t in trials)
    except RuntimeError as exc:
        result.error = str(exc)
        log(f"  [{case.label}] FAILED: {exc}")
    result.others = load.others()
    result.problems = case.problems()
    if result.others > BUSY:
        result.problems.insert(0, f"other processes used {result.others:.0%} of the CPU meanwhile: "
                                  "these numbers are low")
    for line in result.problems:
        log(f"  [{case.label}] {line}")
    log(f"  [{case.label}] done in {time.monotonic() - start:.0f} s")
    return result


# -- the table --------------------------------------------------------------------------------------
COLUMNS = ["size", "path", "sustained msg/s", "vs bare", "MB/s", "peak delivered msg/s",
           "latency at msg/s", "p50 ms", "p99 ms", "p50 vs bare"]


def table(results: list[Result]) -> str:
    bare = {r.size.name: r for r in results if r.route is None}
    lines = ["| " + " | ".join(COLUMNS) + " |", "|---|---|" + "--:|" * (len(COLUMNS) - 2)]
    for r in results:
        cells = [r.size.name, r.path, *row(r, bare.get(r.size.name))]
        cells += [""] * (len(COLUMNS) - len(cells))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def row(r: Result, bare: Result | None) -> list[str]:
    """The cells after size and path."""
    if r.error:
        return ["failed: " + r.error.splitlines()[0]]
    return throughput_cells(r, bare) + latency_cells(r.latency, bare.latency if bare else None)


def throughput_cells(r: Result, bare: Result | None) -> list[str]:
    s = r.sustained
    if s is None:  # not even the search's lowest rate passed
        return ["-", "-", "-", f"{r.peak:,.0f}"]
    at_least = "≥ " if s.publisher_bound or s.rate >= r.size.ceiling else ""
    return [f"{at_least}{s.offered:,.0f}",
            ratio(s.offered, bare.sustained.offered if bare and bare.sustained else None),
            f"{s.offered * r.size.bytes / 1e6:,.1f}", f"{r.peak:,.0f}"]


def latency_cells(lat: Trial | None, bare: Trial | None) -> list[str]:
    if lat is None:
        return []
    overloaded = "" if lat.ok else f" ({lat.in_time / max(lat.sent, 1):.0%} delivered)"
    return [f"{lat.offered:,.0f}{overloaded}", ms(lat.p50_us), ms(lat.p99_us),
            ratio(lat.p50_us, bare.p50_us if bare else None)]


def ratio(value: float | None, base: float | None) -> str:
    return f"{value / base:.2f}" if value is not None and base else "-"


def verdict(results: list[Result]) -> str:
    found = [r for r in results if r.size.name == TARGET_SIZE and r.route == TARGET_ROUTE]
    goal = (f"target: {TARGET_SIZE} over {TARGET_ROUTE.label} sustained >= {TARGET_RATE:,} msg/s "
            f"end to end (ros2_socket_bridge, which rosgate replaces: ~{REPLACED_RATE:,})")
    if not found or found[0].sustained is None:
        return f"{goal}: NOT MEASURED in this run"
    got = found[0].sustained.offered
    met = "MET" if got >= TARGET_RATE else "NOT MET"
    return f"{goal}: {met} ({got:,.0f} msg/s, {got / REPLACED_RATE:.1f}x the replaced bridge)"


def report(results: list[Result], settings: Settings, elapsed: float, others: float) -> str:
    mode = "quick" if settings.quick else "full"
    cpu = next((line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo")
                if line.startswith("model name")), platform.processor())
    notes = [f"- {r.size.name} {r.path}: {line}" for r in results for line in r.problems[:6]]
    parts = [
        "# rosgate benchmark: bridged vs bare rclpy",
        "",
        f"{time.strftime('%Y-%m-%d %H:%M')}, rosgate {revision()}, {mode} run "
        f"({settings.trial_seconds:g} s trials), {os.cpu_count()} cores ({cpu}), "
        f"Python {platform.python_version()}, {elapsed / 60:.1f} min; other processes used "
        f"{others:.0%} of the CPU meanwhile. Sustained: highest steady offered rate with >= "
        f"{DELIVERED:.0%} delivered by the trial's end + {GRACE:g} s. '≥': the publisher (or "
        "the search's ceiling) was the limit, not the path. Peak: the most delivered per second "
        "in any trial. Ratios: bridged / bare rclpy at the same size.",
        "",
        table(results),
        "",
        f"**{verdict(results)}**",
    ]
    if notes:
        parts += ["", "Notes: other load, and the bridges' warnings and drop counters:", "", *notes]
    return "\n".join(parts) + "\n"


def revision() -> str:
    """The commit measured, and whether the working tree differed from it."""
    git = ["git", "-C", str(HERE)]
    head = subprocess.run([*git, "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    dirty = subprocess.run([*git, "status", "--porcelain", "--untracked-files=no"],
                           capture_output=True, text=True)
    if head.returncode:
        return "(not a git checkout)"
    return head.stdout.strip() + (" + uncommitted changes" if dirty.stdout.strip() else "")


# -- main ---------------------------------------------------------------------------------------------
def plan(settings: Settings, only: list[str] | None,
         paths: list[str] | None) -> list[tuple[Size, Route | None]]:
    wanted = {normalize(o) for o in only} if only else None
    unknown = (wanted or set()) - {s.key for s in SIZES}
    if unknown:
        sys.exit(f"bench: unknown size {', '.join(sorted(unknown))}; sizes: "
                 f"{', '.join(s.name.replace(' ', '') for s in SIZES)}")
    cases: list[tuple[Size, Route | None]] = []
    for size in SIZES:
        if wanted and size.key not in wanted:
            continue
        routes = QUICK_ROUTES if settings.quick else ROUTES
        if size.name == TARGET_SIZE:
            routes = [*routes, CLIENT_SERVER]
        cases += [(size, None), *[(size, route) for route in routes]]
    if paths:
        cases = [(size, route) for size, route in cases
                 if (route.label if route else "bare") in paths]
    return cases


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="fewer paths, shorter trials")
    parser.add_argument("--only", action="append", metavar="SIZE",
                        help="only this size: 100B, 2.5kB, 10kB or 1MB (repeatable)")
    parser.add_argument("--path", action="append", metavar="PATH",
                        help="only this path, e.g. bare or udp/cdr/fernet (repeatable)")
    parser.add_argument("--keep", action="store_true",
                        help="keep the bringup.yaml files and logs (their folder is printed)")
    parser.add_argument("--out", type=Path, default=HERE / "results.md",
                        help="where to write the table (default: bench/results.md)")
    args = parser.parse_args()
    settings = QUICK if args.quick else FULL
    cases = plan(settings, args.only, args.path)
    log(f"bench: {len(cases)} cases, {'quick' if settings.quick else 'full'} run")
    start, load = time.monotonic(), Load()
    results = []
    with tempfile.TemporaryDirectory(prefix="rosgate-bench-") as tmp:
        if args.keep:
            tmp = tempfile.mkdtemp(prefix="rosgate-bench-")
            log(f"bench: keeping files and logs in {tmp}")
        for i, (size, route) in enumerate(cases):
            folder = Path(tmp) / f"case{i:02d}"
            folder.mkdir()
            results.append(measure(size, route, settings, folder))
    text = report(results, settings, time.monotonic() - start, load.others())
    print(text)
    args.out.write_text(text)
    log(f"bench: wrote {args.out} in {(time.monotonic() - start) / 60:.1f} min")
    return 1 if any(r.error for r in results) else 0


if __name__ == "__main__":
    sys.exit(main())
