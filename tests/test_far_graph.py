"""The far graph, mirrored honestly: a service or an action bridged across appears on the calling
side only while a real server for it runs on the serving side, and goes when it goes — for
listed entries as for the ones patterns find. Real ``rosgate run`` processes, each side in its
own DDS domain."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from conftest import free_port, wait_until
from std_srvs.srv import Trigger
from test_msgs.action import Fibonacci
from test_services import DEEP

ABSENT_FOR = 2.0  # seconds a caller waits for a proxy that must not be there


def answer(text: str) -> Any:
    return lambda request, response: (setattr(response, "message", text), response)[1]


def servers(side: Any, name: str) -> int:
    return side.ros.node.count_services(name)


def test_a_proxy_exists_only_while_its_real_server_does(bridge, tmp_path: Path, domain,
                                                        ros_side, action_side):
    from test_actions import Goal, fibonacci, warmed_up

    ds, dc, port = domain(), domain(), free_port()
    server_file = tmp_path / "server.yaml"
    server_file.write_text(f"bridge: {{name: base, role: server, server: '127.0.0.1:{port}'}}\n")
    bridge(server_file, ds)
    client_file = tmp_path / "client.yaml"
    client_file.write_text(f"""
bridge: {{name: robot1, role: client, server: '127.0.0.1:{port}'}}
services:
  - {{service: /robot1/ping, type: std_srvs/srv/Trigger, direction: receive}}  # served on the robot
  - {{service: /base/ping, type: std_srvs/srv/Trigger, direction: transmit}}   # served on the base
actions:
  - {{action: /fib, type: test_msgs/action/Fibonacci, direction: transmit}}    # served on the base
""")
    client = bridge(client_file, dc)
    assert client.wait_log("server 'base' up", 30), client.log
    robot, base = ros_side(dc, "robot"), ros_side(ds, "base")
    to_robot = base.ros.node.create_client(Trigger, "/robot1/ping", qos_profile=DEEP)
    to_base = robot.ros.node.create_client(Trigger, "/base/ping", qos_profile=DEEP)
    goals = action_side(dc, "goals").client(Fibonacci, "/fib")
    # nobody serves them: no proxy says otherwise (the three nodes were made together: once
    # one has looked for ABSENT_FOR seconds, the others have had as long)
    assert not to_robot.wait_for_service(timeout_sec=ABSENT_FOR)
    assert not to_base.wait_for_service(timeout_sec=0.2)
    assert not goals.wait_for_server(timeout_sec=0.2)
    assert servers(base, "/robot1/ping") == servers(robot, "/base/ping") == 0

    real = [robot.ros.node.create_service(Trigger, "/robot1/ping", answer("from the robot"),
                                          qos_profile=DEEP),
            base.ros.node.create_service(Trigger, "/base/ping", answer("from the base"),
                                         qos_profile=DEEP)]
    fib = action_side(ds, "fib").fibonacci_server("/fib")
    assert to_robot.wait_for_service(timeout_sec=10) and to_base.wait_for_service(timeout_sec=10)
    for client_, text in ((to_robot, "from the robot"), (to_base, "from the base")):
        future = client_.call_async(Trigger.Request())
        assert wait_until(future.done, 10), "no answer"
        assert future.result() == Trigger.Response(success=False, message=text)
    goal = Goal(warmed_up(goals, Fibonacci.Goal(order=1)), Fibonacci.Goal(order=3))
    assert goal.handle.accepted and list(goal.result().result.sequence) == fibonacci(4)

    # the real servers go: so do their proxies, and the action's
    robot.ros.node.destroy_service(real[0])
    base.ros.node.destroy_service(real[1])
    fib.destroy()
    assert wait_until(lambda: servers(base, "/robot1/ping") == 0, 10)
    assert wait_until(lambda: servers(robot, "/base/ping") == 0, 10)
    assert wait_until(lambda: servers(robot, "/fib/_action/send_goal") == 0, 10)
    assert not goals.wait_for_server(timeout_sec=1)
    assert client.wait_log("/robot1/ping (from base): its server here is gone", 5), client.log


def test_what_a_far_side_says_of_its_server_is_read_strictly():
    import pytest

    from rosgate.announce import served

    assert served(b'{"type":"std_srvs/srv/Trigger","served":false}') is False
    assert served({"type": "std_srvs/srv/Trigger", "served": True}) is True
    assert served({"type": "std_srvs/srv/Trigger"}) is True  # an older rosgate: as before
    for bad in ({"type": "x", "served": "yes"}, {"type": "x", "served": 1}):
        with pytest.raises(ValueError, match="served"):
            served(bad)
