"""Pattern entries against real bridges and real rclpy nodes, each side in its own domain: what
appears under a pattern after both bridges are up crosses, field by field, within 1 s; what is
outside it or denied never appears on the far side; a server's policy judges found names as it
judges listed ones; a name whose publishers all went is gone after the grace."""

from __future__ import annotations

import time

from conftest import free_port, wait_until
from std_msgs.msg import String


def server_and_client(engines, domain, topics: str, rules: str = "",
                      bridge: str = "", ) -> tuple:
    ds, dc, port = domain(), domain(), free_port()
    server = engines(f"""
bridge: {{name: base, role: server, server: '127.0.0.1:{port}'}}
{rules}""", ds)
    client = engines(f"""
bridge: {{name: robot1, role: client, server: '127.0.0.1:{port}'{bridge}}}
topics:
{topics}""", dc)
    return server, client, ds, dc


def graph_has(node, name: str) -> bool:
    return any(n == name for n, _ in node.get_topic_names_and_types())


def test_a_topic_published_after_both_bridges_are_up_crosses(engines, domain, ros_side):
    server, client, ds, dc = server_and_client(
        engines, domain, "  - {topic: /r/**, direction: transmit, deny: [/r/secret/**]}")
    assert wait_until(lambda: client.role.connected.is_set(), 20)
    robot, base = ros_side(dc, "robot"), ros_side(ds, "base")
    inbox = base.listen("/r/deep/chat", String)
    talker = robot.publisher("/r/deep/chat", String)
    start = time.monotonic()
    while not inbox.wait_count(1, 0.05):
        talker.publish(String(data="hello"))
        assert time.monotonic() - start < 10, (__import__("rosgate.discovery").discovery.publishers(client.role.discovery.node), client.role.discovery.status(), client.role.discovery._thread.is_alive(), client.role.found, client.role.routes)
    print("crossed after", time.monotonic() - start)
    assert inbox.items[0].data == "hello"
