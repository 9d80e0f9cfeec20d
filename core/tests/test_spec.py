"""What the resolver decides for an entry is one frozen RouteSpec, and what a link reads of it
is its Delivery: the keys of the file, with the defaults said once."""

from __future__ import annotations

import dataclasses

import pytest
from rosgate_recovery import Fec, Retransmit

from rosgate.builtin import Fragments
from rosgate.config import loads
from rosgate.engine import Engine
from rosgate.spec import CONTROL, Delivery, ServiceSpec, TopicSpec
from rosgate.wire import framing

HEAD = "bridge:\n  name: robot1\n  role: peer\n  peer: 127.0.0.2\n  insecure: true\n"


def plan(text: str):
    return Engine(loads(HEAD + text, file="bringup.yaml")).prepare().plan


def test_a_topic_s_keys_become_its_delivery():
    p = plan("""\
topics:
  - {topic: /camera, type: sensor_msgs/msg/Image, direction: transmit, port: 9,
     priority: data_low, latest_only: false, max_delay: 0.05, recovery: {fec: {overhead: 0.2}}}
  - {topic: /cmd_vel, type: geometry_msgs/msg/Twist, direction: transmit, port: 10}
  - {topic: /mcu, type: geometry_msgs/msg/Twist, direction: transmit, port: 11, codec: msgpack,
     framing: none}
  - {topic: /scan, type: std_msgs/msg/String, direction: transmit, port: 12, qos: sensor_data}
services:
  - {service: /set, type: std_srvs/srv/SetBool, direction: transmit, port: 13}
""")
    camera, twist, mcu, scan = p.topics
    assert all(isinstance(t, TopicSpec) for t in p.topics)
    assert camera.delivery == Delivery(reliable=True, priority=6, latest_only=False,
                                       max_delay=0.05, packetizer=Fec,
                                       packetizer_options=Fec.Options(overhead=0.2))
    # ROS's default QoS is reliable: every message, in order, repaired on a datagram link
    assert twist.delivery == Delivery(reliable=True, priority=5, latest_only=False,
                                      packetizer=Retransmit,
                                      packetizer_options=Retransmit.Options())
    assert mcu.delivery == Delivery(reliable=True, whole=True)
    # best effort: the newest message wins unless the entry says otherwise
    assert scan.delivery == Delivery(reliable=False, latest_only=True)
    (service,) = p.services
    assert isinstance(service, ServiceSpec) and service.delivery == Delivery()
    assert (twist.kind, service.kind, twist.name, service.name) == (
        "topic", "service", "/cmd_vel", "/set")


def test_a_spec_and_its_delivery_are_frozen():
    (twist,) = plan("topics:\n  - {topic: /cmd_vel, type: geometry_msgs/msg/Twist, "
                    "direction: transmit, port: 10}\n").topics
    with pytest.raises(dataclasses.FrozenInstanceError):
        twist.delivery = CONTROL  # type: ignore[misc]
    with pytest.raises(dataclasses.FrozenInstanceError):
        twist.delivery.priority = 0  # type: ignore[misc]
    assert not hasattr(twist, "__dict__")  # slots: no attribute can be added on the way
    assert CONTROL.priority == 0 and not CONTROL.reliable


def test_fragments_is_the_link_s_own_and_claims_no_one_else_s_magic():
    assert Fragments.magic == (framing.FRAGMENT_MAGIC,)
