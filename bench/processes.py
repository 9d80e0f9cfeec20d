"""The processes of one benchmark case, and the files they need.

A case is a publisher, a subscriber and, when bridged, two ``rosgate run`` processes, each a
process of its own so the bridge pays for its own CPU, as it would in use:

    bare:     pub --DDS--> sub                                   (one domain)
    bridged:  pub --DDS--> bridge A ==link==> bridge B --DDS--> sub
              (pub and A in one domain, B and sub in another: the bridge is the only way across)

DDS stays on loopback (``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``) and uses domains 150..169,
away from the tests' 20..119, so a bench run and a test run do not hear each other.
``ROSGATE_BENCH_DOMAINS=FIRST-LAST`` gives a run other domains, so two benchmarks on one machine
do not hear each other either (a subscriber that counts another run's messages reports more
delivered than offered).
"""

from __future__ import annotations

import itertools
import json
import os
import queue
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any, NoReturn

ROOT = Path(__file__).resolve().parent.parent
ENDPOINTS = Path(__file__).resolve().with_name("endpoints.py")
FLOOR = Path(__file__).resolve().with_name("floor.py")
ENDS = Path(__file__).resolve().with_name("constrained_ends.py")
ROSGATE = str(Path(sys.executable).with_name("rosgate"))
CLOCK_TICK = os.sysconf("SC_CLK_TCK")  # /proc/<pid>/stat counts CPU time in these per second
START_TIMEOUT = 30.0
READY_LINE = "running as"

_FIRST, _LAST = (int(n) for n in os.environ.get("ROSGATE_BENCH_DOMAINS", "150-169").split("-"))
_domain_pairs = itertools.cycle(range(_FIRST, _LAST, 2))


def next_domains() -> tuple[int, int]:
    """A fresh pair of DDS domains: (publisher side, subscriber side)."""
    first = next(_domain_pairs)
    return first, first + 1


def free_port() -> int:
    """A port free for both TCP and UDP on 127.0.0.1."""
    while True:
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as tcp:
            tcp.bind(("127.0.0.1", 0))
            port = tcp.getsockname()[1]
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
                try:
                    udp.bind(("127.0.0.1", port))
                except OSError:
                    continue
            return port


@dataclass(frozen=True)
class Checkout:
    """Whose ``rosgate`` a bridge runs: this checkout's (rev "") or another revision's, checked
    out in a worktree of its own with its own .venv (see bench.py --base)."""

    rev: str = ""          # short commit, "" for this checkout
    root: Path = ROOT

    @property
    def rosgate(self) -> str:
        return ROSGATE if not self.rev else str(self.root / ".venv" / "bin" / "rosgate")


HERE_CHECKOUT = Checkout()


def cpu_seconds(pid: int) -> float:
    """CPU time (user + system) a process has used so far, all its threads together
    (/proc/<pid>/stat fields 14 and 15, in clock ticks)."""
    with open(f"/proc/{pid}/stat") as stat:
        fields = stat.read().rsplit(")", 1)[1].split()  # the name (field 2) may hold spaces
    return (int(fields[11]) + int(fields[12])) / CLOCK_TICK


def thread_cpu_seconds(pid: int) -> dict[int, tuple[str, float, float]]:
    """CPU time per thread of a process: thread id -> (its name, user seconds, system seconds).
    Threads that ended meanwhile are missing; Python's own threads are all named after the
    program (Python 3.11 does not name them), DDS's are named by Fast DDS."""
    threads = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            stat = (task / "stat").read_text()
        except OSError:
            continue
        name = stat[stat.index("(") + 1:stat.rindex(")")]
        fields = stat.rsplit(")", 1)[1].split()
        threads[int(task.name)] = (name, int(fields[11]) / CLOCK_TICK, int(fields[12]) / CLOCK_TICK)
    return threads


def ros_env(domain: int, root: Path = ROOT) -> dict[str, str]:
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               PYTHONUNBUFFERED="1")
    # The bridges run the workspace's code as checked out: its source folders go first, so an
    # editable install made before a plugin's sources existed (no .pth for it) does not hide it.
    # Entry points still come from the installed distributions.
    sources = [root / "core" / "src", *sorted(root.glob("plugins/*/src")),
               *sorted(root.glob("libs/*/src"))]
    env["PYTHONPATH"] = os.pathsep.join([*map(str, sources), env.get("PYTHONPATH", "")]).rstrip(
        os.pathsep)
    # counters are logged when a bridge stops; no periodic lines in the middle of a trial
    env["ROSGATE_STATS_EVERY"] = "3600"
    return env


class Lines:
    """Lines a process writes, read by a thread so that waiting for one can time out."""

    def __init__(self, stream: IO[str], name: str):
        self.name = name
        self.queue: queue.Queue[str | None] = queue.Queue()
        self.seen: list[str] = []
        self.ended = threading.Event()
        threading.Thread(target=self._read, args=(stream,), daemon=True).start()

    def _read(self, stream: IO[str]) -> None:
        for line in stream:
            self.seen.append(line.rstrip("\n"))
            self.queue.put(self.seen[-1])
        self.queue.put(None)
        self.ended.set()

    def next(self, timeout: float) -> str:
        try:
            line = self.queue.get(timeout=timeout)
        except queue.Empty:
            raise RuntimeError(f"{self.name}: no answer within {timeout:.0f} s") from None
        if line is None:
            raise RuntimeError(f"{self.name}: exited")
        return line

    def wait_for(self, text: str, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while text not in self.next(max(0.01, deadline - time.monotonic())):
            pass


class Process:
    """A child process stopped with SIGINT (then SIGKILL) when the case ends."""

    proc: subprocess.Popen

    @property
    def pid(self) -> int:
        return self.proc.pid

    def cpu(self) -> float:
        """CPU seconds it has used so far."""
        return cpu_seconds(self.proc.pid)

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


class Relay(Process):
    """``python -m rosgate_emulator udp|tcp``: a relay from ``listen`` to ``target`` on
    127.0.0.1 that loses ``loss`` of the datagrams each way (one datagram one packet: an MTU of
    65,535), nothing else."""

    def __init__(self, kind: str, listen: int, target: int, loss: float = 0.0):
        self.name = f"{kind} relay"
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "rosgate_emulator", kind, "--listen", f"127.0.0.1:{listen}",
             "--target", f"127.0.0.1:{target}", "--loss", str(loss), "--mtu", "65535",
             "--seed", "1"],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
            env=dict(os.environ, PYTHONPATH=str(ROOT / "tools" / "emulator" / "src")))
        self.lines = Lines(self.proc.stdout, self.name)

    def ready(self) -> None:
        self.lines.wait_for("->", START_TIMEOUT)


class Endpoint(Process):
    """The publisher or the subscriber (bench/endpoints.py), driven over stdin/stdout."""

    def __init__(self, role: str, kind: str, size: int, depth: int, domain: int, log: Path,
                 reliability: str = "reliable", prefix: tuple[str, ...] = (),
                 env: dict[str, str] | None = None):
        self.start(role, [str(ENDPOINTS), role, kind, str(size), str(depth), reliability],
                   domain, log, prefix, env)

    def start(self, name: str, argv: list[str], domain: int, log: Path,
              prefix: tuple[str, ...] = (), env: dict[str, str] | None = None) -> None:
        """``prefix``: what the command runs under (``ip netns exec NAME``); ``env``: more
        environment (a Fast DDS profile)."""
        self.name = name
        self.log = log.open("w")
        self.proc = subprocess.Popen(
            [*prefix, sys.executable, *argv], env={**ros_env(domain), **(env or {})},
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE, stderr=self.log, text=True, bufsize=1)
        self.lines = Lines(self.proc.stdout, name)

    def ready(self) -> None:
        self.lines.wait_for('"ready"', START_TIMEOUT)

    def ask(self, command: str, timeout: float = 10.0) -> dict[str, Any]:
        self.send(command)
        return self.reply(timeout)

    def send(self, command: str) -> None:
        """A command whose answer :meth:`reply` reads later (two ends working at once)."""
        assert self.proc.stdin is not None
        try:
            self.proc.stdin.write(command + "\n")
            self.proc.stdin.flush()
        except OSError as exc:
            self._failed(exc)

    def reply(self, timeout: float = 10.0) -> dict[str, Any]:
        try:
            return json.loads(self.lines.next(timeout))
        except RuntimeError as exc:
            self._failed(exc)

    def _failed(self, exc: Exception) -> NoReturn:
        self.log.flush()
        tail = Path(self.log.name).read_text().strip().splitlines()[-5:]
        raise RuntimeError(f"{self.name}: {exc}; its log ends:\n" + "\n".join(tail)) from None

    def stop(self) -> None:
        try:
            self.proc.stdin.write("quit\n")  # type: ignore[union-attr]
            self.proc.stdin.close()  # type: ignore[union-attr]
            self.proc.wait(5)
        except (OSError, subprocess.TimeoutExpired):
            pass
        super().stop()
        self.log.close()


class StampedEnds(Endpoint):
    """The publisher or the subscriber of bench/constrained_ends.py: several topics at their own
    rates (a Twist beside the measured topic), every arrival with its send stamp."""

    def __init__(self, role: str, spec: list[dict], domain: int, log: Path,
                 prefix: tuple[str, ...] = ()):
        self.start(log.stem, [str(ENDS), role, json.dumps(spec)], domain, log, prefix)

    def settle(self, topic: str, expected: int, quiet: float = 1.0, most: float = 10.0) -> None:
        """Wait until ``expected`` messages of ``topic`` have arrived in all, or none has for
        ``quiet`` seconds (at most ``most``): a late one is counted late, not lost."""
        deadline, last, since = time.monotonic() + most, -1, time.monotonic()
        while time.monotonic() < deadline:
            count = self.ask("count")[topic]
            if count >= expected:
                return
            if count != last:
                last, since = count, time.monotonic()
            elif time.monotonic() - since >= quiet:
                return
            time.sleep(0.1)

    def ages_ms(self, folder: Path, since_ns: int, topic: str) -> list[float]:
        """Receive time minus send stamp (ms) of every arrival on ``topic`` sent since
        ``since_ns``."""
        dump = folder / f"{self.name}-{since_ns}.json"
        self.ask(f"dump {dump}", timeout=30)
        arrivals = json.loads(dump.read_text()).get(topic, [])
        dump.unlink()
        return [(at - sent) / 1e6 for at, sent, _n in arrivals if sent >= since_ns]


class Bridge(Process):
    """A ``rosgate run FILE`` process; its log (stderr) is kept next to its file."""

    def __init__(self, config: Path, domain: int, checkout: Checkout = HERE_CHECKOUT,
                 prefix: tuple[str, ...] = ()):
        self.name = config.stem
        self.config = config
        # the entry script's interpreter is the process itself: its pid is the bridge's
        # (under a prefix, ip netns exec's: it execs the command, so the pid stays the same)
        self.proc = subprocess.Popen([*prefix, checkout.rosgate, "run", str(config)],
                                     env=ros_env(domain, checkout.root),
                                     stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        self.lines = Lines(self.proc.stderr, f"bridge {self.name}")

    def ready(self) -> None:
        try:
            self.lines.wait_for(READY_LINE, START_TIMEOUT)
        except RuntimeError as exc:
            raise RuntimeError(f"{exc}; its log:\n" + "\n".join(self.lines.seen)) from None

    def stop(self) -> None:
        super().stop()
        self.lines.ended.wait(5)  # the counters are the last lines it writes
        self.config.with_suffix(".log").write_text("\n".join(self.lines.seen) + "\n")

    def problems(self) -> list[str]:
        """Log lines worth a look: warnings, errors, and counters that show drops."""
        return [line for line in self.lines.seen
                if " WARNING " in line or " ERROR " in line or "Traceback" in line
                or ("drops:" in line and not line.endswith("drops: none"))]


class Floor(Bridge):
    """One side of the floor (bench/floor.py): where bridge A or B stands, no rosgate in it."""

    def __init__(self, side: str, route: Route, msg_type: str, port: int, depth: int,
                 reliability: str, folder: Path, domain: int):
        self.name = f"floor_{side}"
        self.config = folder / f"{self.name}.yaml"  # not written: its log goes beside it
        self.proc = subprocess.Popen(
            [sys.executable, str(FLOOR), side, route.transport, msg_type, str(port), str(depth),
             reliability],
            env=ros_env(domain), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        self.lines = Lines(self.proc.stderr, self.name)


# -- bringup.yaml ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class Route:
    """How a bridged case crosses: link, codec, cipher, and which pair of roles."""

    transport: str
    codec: str = "cdr"
    cipher: str = "none"
    # "peer" (A transmit, B receive); "client/server" (A client, B server, insecure: true, no
    # handshake); "session" (the same, authenticated: identities, the session's keys); "floor":
    # no rosgate, bench/floor.py's two processes (the least a Python bridge on rclpy does)
    roles: str = "peer"
    rev: str = ""        # whose rosgate: "" this checkout's, else a short commit (--base)
    #: udp's max_frame in the files; None: none, as a user's file (udp takes it from the path)
    max_frame: int | None = 65_000
    #: the topic's QoS in both files, the publisher's and the subscriber's
    reliability: str = "reliable"
    #: the topic's batch window as the file writes it ("2ms"); "": none
    batch: str = ""
    #: the share of UDP datagrams lost each way between A and B (a relay in front of B's port;
    #: the main line's TCP crosses it untouched); 0: none, no relay
    loss: float = 0.0

    @property
    def default_file(self) -> bool:
        """The file a user writes: a session with its keys and nothing else set."""
        return self.roles == "session" and self.max_frame is None

    @property
    def path(self) -> str:
        """The label without the revision: what --path and --profile-path match."""
        name = f"{self.transport}/{self.codec}/{self.cipher}"
        if self.default_file:
            qos = "best effort" if self.reliability == "best_effort" else "reliable"
            return (f"default file, {qos}" + (f", batch {self.batch}" if self.batch else "")
                    + (f", {self.loss:.0%} datagram loss" if self.loss else ""))
        if self.roles == "session":
            return f"{name} client/server authenticated"
        if self.roles == "floor":
            return f"{self.transport} floor (no rosgate)"
        return name if self.roles == "peer" else f"{name} client/server"

    @property
    def label(self) -> str:
        return f"{self.path} @{self.rev}" if self.rev else self.path


def session_keys(folder: Path, topics: tuple[str, ...] = ("/bench",)) -> tuple[str, str]:
    """Identities for an authenticated client/server pair, made once in ``folder``: what each
    file's bridge: mapping adds, and the server's clients: with a policy for ``topics``."""
    public = {}
    for name in ("bench_a", "bench_b"):
        key = folder / f"{name}.key"
        if not key.exists():
            subprocess.run([ROSGATE, "keygen", "identity", "--out", str(key)], check=True,
                           capture_output=True)
        public[name] = subprocess.run([ROSGATE, "pubkey", str(key)], check=True,
                                      capture_output=True, text=True).stdout.strip()
    client = f", identity: {folder / 'bench_a.key'}, server_key: {public['bench_b']}"
    allowed = ", ".join(f"{{name: {name}, direction: transmit}}" for name in topics)
    server = (f", identity: {folder / 'bench_b.key'}}}\nclients: {{bench_a: {{key: "
              f"{public['bench_a']}, topics: [{allowed}]}}")
    return client, server


def knows_max_frame(root: Path) -> bool:
    """Whether a checkout's udp plugin takes the max_frame option (real links: its default is a
    safe size for real networks, 1,200 bytes)."""
    module = root / "plugins" / "transport_udp" / "src" / "rosgate_transport_udp" / "__init__.py"
    return "max_frame: int" in module.read_text()


def refuses_open_links(root: Path) -> bool:
    """Whether a checkout refuses a peer (or any entry anyone could write to) unless the file
    says insecure: true; an older one knows no insecure: for peers and refuses the key."""
    return "open_doors" in (root / "core" / "src" / "rosgate" / "engine.py").read_text()


def knows_insecure(root: Path) -> bool:
    """Whether a checkout's client and server take insecure: (from sessions on)."""
    return any("insecure" in path.read_text()
               for path in (root / "core" / "src" / "rosgate").rglob("*.py"))


#: the Twist beside a measured topic (client/server files only): a teleoperation command at
#: 20 Hz in the link's first class, reliable as a teleop node's publisher is
TWIST_TOPIC = "/bench_twist"
TWIST = (f"{{topic: {TWIST_TOPIC}, type: geometry_msgs/msg/Twist, "
         "qos: {reliability: reliable, depth: 10}, priority: real_time, direction: transmit}")


def bringup_files(route: Route, msg_type: str, depth: int, folder: Path,
                  reliability: str = "reliable", root: Path = ROOT, port: int | None = None,
                  dial: int | None = None, twist: bool = False,
                  host: tuple[str, str] = ("127.0.0.1", "127.0.0.1")) -> tuple[Path, Path]:
    """Write bridge A's and bridge B's bringup.yaml; return their paths.

    A route's ``max_frame`` is written into both files (65,000 bytes: loopback's datagrams, the
    bridge's cost per message without fragments); the default file's route has none, as a
    user's file: udp then takes it from the path (an older rosgate: 1,200 bytes). ``port``:
    B's (default: a free one); ``dial``: the port a client dials instead (a relay's). ``twist``:
    the client's file carries :data:`TWIST` as well. ``host``: where the client dials and where
    the server listens (two network namespaces: the far end's address, and the server's own).
    """
    port = port or free_port()
    options = {}
    if route.cipher == "fernet":
        key = folder / "fernet.key"
        if not key.exists():
            subprocess.run([ROSGATE, "keygen", "fernet", "--out", str(key)], check=True,
                           capture_output=True)
        options["fernet"] = f"{{key_file: {key}}}"
    if route.transport == "udp" and route.max_frame and knows_max_frame(root):
        options["udp"] = f"{{max_frame: {route.max_frame}}}"
    plugins = ("plugins: {" + ", ".join(f"{k}: {v}" for k, v in options.items()) + "}\n"
               if options else "")
    # the default file names no link, codec or cipher: udp, cdr, and the session's aead are
    # what a file gets without them (its QoS is the measurement's: deep queues, see README)
    link = ("" if route.default_file else
            f"transport: {route.transport}, codec: {route.codec}, cipher: {route.cipher}, ")
    topic = (f"{{topic: /bench, type: {msg_type}, {link}"
             f"qos: {{reliability: {reliability}, history: keep_last, depth: {depth}}}"
             + (f", batch: {route.batch}" if route.batch else ""))
    if route.roles == "peer":
        # a peer without identities runs open only when its file says so (a revision from
        # before that rule knows no insecure: for peers)
        open_ = ", insecure: true" if refuses_open_links(root) else ""
        a = (f"bridge: {{name: bench_a, role: peer, peer: 127.0.0.1, listen: 127.0.0.1{open_}}}\n"
             f"{plugins}topics:\n  - {topic}, direction: transmit, port: {port}}}\n")
        b = (f"bridge: {{name: bench_b, role: peer, peer: 127.0.0.1, listen: 127.0.0.1{open_}}}\n"
             f"{plugins}topics:\n  - {topic}, direction: receive, port: {port}}}\n")
    else:
        # the client's file holds the topic list; its datagram topic uses the server's port
        names = ("/bench", TWIST_TOPIC) if twist else ("/bench",)
        a_keys, b_keys = session_keys(folder, names) if route.roles == "session" else (
            # a revision from before sessions knows no insecure: (and needs none)
            (", insecure: true",) * 2 if knows_insecure(root) else ("", ""))
        extra = f"  - {TWIST}\n" if twist else ""
        a = (f"bridge: {{name: bench_a, role: client, server: {host[0]}:{dial or port}{a_keys}}}\n"
             f"{plugins}topics:\n  - {topic}, direction: transmit}}\n{extra}")
        b = (f"bridge: {{name: bench_b, role: server, server: {host[1]}:{port}{b_keys}}}\n"
             f"{plugins}")
    paths = folder / "bench_a.yaml", folder / "bench_b.yaml"
    for path, text in zip(paths, (a, b), strict=True):
        path.write_text(text)
    return paths
