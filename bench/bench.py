"""rosgate benchmark: bare rclpy pub->sub against pub->bridge A->link->bridge B->sub, in one run.

    .venv/bin/python bench/bench.py [--quick] [--only SIZE ...] [--path PATH ...] [--keep]
                                    [--cpu-rate MSG/S] [--base REV] [--profile [--profile-path P]]

For every message size and path (bare, or a bridge with a given transport/codec/cipher) it
measures latency (p50/p90/p99) at a moderate fixed rate, then the CPU time each process spends per
message at another fixed rate (utime + stime from /proc/<pid>/stat), then finds the *sustained*
rate — the highest steady offered rate of which >= 95 % arrives by the end of the trial (plus
0.1 s) — by a short search of few-second trials, then offers twice that (overload: how much is
delivered, how late). With --base REV the bridged paths also run with the rosgate of git revision
REV, side by side; with --profile py-spy samples both bridges of one path.
Progress goes to stderr; the tables to stdout and to bench/results.md, plots to bench/plots/,
profiles to bench/profiles/. See bench/README.md for how to read them.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from contextlib import ExitStack
from dataclasses import dataclass, field, replace
from pathlib import Path

import profiling
from processes import (
    HERE_CHECKOUT,
    TWIST_TOPIC,
    Bridge,
    Checkout,
    Endpoint,
    Floor,
    Process,
    Relay,
    Route,
    StampedEnds,
    bringup_files,
    free_port,
    next_domains,
    thread_cpu_seconds,
)

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
#: rosgate's own Fast DDS profile (an 8 MiB shared-memory segment), given to the ends of the
#: "publisher with rosgate's profile" rows
FASTDDS_XML = ROOT / "core" / "src" / "rosgate" / "fastdds.xml"
LARGE_SEGMENT = "ends with rosgate's Fast DDS profile"
DELIVERED = 0.95  # a trial passes when this share of what was offered arrives on time
WARM_UP_TIMEOUT = 30.0
GRACE = 0.1  # seconds after the last send (plus a few message intervals) a message may still arrive
DRAIN_MAX = 10.0  # seconds to let a backlog clear between trials
DRAIN_QUIET = 0.5  # ... and how long nothing must arrive to call it cleared

BUSY = 0.10  # warn when other processes took more than this share of the CPU during a case

CPU_RATE = 2_000  # default fixed rate of the CPU trial (--cpu-rate)
OVERLOAD = 2.0    # the overload trial offers this times the sustained rate

TARGET_SIZE, TARGET_ROUTE, TARGET_RATE = "2.5 kB", Route("udp"), 10_000
REPLACED_RATE = 3_300  # ros2_socket_bridge at 2.5 kB, the system rosgate replaces
OVERLOAD_P99_MS = 50   # target: at 2x sustained, p99 under this for non-reliable topics
TWIST_P99_MS = 20      # ... and a real_time Twist beside it, p99 under this
TWIST_RATE = 20        # Hz, a teleoperation command
FLOOR_CPU_RATIO = 1.5  # target: the default file's CPU per message <= this x the floor's
IMAGE_SHARE = 0.9      # target: 1 MB best effort delivers >= this x bare rclpy's share


@dataclass(frozen=True)
class Size:
    name: str
    kind: str            # endpoints.KINDS: the message type
    bytes: int           # String data length, or Image pixel bytes
    start_rate: float    # the search's first offered rate
    ceiling: float       # never offer more than this
    latency_rate: float  # the fixed rate latency is measured at
    cpu_rate_max: float = math.inf  # the CPU trial offers min(--cpu-rate, this)

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
    # 2,000 images/s would be 2 GB/s: the CPU trial is the latency trial (20/s)
    Size("1 MB", "image", 1024 * 1024, 20, 2_000, 20, cpu_rate_max=20),
]
# the headline: the file a user writes (client/server, identities, nothing else: udp with its
# max_frame from the path, cdr, the session's aead cipher), reliable and best effort
DEFAULT = Route("udp", cipher="aead", roles="session", max_frame=None)
DEFAULT_BE = replace(DEFAULT, reliability="best_effort")
DEFAULTS = [DEFAULT, DEFAULT_BE]
# the same best-effort file with a 2 ms batch window on its topic (shown at 2.5 kB only)
BATCHED = replace(DEFAULT_BE, batch="2ms")
# the default file's reliable topic through a relay that loses datagrams each way (2.5 kB only)
LOSSY = [replace(DEFAULT, loss=loss) for loss in (0.01, 0.05, 0.20)]
# the rows below set udp's max_frame to 65,000 (loopback's datagrams): the bridge's cost per
# message, without fragments
ROUTES = [Route("udp"), Route("udp", codec="msgpack"), Route("udp", cipher="fernet"), Route("tcp")]
QUICK_ROUTES = [Route("udp"), Route("tcp")]
CLIENT_SERVER = Route("udp", roles="client/server")  # shown at 2.5 kB only
# an authenticated session with its default cipher, beside the unauthenticated rows (2.5 kB)
SESSION = Route("udp", cipher="aead", roles="session")
SESSION_RATIO = 0.85  # target: the session sustains >= this much of udp/cdr/none (same run)
# no rosgate: bench/floor.py, what rclpy, Fast DDS and the kernel cost before a bridge does
# anything (udp: one datagram per message, so only sizes that fit one)
FLOORS = [Route("udp", roles="floor"), Route("tcp", roles="floor")]
UDP_FLOOR_MAX = 65_000
ALL_ROUTES = [*DEFAULTS, BATCHED, *LOSSY, *ROUTES, CLIENT_SERVER, SESSION]


@dataclass(frozen=True)
class Settings:
    quick: bool
    trial_seconds: float    # each trial of the sustained-rate search, and the overload trial
    latency_seconds: float  # --quick: the latency trial is the CPU trial, at the CPU rate
    cpu_seconds: float      # the CPU trial
    max_trials: int         # of the search
    close: float            # the search stops when the lowest failure is within this of the pass


# full: within 10 %, so that two rows of the same run can be compared to 0.85x (the session's
# target) and not be 25 % apart from where the search happened to stop
FULL = Settings(False, trial_seconds=2.0, latency_seconds=2.0, cpu_seconds=3.0, max_trials=8,
                close=1.10)
QUICK = Settings(True, trial_seconds=1.0, latency_seconds=2.0, cpu_seconds=2.0, max_trials=5,
                 close=1.25)


@dataclass(frozen=True)
class ProfileSpec:
    path: str        # a route's label without revision, e.g. udp/cdr/none
    size_key: str    # normalized size
    seconds: float
    folder: Path


@dataclass
class Options:
    cpu_rate: float = CPU_RATE
    checkouts: dict[str, Checkout] = field(default_factory=lambda: {"": HERE_CHECKOUT})
    best_effort: frozenset[str] = frozenset({"2.5k"})  # size keys (--best-effort)
    profile: ProfileSpec | None = None


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
    received: int    # everything of this trial that arrived (by the end of the drain)
    in_time: int     # received by the end of the trial plus a short grace
    p50_us: float | None  # latency percentiles over everything received
    p90_us: float | None
    p99_us: float | None
    cpu: dict[str, float] = field(default_factory=dict)  # role (pub, A, B, sub) -> CPU seconds
    #: bridge (A, B) -> thread id -> (thread name, user CPU seconds, system CPU seconds)
    threads: dict[str, dict[int, tuple[str, float, float]]] = field(default_factory=dict)
    #: p99 of the messages sent in the trial's second half: an overload settled into
    p99_settled_us: float | None = None
    tail: int = 0        # arrived while the trial's last quarter was sent
    tail_fresh: int = 0  # ... of them sent in that quarter
    #: the real_time Twist's beside the trial (if the case has one): sent, and the age (ms) of
    #: each that arrived
    twist_sent: int = 0
    twist_ages_ms: list[float] | None = None

    @property
    def newest(self) -> float | None:
        """Of what arrived during the trial's last quarter, the share sent in it: near 1 when
        what a path delivers under an overload is the newest, low when it delivers what
        waited in a queue (300 ms of queue in a 1 s trial: none)."""
        return self.tail_fresh / self.tail if self.tail else None

    @property
    def twist_p99_ms(self) -> float | None:
        return percentile(self.twist_ages_ms, 0.99) if self.twist_ages_ms else None

    @property
    def offered(self) -> float:
        return self.sent / self.seconds

    @property
    def delivered(self) -> float:
        return self.in_time / self.seconds

    @property
    def arrived(self) -> float:
        """The share of what was sent that arrived at all, however late."""
        return self.received / self.sent if self.sent else 0.0

    @property
    def ok(self) -> bool:
        return self.sent > 0 and self.in_time >= DELIVERED * self.sent

    @property
    def publisher_bound(self) -> bool:
        """The publisher could not offer what was asked (short of CPU, or DDS pushed back)."""
        return self.sent < 0.9 * self.rate * self.seconds

    def us_per_msg(self, role: str) -> float | None:
        """CPU µs the process spent per message delivered during this trial."""
        if role not in self.cpu or not self.received:
            return None
        return self.cpu[role] / self.received * 1e6


def percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))]


def grace(rate: float) -> float:
    """How long after the last send arrivals still count for the trial. Short on purpose: a
    path slower than the offered rate builds a backlog, and what is still queued at the end
    was not delivered at that rate (a lenient bound would let short trials hide it)."""
    return GRACE + 5 / rate


class Case:
    """The processes of one (size, path) and the trials run through them."""

    def __init__(self, size: Size, route: Route | None, folder: Path,
                 checkout: Checkout = HERE_CHECKOUT, reliability: str | None = None,
                 twist: bool = False, large_segment: bool = False):
        self.size = size
        self.route = route
        self.folder = folder
        self.checkout = checkout
        #: the QoS of every queue: the route's, unless a trial asks for another
        self.reliability = reliability or (route.reliability if route else "reliable")
        self.trials = 0
        self.a: Bridge | None = None
        self.b: Bridge | None = None
        self.relays: list[Relay] = []  # a lossy route's, between A and B
        #: a real_time Twist at TWIST_RATE beside the overload trial (client/server files)
        self.twist = twist
        self.twist_pub: StampedEnds | None = None
        self.twist_sub: StampedEnds | None = None
        self.published = 0  # every message the publisher sent, warm-ups included
        #: the publisher's and the subscriber's Fast DDS profile: rosgate's (an 8 MiB
        #: shared-memory segment), not Fast DDS's defaults
        self.profile = {"FASTRTPS_DEFAULT_PROFILES_FILE": str(FASTDDS_XML)} if large_segment \
            else {}
        self._stack = ExitStack()

    @property
    def label(self) -> str:
        own = self.route.reliability if self.route else "reliable"
        kind = "" if self.reliability == own else f" {self.reliability.replace('_', '-')}"
        return f"{self.size.name} {self.route.label if self.route else 'bare rclpy'}{kind}"

    @property
    def twist_spec(self) -> list[dict]:
        return [{"topic": TWIST_TOPIC, "kind": "twist", "rate": TWIST_RATE, "size": 48,
                 "reliable": True}]

    @property
    def bridges(self) -> list[Bridge]:
        return [b for b in (self.a, self.b) if b]

    def processes(self) -> dict[str, Process]:
        """Every process of the case by its role: pub, A, B, sub (A and B when bridged)."""
        found = {"pub": self.pub, "A": self.a, "B": self.b, "sub": self.sub}
        return {role: p for role, p in found.items() if p is not None}

    def __enter__(self) -> Case:
        for attempt in (1, 2):
            try:
                with ExitStack() as stack:
                    self._start(stack)
                    self._stack = stack.pop_all()
                return self
            except RuntimeError as exc:
                # a port picked free can be taken (by DDS, or another run's test) before the
                # bridge binds it: start once more, with fresh ports and domains
                if attempt == 2 or "already in use" not in str(exc):
                    raise
                why = next(line for line in str(exc).splitlines() if "already in use" in line)
                log(f"  [{self.label}] could not start ({why.strip()}); again")
        raise AssertionError("unreachable")

    def __exit__(self, *exc: object) -> None:
        self._stack.close()

    def _start(self, stack: ExitStack) -> None:
        """Start everything at once (imports and DDS start-up overlap), then wait for each."""
        size, pub_domain = self.size, next_domains()[0]
        sub_domain = pub_domain + 1 if self.route else pub_domain
        self.folder.mkdir(parents=True, exist_ok=True)

        def started(process):
            stack.callback(process.stop)  # stopped in reverse order: the publisher first
            return process

        self.sub = started(Endpoint("sub", size.kind, size.bytes, size.depth, sub_domain,
                                    self.folder / "sub.log", self.reliability, env=self.profile))
        if self.route and self.route.roles == "floor":
            port, route = free_port(), self.route

            def floor(side: str, domain: int) -> Floor:
                return Floor(side, route, size.msg_type, port, size.depth, self.reliability,
                             self.folder, domain)

            self.b = started(floor("b", sub_domain))
            self.a = started(floor("a", pub_domain))
        elif self.route:
            port, dial = free_port(), None
            if self.route.loss:  # the client dials relays in front of the server's port
                dial = free_port()
                self.relays = [started(Relay("udp", dial, port, self.route.loss)),
                               started(Relay("tcp", dial, port))]
            a, b = bringup_files(self.route, size.msg_type, size.depth, self.folder,
                                 self.reliability, self.checkout.root, port, dial, self.twist)
            self.b = started(Bridge(b, sub_domain, self.checkout))
            self.a = started(Bridge(a, pub_domain, self.checkout))
            if self.twist:
                self.twist_sub = started(StampedEnds("sub", self.twist_spec, sub_domain,
                                                     self.folder / "twist_sub.log"))
                self.twist_pub = started(StampedEnds("pub", self.twist_spec, pub_domain,
                                                     self.folder / "twist_pub.log"))
        self.pub = started(Endpoint("pub", size.kind, size.bytes, size.depth, pub_domain,
                                    self.folder / "pub.log", self.reliability, env=self.profile))
        twists = [p for p in (self.twist_sub, self.twist_pub) if p]
        for process in [self.sub, *self.relays, *self.bridges, *twists, self.pub]:
            process.ready()

    def warm_up(self) -> None:
        """Publish slowly until a message crosses: DDS discovery (and a client's handshake)
        take a moment, and nothing may be measured before."""
        deadline = time.monotonic() + WARM_UP_TIMEOUT
        rate = min(50.0, self.size.latency_rate)
        while time.monotonic() < deadline:
            self.published += self.pub.ask(f"run 0 {rate} 0.5", timeout=30)["sent"]
            if self.sub.ask("stats 0")["received"]:
                break
        else:
            raise RuntimeError(f"{self.label}: nothing arrived within {WARM_UP_TIMEOUT:.0f} s")
        while self.twist_pub and self.twist_sub and not self.twist_sub.ask("count")[TWIST_TOPIC]:
            if time.monotonic() > deadline:
                raise RuntimeError(f"{self.label}: no Twist arrived within "
                                   f"{WARM_UP_TIMEOUT:.0f} s")
            self.twist_pub.ask("once", timeout=30)
            time.sleep(0.1)
        self._drain()

    def trial(self, rate: float, seconds: float, twist: bool = False) -> Trial:
        """Offer ``rate`` for ``seconds``, wait for arrivals to stop, count. The CPU time of
        every process is read before the first send and after the last arrival. ``twist``: the
        case's Twist at TWIST_RATE meanwhile, its own publisher's CPU not counted."""
        self.trials += 1
        processes = self.processes()
        cpu0, threads0 = self._cpu(processes)
        twist_since = time.time_ns()
        twist_pub = self.twist_pub if twist else None
        twist_sub = self.twist_sub if twist_pub else None
        twists_before = twist_sub.ask("count")[TWIST_TOPIC] if twist_sub else 0
        if twist_pub:
            twist_pub.send(f"run {seconds}")
        sent = self.pub.ask(f"run {self.trials} {rate} {seconds}", timeout=seconds * 3 + 30)
        self.published += sent["sent"]
        twists = twist_pub.reply(30)["sent"][TWIST_TOPIC] if twist_pub else 0
        self._drain()
        if twist_sub:
            twist_sub.settle(TWIST_TOPIC, twists_before + twists)
        cpu1, threads1 = self._cpu(processes)
        deadline = sent["end_ns"] + int(grace(rate) * 1e9)
        got = self.sub.ask(f"stats {self.trials} {deadline} {sent['tail_ns']} "
                           f"{sent['end_ns']}")
        threads = {side: {tid: (name, user - before[1], system - before[2])
                          for tid, (name, user, system) in threads1[side].items()
                          for before in [threads0[side].get(tid, (name, 0.0, 0.0))]}
                   for side in threads1}
        return Trial(rate, sent["sent"], sent["seconds"], got["received"], got["in_time"],
                     got["p50_us"], got["p90_us"], got["p99_us"],
                     cpu={role: cpu1[role] - cpu0[role] for role in cpu1}, threads=threads,
                     p99_settled_us=got.get("p99_settled_us"), tail=got["tail"],
                     tail_fresh=got["tail_fresh"], twist_sent=twists,
                     twist_ages_ms=twist_sub.ages_ms(self.folder, twist_since, TWIST_TOPIC)
                     if twist_sub else None)

    @staticmethod
    def _cpu(processes: dict[str, Process]):
        try:
            cpu = {role: p.cpu() for role, p in processes.items()}
            threads = {role: thread_cpu_seconds(p.pid) for role, p in processes.items()
                       if role in ("A", "B")}
        except OSError as exc:
            raise RuntimeError(f"a process of the case exited: {exc}") from None
        return cpu, threads

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
    the best pass and the lowest failure is tried, until the two are within ``settings.close``
    (10 %; --quick 25 %)."""
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
        if good and bad and bad.rate <= settings.close * good.rate:
            break
        rate = next_rate(good, bad, size, settings.close)
        if rate is None:
            break
    return good, trials


def next_rate(good: Trial | None, bad: Trial | None, size: Size,
              close: float = 1.25) -> float | None:
    if bad is None:
        assert good is not None
        return min(good.rate * 4, size.ceiling)
    guess = 0.95 * bad.delivered
    if good is None:
        rate = max(bad.rate / 8, min(guess, bad.rate / 2))
        return rate if rate >= 1 else None
    step = math.sqrt(close)  # a guess this close to either end would not narrow the gap enough
    low, high = good.rate * step, bad.rate / step
    return guess if low < guess < high else math.sqrt(good.rate * bad.rate)


def describe(t: Trial) -> str:
    verdict = "ok" if t.ok else "FAIL"
    bound = " (publisher-bound)" if t.publisher_bound else ""
    late = f", {t.received - t.in_time} later" if t.received > t.in_time else ""
    settled = "" if t.ok else f" (second half {ms(t.p99_settled_us)} ms)"
    cpu = ", CPU µs/msg " + " ".join(f"{role} {us(t.us_per_msg(role))}" for role in t.cpu)
    return (f"asked {t.rate:,.0f}/s: offered {t.offered:,.0f}/s{bound}, delivered "
            f"{t.delivered:,.0f}/s ({t.in_time / max(t.sent, 1):.1%}{late}), "
            f"p50 {ms(t.p50_us)} ms p99 {ms(t.p99_us)} ms{settled}{cpu} -> {verdict}")


def ms(us: float | None) -> str:
    return "-" if us is None else f"{us / 1000:.2f}"


def us(value: float | None) -> str:
    if value is None:
        return "-"
    return f"{value:.1f}" if value < 100 else f"{value:,.0f}"


# -- other work on the machine --------------------------------------------------------------------
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
        (user, nice, system, idle, iowait, irq, softirq,
         steal) = map(int, stat.readline().split()[1:9])
    return (user + nice + system + irq + softirq + steal) / os.sysconf("SC_CLK_TCK")


def own_cpu() -> float:
    """CPU seconds of this process and its children that have ended (every case's processes
    have ended by the time this is read)."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


# -- one case from start to finish ----------------------------------------------------------------
@dataclass
class Hops:
    """Where a case's messages went, from the publisher's count, both bridges' counters for
    /bench (logged when they stop) and the subscriber's: everything since the case started,
    warm-ups included."""

    published: int
    #: bridge A's "sent": what it took from DDS and handed to its link, including what its
    #: send queue later dropped (superseded, ...: sequence numbers B then never sees)
    sent: int | None
    dropped_a: dict[str, int]
    received: int | None    # bridge B published
    dropped_b: dict[str, int]  # B's drops of /bench and of frames for no topic (the link's)
    lost: int               # B: sequence numbers that never came
    subscribed: int         # the subscriber got

    def cells(self) -> list[str]:
        def share(n: int | None, of: int | None) -> str:
            return f"{n:,} ({n / of:.0%})" if n is not None and of else "-"

        reasons = lambda d: ", ".join(f"{k}={v}" for k, v in sorted(d.items())) or "none"
        return [f"{self.published:,}", share(self.sent, self.published), reasons(self.dropped_a),
                share(self.received, self.sent),
                reasons(self.dropped_b) + (f"; lost on the way {self.lost}" if self.lost else ""),
                share(self.subscribed, self.received if self.sent is not None
                      else self.published)]


COUNTERS = re.compile(r"INFO /bench\b[^:]*: sent (\d+) \(\d+ B\), received (\d+) \(\d+ B\)"
                      r"(?:, lost on the way (\d+))?.*drops: (.*)$")
NO_TOPIC = re.compile(r"frames for no topic: (\{.*\})")


def hop_counts(case: Case, subscribed: int) -> Hops:
    def counters(bridge: Bridge | None) -> tuple[int, int, int, dict[str, int]] | None:
        for line in bridge.lines.seen if bridge else []:
            found = COUNTERS.search(line)
            if found:
                drops = {k: int(v) for k, v in re.findall(r"(\w+)=(\d+)", found[4])}
                return int(found[1]), int(found[2]), int(found[3] or 0), drops
        return None

    a, b = counters(case.a), counters(case.b)
    link: dict[str, int] = {}
    for line in case.b.lines.seen if case.b else []:
        found = NO_TOPIC.search(line)
        if found:
            link = {k: int(v) for k, v in re.findall(r"'(\w+)': (\d+)", found[1])}
    return Hops(case.published, a[0] if a else None, a[3] if a else {},
                b[1] if b else None, {**(b[3] if b else {}), **link}, b[2] if b else 0,
                subscribed)


@dataclass
class Result:
    size: Size
    route: Route | None
    reliability: str = "reliable"  # bare rows: the QoS of publisher and subscriber
    #: the publisher and the subscriber publish through rosgate's 8 MiB shared-memory segment
    large_segment: bool = False
    hops: Hops | None = None
    sustained: Trial | None = None
    peak: float = 0.0            # the most delivered per second in any trial
    latency: Trial | None = None
    cpu: Trial | None = None     # the fixed-rate trial CPU per message is measured in
    trials: list[Trial] = field(default_factory=list)  # the search's
    overload: Trial | None = None      # at OVERLOAD x sustained, reliable (the case's QoS)
    overload_be: Trial | None = None   # the same rate, every queue best effort
    #: the session only: a trial at SESSION_RATIO x udp/cdr/none's sustained rate
    session_check: Trial | None = None
    #: the default file only: a trial at DROP_CHECK x its sustained rate in fresh processes,
    #: and the drops both bridges counted in it, by reason
    drop_check: Trial | None = None
    check_drops: dict[str, int] | None = None
    profiles: list[Path] = field(default_factory=list)
    error: str | None = None
    problems: list[str] = field(default_factory=list)
    others: float = 0.0          # share of the CPU other processes used meanwhile
    seconds: float = 0.0

    @property
    def path(self) -> str:
        segment = f", {LARGE_SEGMENT}" if self.large_segment else ""
        if self.route:
            return self.route.label + segment
        return ("bare rclpy" + (", best effort" if self.reliability == "best_effort" else "")
                + segment)

    @property
    def bare(self) -> bool:
        """The bare row every bridged row of its size is compared with (reliable)."""
        return self.route is None and self.reliability == "reliable"

    @property
    def plain(self) -> bool:
        """A row of this checkout's rosgate, ends as they come (the rows targets compare)."""
        return self.route is not None and not self.route.rev and not self.large_segment


def measure(size: Size, route: Route | None, settings: Settings, folder: Path,
            options: Options, reliability: str = "reliable",
            large_segment: bool = False) -> Result:
    result = Result(size, route, reliability, large_segment=large_segment)
    checkout = options.checkouts[route.rev] if route else HERE_CHECKOUT
    # the real_time Twist beside the best-effort default file's overload at the target size
    twist = route == DEFAULT_BE and size.name == TARGET_SIZE
    case = Case(size, route, folder, checkout, None if route else reliability, twist,
                large_segment)
    # --quick: a floor's CPU trial only, for the line that sets the default file against it
    cpu_only = settings.quick and route is not None and route.roles == "floor"
    log(f"[{case.label}] starting")
    start, load = time.monotonic(), Load()
    try:
        with case:
            case.warm_up()
            # latency first, on a quiet path: after an overload trial, queues deep in DDS can
            # take a while to settle, and their wait would be charged to this measurement
            cpu_rate = min(options.cpu_rate, size.cpu_rate_max)
            # --quick: one trial at the CPU rate gives both
            latency_rate = cpu_rate if settings.quick else size.latency_rate
            seconds = max(settings.latency_seconds, 100 / latency_rate)  # >= 100 samples
            result.latency = case.trial(latency_rate, seconds)
            log(f"  [{case.label}] latency: {describe(result.latency)}")
            if cpu_rate == latency_rate and seconds >= settings.cpu_seconds:
                result.cpu = result.latency
            else:
                result.cpu = case.trial(cpu_rate, max(settings.cpu_seconds, 100 / cpu_rate))
                log(f"  [{case.label}] CPU: {describe(result.cpu)}")
            spec = options.profile
            if spec and route and route.path == spec.path and size.key == spec.size_key:
                result.profiles = profile(case, cpu_rate, spec, result.cpu, result.problems)
            if not cpu_only:
                result.sustained, result.trials = find_sustained(case, settings)
            if result.sustained:
                rate = min(OVERLOAD * result.sustained.offered, size.ceiling)
                result.overload = case.trial(rate, settings.trial_seconds, twist=twist)
                log(f"  [{case.label}] {OVERLOAD:g}x sustained: {describe(result.overload)}, "
                    f"{result.overload.arrived:.1%} arrived at all")
            if result.overload and result.overload.twist_ages_ms is not None:
                t = result.overload
                log(f"  [{case.label}] the real_time Twist meanwhile: "
                    f"{len(t.twist_ages_ms or [])} of {t.twist_sent} arrived, p99 "
                    f"{ms(1000 * t.twist_p99_ms) if t.twist_p99_ms is not None else '-'} ms")
            result.peak = max(t.delivered for t in [result.cpu, *result.trials, result.overload]
                              if t)
            subscribed = case.sub.ask("total")["received"]
    except RuntimeError as exc:
        result.error = str(exc)
        log(f"  [{case.label}] FAILED: {exc}")
        subscribed = None
    if subscribed is not None:
        result.hops = hop_counts(case, subscribed)
    result.problems += case.problems()
    # --quick: the best-effort overload only where its target is
    quick_skip = settings.quick and (route is None or replace(route, rev="") != TARGET_ROUTE)
    already = route is not None and route.reliability == "best_effort"
    if result.overload and size.key in options.best_effort and not quick_skip and not already:
        result.overload_be = best_effort_overload(size, route, checkout, folder / "best-effort",
                                                  result.overload.rate, settings, result.problems)
    result.others = load.others()
    if result.others > BUSY:
        result.problems.insert(0, f"other processes used {result.others:.0%} of the CPU meanwhile: "
                                  "these numbers are low")
    for line in result.problems:
        log(f"  [{case.label}] {line}")
    result.seconds = time.monotonic() - start
    log(f"  [{case.label}] done in {result.seconds:.0f} s")
    return result


def best_effort_overload(size: Size, route: Route | None, checkout: Checkout, folder: Path,
                         rate: float, settings: Settings, problems: list[str]) -> Trial | None:
    """The overload trial again with every queue best effort (publisher, both bridges'
    topic QoS, subscriber; same depth): a bridge may then drop rather than queue. Fresh
    processes, since QoS is fixed when they start."""
    case = Case(size, route, folder, checkout, reliability="best_effort")
    try:
        with case:
            case.warm_up()
            trial = case.trial(rate, settings.trial_seconds)
            log(f"  [{case.label}] {OVERLOAD:g}x sustained: {describe(trial)}, "
                f"{trial.arrived:.1%} arrived at all")
    except RuntimeError as exc:
        problems.append(f"best-effort overload trial failed: {exc}")
        return None
    finally:
        problems += [f"best-effort: {line}" for line in case.problems()]
    return trial


def confirm_session(results: list[Result], settings: Settings, options: Options,
                    folder: Path) -> None:
    """The session's target asks whether it sustains SESSION_RATIO x what udp/cdr/none
    sustained in the same run. Two searches each stop within 10 % of their path's limit, so
    their ratio alone is ±10 %; this asks the question directly: fresh session processes, one
    trial at exactly that rate, passing as a search trial passes (>= 95 % in time)."""
    for session in results:
        route = session.route
        if route is None or replace(route, rev="") != SESSION or session.size.name != TARGET_SIZE:
            continue
        plain = next((r for r in results if r.size is session.size
                      and r.route == replace(TARGET_ROUTE, rev=route.rev) and r.sustained), None)
        if plain is None or plain.sustained is None:
            continue
        rate = SESSION_RATIO * plain.sustained.offered
        case = Case(session.size, route, folder / f"session-check{route.rev}",
                    options.checkouts[route.rev])
        try:
            with case:
                case.warm_up()
                session.session_check = case.trial(rate, settings.trial_seconds)
                log(f"  [{case.label}] at {SESSION_RATIO}x {TARGET_ROUTE.label}'s sustained "
                    f"rate: {describe(session.session_check)}")
        except RuntimeError as exc:
            session.problems.append(f"the session's check trial failed: {exc}")


DROP_CHECK = 0.9  # the default file's drop check offers this times its sustained rate
LINK_DROPS = ("superseded", "too_late", "overload")  # what says a bridge gave up on a message


def check_drops(results: list[Result], settings: Settings, options: Options,
                folder: Path) -> None:
    """Whether the default file drops messages below its sustained rate: fresh processes, one
    trial at DROP_CHECK x the sustained rate, then the drop counters both bridges log when
    they stop (in fresh processes they count that trial and the warm-up only)."""
    for r in results:
        route = r.route
        if route is None or not route.default_file or r.sustained is None:
            continue
        case = Case(r.size, route, folder / f"drops-{r.size.key}-{route.reliability}{route.rev}",
                    options.checkouts[route.rev])
        try:
            with case:
                case.warm_up()
                r.drop_check = case.trial(DROP_CHECK * r.sustained.offered,
                                          settings.trial_seconds)
        except RuntimeError as exc:
            r.problems.append(f"the drop check failed: {exc}")
            continue
        r.check_drops = counted_drops(case)
        log(f"  [{case.label}] at {DROP_CHECK:g}x its sustained rate: "
            f"{describe(r.drop_check)}; drops: {r.check_drops or 'none'}")


def counted_drops(case: Case) -> dict[str, int]:
    """Drops by reason from the counters the case's bridges logged when they stopped."""
    found: dict[str, int] = {}
    for bridge in case.bridges:
        for line in bridge.lines.seen:
            if "drops: " not in line:
                continue
            for item in line.rsplit("drops: ", 1)[1].split(", "):
                reason, _, count = item.partition("=")
                if count.isdigit():
                    found[reason] = found.get(reason, 0) + int(count)
    return found


# -- profiles -------------------------------------------------------------------------------------
SIDES = {"peer": ("bridge A, transmit: DDS subscription -> link",
                  "bridge B, receive: link -> DDS publisher"),
         "client/server": ("bridge A, the client, transmit: DDS subscription -> link",
                           "bridge B, the server, receive: link -> DDS publisher")}
SIDES["session"] = SIDES["client/server"]  # the same processes, authenticated


def profile_stem(size: Size, route: Route) -> str:
    name = route.path.replace("/", "-").replace(" ", "-")
    return f"{name}{'@' + route.rev if route.rev else ''}-{size.name.replace(' ', '')}"


def profile(case: Case, rate: float, spec: ProfileSpec, quiet: Trial,
            problems: list[str]) -> list[Path]:
    """py-spy on bridge A during one trial at ``rate``, then on bridge B during another (one
    sampler at a time disturbs the path less); a summary per side."""
    assert case.route and case.a and case.b
    spec.folder.mkdir(parents=True, exist_ok=True)
    stem = profile_stem(case.size, case.route)
    title = (f"{case.label}, {rate:,.0f} msg/s for {spec.seconds:g} s, rosgate "
             f"{case.route.rev or revision()}")
    written = []
    for side, bridge, role in zip("AB", (case.a, case.b), SIDES[case.route.roles], strict=True):
        recording = profiling.Recording(bridge.pid, spec.folder / f"{stem}-{side}.raw")
        try:
            try:
                recording.start()
                trial = case.trial(rate, spec.seconds)
            finally:
                if recording.proc and recording.proc.poll() is None:
                    recording.stop()
        except profiling.ProfileError as exc:
            problems.append(f"profile {side}: {exc}")
            log(f"  [{case.label}] profile of {side} failed: {exc}")
            continue
        log(f"  [{case.label}] profiled {side}: {describe(trial)}")
        summary = profiling.summary(
            profiling.Side(side, role, recording, trial.us_per_msg(side), quiet.us_per_msg(side),
                           quiet.threads.get(side, {}), quiet.received),
            title, trial.received, roots=[case.checkout.root, ROOT],
            latency=f"p50 {ms(trial.p50_us)} ms, p99 {ms(trial.p99_us)} ms, "
                    f"{trial.in_time / max(trial.sent, 1):.1%} in time",
            latency_quiet=f"p50 {ms(quiet.p50_us)} ms, p99 {ms(quiet.p99_us)} ms")
        path = spec.folder / f"{stem}-{side}.txt"
        path.write_text(summary)
        written.append(path)
        log(f"  [{case.label}] wrote {path}")
    return written


# -- the tables -----------------------------------------------------------------------------------
COLUMNS = ["size", "path", "sustained msg/s", "vs bare", "MB/s", "peak delivered msg/s",
           "latency at msg/s", "p50 ms", "p99 ms", "p50 vs bare", "A µs/msg", "B µs/msg",
           f"{OVERLOAD:g}x sustained: delivered", "age p50 ms", "age p99 ms", "newest"]
DETAIL = ["size", "path", "CPU trial msg/s", "pub µs/msg", "A µs/msg", "B µs/msg", "sub µs/msg",
          "A+B vs bare pub+sub", f"{OVERLOAD:g}x: offered msg/s", "delivered", "p50 ms",
          "p99 ms", "p99 ms, 2nd half", f"{OVERLOAD:g}x best effort: offered msg/s", "delivered",
          "p50 ms", "p99 ms", "p99 ms, 2nd half"]


def markdown(columns: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(columns) + " |", "|---|---|" + "--:|" * (len(columns) - 2)]
    for cells in rows:
        cells = cells + [""] * (len(columns) - len(cells))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def table(results: list[Result]) -> str:
    bare = {r.size.name: r for r in results if r.bare}
    return markdown(COLUMNS, [[r.size.name, r.path, *row(r, bare.get(r.size.name))]
                              for r in results])


def row(r: Result, bare: Result | None) -> list[str]:
    """The cells after size and path."""
    if r.error and not r.latency:
        return ["failed: " + r.error.splitlines()[0]]
    cells = (throughput_cells(r, bare) + latency_cells(r.latency, bare.latency if bare else None)
             + cpu_cells(r) + overload_cells(r))
    if r.error:
        cells[-1] += " (failed: " + r.error.splitlines()[0] + ")"
    return cells


def throughput_cells(r: Result, bare: Result | None) -> list[str]:
    s = r.sustained
    if s is None:  # not even the search's lowest rate passed
        return ["-", "-", "-", f"{r.peak:,.0f}" if r.trials else "-"]
    at_least = "≥ " if s.publisher_bound or s.rate >= r.size.ceiling else ""
    return [f"{at_least}{s.offered:,.0f}",
            ratio(s.offered, bare.sustained.offered if bare and bare.sustained else None),
            f"{s.offered * r.size.bytes / 1e6:,.1f}", f"{r.peak:,.0f}"]


def latency_cells(lat: Trial | None, bare: Trial | None) -> list[str]:
    if lat is None:
        return ["-"] * 4
    return [at_rate(lat), ms(lat.p50_us), ms(lat.p99_us),
            ratio(lat.p50_us, bare.p50_us if bare else None)]


def at_rate(t: Trial) -> str:
    """A fixed-rate trial's rate, and how much arrived if it overloaded the path."""
    overloaded = "" if t.ok else f" ({t.in_time / max(t.sent, 1):.0%} delivered)"
    return f"{t.offered:,.0f}{overloaded}"


def cpu_cells(r: Result) -> list[str]:
    """A and B µs/msg; on the bare row the publisher's and the subscriber's."""
    if r.cpu is None:
        return ["-", "-"]
    if r.route is None:
        return [f"pub {us(r.cpu.us_per_msg('pub'))}", f"sub {us(r.cpu.us_per_msg('sub'))}"]
    return [us(r.cpu.us_per_msg("A")), us(r.cpu.us_per_msg("B"))]


def overload_cells(r: Result) -> list[str]:
    """The overload trial: the share that arrived, the age (receive time minus the
    publisher's stamp) of what arrived, and of what arrived during the trial's last quarter
    the share sent in it (:attr:`Trial.newest`)."""
    t = r.overload
    if t is None or r.sustained is None:
        return ["-"] * 4
    factor = t.offered / r.sustained.offered
    short = f" (at {factor:.1f}x)" if factor < 0.9 * OVERLOAD else ""
    return [f"{t.arrived:.1%}{short}", ms(t.p50_us), ms(t.p99_us),
            "-" if t.newest is None else f"{t.newest:.0%}"]


def detail_table(results: list[Result]) -> str:
    bare = {r.size.name: r for r in results if r.bare}
    rows = []
    for r in results:
        cells = [r.size.name, r.path]
        c = r.cpu
        if c is None:
            rows.append(cells + ["-"])
            continue
        cells += [at_rate(c), *(us(c.us_per_msg(role)) for role in ("pub", "A", "B", "sub"))]
        b = bare.get(r.size.name)
        rclpy = (sum(b.cpu.cpu.get(role, 0) for role in ("pub", "sub")) / b.cpu.received
                 if b and b.cpu and b.cpu.received else None)
        mine = (sum(c.cpu.get(role, 0) for role in ("A", "B")) / c.received
                if r.route and c.received else None)
        cells.append(ratio(mine, rclpy) if r.route else ratio(rclpy, rclpy))
        for t in (r.overload, r.overload_be):
            cells += ([f"{t.offered:,.0f}", f"{t.arrived:.1%}", ms(t.p50_us), ms(t.p99_us),
                       ms(t.p99_settled_us)] if t else ["-"] * 5)
        rows.append(cells)
    return markdown(DETAIL, rows)


def compare_table(results: list[Result]) -> str | None:
    """This checkout against the base revision, path by path."""
    pairs = []
    for r in results:
        if r.route and r.route.rev:
            mine = next((m for m in results if m.size == r.size and not m.large_segment
                         and m.route == replace(r.route, rev="")), None)
            if mine:
                pairs.append((mine, r))
    if not pairs:
        return None
    rev = pairs[0][1].route.rev

    def vs(a: float | None, b: float | None, fmt) -> str:
        return "-" if a is None or b is None else f"{fmt(a)} vs {fmt(b)} ({ratio(a, b)}x)"

    number = lambda v: f"{v:,.0f}"
    rows = []
    for mine, base in pairs:
        cpu = lambda r, side: r.cpu.us_per_msg(side) if r.cpu else None
        rows.append([mine.size.name, mine.path,
                     vs(mine.sustained and mine.sustained.offered,
                        base.sustained and base.sustained.offered, number),
                     vs(cpu(mine, "A"), cpu(base, "A"), us), vs(cpu(mine, "B"), cpu(base, "B"), us),
                     vs(mine.latency and mine.latency.p50_us, base.latency and base.latency.p50_us,
                        ms),
                     vs(mine.overload and mine.overload.p99_us,
                        base.overload and base.overload.p99_us, ms),
                     vs(mine.overload and mine.overload.p99_settled_us,
                        base.overload and base.overload.p99_settled_us, ms)])
    return markdown(["size", "path", f"sustained msg/s: this vs @{rev}", "A µs/msg", "B µs/msg",
                     "p50 ms", f"{OVERLOAD:g}x p99 ms", f"{OVERLOAD:g}x p99 ms, 2nd half"], rows)


def ratio(value: float | None, base: float | None) -> str:
    return f"{value / base:.2f}" if value is not None and base else "-"


def session_verdicts(results: list[Result]) -> list[str]:
    """The authenticated session against the unauthenticated rows of the same run."""
    def found(route: Route, rev: str) -> Result | None:
        return next((r for r in results if r.size.name == TARGET_SIZE and r.route
                     and r.route == replace(route, rev=rev) and r.sustained is not None), None)

    def sustained(route: Route, rev: str) -> float | None:
        r = found(route, rev)
        return r.sustained.offered if r and r.sustained else None

    goal = (f"target: {TARGET_SIZE} over an authenticated client/server session "
            f"({SESSION.label}) sustained >= {SESSION_RATIO}x {TARGET_ROUTE.label} of the same run")
    lines = []
    revs = sorted({r.route.rev for r in results if r.route and r.route.roles == "session"})
    for rev in revs or [""]:
        session, plain = sustained(SESSION, rev), sustained(TARGET_ROUTE, rev)
        unauthenticated = sustained(CLIENT_SERVER, rev)
        who = f" with rosgate @{rev}" if rev else ""
        if session is None or not plain:
            lines.append(f"{goal}{who}: NOT MEASURED in this run")
            continue
        mine, theirs = found(SESSION, rev), found(TARGET_ROUTE, rev)
        check = mine.session_check if mine else None
        confirmed = check is not None and check.ok
        met = "MET" if session >= SESSION_RATIO * plain or confirmed else "NOT MET"
        against = (f"; {session / unauthenticated:.2f}x the unauthenticated client/server row "
                   f"({unauthenticated:,.0f})" if unauthenticated else "")
        peaks = (f"; peak delivered {mine.peak / theirs.peak:.2f}x ({mine.peak:,.0f} against "
                 f"{theirs.peak:,.0f})" if mine and theirs and theirs.peak else "")
        checked = (f"; a trial of the session at {SESSION_RATIO}x {TARGET_ROUTE.label}'s "
                   f"sustained rate ({check.offered:,.0f} msg/s) delivered "
                   f"{check.in_time / max(check.sent, 1):.1%} in time: "
                   f"{'passed' if check.ok else 'failed'}" if check else "")
        lines.append(f"{goal}{who}: {met} (sustained {session:,.0f} msg/s, {session / plain:.2f}x "
                     f"{TARGET_ROUTE.label}'s {plain:,.0f}{against}{peaks}{checked})")
    return lines


def verdicts(results: list[Result]) -> list[str]:
    lines = []
    goal = (f"target: {TARGET_SIZE} over {TARGET_ROUTE.label} sustained >= {TARGET_RATE:,} msg/s "
            f"end to end (ros2_socket_bridge, which rosgate replaces: ~{REPLACED_RATE:,})")
    found = [r for r in results if r.size.name == TARGET_SIZE and r.route
             and replace(r.route, rev="") == TARGET_ROUTE]
    if not found or all(r.sustained is None for r in found):
        lines.append(f"{goal}: NOT MEASURED in this run")
    for r in found:
        if r.sustained is None:
            continue
        got = r.sustained.offered
        met = "MET" if got >= TARGET_RATE else "NOT MET"
        who = f" with rosgate @{r.route.rev}" if r.route.rev else ""
        lines.append(f"{goal}{who}: {met} ({got:,.0f} msg/s, "
                     f"{got / REPLACED_RATE:.1f}x the replaced bridge)")
    lines += session_verdicts(results)
    goal = (f"target: at {OVERLOAD:g}x the sustained rate, p99 < {OVERLOAD_P99_MS} ms for a "
            f"non-reliable topic ({TARGET_SIZE} {TARGET_ROUTE.label}, every queue best effort)")
    measured = [r for r in found if r.overload_be]
    if not measured:
        lines.append(f"{goal}: NOT MEASURED in this run")
    for r in measured:
        t = r.overload_be
        met = "MET" if t.p99_us is not None and t.p99_us < OVERLOAD_P99_MS * 1000 else "NOT MET"
        who = f" with rosgate @{r.route.rev}" if r.route.rev else ""
        lines.append(f"{goal}{who}: {met} (p99 {ms(t.p99_us)} ms, {t.arrived:.1%} delivered; "
                     f"p99 of the trial's second half {ms(t.p99_settled_us)} ms)")
    return lines


# -- the fast path's targets, each beside what the floor (no rosgate) reaches in the same run -----
UDP, TCP = Route("udp"), Route("tcp")
UDP_FLOOR, TCP_FLOOR = FLOORS


def fast_path_targets(results: list[Result], cpu_rate: float) -> str | None:
    """A table: each target of the fast path, rosgate's value, the floor's, the verdict. A target
    the floor misses too is one no Python bridge on rclpy reaches on this machine."""
    found = {(r.size.name, r.route): r for r in results if r.bare or r.plain}

    def get(size: str, route: Route | None) -> Result | None:
        return found.get((size, route))

    def vs_bare(size: str, route: Route) -> float | None:
        r, bare = get(size, route), get(size, None)
        if r is None or bare is None or r.sustained is None or bare.sustained is None:
            return None
        return r.sustained.offered / bare.sustained.offered

    def latency(size: str, route: Route, field_: str) -> float | None:
        r, bare = get(size, route), get(size, None)
        if r is None or bare is None or r.latency is None or bare.latency is None:
            return None
        mine, theirs = getattr(r.latency, field_), getattr(bare.latency, field_)
        return mine / theirs if mine is not None and theirs else None

    def tcp_vs_udp(tcp: Route, udp: Route) -> float | None:
        a, b = get("2.5 kB", tcp), get("2.5 kB", udp)
        if a is None or b is None or a.sustained is None or b.sustained is None:
            return None
        return a.sustained.offered / b.sustained.offered

    def cpu(size: str, route: Route) -> float | None:
        r = get(size, route)
        if r is None or r.cpu is None:
            return None
        sides = [r.cpu.us_per_msg(side) for side in ("A", "B")]
        return max(sides) if None not in sides else None  # type: ignore[type-var]

    rows: list[tuple[str, float | None, float | None, Callable[[float], bool], str]] = [
        ("2.5 kB udp/cdr/none sustained >= 0.45x bare", vs_bare("2.5 kB", UDP),
         vs_bare("2.5 kB", UDP_FLOOR), lambda v: v >= 0.45, "x"),
        ("100 B udp/cdr/none sustained >= 0.4x bare", vs_bare("100 B", UDP),
         vs_bare("100 B", UDP_FLOOR), lambda v: v >= 0.4, "x"),
        ("2.5 kB tcp/cdr/none within 10 % of udp/cdr/none", tcp_vs_udp(TCP, UDP),
         tcp_vs_udp(TCP_FLOOR, UDP_FLOOR), lambda v: v >= 0.9, "x udp"),
        ("2.5 kB authenticated session (aead) sustained >= 0.4x bare",
         vs_bare("2.5 kB", SESSION), vs_bare("2.5 kB", UDP_FLOOR), lambda v: v >= 0.4, "x"),
        ("1 MB udp/cdr/none sustained >= 0.4x bare", vs_bare("1 MB", UDP),
         vs_bare("1 MB", TCP_FLOOR), lambda v: v >= 0.4, "x"),
        ("1 MB tcp/cdr/none sustained >= 0.4x bare", vs_bare("1 MB", TCP),
         vs_bare("1 MB", TCP_FLOOR), lambda v: v >= 0.4, "x"),
        ("100 B udp at 1,000 msg/s: p50 <= 2.3x bare", latency("100 B", UDP, "p50_us"),
         latency("100 B", UDP_FLOOR, "p50_us"), lambda v: v <= 2.3, "x"),
        ("100 B udp at 1,000 msg/s: p99 <= 3x bare", latency("100 B", UDP, "p99_us"),
         latency("100 B", UDP_FLOOR, "p99_us"), lambda v: v <= 3.0, "x"),
        ("100 B tcp at 1,000 msg/s: p50 <= 2.3x bare", latency("100 B", TCP, "p50_us"),
         latency("100 B", TCP_FLOOR, "p50_us"), lambda v: v <= 2.3, "x"),
    ]
    if cpu_rate == CPU_RATE:
        rows.append((f"2.5 kB udp/cdr/none: CPU <= 30 µs/msg on each side at {CPU_RATE:,} msg/s "
                     "(the larger of A and B)", cpu("2.5 kB", UDP), cpu("2.5 kB", UDP_FLOOR),
                     lambda v: v <= 30, " µs"))
    lines = []
    for goal, mine, floor, met, unit in rows:
        if mine is None:
            continue
        digits = 0 if unit == " µs" else 2
        if met(mine):
            verdict = "MET"
        elif floor is not None and not met(floor):
            verdict = "NOT MET; the floor does not meet it either"
        else:
            verdict = "NOT MET"
        lines.append([goal, f"{mine:.{digits}f}{unit}",
                      f"{floor:.{digits}f}{unit}" if floor is not None else "-", verdict])
    if not lines:
        return None
    return markdown(["fast-path target", "rosgate", "floor (no rosgate)", "verdict"], lines)


# -- the default file's targets, measured beside the rows they compare with --------------------
DEFAULT_VS_BARE = 0.4      # the default file sustains at least this much of bare rclpy
DEFAULT_VS_LOOPBACK = 0.9  # ... and of the same file with max_frame 65,000
UDP_VS_FLOOR = 0.9         # udp/cdr/none against the udp floor, 2.5 kB
IMAGE_CPU_US = 1_000       # 1 MB images: CPU per image on each side
BATCH_CPU_US, BATCH_P99_MS = 30, 3  # with a 2 ms batch window, 2,000 msg/s of 2.5 kB


def default_file_targets(results: list[Result]) -> str | None:
    """A table: each target of the default file, what was measured, the verdict."""
    found = {(r.size.name, r.route): r for r in results if r.bare or r.plain}

    def sustained(size: str, route: Route | None) -> float | None:
        r = found.get((size, route))
        return r.sustained.offered if r and r.sustained else None

    def vs(size: str, route: Route, base: Route | None) -> float | None:
        mine, theirs = sustained(size, route), sustained(size, base)
        return mine / theirs if mine is not None and theirs else None

    lines = []
    for size in ("100 B", "2.5 kB", "10 kB"):
        for route in (DEFAULT_BE, DEFAULT):
            r, got = found.get((size, route)), vs(size, route, None)
            if r is None or got is None:
                continue
            drops = r.check_drops
            late = {k: v for k, v in (drops or {}).items() if k in LINK_DROPS}
            said = ("no drop check" if drops is None else ", ".join(
                f"{k}={v}" for k, v in late.items()) or "none of " + "/".join(LINK_DROPS))
            met = got >= DEFAULT_VS_BARE and drops is not None and not late
            lines.append([f"{size} {route.path}: sustained >= {DEFAULT_VS_BARE}x bare, no "
                          f"{'/'.join(LINK_DROPS)} drop at {DROP_CHECK}x it",
                          f"{got:.2f}x; {said}", "MET" if met else "NOT MET"])
    got = vs("2.5 kB", DEFAULT, SESSION)
    if got is not None:
        lines.append([f"2.5 kB {DEFAULT.path} sustains >= {DEFAULT_VS_LOOPBACK}x the same file "
                      f"with max_frame 65000 ({SESSION.path})", f"{got:.2f}x",
                      "MET" if got >= DEFAULT_VS_LOOPBACK else "NOT MET"])
    got = vs("2.5 kB", UDP, UDP_FLOOR)
    if got is not None:
        lines.append([f"2.5 kB udp/cdr/none sustains >= {UDP_VS_FLOOR}x the udp floor",
                      f"{got:.2f}x", "MET" if got >= UDP_VS_FLOOR else "NOT MET"])
    image = found.get(("1 MB", DEFAULT))
    if image and image.cpu:
        sides = [image.cpu.us_per_msg(side) for side in ("A", "B")]
        if None not in sides:
            worst = max(v for v in sides if v is not None)
            lines.append([f"1 MB {DEFAULT.path}: CPU per image <= {IMAGE_CPU_US / 1000:g} ms on "
                          "each side", f"A {us(sides[0])} µs, B {us(sides[1])} µs",
                          "MET" if worst <= IMAGE_CPU_US else "NOT MET"])
    batched = found.get(("2.5 kB", BATCHED))
    if batched and batched.cpu and batched.cpu.rate == CPU_RATE:
        sides = [batched.cpu.us_per_msg(side) for side in ("A", "B")]
        p99 = batched.cpu.p99_us
        if None not in sides and p99 is not None:
            worst = max(v for v in sides if v is not None)
            lines.append([f"2.5 kB {BATCHED.path} at {CPU_RATE:,} msg/s: CPU <= {BATCH_CPU_US} "
                          f"µs per message on each side, p99 <= {BATCH_P99_MS} ms",
                          f"A {us(sides[0])} µs, B {us(sides[1])} µs; p99 {ms(p99)} ms",
                          "MET" if worst <= BATCH_CPU_US and p99 <= BATCH_P99_MS * 1000
                          else "NOT MET"])
    if not lines:
        return None
    return markdown(["default-file target", "measured", "verdict"], lines)


# -- overload, images and CPU against the floor: one line each ------------------------------------
NEWEST = 0.8  # "what is delivered is the newest": this share of the last quarter's arrivals


def fresh_data_verdicts(results: list[Result]) -> list[str]:
    """At 2x the sustained rate, the best-effort default file's age of what it delivers,
    whether that is the newest, and the real_time Twist beside it."""
    lines = []
    for r in results:
        t = r.overload
        if r.route is None or replace(r.route, rev="") != DEFAULT_BE or t is None \
                or r.size.name != TARGET_SIZE:
            continue
        fresh = t.p99_us is not None and t.p99_us <= OVERLOAD_P99_MS * 1000 \
            and t.newest is not None and t.newest >= NEWEST
        newest = "-" if t.newest is None else f"{t.newest:.0%}"
        line = (f"at {OVERLOAD:g}x the sustained rate ({t.offered:,.0f} msg/s), {r.size.name} "
                f"{r.path}: age p99 <= {OVERLOAD_P99_MS} ms and the newest delivered (>= "
                f"{NEWEST:.0%} of the last quarter's arrivals sent in it): "
                f"{'MET' if fresh else 'NOT MET'} (age p50 {ms(t.p50_us)} ms, p99 "
                f"{ms(t.p99_us)} ms, {t.arrived:.1%} delivered, newest {newest})")
        if t.twist_ages_ms is not None:
            p99 = t.twist_p99_ms
            ok = p99 is not None and p99 <= TWIST_P99_MS and len(t.twist_ages_ms) >= t.twist_sent
            p50 = percentile(t.twist_ages_ms, 0.5) if t.twist_ages_ms else None
            said = lambda v: "-" if v is None else f"{v:.1f}"
            line += (f"; a real_time Twist at {TWIST_RATE} Hz beside it, p99 <= {TWIST_P99_MS} "
                     f"ms: {'MET' if ok else 'NOT MET'} ({len(t.twist_ages_ms)} of "
                     f"{t.twist_sent} arrived, p50 {said(p50)} ms, p99 {said(p99)} ms)")
        lines.append(line)
    return lines


def floor_for(size: Size) -> Route:
    """The floor a size's CPU is compared with: udp's where a message fits one datagram."""
    return UDP_FLOOR if size.bytes <= UDP_FLOOR_MAX else TCP_FLOOR


def cpu_against_floor(results: list[Result], cpu_rate: float) -> list[str]:
    """One line per size: the default file's CPU per message on each side against the floor's
    (the least a Python bridge on rclpy spends) in the same run."""
    lines = []
    for size in SIZES:
        floor = next((r for r in results if r.size is size and r.route == floor_for(size)
                      and r.cpu), None)
        mine = [r for r in results if r.size is size and r.route and r.route.default_file
                and r.plain and not r.route.batch and not r.route.loss and r.cpu]
        if floor is None or floor.cpu is None or not mine:
            continue
        fa, fb = floor.cpu.us_per_msg("A"), floor.cpu.us_per_msg("B")
        parts = []
        for r in mine:
            assert r.cpu is not None
            a, b = r.cpu.us_per_msg("A"), r.cpu.us_per_msg("B")
            ratios = [x / f for x, f in ((a, fa), (b, fb)) if x is not None and f]
            met = len(ratios) == 2 and max(ratios) <= FLOOR_CPU_RATIO
            parts.append(f"{r.path} A {us(a)} / B {us(b)} = "
                         + " / ".join(f"{x:.2f}x" for x in ratios)
                         + f" ({'MET' if met else 'NOT MET'})")
        rate = floor.cpu.offered
        lines.append(f"{size.name} CPU µs/msg at {rate:,.0f} msg/s, target <= {FLOOR_CPU_RATIO}x "
                     f"the floor on each side: {floor.path} A {us(fa)} / B {us(fb)}; "
                     + "; ".join(parts))
    return lines


def image_share(results: list[Result]) -> list[str]:
    """1 MB best effort at 20 images/s (the latency trial): the share the default file
    delivers against what Fast DDS alone delivers in the same run, ends with Fast DDS's
    defaults and ends with rosgate's profile."""
    lines = []
    for size, segment in ((s, large) for s in SIZES for large in (False, True)):
        bare = next((r for r in results if r.size is size and r.route is None
                     and r.reliability == "best_effort" and r.large_segment == segment
                     and r.latency), None)
        if bare is None or bare.latency is None:
            continue
        for r in results:
            if r.size is not size or r.route != DEFAULT_BE or r.latency is None \
                    or r.large_segment != segment:
                continue
            got, theirs = r.latency.arrived, bare.latency.arrived
            met = got >= IMAGE_SHARE * theirs and (theirs < 0.9 or got >= 0.9)
            lines.append(f"{size.name} best effort at {r.latency.offered:,.0f}/s: {r.path} "
                         f"delivers >= {IMAGE_SHARE}x the share {bare.path} delivers (and >= 90 % "
                         f"where bare does): {'MET' if met else 'NOT MET'} ({got:.0%} against "
                         f"{theirs:.0%}, {got / theirs if theirs else 0:.2f}x)")
    return lines


HOPS = ["size", "path", "published", "bridge A took", "A dropped", "B published",
        "B and link dropped", "subscriber got"]


def hops_table(results: list[Result]) -> str | None:
    """Where the messages went, hop by hop (everything of the case, warm-ups included): 1 MB
    rows, and the default file's rows at every size."""
    rows = [[r.size.name, r.path, *r.hops.cells()] for r in results if r.hops and (
        r.size.kind == "image" and (r.route is None or r.route.roles != "floor")
        or r.route is not None and r.route.default_file)]
    return markdown(HOPS, rows) if rows else None


def report(results: list[Result], settings: Settings, options: Options, elapsed: float,
           others: float, out: Path, plots: list[Path], base: str | None) -> str:
    mode = "quick" if settings.quick else "full"
    cpu = next((line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo")
                if line.startswith("model name")), platform.processor())
    notes = [f"- {r.size.name} {r.path}: {line}" for r in results for line in r.problems[:6]]
    link = lambda p: os.path.relpath(p, out.parent)
    be_sizes = [s.name for s in SIZES if s.key in options.best_effort]
    based = f"; base {base}" if base else ""
    parts = [
        "# rosgate benchmark: bridged vs bare rclpy",
        "",
        f"{time.strftime('%Y-%m-%d %H:%M')}, rosgate {revision()}{based}, {mode} run "
        f"({settings.trial_seconds:g} s trials), {os.cpu_count()} cores ({cpu}), "
        f"Python {platform.python_version()}, {elapsed / 60:.1f} min; other processes used "
        f"{others:.0%} of the CPU meanwhile. Sustained: highest steady offered rate with >= "
        f"{DELIVERED:.0%} delivered by the trial's end + {GRACE:g} s. '≥': the publisher (or "
        "the search's ceiling) was the limit, not the path. Peak: the most delivered per second "
        "in any trial. Ratios: bridged / bare rclpy at the same size. µs/msg: CPU time "
        "(utime + stime, /proc/<pid>/stat) of bridge A and bridge B (bare row: publisher and "
        f"subscriber) per message delivered in a {settings.cpu_seconds:g} s trial at "
        f"{options.cpu_rate:,.0f} msg/s (1 MB: 20 msg/s)"
        + ("; --quick measures latency in that same trial" if settings.quick else "")
        + f". {OVERLOAD:g}x sustained: a "
        f"{settings.trial_seconds:g} s trial at twice the sustained rate after the search; "
        "delivered: the share that arrived at all, however late; p99: of what arrived.",
        "",
        "The default file: what a user writes after the README's Security section — a "
        "client/server session with identities and nothing else: udp with the max_frame it "
        "takes from the path, cdr, the session's aead cipher (the topic's QoS is the "
        "measurement's: reliable or best effort, deep queues). The other rows set udp's "
        "max_frame to 65,000 (loopback's datagrams).",
        "",
        table(results),
        "",
        *[f"**{line}**" for line in verdicts(results)],
        *[f"**{line}**" for line in fresh_data_verdicts(results)],
        *[f"**{line}**" for line in cpu_against_floor(results, options.cpu_rate)],
        *[f"**{line}**" for line in image_share(results)],
        "",
        "## Where the time goes: CPU per message, and overload",
        "",
        "CPU trial: the fixed-rate trial the µs/msg are measured in ('(x % delivered)' if it "
        "overloaded the path). A+B vs bare pub+sub: what the two bridges spend per message "
        "against what rclpy's publisher and subscriber spend in the bare case. "
        f"{OVERLOAD:g}x best effort: the same overload again with the publisher, both bridges' "
        "topic QoS and the subscriber best effort (same depth), in fresh processes; "
        + (f"run at {', '.join(be_sizes)}" if be_sizes else "not run (--best-effort none)")
        + (f", for {TARGET_ROUTE.label} only (--quick)" if settings.quick else "") + ".",
        "",
        detail_table(results),
    ]
    hops = hops_table(results)
    if hops:
        parts += ["", "## Where messages go, hop by hop", "",
                  "Every message of the case, warm-ups and every trial: the publisher's count, "
                  "what bridge A took from DDS and handed to its link (its `sent` counter), what "
                  "its send queue dropped of those, what bridge B published, its drops and the "
                  "link's (frames for no topic; lost on the way: sequence numbers B never saw, "
                  "A's dropped ones among them), and what the subscriber got. Each share is of "
                  "the hop before: publisher -> A is DDS on this machine, A -> B the bridges and "
                  "the link, B -> subscriber DDS again. 1 MB rows, and the default file's at "
                  "every size.", "", hops]
    defaults = default_file_targets(results)
    if defaults:
        parts += ["", "## The default file's targets", "",
                  f"Drop check: fresh processes, one {settings.trial_seconds:g} s trial at "
                  f"{DROP_CHECK:g}x the row's sustained rate, then the drops both bridges "
                  "counted (superseded: a latest-only message replaced by a newer one while it "
                  "waited to be sent; too_late: one that waited longer than it may; overload: "
                  "one shed while its topic stayed behind).", "",
                  defaults]
    targets = fast_path_targets(results, options.cpu_rate)
    if targets:
        parts += ["", "## The fast path's targets, and the floor", "",
                  "The floor: bench/floor.py in place of both bridges, no rosgate — a raw "
                  "subscription whose callback sends each message as it came, and a thread that "
                  "receives and publishes it (udp: one datagram per message, so not at 1 MB; "
                  "tcp: a length and the bytes). What rclpy, Fast DDS and the kernel cost on "
                  "this machine before a bridge does anything. The 1 MB udp target is set "
                  "against the tcp floor; the session's against the udp floor (no cipher).", "",
                  targets]
    compared = compare_table(results)
    if compared:
        parts += ["", f"## This checkout against {base}", "", compared]
    if plots:
        parts += ["", "Plots: " + ", ".join(f"[{p.stem}]({link(p)})" for p in plots)]
    profiles = [p for r in results for p in r.profiles]
    if profiles:
        parts += ["", "Profiles (py-spy): " + ", ".join(f"[{p.name}]({link(p)})" for p in profiles)]
    if notes:
        parts += ["", "Notes: other load, and the bridges' warnings and drop counters:", "", *notes]
    return "\n".join(parts) + "\n"


def revision(root: Path = ROOT) -> str:
    """The commit measured, and whether the working tree differed from it."""
    git = ["git", "-C", str(root)]
    head = subprocess.run([*git, "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    dirty = subprocess.run([*git, "status", "--porcelain", "--untracked-files=no"],
                           capture_output=True, text=True)
    if head.returncode:
        return "(not a git checkout)"
    return head.stdout.strip() + (" + uncommitted changes" if dirty.stdout.strip() else "")


# -- another revision's rosgate (--base) ----------------------------------------------------------
def find_uv() -> str:
    for candidate in (os.environ.get("UV"), shutil.which("uv"), ROOT / ".tools" / "bin" / "uv"):
        if candidate and Path(candidate).exists():
            return str(candidate)
    sys.exit("bench: --base needs uv (on PATH, in .tools/bin/, or UV=/path/to/uv): run `make sync`")


def base_checkout(rev: str, stack: ExitStack) -> Checkout:
    """REV checked out in a temporary git worktree (outside this checkout's files) with a .venv
    of its own (uv sync --inexact); removed when ``stack`` closes."""
    git = ["git", "-C", str(ROOT)]
    found = subprocess.run([*git, "rev-parse", "--verify", "--quiet", f"{rev}^{{commit}}"],
                           capture_output=True, text=True)
    if found.returncode:
        sys.exit(f"bench: --base {rev}: no such commit here")
    sha = found.stdout.strip()
    short = subprocess.run([*git, "rev-parse", "--short", sha], capture_output=True, text=True,
                           check=True).stdout.strip()
    uv = find_uv()
    folder = Path(tempfile.mkdtemp(prefix=f"rosgate-base-{short}-"))
    tree = folder / "rosgate"

    def remove() -> None:
        subprocess.run([*git, "worktree", "remove", "--force", str(tree)], capture_output=True)
        shutil.rmtree(folder, ignore_errors=True)
        subprocess.run([*git, "worktree", "prune"], capture_output=True)
        log(f"bench: removed the worktree of {short}")

    stack.callback(remove)
    start = time.monotonic()
    log(f"bench: --base {rev} = {short}: checking it out in {tree}, syncing its .venv")
    subprocess.run([*git, "worktree", "add", "--detach", "--quiet", str(tree), sha], check=True)
    env = {k: v for k, v in os.environ.items()
           if k not in ("VIRTUAL_ENV", "UV_PROJECT_ENVIRONMENT")}
    # with bytecode, as make sync does: the base's bridges start as fast as this checkout's
    synced = subprocess.run([uv, "sync", "--inexact", "--quiet", "--compile-bytecode"], cwd=tree,
                            env=env, capture_output=True, text=True)
    subprocess.run([str(tree / ".venv/bin/python"), "-m", "compileall", "-q", "core/src",
                    "plugins", "libs"], cwd=tree, capture_output=True)
    checkout = Checkout(short, tree)
    if synced.returncode or not Path(checkout.rosgate).exists():
        sys.exit(f"bench: uv sync of {short} failed:\n{synced.stderr.strip()[-2000:]}")
    log(f"bench: {short} ready in {time.monotonic() - start:.0f} s")
    return checkout


# -- main -----------------------------------------------------------------------------------------
def knows_batch(rev: str, root: Path = ROOT) -> bool:
    """Whether a revision's topics take a batch window (``batch:``): declared in its schema.py,
    or, since an entry's keys have a module of their own, in its entries.py."""
    for module in ("schema.py", "entries.py"):
        found = subprocess.run(["git", "-C", str(root), "show",
                                f"{rev}:core/src/rosgate/config/{module}"],
                               capture_output=True, text=True)
        if found.returncode == 0 and "    batch: " in found.stdout:
            return True
    return False


#: a case to run: size and route (None: bare), and for a bare case its QoS if not reliable
Planned = tuple[Size, Route | None] | tuple[Size, Route | None, str, bool]
BARE_BE = "bare best effort"  # what --path matches for the bare best-effort 1 MB rows


def plan(settings: Settings, only: list[str] | None, paths: list[str] | None,
         base: str | None = None,
         profile_spec: ProfileSpec | None = None) -> list[Planned]:
    wanted = {normalize(o) for o in only} if only else None
    unknown = (wanted or set()) - {s.key for s in SIZES}
    if unknown:
        sys.exit(f"bench: unknown size {', '.join(sorted(unknown))}; sizes: {size_names()}")
    cases: list[Planned] = []
    for size in SIZES:
        if wanted and size.key not in wanted:
            continue
        routes = [*DEFAULTS, *(QUICK_ROUTES if settings.quick else ROUTES)]
        if size.name == TARGET_SIZE:
            routes = [*routes, BATCHED, *LOSSY, CLIENT_SERVER, SESSION]
        floors = [f for f in FLOORS if f.transport == "tcp" or size.bytes <= UDP_FLOOR_MAX]
        if settings.quick and not paths:
            # --quick: the CPU trial of the floor the CPU line compares with (udp; tcp at 1 MB)
            floors = [f for f in floors if f == floor_for(size)]
        if paths:
            routes = [route for route in routes if route.path in paths]
            floors = [floor for floor in floors if floor.path in paths]
        if not paths or "bare" in paths:
            cases.append((size, None))
        if size.kind == "image" and (not paths or BARE_BE in paths):
            # what Fast DDS alone delivers of best-effort images, beside the default file's;
            # and both again with a publisher (and subscriber) given rosgate's profile
            cases += [(size, None, "best_effort", False), (size, None, "best_effort", True)]
        cases += [(size, floor) for floor in floors]  # not rosgate: no base twin
        for route in routes:  # this checkout's and the base's side by side (a base that
            # knows batch windows measures its own: an older one refuses the key)
            twin = base and (not route.batch or knows_batch(base))
            cases += [(size, route)] + ([(size, replace(route, rev=base))] if twin else [])
            if route == DEFAULT_BE and size.kind == "image":
                cases.append((size, route, "best_effort", True))
    if profile_spec and not any(case[1] and case[1].path == profile_spec.path
                                and case[0].key == profile_spec.size_key for case in cases):
        size = next(s for s in SIZES if s.key == profile_spec.size_key)
        route = next(r for r in ALL_ROUTES if r.path == profile_spec.path)
        cases += [(size, route)] + ([(size, replace(route, rev=base))] if base else [])
    return cases


def size_names() -> str:
    return ", ".join(s.name.replace(" ", "") for s in SIZES)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="fewer paths, shorter trials")
    parser.add_argument("--only", action="append", metavar="SIZE",
                        help=f"only this size: {size_names()} (repeatable)")
    parser.add_argument("--path", action="append", metavar="PATH",
                        help="only this path, e.g. bare or udp/cdr/fernet (repeatable)")
    parser.add_argument("--keep", action="store_true",
                        help="keep the bringup.yaml files and logs (their folder is printed)")
    parser.add_argument("--out", default=str(HERE / "results.md"),
                        help="where to write the tables (default: bench/results.md; '-': "
                             "stdout only, and no plots unless --plots)")
    parser.add_argument("--plots", type=Path, metavar="DIR",
                        help="where to draw the plots (default: plots/ beside --out)")
    parser.add_argument("--cpu-rate", type=float, default=CPU_RATE, metavar="MSG/S",
                        help=f"the CPU trial's fixed rate (default {CPU_RATE:,}; 1 MB: at most 20)")
    parser.add_argument("--best-effort", action="append", metavar="SIZE",
                        help="sizes whose overload trial is repeated best effort (default "
                             "2.5kB; repeatable; 'none': no size, 'all': every size)")
    parser.add_argument("--base", metavar="REV",
                        help="also run the bridged paths with the rosgate of git revision REV "
                             "(a temporary worktree with its own .venv)")
    parser.add_argument("--profile", action="store_true",
                        help="py-spy on bridge A and B during a fixed-rate trial of one path "
                             "(writes bench/profiles/)")
    parser.add_argument("--profile-path", default="udp/cdr/none", metavar="PATH",
                        help="the path --profile samples (default udp/cdr/none)")
    parser.add_argument("--profile-size", default="2.5kB", metavar="SIZE",
                        help="... at this size (default 2.5kB)")
    parser.add_argument("--profile-seconds", type=float, default=8.0, metavar="S",
                        help="how long each side's profiled trial offers --cpu-rate (default 8)")
    args = parser.parse_args()
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # clean up processes and worktree
    settings = QUICK if args.quick else FULL

    options = Options(cpu_rate=args.cpu_rate)
    if args.best_effort:
        chosen = {normalize(s) for s in args.best_effort}
        if "all" in chosen:
            chosen = {s.key for s in SIZES}
        chosen.discard("none")
        if chosen - {s.key for s in SIZES}:
            sys.exit(f"bench: --best-effort: unknown size; sizes: {size_names()}, all, none")
        options.best_effort = frozenset(chosen)
    if args.profile:
        if not profiling.PYSPY.exists():
            sys.exit(f"bench: --profile needs py-spy ({profiling.PYSPY}): run `make sync`")
        key = normalize(args.profile_size)
        if key not in {s.key for s in SIZES}:
            sys.exit(f"bench: --profile-size {args.profile_size}: sizes: {size_names()}")
        if args.profile_path not in {r.path for r in ALL_ROUTES}:
            sys.exit(f"bench: --profile-path {args.profile_path}: one of "
                     f"{', '.join(r.path for r in ALL_ROUTES)}")
        options.profile = ProfileSpec(args.profile_path, key, args.profile_seconds,
                                      HERE / "profiles")
    start, load = time.monotonic(), Load()
    results = []
    with ExitStack() as stack:
        base = base_rev = None
        if args.base:
            checkout = base_checkout(args.base, stack)
            options.checkouts[checkout.rev] = checkout
            base_rev = checkout.rev
            base = f"{args.base} = {base_rev}" if args.base != base_rev else base_rev
        cases = plan(settings, args.only, args.path, base_rev, options.profile)
        log(f"bench: {len(cases)} cases, {'quick' if settings.quick else 'full'} run")
        tmp = stack.enter_context(tempfile.TemporaryDirectory(prefix="rosgate-bench-"))
        if args.keep:
            tmp = tempfile.mkdtemp(prefix="rosgate-bench-")
            log(f"bench: keeping files and logs in {tmp}")
        for i, (size, route, *qos) in enumerate(cases):
            folder = Path(tmp) / f"case{i:02d}"
            results.append(measure(size, route, settings, folder, options, *qos))
        confirm_session(results, settings, options, Path(tmp))
        check_drops(results, settings, options, Path(tmp))
    out = None if args.out == "-" else Path(args.out)
    plots_dir = args.plots or (out.parent / "plots" if out else None)
    drawn = []
    if plots_dir:
        try:
            import plots

            drawn = plots.draw(results, plots_dir)
            log(f"bench: drew {', '.join(str(p) for p in drawn)}")
        except ImportError as exc:
            log(f"bench: no plots ({exc}): run `make sync`")
        except Exception as exc:  # a plotting bug must not cost the run's tables
            log(f"bench: drawing the plots failed: {type(exc).__name__}: {exc}")
    text = report(results, settings, options, time.monotonic() - start, load.others(),
                  out or Path.cwd() / "-", drawn, base)
    print(text)
    if out:
        out.write_text(text)
    log(f"bench: {'wrote ' + str(out) if out else 'done'} in "
        f"{(time.monotonic() - start) / 60:.1f} min")
    return 1 if any(r.error for r in results) else 0


if __name__ == "__main__":
    sys.exit(main())
