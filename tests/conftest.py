"""Shared test harness: fresh ROS domains, free ports, bridge processes, ROS sides.

Every test gets DDS domains of its own and keeps DDS on loopback, so tests never hear each
other. Waiting is always on an event with a timeout, never a fixed sleep.
"""

from __future__ import annotations

import itertools
import logging
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
from action_sides import ActionSide
from rosgate_testing import free_port  # tests also import it from here
from workers import alone_first, domain_ports, take_turns, worker_share

from rosgate import identity
from rosgate.config import loads
from rosgate.engine import Engine

os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"

ROSGATE = str(Path(sys.executable).with_name("rosgate"))
# ROSGATE_TEST_DOMAINS=FIRST-LAST gives a test run its own DDS domains, so two runs on one
# machine never hear each other (default 20-119; the benchmark uses 150 and up)
_FIRST, _LAST = (int(n) for n in os.environ.get("ROSGATE_TEST_DOMAINS", "20-119").split("-"))
if "PYTEST_XDIST_WORKER" in os.environ:  # one of make test's workers
    _FIRST, _LAST = worker_share(_FIRST, _LAST, os.environ["PYTEST_XDIST_WORKER"],
                                 int(os.environ["PYTEST_XDIST_WORKER_COUNT"]))
    # pytest-xdist sets COLUMNS=80 and LINES=24 in its workers: a program started in a
    # pseudo-terminal of another size (rosgate top's test) would believe them over the terminal
    os.environ.pop("COLUMNS", None)
    os.environ.pop("LINES", None)
# free_port (rosgate_testing) hands out these, for every test of this process and the scripts
# it starts (tests/soak)
os.environ["ROSGATE_TEST_PORTS"] = "{}-{}".format(*domain_ports(_FIRST, _LAST))
# and their status sockets in a folder of this process's own: bridges of two workers (or two runs)
# are often both named "a" or "b"
os.environ.setdefault("ROSGATE_RUNTIME_DIR", tempfile.mkdtemp(prefix="rosgate-test-run-"))
# and what servers keep across restarts (their recent clients), never in the user's own folder
os.environ.setdefault("ROSGATE_STATE_DIR", tempfile.mkdtemp(prefix="rosgate-test-state-"))
_domains = itertools.count()


def next_domain() -> int:
    return _FIRST + next(_domains) % (_LAST - _FIRST + 1)


def pytest_configure(config: pytest.Config) -> None:
    take_turns(config)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    alone_first(items)


@pytest.fixture
def domain() -> Callable[[], int]:
    """Call it for each fresh DDS domain a test needs."""
    return next_domain


def wait_until(predicate: Callable[[], bool], timeout: float = 10.0) -> bool:
    """Poll a counter the engine updates from its own threads (no event to wait on)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.02)
    return predicate()


ALLOW_ALL = [{"name": "/**", "direction": "both", "ports": ["1-65535"],
              "ciphers": ["none", "aead", "nacl", "fernet"]}]


class Auth:
    """Identities for the bridges of the test run, made in a folder of their own: every client
    and server file runs authenticated unless it says ``insecure: true`` or names its own
    ``identity``. Servers list the clients below with a policy that allows everything (the
    policy tests write their own). A peer file without identities is run as it is written,
    open, with ``insecure: true`` added (the tests of what peers carry; the tests of
    authenticated peers name their identities)."""

    CLIENTS = ("robot1", "robot2", "robot3", "bench_a")

    def __init__(self) -> None:
        import atexit
        import shutil
        import tempfile

        self.folder = Path(tempfile.mkdtemp(prefix="rosgate-keys-"))
        atexit.register(shutil.rmtree, self.folder, True)
        self.public: dict[str, str] = {}
        for name in ("server", *self.CLIENTS):
            self.identity(name)

    def identity(self, name: str) -> Path:
        """``name``'s private key file (made on first use); its public key in ``public``."""
        path = self.folder / f"{name}.key"
        if not path.exists():
            key = identity.generate()
            identity.write_private(path, key)
            self.public[name] = identity.encode(identity.public_of(key))
        return path

    def secure(self, text: str) -> str:
        data = yaml.safe_load(text)
        bridge = data.get("bridge") if isinstance(data, dict) else None
        if (not isinstance(bridge, dict) or bridge.get("role") not in ("client", "server", "peer")
                or "insecure" in bridge or "identity" in bridge):
            return text
        if bridge["role"] == "peer":
            bridge["insecure"] = True
        elif bridge["role"] == "server":
            bridge["identity"] = str(self.identity("server"))
            data["clients"] = {name: {"key": self.public[name], "topics": ALLOW_ALL,
                                      "services": ALLOW_ALL, "actions": ALLOW_ALL}
                               for name in self.CLIENTS}
        else:
            bridge["identity"] = str(self.identity(bridge["name"]))
            bridge["server_key"] = self.public["server"]
        return yaml.safe_dump(data, sort_keys=False)


AUTH = Auth()


class Inbox:
    """Collects what a subscription receives; wait for a count or a predicate."""

    def __init__(self) -> None:
        self.items: list[Any] = []
        self._cond = threading.Condition()

    def put(self, item: Any) -> None:
        with self._cond:
            self.items.append(item)
            self._cond.notify_all()

    def wait_for(self, predicate: Callable[[list[Any]], bool], timeout: float) -> bool:
        with self._cond:
            return self._cond.wait_for(lambda: predicate(self.items), timeout)

    def wait_count(self, n: int, timeout: float) -> bool:
        return self.wait_for(lambda items: len(items) >= n, timeout)


class RosSide:
    """A plain ROS node in one domain: the talker or the listener of a test."""

    def __init__(self, domain_id: int, name: str):
        from rosgate.ros import RosNode

        self.ros = RosNode(name, domain_id)
        self.domain_id = domain_id

    def listen(self, topic: str, msg_type: type, qos: Any = 100) -> Inbox:
        inbox = Inbox()
        self.ros.subscribe(msg_type, topic, qos, inbox.put, raw=False)
        return inbox

    def publisher(self, topic: str, msg_type: type, qos: Any = 100) -> Any:
        return self.ros.publisher(msg_type, topic, qos)

    def close(self) -> None:
        self.ros.close()


@pytest.fixture(autouse=True)
def _runtime_dir(tmp_path_factory, monkeypatch):
    """Each test's bridges keep their status sockets in a folder of the test's own: a bridge of
    the test before (still stopping) may bear the same name; and their state: a server of the
    test before must not have made this test's clients known."""
    monkeypatch.setenv("ROSGATE_RUNTIME_DIR", str(tmp_path_factory.mktemp("run")))
    monkeypatch.setenv("ROSGATE_STATE_DIR", str(tmp_path_factory.mktemp("state")))


def sides_of(kind: Callable[[int, str], Any]) -> Iterator[Callable[..., Any]]:
    """A fixture's maker of ROS sides of ``kind``, each closed when the test ends."""
    sides: list[Any] = []

    def make(domain_id: int, name: str = "side") -> Any:
        side = kind(domain_id, f"{name}_{domain_id}")
        sides.append(side)
        return side

    yield make
    for side in sides:
        side.close()


@pytest.fixture
def ros_side():
    yield from sides_of(RosSide)


@pytest.fixture
def action_side():
    """Sides with rclpy's own action servers and clients (tests/test_actions.py)."""
    yield from sides_of(ActionSide)


def warm_up(publisher: Any, inbox: Inbox, message: Any, timeout: float = 30.0,
            every: float = 0.2) -> int:
    """Publish ``message`` until one arrives in ``inbox`` (the session is up and DDS has matched
    both ends); how many were published."""
    deadline, sent = time.monotonic() + timeout, 0
    while not inbox.wait_count(1, every):
        assert time.monotonic() < deadline, "nothing crossed the bridge"
        publisher.publish(message)
        sent += 1
    return sent


def cross(publisher: Any, inbox: Inbox, make: Callable[[int | None], Any],
          is_warmup: Callable[[Any], bool], count: int, timeout: float = 20.0,
          interval: float = 0.005) -> list[Any]:
    """Publish warm-up messages (``make(None)``) until one crosses — discovery and handshakes
    take a moment — then ``count`` numbered ones (``make(0)``...); return the numbered messages
    that arrived, in arrival order, once all came or ``timeout`` passed."""
    deadline = time.monotonic() + timeout
    start = len(inbox.items)
    while not inbox.wait_count(start + 1, 0.2):
        assert time.monotonic() < deadline, "nothing crossed the bridge"
        publisher.publish(make(None))
    for n in range(count):
        publisher.publish(make(n))
        time.sleep(interval)  # paces the publisher; nothing waits on this
    numbered = lambda items: [m for m in items[start:] if not is_warmup(m)]
    inbox.wait_for(lambda items: len(numbered(items)) >= count,
                   max(1.0, deadline - time.monotonic()))
    return numbered(list(inbox.items))


def settle(inbox: Inbox, quiet: float = 0.5, timeout: float = 10.0) -> None:
    """Wait until nothing new has arrived for ``quiet`` seconds (what was in flight is in)."""
    deadline = time.monotonic() + timeout
    seen = -1
    while time.monotonic() < deadline and seen != len(inbox.items):
        seen = len(inbox.items)
        inbox.wait_count(seen + 1, quiet)


class Bridge:
    """A ``rosgate run`` process."""

    def __init__(self, config: Path, domain_id: int, ready: str = "running as",
                 env: dict[str, str] | None = None, rosgate: str = ROSGATE,
                 prefix: list[str] | None = None):
        env = dict(os.environ if env is None else env, ROS_DOMAIN_ID=str(domain_id),
                   PYTHONUNBUFFERED="1")
        config.write_text(AUTH.secure(config.read_text()))
        self.config = config
        self.lines: list[str] = []
        self._cond = threading.Condition()
        self._interrupted = False
        # prefix: what runs it, e.g. ``ip netns exec NAME`` (which execs it: the same process)
        self.proc = subprocess.Popen([*(prefix or []), rosgate, "run", str(config)], env=env,
                                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()
        if not self.wait_log(ready, 60):  # imports alone take seconds of CPU, shared with others
            self.stop()
            raise AssertionError(f"bridge {config.name} did not start:\n{self.log}")

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            with self._cond:
                self.lines.append(line.rstrip("\n"))
                self._cond.notify_all()

    @property
    def log(self) -> str:
        with self._cond:
            return "\n".join(self.lines)

    def wait_log(self, text: str, timeout: float) -> bool:
        with self._cond:
            return self._cond.wait_for(lambda: any(text in line for line in self.lines)
                                       or self.proc.poll() is not None and text not in self.log,
                                       timeout) and any(text in line for line in self.lines)

    def interrupt(self) -> None:
        """Ask it to stop (SIGINT, once) without waiting: ``stop`` waits for it."""
        if not self._interrupted and self.proc.poll() is None:
            self._interrupted = True
            self.proc.send_signal(signal.SIGINT)

    def stop(self) -> int:
        if self.proc.poll() is None:
            self.interrupt()
            try:
                self.proc.wait(15)
            except subprocess.TimeoutExpired:
                # it did not stop: its threads' stacks into its log (rosgate run's SIGUSR1), so
                # the failure says where it hangs
                self.proc.send_signal(signal.SIGUSR1)
                self.wait_log("(most recent call first)", 5)
                self.proc.kill()
                self.proc.wait()
        self._reader.join(5)
        return self.proc.returncode


@pytest.fixture
def engines():
    started: list[Engine] = []

    """Start engines in this process, each with its own rclpy context and DDS domain."""

    def start(text: str, domain_id: int, base_dir: Path | None = None) -> Engine:
        engine = Engine(loads(AUTH.secure(text), file="test.yaml", base_dir=base_dir),
                        domain_id=domain_id)
        started.append(engine.prepare().start())
        return engine

    yield start
    for engine in started:
        engine.stop()


class LogRecorder(logging.Handler):
    """Collects what the rosgate logger says; a test waits for a line to appear."""

    def __init__(self) -> None:
        super().__init__()
        self.messages: list[str] = []
        self.records: list[logging.LogRecord] = []
        self.cond = threading.Condition()

    def emit(self, record: logging.LogRecord) -> None:
        with self.cond:
            self.messages.append(record.getMessage())
            self.records.append(record)
            self.cond.notify_all()

    def having(self, part: str) -> list[str]:
        with self.cond:
            return [m for m in self.messages if part in m]

    def wait(self, part: str, count: int = 1, timeout: float = 10.0) -> bool:
        with self.cond:
            return self.cond.wait_for(lambda: len(self.having(part)) >= count, timeout)


@pytest.fixture
def logs():
    logger = logging.getLogger("rosgate")
    recorder, level = LogRecorder(), logger.level
    logger.addHandler(recorder)
    logger.setLevel(logging.INFO)  # "up" is news, not a warning
    yield recorder
    logger.removeHandler(recorder)
    logger.setLevel(level)


@pytest.fixture
def bridge():
    started: list[Bridge] = []

    def start(config: Path, domain_id: int, **kwargs: Any) -> Bridge:
        b = Bridge(config, domain_id, **kwargs)
        started.append(b)
        return b

    yield start
    for b in started:  # all at once: their shutdowns overlap instead of adding up
        b.interrupt()
    codes = [b.stop() for b in started]  # every one, before any assertion can stop the loop
    for b, code in zip(started, codes, strict=True):
        assert "Traceback" not in b.log, b.log
        assert code == 0, f"bridge {b.config.name} exited {code}:\n{b.log}"


class StreamKind:
    """A stream transport as bringup.yaml spells it: tcp on 127.0.0.1, or bt over the bt
    plugin's AF_UNIX stand-in for a radio (channels for ports, a device address for a host)."""

    def __init__(self, name: str, directory: str):
        self.name = name
        self.host = "127.0.0.1" if name == "tcp" else "AA:BB:CC:DD:EE:01"
        self.options = "{}" if name == "tcp" else f"{{emulate_dir: {directory}}}"
        self.plugins = f"{{{name}: {self.options}}}"  # a whole plugins: section
        self._channels = itertools.count(1)

    def port(self) -> int:
        return free_port() if self.name == "tcp" else next(self._channels)

    def address(self, port: int) -> str:
        return f"{self.host}:{port}" if self.name == "tcp" else f"{self.host}/{port}"


@pytest.fixture(params=["tcp", "bt"])
def stream_kind(request):
    """Each stream-link test runs over tcp and over bt."""
    import tempfile

    with tempfile.TemporaryDirectory(prefix="bt", dir="/tmp") as directory:  # AF_UNIX: short paths
        yield StreamKind(request.param, directory)
