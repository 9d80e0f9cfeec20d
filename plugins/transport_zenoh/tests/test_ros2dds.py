"""zenoh-bridge-ros2dds's convention as text: action parts and their tokens (liveliness_mgt.rs,
ros2_utils.rs)."""

from __future__ import annotations

import pytest
from rosgate_transport_zenoh import ros2dds
from rosgate_transport_zenoh.ros2dds import Announced, Kind


@pytest.mark.parametrize("name, part", [
    ("/fib/_action/send_goal", "send_goal"),
    ("bot1/fib/_action/cancel_goal", "cancel_goal"),
    ("/a/b/fib/_action/get_result", "get_result"),
    ("/fib/_action/feedback", "feedback"),
    ("/fib/_action/status", "status"),
    ("/fib/_action/other", None),  # not a part
    ("/_action/status", None),  # no action before it
    ("/fib/action/status", None),
    ("/fib/_action/status/more", None),
])
def test_an_actions_parts_are_told_apart_by_the_names_end(name, part):
    assert ros2dds.action_part(name) == part


def test_an_actions_token_is_on_its_key_with_its_type():
    key, action_type = ros2dds.action_of("bot1/fib/_action/send_goal",
                                         "test_msgs/action/Fibonacci_SendGoal")
    assert (key, action_type) == ("bot1/fib", "test_msgs/action/Fibonacci")
    served = ros2dds.token("z1", Kind.ACTION_SERVER, key, action_type)
    called = ros2dds.token("z1", Kind.ACTION_CLIENT, key, action_type)
    assert served == "@/z1/@ros2_lv/AS/bot1§fib/test_msgs§action§Fibonacci"
    assert called == "@/z1/@ros2_lv/AC/bot1§fib/test_msgs§action§Fibonacci"
    assert ros2dds.parse(served) == Announced("z1", Kind.ACTION_SERVER, "bot1/fib",
                                              "test_msgs/action/Fibonacci")
    assert ros2dds.parse(served + "/:1:0:0,10") is None  # an action's token has no QoS


def test_the_graph_names_the_package_of_a_type_not_installed_here(caplog):
    from rosgate_transport_zenoh.dialect import Graph

    graph = Graph("own")
    qos = ros2dds.Qos.parse(":1:0:0,10")
    gadget = ros2dds.token("z7", Kind.PUBLISHER, "bot7/gadget", "gadget_msgs/msg/Gadget", qos)
    odom = ros2dds.token("z7", Kind.PUBLISHER, "bot7/odom", "std_msgs/msg/String", qos)
    with caplog.at_level("INFO", logger="rosgate"):
        graph.changed(gadget, True)
        graph.changed(odom, True)
    lines = [r.getMessage() for r in caplog.records]
    assert lines == [
        "zenoh-bridge-ros2dds z7: publisher on bot7/gadget [gadget_msgs/msg/Gadget] (its type is "
        "not installed on this side: interface package 'gadget_msgs' is not installed (apt "
        "install ros-$ROS_DISTRO-gadget-msgs, or pip install ros-jazzy-gadget-msgs))",
        "zenoh-bridge-ros2dds z7: publisher on bot7/odom [std_msgs/msg/String]"]
