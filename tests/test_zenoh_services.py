"""Services over zenoh: one call is one query; timeouts and failure answers as on any link.
Two engines in this process (each in its own DDS domain) through a ``rosgate router`` process."""

from __future__ import annotations

import threading
import time

import pytest
from std_srvs.srv import SetBool, Trigger
from test_services import DEEP, Caller, echo_set_bool
from test_zenoh_fleet import Router


@pytest.fixture
def router():
    r = Router()
    yield r
    r.stop()


def test_calls_concurrent_slow_and_unserved_over_zenoh(router, engines, domain, ros_side):
    plugin = f"plugins: {{zenoh: {{mode: client, connect: [{router.endpoint}]}}}}\n"
    da, db = domain(), domain()
    engines("bridge: {name: robot, role: peer, defaults: {transport: zenoh}}\n" + plugin + """
services:
  - {service: /set, type: std_srvs/srv/SetBool, direction: receive, remote: r/set, timeout: 2}
  - {service: /slow, type: std_srvs/srv/Trigger, direction: receive, remote: r/slow, timeout: 1}
""", da)
    base = engines("bridge: {name: base, role: peer, defaults: {transport: zenoh}}\n" + plugin + """
services:
  - {service: /set, type: std_srvs/srv/SetBool, direction: transmit, remote: r/set, timeout: 2}
  - {service: /slow, type: std_srvs/srv/Trigger, direction: transmit, remote: r/slow, timeout: 1}
  - {service: /nobody, type: std_srvs/srv/Trigger, direction: transmit, remote: r/nobody,
     timeout: 5}
""", db)
    robot_side, base_side = ros_side(da, "robot"), ros_side(db, "base")
    robot_side.ros.node.create_service(SetBool, "/set", echo_set_bool, qos_profile=DEEP)
    never = threading.Event()
    robot_side.ros.node.create_service(Trigger, "/slow", lambda req, resp: (never.wait(3), resp)[1],
                                       qos_profile=DEEP)

    caller = Caller(base_side, SetBool, "/set")
    caller.warm_up(SetBool.Request(data=True))
    answers = caller.call_many([SetBool.Request(data=i % 2 == 0) for i in range(20)], 10)
    assert [a.message for a in answers] == [f"data={i % 2 == 0}" for i in range(20)]

    started = time.monotonic()
    slow = Caller(base_side, Trigger, "/slow").call(Trigger.Request(), timeout=10)
    assert not slow.success and slow.message.startswith("rosgate: ")
    assert "within 1 s" in slow.message
    assert time.monotonic() - started < 3

    started = time.monotonic()
    nobody = Caller(base_side, Trigger, "/nobody").call(Trigger.Request(), timeout=10)
    assert nobody.message.startswith("rosgate: nothing on zenoh answered on r/nobody")
    assert time.monotonic() - started < 2.5, "no server is answered at once, not at the timeout"
    drops = {r.label: dict(r.counters.drops) for r in base.routes()}
    assert drops["/nobody"] == {"no_server": 1}
    never.set()
