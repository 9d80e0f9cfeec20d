"""No open door on zenoh: a robot that receives ``/cmd_vel`` and serves ``/reset`` over zenoh is
refused by ``rosgate check`` and ``rosgate run`` unless every link its session has, or can get,
is mutual TLS (or the entry has a keyed cipher) — and a stranger's zenoh session (python zenoh,
no certificate) publishes, calls and reads nothing of the fixed file. Real ``rosgate router``
and ``rosgate run`` processes, real rclpy on the robot's side.

The three files an outside review found open, each one setting away from the fleet example:
(a) no ``tls:``; (b) ``tls:`` kept but the endpoint written ``tcp/...``; (c) the example with
``mode: peer``, whose session listens on zenoh's default ``tcp/[::]:0`` on every interface, a
door no router's access control sees. Before the judgement, each passed ``check`` and ran with
no ``INSECURE`` line, and the stranger published 20 of 20 Twists, had ``/reset`` served 3 of 3
times and read the robot's odometry, in each variant (measured here, 2 cores, shared machine).
"""

from __future__ import annotations

import json
import os
import subprocess
import time
from pathlib import Path

import pytest
import zenoh
from conftest import ROSGATE, wait_until
from geometry_msgs.msg import Twist
from nav_msgs.msg import Odometry
from rclpy.serialization import serialize_message
from std_srvs.srv import Trigger
from test_services import DEEP
from test_zenoh_fleet import Router

from rosgate.wire import envelope
from rosgate.wire.envelope import topic_id_for

TIMEOUT = 20.0
CMD, RESET, ODOM = "fleet/robot1/cmd_vel", "fleet/robot1/reset", "fleet/robot1/odom"
TWISTS, CALLS = 20, 3
STRANGE, BASE = 666.0, 1.0  # the stranger's Twists say linear.x = 666 + n, the base's 1 + n
WARM_UP = 100.0  # until one crosses

ENTRIES = f"""\
topics:
  - {{topic: /odom, type: nav_msgs/msg/Odometry, direction: transmit, remote: {ODOM}}}
  - {{topic: /cmd_vel, type: geometry_msgs/msg/Twist, direction: receive, remote: {CMD}}}
services:
  - {{service: /reset, type: std_srvs/srv/Trigger, direction: receive, remote: {RESET}}}
"""

#: the zenoh options of each open robot file, and whether its router runs with --tls
OPEN = {
    "a-no-tls": ("mode: client, connect: [{tcp}]", False),
    "b-tls-but-tcp-endpoint": ("mode: client, connect: [{tcp}], tls: {certs}", False),
    "c-mode-peer": ("mode: peer, connect: [{tls}], tls: {certs}", True),
}
#: the fixed files: TLS everywhere, behind the router's access control
FIXED = {
    "client": "mode: client, connect: [{tls}], tls: {certs}",
    "peer-tls-listener": "mode: peer, connect: [{tls}], listen: [tls/127.0.0.1:{port}], "
                         "tls: {certs}",
}


@pytest.fixture(scope="module")
def certs(tmp_path_factory):
    folder = tmp_path_factory.mktemp("certs")
    made = subprocess.run([ROSGATE, "certs", "--out", str(folder), "router", "robot1", "base"],
                          capture_output=True, text=True, timeout=60)
    assert made.returncode == 0, made.stderr
    return folder


def robot_file(tmp: Path, zenoh_options: str, insecure: str = "") -> Path:
    path = tmp / "robot1.yaml"
    path.write_text(f"bridge: {{name: robot1, role: peer, defaults: {{transport: zenoh}}"
                    f"{insecure}}}\nplugins:\n  zenoh: {{{zenoh_options}}}\n{ENTRIES}")
    return path


def options(template: str, router: Router, certs: Path, port: int = 0) -> str:
    host = router.endpoint.split("/", 1)[1]
    return template.format(tcp=f"tcp/{host}", tls=f"tls/{host}", certs=certs, port=port)


def listening(pid: int) -> list[int]:
    """The TCP ports process ``pid`` listens on (its sockets' inodes in /proc/net/tcp*)."""
    inodes = set()
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        try:
            target = os.readlink(fd)
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
    ports = []
    for table in ("tcp", "tcp6"):
        for row in Path(f"/proc/{pid}/net/{table}").read_text().splitlines()[1:]:
            fields = row.split()
            if fields[3] == "0A" and fields[9] in inodes:  # LISTEN
                ports.append(int(fields[1].rsplit(":", 1)[1], 16))
    return ports


def frame(key: str, flags: int, seq: int, payload: bytes) -> bytes:
    return envelope.pack(flags, topic_id_for(key), 7, seq, time.time_ns()) + payload


class Session:
    """A zenoh peer dialing ``endpoints`` (TLS settings: ``tls``, else none): it publishes
    Twists on the robot's command key, calls its reset, and reads its odometry."""

    def __init__(self, endpoints: list[str], tls: dict | None = None, mode: str = "peer"):
        config: dict = {"mode": mode, "connect": {"endpoints": endpoints},
                        "scouting": {"multicast": {"enabled": False},
                                     "gossip": {"enabled": False}}}
        if mode == "peer":
            config["listen"] = {"endpoints": []}
        if tls is not None:
            config["transport"] = {"link": {"tls": tls}}
        self.session = zenoh.open(zenoh.Config.from_json5(json.dumps(config)))
        self.read: list[bytes] = []
        self.session.declare_subscriber(ODOM, zenoh.handlers.Callback(
            lambda s: self.read.append(s.payload.to_bytes()), indirect=False))
        self.publisher = self.session.declare_publisher(CMD)
        self.querier = self.session.declare_querier(RESET, timeout=5.0)
        self.seq = 0

    def heard(self, timeout: float) -> bool:
        """Whether the robot's subscription and queryable are known to this session."""
        return wait_until(lambda: self.publisher.matching_status.matching
                          and self.querier.matching_status.matching, timeout)

    def publish(self, x: float, count: int = 1) -> None:
        for n in range(count):
            self.seq += 1
            twist = Twist()
            twist.linear.x = x + n
            self.publisher.put(frame(CMD, 0, self.seq, serialize_message(twist)))

    def call(self) -> bool:
        """One call of /reset; whether an answer (not a failure) came back."""
        self.seq += 1
        request = frame(RESET, envelope.FLAG_REQUEST, self.seq,
                        serialize_message(Trigger.Request()))
        answers = [r.ok.payload.to_bytes() for r in self.querier.get(payload=request)
                   if r.ok is not None]
        return any(envelope.unpack(a).flags & envelope.FLAG_REPLY
                   and not envelope.unpack(a).flags & envelope.FLAG_FAILED for a in answers)

    def close(self) -> None:
        self.session.close()


class Robot:
    """robot1's ROS side: what reached /cmd_vel, how often /reset was served; /odom fed."""

    def __init__(self, side):
        self.side = side
        self.cmd = side.listen("/cmd_vel", Twist)
        self.resets = 0

        def serve(request, response):
            self.resets += 1
            response.success, response.message = True, "reset"
            return response

        side.ros.node.create_service(Trigger, "/reset", serve, qos_profile=DEEP)
        self.odom = side.publisher("/odom", Odometry)

    def sent(self, x: float) -> list[float]:
        """The Twists published here of the 20 that say x, x + 1, ..."""
        return [m.linear.x for m in self.cmd.items if x <= m.linear.x < x + TWISTS]


def attack(session: Session, robot: Robot, x: float, heard_within: float
           ) -> tuple[int, int, int]:
    """What ``session`` gets done: (its Twists published on the robot's ROS side, its calls of
    /reset served there, odometry samples it read). It first sends until one Twist crosses (ROS
    discovery on the robot's side takes a moment), then 20 more (linear.x = x, x + 1, ...) and
    3 calls, while the robot publishes its odometry."""
    resets = robot.resets
    deadline = time.monotonic() + heard_within
    while time.monotonic() < deadline:
        if not session.heard(0.1):
            continue
        session.publish(WARM_UP)
        if robot.cmd.wait_for(lambda items: any(m.linear.x == WARM_UP for m in items), 0.2):
            session.publish(x, TWISTS)
            answered = sum(session.call() for _ in range(CALLS))
            wait_until(lambda: len(robot.sent(x)) >= TWISTS, 10)
            assert robot.resets - resets == answered
            break
    for _ in range(25):
        robot.odom.publish(Odometry(child_frame_id="robot1_base"))
        if wait_until(lambda: bool(session.read), 0.1):
            break
    return len(robot.sent(x)), robot.resets - resets, len(session.read)


@pytest.mark.parametrize("variant", OPEN)
def test_check_and_run_refuse_a_robot_file_a_stranger_could_write_to(variant, tmp_path, certs,
                                                                     domain):
    template, tls_router = OPEN[variant]
    router = Router(*(("--tls", str(certs), "--robot", "robot1", "--base", "base")
                      if tls_router else ()), scheme="tls" if tls_router else "tcp")
    try:
        path = robot_file(tmp_path, options(template, router, certs))
        check = subprocess.run([ROSGATE, "check", str(path)], capture_output=True, text=True,
                               timeout=60)
        assert check.returncode == 2, (variant, check.stdout, check.stderr)
        run = subprocess.run([ROSGATE, "run", str(path)], capture_output=True, text=True,
                             timeout=60, env=dict(os.environ, ROS_DOMAIN_ID=str(domain())))
    finally:
        router.stop()
    for result in (check, run):
        assert result.returncode == 2, (variant, result.stdout, result.stderr)
        assert "Traceback" not in result.stderr
        said = result.stderr
        assert f"{path}:3:" in said, said  # the line of plugins.zenoh, where the fix goes
        assert "/cmd_vel" in said and "topics[1]" in said and "(and 1 more entry)" in said, said
        assert "bridge.insecure" in said or "insecure: true" in said, said
    assert "running as" not in run.stdout + run.stderr
    said = check.stderr
    if variant == "a-no-tls":
        assert "no mutual TLS" in said and "tls: <folder>" in said and "rosgate certs" in said
    elif variant == "b-tls-but-tcp-endpoint":
        assert "connect endpoint tcp/127.0.0.1:" in said and "is not TLS" in said, said
        assert "tls/127.0.0.1:" in said, said  # the fix: the same endpoint, written tls/
    else:
        assert "mode: peer" in said and "tcp/[::]:0" in said and "mode: client" in said, said


@pytest.mark.parametrize("variant", OPEN)
def test_with_insecure_true_a_stranger_gets_in_and_run_names_the_open_entries(
        variant, tmp_path, certs, bridge, domain, ros_side):
    """What ``insecure: true`` accepts, seen: the stranger's 20 Twists published, 3 calls
    served, odometry read — and the bridge says at start which entries are open."""
    template, tls_router = OPEN[variant]
    router = Router(*(("--tls", str(certs), "--robot", "robot1", "--base", "base")
                      if tls_router else ()), scheme="tls" if tls_router else "tcp")
    stranger = None
    try:
        d = domain()
        robot = Robot(ros_side(d, "robot1"))
        path = robot_file(tmp_path, options(template, router, certs), ", insecure: true")
        running = bridge(path, d)
        host = router.endpoint.split("/", 1)[1]
        if tls_router:  # the robot's own listener, which the router never sees
            ports = listening(running.proc.pid)
            assert ports, "mode: peer listens on zenoh's default tcp/[::]:0"
            targets = [f"tcp/127.0.0.1:{port}" for port in ports]
        else:
            targets = [f"tcp/{host}"]
        stranger = Session(targets)
        published, called, read = attack(stranger, robot, STRANGE, TIMEOUT)
        assert (published, called) == (TWISTS, CALLS), (published, called, running.log)
        assert sorted(robot.sent(STRANGE)) == [STRANGE + n for n in range(TWISTS)]
        assert read >= 1
        log = running.log
        assert "INSECURE" in log and "topics[1]" in log and "/cmd_vel" in log, log
        assert "services[0]" in log and "/reset" in log, log
    finally:
        if stranger is not None:
            stranger.close()
        router.stop()


@pytest.mark.parametrize("variant", FIXED)
def test_the_fixed_file_passes_and_the_stranger_gets_nothing(
        variant, tmp_path, certs, bridge, domain, ros_side):
    """TLS on every link, the router's access control as in examples/fleet: the base (the
    fleet's certificate) commands, resets and reads robot1; the stranger, dialing the router
    (plain TCP, TLS without a certificate) and every port the robot listens on: 0 published,
    0 called, 0 read."""
    from rosgate_testing import free_port

    router = Router("--tls", str(certs), "--robot", "robot1", "--base", "base", scheme="tls")
    strangers: list[Session] = []
    base = None
    try:
        # insecure: false said, so the test harness leaves the file as it is
        path = robot_file(tmp_path, options(FIXED[variant], router, certs, free_port()),
                          ", insecure: false")
        check = subprocess.run([ROSGATE, "check", str(path)], capture_output=True, text=True,
                               timeout=60)
        assert check.returncode == 0, check.stderr
        d = domain()
        robot = Robot(ros_side(d, "robot1"))
        running = bridge(path, d)
        assert "INSECURE" not in running.log
        host = router.endpoint.split("/", 1)[1]
        ports = listening(running.proc.pid)
        targets = [f"tcp/{host}", f"tls/{host}",
                   *(f"{s}/127.0.0.1:{p}" for p in ports for s in ("tcp", "tls"))]
        # no certificate: the CA alone (so TLS itself is tried), or nothing at all
        strangers = [Session(targets, {"root_ca_certificate": str(certs / "ca.pem")}),
                     Session(targets)]
        results = [attack(s, robot, STRANGE, 3.0) for s in strangers]
        base = Session([router.endpoint], {
            "root_ca_certificate": str(certs / "ca.pem"), "enable_mtls": True,
            "connect_certificate": str(certs / "base.pem"),
            "connect_private_key": str(certs / "base.key"), "verify_name_on_connect": False},
            mode="client")
        published, called, read = attack(base, robot, BASE, TIMEOUT)
        assert (published, called) == (TWISTS, CALLS) and read, "the control: the base gets in"
        # the strangers kept dialing and listening all along, beside the base
        assert results == [(0, 0, 0), (0, 0, 0)]
        assert robot.sent(STRANGE) == [] and [s.read for s in strangers] == [[], []]
    finally:
        for s in [*strangers, *([base] if base else [])]:
            s.close()
        router.stop()


def test_plugins_zenoh_insecure_is_refused_pointing_to_bridge_insecure(tmp_path):
    path = robot_file(tmp_path, "mode: client, connect: [tcp/127.0.0.1:7447], insecure: true")
    result = subprocess.run([ROSGATE, "check", str(path)], capture_output=True, text=True,
                            timeout=60)
    assert result.returncode == 2, result.stdout
    assert f"{path}:3:" in result.stderr and "plugins.zenoh.insecure" in result.stderr
    assert "bridge.insecure" in result.stderr
    assert "Traceback" not in result.stderr
