"""A receiving pattern on a peer bridge whose bus is zenoh: a real ``rosgate run`` takes the
topics announced under it on the zenoh side by their liveliness tokens, the type read from the
token, and publishes them on its ROS side field by field; what the pattern's ``deny`` or the
pattern itself leaves out never appears on the ROS graph. Announced as rmw_zenoh nodes announce
them (``speak: rmw_zenoh``: tokens written out in test_zenoh_rmw.RmwNode from rmw_zenoh's
sources) and as zenoh-bridge-ros2dds does (``speak: ros2dds``)."""

from __future__ import annotations

import subprocess
import time
from pathlib import Path

import pytest
from conftest import ROSGATE, wait_until
from geometry_msgs.msg import Twist
from rclpy.serialization import serialize_message
from rosgate_top.client import StatusClient
from std_msgs.msg import String
from test_status import runtime_dir  # noqa: F401 (a fixture)
from test_zenoh_fleet import Router, zenoh_plugin
from test_zenoh_rmw import STRING, TWIST, RmwNode
from test_zenoh_ros2dds import plain, twist  # noqa: F401 (a fixture)

TIMEOUT = 20.0


@pytest.fixture
def router():
    r = Router()
    yield r
    r.stop()


def bot_file(tmp: Path, router: Router, speak: str) -> Path:
    path = tmp / "bot1.yaml"
    path.write_text(f"""\
# zenoh without TLS: the router of a test on loopback
bridge: {{name: bot1, role: peer, defaults: {{transport: zenoh, codec: cdr}}, insecure: true,
         pattern_grace: 1}}
{zenoh_plugin(router, f", speak: {speak}")}topics:
  - {{topic: /robot1/**, direction: receive, framing: none, deny: [/robot1/secret/**]}}
""")
    return path


def until_it_arrives(inbox, put, timeout: float = TIMEOUT) -> float:
    """Put a sample every 100 ms until one is published on the ROS side: seconds it took."""
    start = time.monotonic()
    while not inbox.wait_count(1, 0.1):
        assert time.monotonic() - start < timeout, "nothing was published on the ROS side"
        put()
    return time.monotonic() - start


def names(side) -> set[str]:
    return {name for name, _ in side.ros.node.get_topic_names_and_types()}


def test_topics_rmw_zenoh_nodes_announce_under_a_pattern_are_bridged(
        tmp_path, router, bridge, domain, ros_side, runtime_dir):  # noqa: F811 (the fixture)
    d = domain()
    bot = bridge(bot_file(tmp_path, router, "rmw_zenoh"), d)
    node = RmwNode(router, d, "driver")
    try:
        robot = ros_side(d, "robot")
        inbox = robot.listen("/robot1/cmd_vel", Twist)
        # announced after the bridge is up, as a node started later would
        node.announce("MP", "/robot1/cmd_vel", TWIST, "::,10:,:,:,,")
        for name in ("/robot1/secret/key", "/elsewhere/chat"):
            node.announce("MP", name, STRING, "::,10:,:,:,,")
        # a type this side does not have: said with the package to install, counted, no route
        node.announce("MP", "/robot1/odd", ("odd_msgs::msg::dds_::Odd_", "RIHS01_" + "0" * 64),
                      "::,10:,:,:,,")
        publisher = node.session.declare_publisher(node.key("/robot1/cmd_vel", TWIST))
        message = twist()
        until_it_arrives(inbox, lambda: publisher.put(serialize_message(message),
                                                      attachment=node.attachment()))
        got = inbox.items[0]
        assert (got.linear.x, got.linear.y, got.angular.z) == (1.5, -0.25, 0.75)
        assert bot.wait_log("bot1: topics[0] /robot1/** found /robot1/cmd_vel "
                            "(geometry_msgs/msg/Twist) on zenoh: bridged", TIMEOUT), bot.log
        # the ROS side has its publisher, of the type the token said; the others never appear
        assert wait_until(lambda: ("/robot1/cmd_vel", ["geometry_msgs/msg/Twist"]) in
                          robot.ros.node.get_topic_names_and_types(), TIMEOUT)
        # judged in the order announced: the odd type last
        assert bot.wait_log("/robot1/odd (odd_msgs/msg/Odd) cannot be bridged: ", TIMEOUT)
        assert not names(robot) & {"/robot1/secret/key", "/elsewhere/chat"}
        assert "found /robot1/secret/key" not in bot.log and "found /elsewhere" not in bot.log
        # its status names the pattern that made the route
        with StatusClient("bot1") as ask:
            status = ask.status()
        assert [(e["direction"], e["type"], e["pattern"]) for e in status["entries"]] == [
            ("receive", "geometry_msgs/msg/Twist", "/robot1/**")]
        assert status["patterns"] == {"found": ["/robot1/cmd_vel"], "refused": {"unroutable": 1}}
        assert "interface package 'odd_msgs' is not installed" in bot.log and "/robot1/odd" \
            not in names(robot)
        # its publisher's token goes: after the grace the route goes, its ROS publisher too
        publisher.undeclare()
        node.held[1].undeclare()
        assert bot.wait_log("bot1: /robot1/cmd_vel is gone (no publisher for 1 s): its route is "
                            "removed", TIMEOUT), bot.log
        assert wait_until(lambda: not robot.ros.node.get_publishers_info_by_topic(
            "/robot1/cmd_vel"), TIMEOUT)
        # and comes back with a publisher that appears again
        node.announce("MP", "/robot1/cmd_vel", TWIST, "::,10:,:,:,,")
        assert wait_until(lambda: bot.log.count("found /robot1/cmd_vel") == 2, TIMEOUT), bot.log
    finally:
        node.close()


def test_topics_a_ros2dds_bridge_announces_under_a_pattern_are_bridged(
        tmp_path, router, plain, bridge, domain, ros_side):  # noqa: F811 (the fixture)
    d = domain()
    path = bot_file(tmp_path, router, "ros2dds")
    checked = subprocess.run([ROSGATE, "check", str(path)], capture_output=True, text=True,
                             timeout=60)
    assert checked.returncode == 0, checked.stderr
    assert "  /robot1/** <- robot1/**  [type from the graph] zenoh cdr none  (pattern)\n" \
           "    takes the topics announced on zenoh under it, as they appear\n" in checked.stdout
    bot = bridge(path, d)
    robot = ros_side(d, "robot")
    inbox = robot.listen("/robot1/status", String)
    # the token a zenoh-bridge-ros2dds base declares for a ROS publisher of /robot1/status
    # behind it (liveliness_mgt.rs), and its frames: bare CDR on the ROS name's key
    token = plain.liveliness().declare_token(
        f"@/{plain.zid()}/@ros2_lv/MP/robot1§status/std_msgs§msg§String/:1:0:0,10")
    payload = serialize_message(String(data="all well"))
    until_it_arrives(inbox, lambda: plain.put("robot1/status", payload))
    assert inbox.items[0].data == "all well"
    assert bot.wait_log("found /robot1/status (std_msgs/msg/String) on zenoh: bridged",
                        TIMEOUT), bot.log
    token.undeclare()
