"""Profiles of the two bridges: py-spy samples bridge A and bridge B during a fixed-rate trial.

    py-spy record --pid PID --rate 100 --format raw --threads --function --full-filenames [--native]

``--native`` adds the C frames (rclpy's extension, libc, CPython itself) below and between the
Python ones; where py-spy cannot unwind them it is retried without. py-spy only walks threads that
run Python: threads that never do (Fast DDS's own receive and event threads) are not sampled, so
the summary also lists every thread's CPU time from /proc (utime + stime), measured over the
case's unprofiled CPU trial. py-spy stops the process for every sample (needed for --native):
the profiled trial runs slower and later than an unprofiled one, so read shares, not totals.

The raw output is one line per distinct stack, frames root first, separated by ``;``, then a space
and the number of samples: ``thread (TID): NAME;frame;...;frame COUNT``. Samples in which a thread
was idle (its innermost named frame a wait: poll for a datagram, a DDS event's condition, a lock)
are left out and listed apart, so what remains is where the threads were busy. The summary counts,
per function:

* own: samples with the function on top of the stack (where the time is spent itself);
* total: samples with the function anywhere on the stack (itself and what it calls).
"""

from __future__ import annotations

import re
import signal
import subprocess
import sys
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

PYSPY = Path(sys.executable).with_name("py-spy")
# samples per second: on 2 cores, --native at 500/s and at 200/s fell seconds behind and took more
# than a core itself (the path then backed up: p50 0.4 -> 150 ms); at 100/s, one bridge at a time,
# it takes ~30-45 % of a core and the trial stays close to an unprofiled one
RATE = 100
TOP = 15
ATTACH_TIMEOUT = 15.0

THREAD = re.compile(r"^thread \((0x[0-9a-fA-F]+|\d+)\)(?::\s*(.*))?$")


class ProfileError(RuntimeError):
    pass


@dataclass
class Recording:
    """One py-spy process recording one bridge."""

    pid: int
    raw: Path
    native: bool = True
    proc: subprocess.Popen | None = None
    output: Path = field(init=False)
    started: float = 0.0
    seconds: float = 0.0
    samples: int = 0  # what py-spy reports as "Samples: N" (it skips rounds it finds all idle)
    errors: int = 0
    behind: float = 0.0  # the most py-spy said it fell behind, seconds

    def __post_init__(self) -> None:
        self.output = self.raw.with_suffix(".pyspy.log")

    def start(self) -> None:
        """Attach, retrying without --native if native unwinding is not possible here."""
        for native in ([True, False] if self.native else [False]):
            self.native = native
            if self._attach():
                return
        raise ProfileError(f"py-spy could not attach to {self.pid}: "
                           + self.output.read_text().strip()[-400:])

    def _attach(self) -> bool:
        command = [str(PYSPY), "record", "--pid", str(self.pid), "--rate", str(RATE),
                   "--format", "raw", "--threads", "--function", "--full-filenames",
                   "-o", str(self.raw)] + (["--native"] if self.native else [])
        with self.output.open("w") as out:
            self.proc = subprocess.Popen(command, stdout=out, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + ATTACH_TIMEOUT
        while time.monotonic() < deadline:
            if "Sampling process" in self.output.read_text():
                self.started = time.monotonic()
                return True
            if self.proc.poll() is not None:
                return False
            time.sleep(0.05)
        self.proc.kill()
        self.proc.wait()
        return False

    def stop(self) -> None:
        """Stop sampling (py-spy writes its file on SIGINT, as on Ctrl-C)."""
        assert self.proc is not None
        self.seconds = time.monotonic() - self.started
        self.proc.send_signal(signal.SIGINT)
        try:
            self.proc.wait(60)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        text = self.output.read_text()
        found = re.search(r"Samples: (\d+) Errors: (\d+)", text)
        if not found or not self.raw.exists():
            raise ProfileError(f"py-spy wrote no profile of {self.pid}: {text.strip()[-400:]}")
        self.samples, self.errors = int(found[1]), int(found[2])
        self.behind = max((float(x) for x in re.findall(r"([\d.]+)s behind in sampling", text)),
                          default=0.0)


# -- reading the raw stacks -----------------------------------------------------------------------
def read_stacks(raw: Path) -> list[tuple[list[str], int]]:
    stacks = []
    for line in raw.read_text().splitlines():
        frames, _, count = line.rpartition(" ")
        if frames and count.isdigit():
            stacks.append((frames.split(";"), int(count)))
    return stacks


def short_frame(frame: str, roots: list[Path]) -> str:
    """``name (/long/path/file.py:12)`` -> ``name (rosgate/links/datagram.py:12)``; an address in a
    library without symbols -> ``[libc.so.6]``; a C function -> ``sendto [libc.so.6]``."""
    name, sep, where = frame.rpartition(" (")
    if not sep:
        return frame
    where = where.removesuffix(")")
    file, colon, line = where.rpartition(":")
    if not colon or not line.isdigit():
        file, line = where, ""
    file = short_path(file, roots)
    if not line:
        return f"[{file}]" if name.startswith("0x") else f"{name} [{file}]"
    return f"{name} ({file}:{line})"


def short_path(file: str, roots: list[Path]) -> str:
    for marker in ("/site-packages/", "/dist-packages/"):
        if marker in file:
            return file.split(marker, 1)[1]
    for root in roots:
        prefix = str(root) + "/"
        if file.startswith(prefix):
            rest = file[len(prefix):]
            # core/src/rosgate/links/base.py -> rosgate/links/base.py,
            # plugins/x/src/pkg/m.py -> pkg/m.py
            return rest.split("/src/", 1)[1] if "/src/" in rest else rest
    match = re.search(r"/lib/python3\.\d+/(.*)$", file)
    if match:
        return match[1]
    return file.rsplit("/", 1)[-1]


# Innermost named frames that mean "waiting, not running": a sample whose innermost named frame is
# one of these is idle. py-spy has its own idle test, but with --native it did not recognise these
# waits here (the innermost libc frames below them have no symbols), so it is done again here.
# udp's receive waits inside recvmsg (under the socket's SO_RCVTIMEO), so a sample there is the
# wait nearly always: copying one datagram out is about a microsecond.
WAITS = {"recvmsg", "poll", "ppoll", "select", "pselect", "pselect6", "epoll_wait", "epoll_pwait",
         "pthread_cond_wait", "pthread_cond_timedwait", "pthread_cond_clockwait",
         "sem_wait", "sem_timedwait", "sem_clockwait", "PyThread_acquire_lock_timed", "take_gil",
         "nanosleep", "clock_nanosleep", "usleep", "accept", "accept4", "pause", "sigwait",
         "sigtimedwait"}


def frame_name(short: str) -> str | None:
    """The function of a shortened frame; None for a bare address."""
    if short.startswith("["):
        return None
    return short.rsplit(" [", 1)[0].rsplit(" (", 1)[0]


def is_python(short: str) -> bool:
    return short.endswith(")") and ".py:" in short


@dataclass
class Profile:
    """What one side's stacks add up to. Idle samples (innermost named frame a wait) are
    counted apart, by what waits and where."""

    threads: Counter  # (tid, python thread name) -> busy samples
    own: Counter      # function -> busy samples with it on top
    total: Counter    # function -> busy samples with it anywhere on the stack
    samples: int      # busy samples, all threads
    idle: int         # idle samples, all threads
    waits: Counter    # "wait in Python function" -> idle samples
    idle_threads: Counter  # (tid, python thread name) -> idle samples

    @classmethod
    def of(cls, stacks: list[tuple[list[str], int]], roots: list[Path]) -> Profile:
        threads: Counter = Counter()
        own: Counter = Counter()
        total: Counter = Counter()
        waits: Counter = Counter()
        idle_threads: Counter = Counter()
        samples = idle = 0
        for frames, count in stacks:
            thread = THREAD.match(frames[0]) if frames else None
            key = (0, "?")
            if thread:
                tid = int(thread[1], 16) if thread[1].startswith("0x") else int(thread[1])
                key = (tid, thread[2] or "")
                frames = frames[1:]
            names = [short_frame(f, roots) for f in frames]
            named = [n for n in names if frame_name(n) is not None]
            innermost = frame_name(named[-1]) if named else None
            if innermost in WAITS:
                idle += count
                python = next((n for n in reversed(names) if is_python(n)), "?")
                waits[f"{innermost} in {python}"] += count
                idle_threads[key] += count
                continue
            samples += count
            threads[key] += count
            # an address without a symbol says only which library: name its nearest named caller
            if names and names[-1].startswith("["):
                own[f"{names[-1]} in {named[-1] if named else '?'}"] += count
            elif names:
                own[names[-1]] += count
            else:
                own["(no frame)"] += count
            for name in set(named):  # bare addresses (e.g. every thread's libc root) say nothing
                total[name] += count
        return cls(threads, own, total, samples, idle, waits, idle_threads)


# -- the summary ----------------------------------------------------------------------------------
@dataclass
class Side:
    """One bridge's part of a profile run."""

    name: str                     # "A" or "B"
    role: str                     # e.g. "bridge A (transmit: DDS -> link)"
    recording: Recording
    cpu_us: float | None          # CPU µs/msg (utime+stime) over the profiled trial
    cpu_us_quiet: float | None    # ... and over the unprofiled CPU trial, for comparison
    threads_cpu: dict[int, tuple[str, float, float]]  # tid -> (name, user s, system s), unprofiled
    quiet_messages: int           # messages of the unprofiled trial


def summary(side: Side, title: str, messages: int, roots: list[Path], latency: str = "-",
            latency_quiet: str = "-") -> str:
    rec = side.recording
    profile = Profile.of(read_stacks(rec.raw), roots)
    rate = RATE

    def us(samples: int) -> str:  # busy time per message that these samples stand for
        return f"{samples / rate / messages * 1e6:8.1f}" if messages and rate else "       -"

    def pct(samples: int) -> str:
        return f"{samples / profile.samples:6.1%}" if profile.samples else "     -"

    lines = [
        f"# {title}: {side.role}",
        "",
        f"py-spy record --rate {RATE} --threads --function{' --native' if rec.native else ''} "
        f"for {rec.seconds:.1f} s (this bridge only): {profile.samples:,} busy thread-samples, "
        f"{profile.idle:,} idle ones left out (innermost named frame a wait: poll, a lock, a "
        f"condition), errors: {rec.errors:,}"
        + (f", fell up to {rec.behind:.1f} s behind (µs/msg below are low)" if rec.behind > 0.5
           else "") + f"; {messages:,} messages delivered meanwhile.",
        f"CPU (utime+stime, /proc) per message: {fmt(side.cpu_us)} µs while profiled, "
        f"{fmt(side.cpu_us_quiet)} µs in the unprofiled CPU trial (py-spy stops the process "
        f"{RATE} times a second: read shares, not totals).",
        f"Latency meanwhile: {latency} (unprofiled CPU trial: {latency_quiet}).",
        "'µs/msg' below: busy samples / sampling rate / messages, i.e. busy thread time per "
        "message that the function stands for.",
        "",
        "## CPU per thread (unprofiled CPU trial, /proc/<pid>/task/*/stat)",
        "",
        "  tid      name             CPU ms  system   µs/msg   py-spy thread",
    ]
    names = {tid: name for tid, name in profile.threads}
    names.update({tid: name for tid, name in profile.idle_threads})
    cpu = {tid: (comm, user + system, system)
           for tid, (comm, user, system) in side.threads_cpu.items()}
    for tid, (comm, seconds, system) in sorted(cpu.items(), key=lambda kv: -kv[1][1]):
        if seconds <= 0:
            continue
        per = (f"{seconds / side.quiet_messages * 1e6:8.1f}" if side.quiet_messages
               else "       -")
        lines.append(f"  {tid:<8} {comm:<15} {seconds * 1000:7.0f} {system / seconds:7.0%} {per}"
                     f"   {names.get(tid, '-')}")
    idle = sum(1 for _, seconds, _ in cpu.values() if seconds <= 0)
    if idle:
        lines.append(f"  ({idle} more threads used no measurable CPU)")
    lines += ["", "## busy samples per Python thread (profiled trial)", "",
              "  samples   share    µs/msg  thread"]
    for (tid, name), n in profile.threads.most_common():
        lines.append(f"  {n:7,} {pct(n)} {us(n)}  {name or '?'} ({tid})")
    for heading, counter in (("own time (the function on top of the stack)", profile.own),
                             ("total time (the function anywhere on the stack)", profile.total)):
        lines += ["", f"## top {TOP} by {heading}", "", "  samples   share    µs/msg  function"]
        for name, n in counter.most_common(TOP):
            lines.append(f"  {n:7,} {pct(n)} {us(n)}  {name}")
    lines += ["", "## where the threads waited (idle samples, left out above)", "",
              "  samples  wait in (the innermost Python frame)"]
    for name, n in profile.waits.most_common(8):
        lines.append(f"  {n:7,}  {name}")
    return "\n".join(lines) + "\n"


def fmt(value: float | None) -> str:
    return "-" if value is None else f"{value:.1f}"


def top_lines(text: str, heading: str, n: int) -> list[str]:
    """The first ``n`` rows of one section of a summary (for the README)."""
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("## ") and heading in line)
    return lines[start + 2:start + 3 + n]
