"""Per-topic behaviour: stale warnings, rate limits, QoS, dedicated ports."""

from __future__ import annotations

import time

from conftest import cross, free_port
from std_msgs.msg import String

from rosgate.rostypes import is_reliable, qos_profile


def text(i: int | None) -> String:
    return String(data="warmup" if i is None else f"m{i}")


def is_warmup(m: String) -> bool:
    return m.data == "warmup"


def pair(engines, domain, extra_bridge: str = "", topic_extra: str = "", transport: str = "udp"):
    da, db, port = domain(), domain(), free_port()
    topic = (f"topic: /t, type: std_msgs/msg/String, port: {port}, transport: {transport}"
             f"{topic_extra}")
    a = engines(f"""
bridge: {{name: a, role: peer, peer: 127.0.0.1, listen: 127.0.0.1}}
topics: [{{{topic}, direction: transmit}}]""", da)
    b = engines(f"""
bridge: {{name: b, role: peer, peer: 127.0.0.1, listen: 127.0.0.1{extra_bridge}}}
topics: [{{{topic}, direction: receive}}]""", db)
    return a, b, da, db


def test_stale_warnings_are_capped_and_reset_when_data_returns(engines, domain, ros_side, logs):
    stale = "no data for"
    a, b, da, db = pair(engines, domain, ", stale_after: 0.6, stale_warnings: 2")
    inbox = ros_side(db, "listener").listen("/t", String)
    talker = ros_side(da, "talker").publisher("/t", String)
    cross(talker, inbox, text, is_warmup, 1)
    # (a loaded machine may take longer than stale_after to carry the first message: warnings
    # said before it are not this test's, so the count starts here)
    mark = len(logs.having(stale))
    # silence: exactly two warnings, then quiet for as long again as both took
    assert logs.wait(stale, mark + 2, 5)
    assert not logs.wait(stale, mark + 3, 2.0)
    assert [m.split(": ", 1)[1].split(" (")[1] for m in logs.having(stale)[mark:]] == \
        ["warning 1 of 2)", "warning 2 of 2)"]
    # data returns: the count starts again
    cross(talker, inbox, lambda i: text(None if i is None else 10 + i), is_warmup, 1)
    mark = len(logs.having(stale))
    assert logs.wait(stale, mark + 1, 5)
    assert logs.having(stale)[mark].endswith("(warning 1 of 2)")


def test_max_rate_drops_and_counts_the_excess(engines, domain, ros_side):
    a, b, da, db = pair(engines, domain, topic_extra=", max_rate: 5")
    inbox = ros_side(db, "listener").listen("/t", String)
    talker = ros_side(da, "talker").publisher("/t", String)
    cross(talker, inbox, text, is_warmup, 0)
    route = a.routes()[0]
    # warm-up messages still on their way would land after the snapshot: let them settle first
    settled = lambda: route.counters.sent + route.counters.drops["rate_limit"]
    last, quiet_since = settled(), time.monotonic()
    while time.monotonic() - quiet_since < 0.5:
        time.sleep(0.05)
        if settled() != last:
            last, quiet_since = settled(), time.monotonic()
    before_sent, before_limited = route.counters.sent, route.counters.drops["rate_limit"]
    start = time.monotonic()
    for i in range(60):
        talker.publish(text(i))
        time.sleep(0.01)  # pacing: 100 Hz offered against a 5 Hz limit
    elapsed = time.monotonic() - start
    deadline = time.monotonic() + 5
    while (route.counters.sent + route.counters.drops["rate_limit"]
           - before_sent - before_limited) < 60:
        assert time.monotonic() < deadline, route.counters
        time.sleep(0.02)
    sent = route.counters.sent - before_sent
    assert 1 <= sent <= int(elapsed * 5) + 1
    assert route.counters.drops["rate_limit"] - before_limited == 60 - sent


def test_which_qos_forms_are_reliable_and_so_queue_while_a_link_is_down():
    assert [is_reliable(q) for q in (10, "default", "system_default", "best_available",
                                     {"depth": 3}, {"reliability": "reliable"})] == [True] * 6
    assert [is_reliable(q) for q in ("sensor_data", {"reliability": "best_effort"})] == [False] * 2


def test_qos_forms_map_to_profiles():
    from rclpy import qos

    assert qos_profile(7).depth == 7
    assert qos_profile("sensor_data") == qos.qos_profile_sensor_data
    p = qos_profile({"reliability": "best_effort", "durability": "transient_local",
                     "history": "keep_all", "depth": 3})
    assert (p.reliability, p.durability, p.history, p.depth) == (
        qos.ReliabilityPolicy.BEST_EFFORT, qos.DurabilityPolicy.TRANSIENT_LOCAL,
        qos.HistoryPolicy.KEEP_ALL, 3)


def test_client_server_stream_topics_on_ports_of_their_own_both_ways(engines, domain, ros_side,
                                                                      stream_kind):
    ds, dc = domain(), domain()
    k = stream_kind
    main, up, down = k.port(), k.port(), k.port()
    engines(f"""
bridge: {{name: base, role: server, server: '{k.address(main)}', main_line: {k.name}}}
plugins: {k.plugins}""", ds)
    client = engines(f"""
bridge: {{name: robot1, role: client, server: '{k.address(main)}', main_line: {k.name}}}
plugins: {k.plugins}
topics:
  - {{topic: /up, type: std_msgs/msg/String, direction: transmit, transport: {k.name}, port: {up}}}
  - {{topic: /down, type: std_msgs/msg/String, direction: receive, transport: {k.name},
      port: {down}}}
""", dc)
    robot, base = ros_side(dc, "robot"), ros_side(ds, "base")
    got = cross(robot.publisher("/up", String), base.listen("/up", String), text, is_warmup, 20)
    assert [m.data for m in got] == [f"m{i}" for i in range(20)]
    got = cross(base.publisher("/down", String), robot.listen("/down", String), text, is_warmup, 20)
    assert [m.data for m in got] == [f"m{i}" for i in range(20)]
    assert all(not r.counters.drops for r in client.routes())
