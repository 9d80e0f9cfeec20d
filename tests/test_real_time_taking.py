"""A real_time topic's subscription is taken on a thread of its own: a flooded topic whose
callback is busy (here: held until the test lets go) delays none of its messages, and its
shallow history overwrites none of them."""

from __future__ import annotations

import threading

from conftest import Inbox, cross, free_port, wait_until
from geometry_msgs.msg import Twist, Vector3
from rclpy import qos
from std_msgs.msg import String

from rosgate.ros import RosNode

TWISTS = 40


def test_a_real_time_subscription_is_taken_while_a_flooded_one_is_busy(domain, ros_side):
    d = domain()
    talker = ros_side(d, "talker")
    bridge = RosNode(f"taking_{d}", d)
    try:
        held, release = threading.Event(), threading.Event()
        bulk = Inbox()

        def busy(message: String) -> None:  # the flooded topic's callback, stuck in its work
            held.set()
            release.wait(60)
            bulk.put(message.data)

        latest = qos.QoSProfile(depth=2, reliability=qos.ReliabilityPolicy.BEST_EFFORT)
        bridge.subscribe(String, "/flood", latest, busy, raw=False)
        twists = Inbox()
        # keep-last 2: a Twist that is not taken before the next two is overwritten
        bridge.subscribe(Twist, "/cmd_vel", 2, twists.put, raw=False, real_time=True)
        flood = talker.publisher("/flood", String, latest)
        cmd_vel = talker.publisher("/cmd_vel", Twist, 10)

        def matched() -> bool:
            return (flood.get_subscription_count() > 0
                    and cmd_vel.get_subscription_count() > 0)

        assert wait_until(matched, 20), "the subscriptions never matched"
        for _ in range(200):  # until the flooded topic's callback is stuck in its first message
            flood.publish(String(data="x" * 2500))
            if held.wait(0.05):
                break
        assert held.is_set(), "the flooded topic's callback never ran"

        for i in range(TWISTS):  # the flood goes on between the Twists
            for _ in range(50):
                flood.publish(String(data="x" * 2500))
            cmd_vel.publish(Twist(linear=Vector3(x=float(i)), angular=Vector3(z=-float(i))))
            assert twists.wait_count(i + 1, 20), (
                f"Twist {i} was not taken while the flooded topic's callback was busy "
                f"({len(twists.items)} of {i + 1} taken)")
        assert not release.is_set() and bulk.items == []  # all of it while the flood was stuck
        assert [(t.linear.x, t.angular.z) for t in twists.items] == [
            (float(i), -float(i)) for i in range(TWISTS)]
        assert all(t.linear.y == t.linear.z == t.angular.x == t.angular.y == 0.0
                   for t in twists.items)

        release.set()  # and the flooded topic is taken again afterwards
        flood.publish(String(data="after"))
        assert bulk.wait_for(lambda got: "after" in got, 20), bulk.items[-3:]
    finally:
        release.set()
        bridge.close()


def test_a_bridge_takes_its_real_time_topic_on_a_node_of_its_own(engines, domain, ros_side):
    """A peer pair carrying a Twist of priority real_time beside a topic of the default
    priority: the Twist crosses whole, and the graph shows who takes what."""
    da, db, flood_port, twist_port = domain(), domain(), free_port(), free_port()
    topics = (f"{{topic: /flood, type: std_msgs/msg/String, port: {flood_port}, "
              f"direction: %s}}, {{topic: /cmd_vel, type: geometry_msgs/msg/Twist, "
              f"port: {twist_port}, priority: real_time, direction: %s}}")
    engines(f"""
bridge: {{name: rt_a, role: peer, peer: 127.0.0.1, listen: 127.0.0.1}}
topics: [{topics % ('transmit', 'transmit')}]""", da)
    engines(f"""
bridge: {{name: rt_b, role: peer, peer: 127.0.0.1, listen: 127.0.0.1}}
topics: [{topics % ('receive', 'receive')}]""", db)
    talker = ros_side(da, "talker")
    cmd_vel, flood = (talker.publisher("/cmd_vel", Twist), talker.publisher("/flood", String))
    listener = ros_side(db, "listener")
    twists, floods = listener.listen("/cmd_vel", Twist), listener.listen("/flood", String)

    def twist(i: int | None) -> Twist:
        i = -1 if i is None else i
        return Twist(linear=Vector3(x=float(i), y=0.5, z=-0.5), angular=Vector3(z=float(i) / 4))

    got = cross(cmd_vel, twists, twist, lambda t: t.linear.x == -1.0, 5)
    assert [(t.linear.x, t.linear.y, t.linear.z, t.angular.x, t.angular.y, t.angular.z)
            for t in got] == [(float(i), 0.5, -0.5, 0.0, 0.0, i / 4) for i in range(5)]
    assert [m.data for m in cross(flood, floods, lambda i: String(data=f"f{i}"),
                                  lambda m: m.data == "fNone", 3)] == ["f0", "f1", "f2"]

    def takers(topic: str) -> set[str]:
        return {info.node_name for info in talker.ros.node.get_subscriptions_info_by_topic(topic)}

    assert takers("/cmd_vel") == {"rosgate_rt_a_real_time"}
    assert takers("/flood") == {"rosgate_rt_a"}
