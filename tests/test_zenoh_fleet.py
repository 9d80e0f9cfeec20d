"""Fleets over zenoh, end to end: real ``rosgate router`` and ``rosgate run`` processes on
loopback (explicit endpoints, multicast scouting off), real rclpy on every side, each side in a
DDS domain of its own so the only way across is the bus."""

from __future__ import annotations

import signal
import subprocess
import threading
import time
from pathlib import Path

import pytest
from conftest import ROSGATE, cross, free_port, wait_until
from std_msgs.msg import String
from std_srvs.srv import Trigger
from test_services import DEEP, Caller


class Router:
    """A ``rosgate router`` process on a fixed loopback port; it can be killed and started again."""

    def __init__(self, *args: str, scheme: str = "tcp") -> None:
        self.endpoint = f"{scheme}/127.0.0.1:{free_port()}"
        self.args = list(args)  # more of rosgate router's arguments (--tls DIR, --robot NAME)
        self.proc: subprocess.Popen | None = None
        self.start()

    def start(self) -> None:
        self.proc = subprocess.Popen([ROSGATE, "router", "--listen", self.endpoint, *self.args],
                                     stderr=subprocess.PIPE, text=True)
        assert self.proc.stderr is not None
        line = self.proc.stderr.readline()
        assert "router running" in line, line
        threading.Thread(target=self.proc.stderr.read, daemon=True).start()  # keep it drained

    def kill(self) -> None:
        assert self.proc is not None
        self.proc.kill()
        self.proc.wait()

    def stop(self) -> int:
        assert self.proc is not None
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            return self.proc.wait(10)
        return 0


@pytest.fixture
def router():
    r = Router()
    yield r
    r.stop()


def zenoh_plugin(router: Router, extra: str = "") -> str:
    # reconnection within half a second, so a router restart costs the test little
    return (f"plugins:\n  zenoh: {{mode: client, connect: {{endpoints: [{router.endpoint}], "
            f"retry: {{period_init_ms: 100, period_max_ms: 500}}}}{extra}}}\n")


def robot_file(tmp: Path, name: str, router: Router) -> Path:
    path = tmp / f"{name}.yaml"
    path.write_text(f"""\
bridge: {{name: {name}, role: peer, defaults: {{transport: zenoh}}}}
{zenoh_plugin(router)}topics:
  - {{topic: /odom, type: std_msgs/msg/String, direction: transmit, remote: fleet/{name}/odom}}
  - {{topic: /cmd, type: std_msgs/msg/String, direction: receive, remote: fleet/{name}/cmd}}
services:
  - {{service: /reset, type: std_srvs/srv/Trigger, direction: receive,
      remote: fleet/{name}/reset, timeout: 3}}
  - {{service: /base/ping, type: std_srvs/srv/Trigger, direction: transmit,
      remote: fleet/base/ping, timeout: 3}}
""")
    return path


def base_file(tmp: Path, router: Router, fleet_timeout: float = 30) -> Path:
    path = tmp / "base.yaml"
    path.write_text(f"""\
bridge: {{name: base, role: peer, defaults: {{transport: zenoh}}, fleet_timeout: {fleet_timeout}}}
{zenoh_plugin(router)}topics:
  - {{topic: '/{{robot}}/odom', type: std_msgs/msg/String, direction: receive,
      remote: 'fleet/{{robot}}/odom'}}
  - {{topic: '/{{robot}}/cmd', type: std_msgs/msg/String, direction: transmit,
      remote: 'fleet/{{robot}}/cmd'}}
services:
  - {{service: '/{{robot}}/reset', type: std_srvs/srv/Trigger, direction: transmit,
      remote: 'fleet/{{robot}}/reset', timeout: 3}}
  - {{service: /base/ping, type: std_srvs/srv/Trigger, direction: receive,
      remote: fleet/base/ping, timeout: 3}}
""")
    return path


def text(tag: str):
    return lambda i: String(data=f"{tag}-warmup" if i is None else f"{tag}-{i}")


def is_warmup(m: String) -> bool:
    return m.data.endswith("-warmup")


def answering(message: str):
    def serve(request, response):
        response.success, response.message = True, message
        return response
    return serve


def test_two_robots_and_a_base_through_one_router_both_ways_and_a_router_restart(
        tmp_path, router, bridge, domain, ros_side):
    robots = ["robot1", "robot2"]
    d = {name: domain() for name in [*robots, "base"]}
    sides = {name: ros_side(d[name], name) for name in d}
    base = bridge(base_file(tmp_path, router), d["base"])
    for name in robots:
        bridge(robot_file(tmp_path, name, router), d[name])
        sides[name].ros.node.create_service(Trigger, "/reset", answering(f"{name} reset"),
                                            qos_profile=DEEP)
    sides["base"].ros.node.create_service(Trigger, "/base/ping", answering("pong"),
                                          qos_profile=DEEP)

    def topics_cross(round_: str) -> None:
        for name in robots:  # up: each robot's /odom becomes /<robot>/odom on the base
            got = cross(sides[name].publisher("/odom", String),
                        sides["base"].listen(f"/{name}/odom", String), text(f"{name}{round_}"),
                        is_warmup, 20)
            assert [m.data for m in got] == [f"{name}{round_}-{i}" for i in range(20)]
        for name in robots:  # down: the base's /<robot>/cmd reaches that robot's /cmd only
            inbox = sides[name].listen("/cmd", String)
            got = cross(sides["base"].publisher(f"/{name}/cmd", String), inbox,
                        text(f"to-{name}{round_}"), is_warmup, 20)
            assert [m.data for m in got] == [f"to-{name}{round_}-{i}" for i in range(20)]
            assert all(m.data.startswith(f"to-{name}") for m in inbox.items)

    def services_cross() -> None:
        for name in robots:  # the base calls each robot
            answer, _ = Caller(sides["base"], Trigger, f"/{name}/reset").warm_up(Trigger.Request())
            assert answer == Trigger.Response(success=True, message=f"{name} reset")
        for name in robots:  # each robot calls the base
            answer, _ = Caller(sides[name], Trigger, "/base/ping").warm_up(Trigger.Request())
            assert answer == Trigger.Response(success=True, message="pong")

    topics_cross("")
    services_cross()

    router.kill()
    assert base.wait_log("fleet: robot robot1 left", 10)
    router.start()  # the same port: the bridges reconnect by themselves
    assert base.wait_log("fleet: robot robot1 is back", 15)
    topics_cross("-again")
    services_cross()
    # one ROS publisher per robot and topic, announced once, the restart notwithstanding
    for name in robots:
        assert base.log.count(f"fleet: publishing /{name}/odom for robot {name}") == 1
        assert base.log.count(f"fleet: sending /{name}/cmd to robot {name}") == 1
        assert base.log.count(f"fleet: offering /{name}/reset, served by robot {name}") == 1


def test_a_robot_that_leaves_is_logged_once_and_its_routes_dropped_after_the_timeout(
        tmp_path, router, bridge, domain, ros_side):
    d_robot, d_base = domain(), domain()
    base = bridge(base_file(tmp_path, router, fleet_timeout=2), d_base)
    robot = bridge(robot_file(tmp_path, "robot7", router), d_robot)
    base_side = ros_side(d_base, "base")
    cross(ros_side(d_robot, "robot7").publisher("/odom", String),
          base_side.listen("/robot7/odom", String), text("r7"), is_warmup, 3)
    node = base_side.ros.node
    assert wait_until(lambda: node.count_publishers("/robot7/odom") == 1)
    base_side.publisher("/robot7/cmd", String)  # the base subscribes once /cmd has a publisher
    assert wait_until(lambda: node.count_subscribers("/robot7/cmd") == 1)
    started = time.monotonic()
    assert robot.stop() == 0
    assert base.wait_log("fleet: robot robot7 left (its liveliness token is gone)", 10)
    assert base.wait_log("fleet: robot robot7 dropped", 10)
    assert time.monotonic() - started >= 2
    assert wait_until(lambda: node.count_publishers("/robot7/odom") == 0)
    assert wait_until(lambda: node.count_subscribers("/robot7/cmd") == 0)
    assert "/robot7/reset" not in dict(node.get_service_names_and_types())
    assert base.log.count("fleet: robot robot7 left") == 1
    assert base.log.count("fleet: robot robot7 dropped") == 1
