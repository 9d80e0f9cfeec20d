"""What an operator sees of the routes pattern entries make, on one real client/server pair in
this process (ROS sides in their own domains): the status (the socket's JSON) names the pattern
that made each route, on both sides; ``rosgate top`` and ``/diagnostics`` show it; both logs say
when a found name's route appears and when it goes after the grace."""

from __future__ import annotations

import subprocess

from conftest import ROSGATE, free_port, wait_until
from std_msgs.msg import String
from test_diagnostics import OK, DiagnosticsInbox
from test_patterns import first_crossing
from test_status import entry, runtime_dir  # noqa: F401 (a fixture)


def entries(status, name):
    return [e for e in status["entries"] if e["name"] == name]


def test_tools_show_the_routes_patterns_made_and_the_logs_their_coming_and_going(
        engines, domain, ros_side, logs, runtime_dir):  # noqa: F811 (the fixture)
    ds, dc, port = domain(), domain(), free_port()
    server = engines(f"bridge: {{name: base, role: server, server: 127.0.0.1:{port}, "
                     "pattern_grace: 1}", ds)
    client = engines(f"""
bridge: {{name: robot1, role: client, server: 127.0.0.1:{port}, pattern_grace: 1}}
topics:
  - {{topic: /listed, type: std_msgs/msg/String, direction: transmit}}
  - {{topic: /r/**, direction: transmit}}
  - {{topic: /in/**, direction: receive, remote: /out/**}}
""", dc)
    robot, base = ros_side(dc, "robot"), ros_side(ds, "base")
    diagnostics = DiagnosticsInbox(robot)
    up, down = robot.publisher("/r/up", String), base.publisher("/out/down", String)
    first_crossing(up, base.listen("/r/up", String), String(data="up"), timeout=30)
    first_crossing(down, robot.listen("/in/down", String), String(data="down"), timeout=30)

    # the status, on both sides: each route a pattern made names it; a listed one does not
    mine, theirs = client.status(), server.status()
    assert [(e["direction"], e["pattern"]) for e in entries(mine, "/r/up")] == [
        ("transmit", "/r/**")]
    assert [(e["direction"], e["pattern"]) for e in entries(mine, "/in/down")] == [
        ("receive", "/in/**")]
    assert entry(mine, "/listed")["pattern"] is None
    assert [(e["direction"], e["peer"], e["pattern"]) for e in entries(theirs, "/r/up")] == [
        ("receive", "robot1", "/r/**")]
    assert [(e["direction"], e["pattern"]) for e in entries(theirs, "/out/down")] == [
        ("transmit", "/in/**")]
    assert entry(theirs, "/listed")["pattern"] is None

    # rosgate top: the rows of found names say which pattern; the listed one says nothing more
    shown = subprocess.run([ROSGATE, "top", "robot1", "--once", "--interval", "0.2"],
                           capture_output=True, text=True, timeout=60)
    assert shown.returncode == 0, shown.stderr
    rows = {line.split("│")[1].strip(): line for line in shown.stdout.splitlines()
            if line.count("│") > 3}
    assert "/r/up (found by /r/**)" in rows and "/in/down (found by /in/**)" in rows, rows
    assert "/listed" in rows and "topic" in rows["/listed"], rows

    # /diagnostics: the pattern among the values of the found name's status
    found = diagnostics.wait_status("rosgate: robot1: topic /r/up (to base)", OK)
    values = {kv.key: kv.value for kv in found.values}
    assert values["pattern"] == "/r/**" and values["type"] == "std_msgs/msg/String"
    listed = diagnostics.wait_status("rosgate: robot1: topic /listed (to base)", OK)
    assert "pattern" not in {kv.key for kv in listed.values}

    # the logs: each side says the route appeared ...
    assert logs.wait("robot1: topics[1] /r/** found /r/up (std_msgs/msg/String): bridged")
    assert logs.wait("client 'robot1': its pattern /r/** found /r/up (std_msgs/msg/String): "
                     "bridged")
    assert logs.wait("robot1: topics[2] /in/** found /in/down (std_msgs/msg/String): bridged")
    assert logs.wait("client 'robot1': its pattern /in/** found /out/down "
                     "(std_msgs/msg/String): bridged")
    # ... and, its publishers gone for the grace, that it went, on both sides
    robot.ros.destroy(up)
    base.ros.destroy(down)
    assert logs.wait("robot1: /r/up is gone (no publisher for 1 s): its route is removed")
    assert logs.wait("client 'robot1': /r/up (from robot1) is no longer found by its pattern "
                     "/r/**: its route is removed")
    assert logs.wait("robot1: /in/down is no longer offered: its route is removed")
    assert logs.wait("client 'robot1': /out/down (to robot1) is no longer found by its pattern "
                     "/in/**: its route is removed")
    assert wait_until(lambda: not {"/r/up", "/in/down"} & {
        e["name"] for e in client.status()["entries"]})
    assert not {"/r/up", "/out/down"} & {e["name"] for e in server.status()["entries"]}
