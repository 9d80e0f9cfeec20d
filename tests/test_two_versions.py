"""Two robots on two versions of one custom message: ``rosgate_test_versions/msg/Reading``,
generated and compiled here by ROS's own generators (tests/generated.py), v1 ``float64 value``
and v2 ``float64 value`` + ``string unit``, each in a prefix of its own. Every bridge, talker and
listener is a process whose PYTHONPATH, LD_LIBRARY_PATH and AMENT_PREFIX_PATH hold one version.

The type check refuses the entry on every role (a peer link, client/server, a zenoh bus through
a real ``rosgate router``): the hashes differ as the type supports give them, nothing is
published, every frame is counted ``type_mismatch``, and the refusing bridge says so in one
sentence naming both hashes. One version on both sides crosses exact (the control)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import generated
import pytest
from conftest import free_port, wait_until
from rosgate_top.client import StatusClient
from test_zenoh_fleet import Router, zenoh_plugin
from test_zenoh_type_check import router  # noqa: F401  (the zenoh role's router, a fixture)

from rosgate import runtime

PACKAGE = "rosgate_test_versions"
VERSIONS = {"v1": {"Reading": "float64 value\n"},
            "v2": {"Reading": "float64 value\nstring unit\n"}}
TYPE = f"{PACKAGE}/msg/Reading"

# a talker or a listener of /reading, in whichever version its environment holds
NODE = """
import sys, time, rclpy
from rclpy.qos import QoSProfile
from rosgate_test_versions.msg import Reading
from rosgate.rostypes import type_hash

role = sys.argv[1]
if role == "hash":
    print(type_hash(Reading), flush=True)
    raise SystemExit
rclpy.init()
node = rclpy.create_node("versions_" + role)
has_unit = "unit" in Reading.get_fields_and_field_types()
if role == "listen":
    def got(m):
        print("got", repr(m.value), repr(m.unit) if has_unit else "-", flush=True)
    keep = node.create_subscription(Reading, "/reading", got, QoSProfile(depth=100))
    print("ready", flush=True)
    rclpy.spin(node)
else:
    publisher = node.create_publisher(Reading, "/reading", QoSProfile(depth=100))
    print("ready", flush=True)
    for i in range(1, 100000):
        message = Reading(value=i + 0.25)
        if has_unit:
            message.unit = "°C ✓"
        publisher.publish(message)
        print("published", i, flush=True)
        time.sleep(0.05)  # a sensor at 20 Hz
"""


@pytest.fixture(scope="session")
def versions() -> dict[str, Path]:
    """Each version's prefix, built once and kept between runs (under the temporary folder,
    keyed by the definitions): about ten seconds each the first time."""
    base = Path(tempfile.gettempdir()) / f"rosgate-generated-{os.getuid()}"
    return {version: generated.build(base / f"{version}-{generated.digest(messages)}", PACKAGE,
                                     messages)
            for version, messages in VERSIONS.items()}


@pytest.fixture
def status_dir(monkeypatch) -> Iterator[Path]:
    """The bridges' status sockets, in a folder of the test's own (AF_UNIX: a short path)."""
    with tempfile.TemporaryDirectory(prefix="rg", dir="/tmp") as folder:
        path = Path(folder) / "run"
        monkeypatch.setenv(runtime.RUNTIME_VARIABLE, str(path))
        yield path


class Node:
    """A talker or a listener process in one version's environment; its lines as they come."""

    def __init__(self, prefix: Path, domain_id: int, role: str):
        env = generated.environment(prefix)
        env["ROS_DOMAIN_ID"] = str(domain_id)
        self.proc = subprocess.Popen([sys.executable, "-c", NODE, role], env=env, text=True,
                                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
        self.lines: list[str] = []
        self._cond = threading.Condition()
        threading.Thread(target=self._read, daemon=True).start()

    def ready(self) -> Node:
        assert self.wait(lambda lines: "ready" in lines, 30), self.lines
        return self

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            with self._cond:
                self.lines.append(line.rstrip("\n"))
                self._cond.notify_all()

    def wait(self, predicate: Any, timeout: float) -> bool:
        with self._cond:
            return self._cond.wait_for(lambda: predicate(self.lines), timeout)

    def having(self, start: str) -> list[str]:
        with self._cond:
            return [line for line in self.lines if line.startswith(start)]

    def stop(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:  # rclpy's own SIGTERM handling, on a loaded machine
            self.proc.kill()
            self.proc.wait(10)


@pytest.fixture
def nodes() -> Iterator[Any]:
    started: list[Node] = []

    def start(prefix: Path, domain_id: int, role: str) -> Node:
        started.append(Node(prefix, domain_id, role))
        return started[-1]

    yield start
    for node in started:
        node.stop()


@pytest.fixture(scope="session")
def hashes(versions) -> dict[str, str]:
    """Each version's RIHS01 hash, as its type support gives it."""
    return {version: hash_of(prefix) for version, prefix in versions.items()}


def hash_of(prefix: Path) -> str:
    done = subprocess.run([sys.executable, "-c", NODE, "hash"], env=generated.environment(prefix),
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    return done.stdout.strip()


def described_hash(prefix: Path) -> str:
    """The hash the generator wrote into the type description it made the type support from."""
    description = json.loads((prefix / "gen" / "type_description" / "msg" / "Reading.json")
                             .read_text())
    [entry] = [h for h in description["type_hashes"] if h["type_name"] == TYPE]
    return str(entry["hash_string"])


def receiving(name: str) -> dict[str, Any]:
    """The bridge ``name``'s receiving /reading entry, from its status socket."""
    [entry] = entries(name)
    return entry


def entries(name: str) -> list[dict[str, Any]]:
    """The bridge ``name``'s receiving /reading entries: none yet on a server whose client has
    not said hello (it makes a client's entries then), else one."""
    with StatusClient(name) as client:
        status = client.status()
    return [e for e in status["entries"] if e["name"] == "/reading"
            and e["direction"] == "receive"]


def files(tmp_path: Path, role: str, port: int,
          bus_router: Router | None = None) -> tuple[tuple[str, Path], tuple[str, Path]]:
    """(name, file) of the sending bridge and of the receiving one; the zenoh role's both
    reach each other through ``bus_router``."""
    if role == "zenoh":
        assert bus_router is not None
        sides = [(name, f"bridge: {{name: {name}, role: peer, defaults: {{transport: zenoh}}}}\n"
                        f"{zenoh_plugin(bus_router)}topics: [{{topic: /reading, type: {TYPE}, "
                        f"direction: {direction}, remote: fleet/reading}}]\n")
                 for name, direction in (("robot1", "transmit"), ("base", "receive"))]
    elif role == "peer":
        entry = f"{{topic: /reading, type: {TYPE}, port: {port}, direction: "
        sides = [(name, f"bridge: {{name: {name}, role: peer, peer: 127.0.0.1, listen: "
                        f"127.0.0.1}}\ntopics: [{entry}{direction}}}]\n")
                 for name, direction in (("a", "transmit"), ("b", "receive"))]
    else:
        entry = f"{{topic: /reading, type: {TYPE}, direction: transmit}}"
        sides = [("robot1", f"bridge: {{name: robot1, role: client, server: '127.0.0.1:{port}'}}"
                            f"\ntopics: [{entry}]\n"),
                 ("base", f"bridge: {{name: base, role: server, server: '127.0.0.1:{port}'}}\n")]
    paths = []
    for name, text in sides:
        path = tmp_path / f"{name}.yaml"
        path.write_text(text)
        paths.append((name, path))
    return paths[0], paths[1]


def start_pair(bridge, tmp_path: Path, role: str, sending: tuple[Path, int],
               receiving_side: tuple[Path, int],
               bus_router: Router | None = None) -> tuple[Any, Any]:
    """Bridges for (version prefix, domain) each, the receiving one first (a server must be up
    before its client; a peer or bus receiver hears its sender's first announcement)."""
    (_, send_file), (_, receive_file) = files(tmp_path, role, free_port(), bus_router)
    receiver = bridge(receive_file, receiving_side[1],
                      env=generated.environment(receiving_side[0]))
    sender = bridge(send_file, sending[1], env=generated.environment(sending[0]))
    return sender, receiver


def test_the_two_versions_hashes_differ_as_their_type_supports_give_them(versions, hashes):
    v1, v2 = hashes["v1"], hashes["v2"]
    assert v1.startswith("RIHS01_") and v2.startswith("RIHS01_") and len(v1) == len(v2) == 71
    assert v1 != v2
    assert (v1, v2) == (described_hash(versions["v1"]), described_hash(versions["v2"]))


def bus(request: pytest.FixtureRequest, role: str) -> Router | None:
    """A ``rosgate router`` for the zenoh role (none for the others)."""
    return request.getfixturevalue("router") if role == "zenoh" else None


@pytest.mark.parametrize("role", ["peer", "client_server", "zenoh"])
def test_two_versions_of_one_message_are_refused_counted_and_said(
        versions, hashes, bridge, domain, nodes, tmp_path, status_dir, request, role):
    ds, dr = domain(), domain()
    listener = nodes(versions["v2"], dr, "listen")  # starting while the bridges start
    talker = nodes(versions["v1"], ds, "talk")
    sender, receiver = start_pair(bridge, tmp_path, role, (versions["v1"], ds),
                                  (versions["v2"], dr), bus(request, role))
    name = "b" if role == "peer" else "base"
    listener.ready(), talker.ready()
    assert wait_until(lambda: any(e["drops"].get("type_mismatch", 0) >= 10
                                  for e in entries(name)), 30), \
        (entries(name), receiver.log, sender.log)
    entry = receiving(name)
    assert entry["received"] == 0 and set(entry["drops"]) == {"type_mismatch"}, entry
    assert entry["type"] == TYPE
    assert len(talker.having("published")) >= 10
    assert listener.having("got") == []
    label = "/reading (from robot1)" if role == "client_server" else "/reading"
    said = [line for line in receiver.log.splitlines() if "refused, the far side's type" in line]
    assert len(said) == 1, receiver.log
    assert said[0].endswith(
        f"{label}: refused, the far side's type is {TYPE} ({hashes['v1']}) and this "
        f"side's is {TYPE} ({hashes['v2']}), so its frames are dropped"), said


@pytest.mark.parametrize("role", ["peer", "zenoh"])
def test_one_version_on_both_sides_crosses_exact(versions, bridge, domain, nodes, tmp_path,
                                                 status_dir, request, role):
    """The control: the generated package itself crosses, field by field."""
    ds, dr = domain(), domain()
    listener = nodes(versions["v2"], dr, "listen")
    talker = nodes(versions["v2"], ds, "talk")
    _, receiver = start_pair(bridge, tmp_path, role, (versions["v2"], ds), (versions["v2"], dr),
                            bus(request, role))
    listener.ready(), talker.ready()
    assert listener.wait(lambda lines: sum(line.startswith("got") for line in lines) >= 5, 30), \
        listener.lines
    for line in listener.having("got"):
        _, value, unit = line.split(" ", 2)
        assert float(value) % 1 == 0.25 and unit == "'°C ✓'", line
    entry = receiving("b" if role == "peer" else "base")
    assert entry["received"] >= 5 and not entry["drops"], entry
    assert "refused" not in receiver.log
