"""How a status becomes diagnostic statuses: the level, the message and the values of each entry,
link and peer, without ROS (the published array: tests/test_diagnostics.py)."""

from __future__ import annotations

from typing import Any

from rosgate_diagnostics import ERROR, OK, WARN, assess


def entry(**changes: Any) -> dict[str, Any]:
    e = {"kind": "topic", "name": "/scan", "direction": "transmit", "peer": "base",
         "type": "sensor_msgs/msg/LaserScan", "transport": "udp", "port": None, "sent": 10,
         "bytes_sent": 1000, "received": 0, "bytes_received": 0, "lost": 0, "drops": {},
         "queue": 0, "stale": None, "silence": None, "latency": None, "refused": None}
    return {**e, **changes}


def link(**changes: Any) -> dict[str, Any]:
    return {"name": "udp", "up": True, "frames_out": 10, "bytes_out": 1000, "packets_out": 10,
            "frames_in": 0, "bytes_in": 0, "packets_in": 0, "queue": 0, "bandwidth": None,
            "rtt": None, **changes}


def status(entries, links=(), peers=({"name": "base", "up": True},), time=10.0):
    return {"bridge": "robot1", "time": time, "entries": list(entries), "links": list(links),
            "peers": list(peers)}


def test_a_flowing_topic_is_ok_with_its_counters():
    [(level, name, message, values)] = assess(status([entry()], peers=()), None)
    assert (level, name, message) == (OK, "topic /scan (to base)", "ok")
    assert values == [("direction", "transmit"), ("peer", "base"),
                      ("type", "sensor_msgs/msg/LaserScan"), ("transport", "udp"), ("sent", 10),
                      ("bytes_sent", 1000), ("received", 0), ("bytes_received", 0), ("lost", 0),
                      ("queue", 0)]


def test_the_worst_reason_wins_and_is_said():
    entries = [entry(name="/a", refused="policy", peer="other"),
               entry(name="/b", peer="down1"),
               entry(name="/c", direction="receive", stale=True, silence=7.4),
               entry(name="/d", drops={"rate_limit": 3})]
    peers = [{"name": "down1", "up": False}, {"name": "base", "up": True},
             {"name": "new", "up": None}]
    found = {name: (level, message) for level, name, message, _ in
             assess(status(entries, peers=peers), None)}
    assert found == {
        "topic /a (to other)": (ERROR, "refused by other: policy"),
        "topic /b (to down1)": (ERROR, "peer down1 is down"),
        "topic /c (from base)": (WARN, "stale: no message for 7 s"),
        "topic /d (to base)": (WARN, "dropped rate_limit=3"),
        "peer down1": (ERROR, "down"), "peer base": (OK, "up"), "peer new": (OK, "unknown")}


def test_drops_warn_only_while_they_grow():
    before = status([entry(drops={"rate_limit": 3, "queue_full": 1})])
    grown = status([entry(drops={"rate_limit": 5, "queue_full": 1})], time=11.0)
    level, _, message, values = assess(grown, before)[0]
    assert (level, message) == (WARN, "dropped rate_limit=2")
    assert values[-2:] == [("drops.queue_full", 1), ("drops.rate_limit", 5)]
    level, _, message, _ = assess(grown, grown)[0]
    assert (level, message) == (OK, "ok")


def test_a_receiving_topic_says_its_silence():
    _, name, _, values = assess(status([entry(direction="receive", silence=2.46)]), None)[0]
    assert name == "topic /scan (from base)"
    assert values[-1] == ("silence", "2.5")


def test_a_link_is_down_over_budget_or_up():
    before = status([], [link(), link(name="tcp", bandwidth=8000.0)])
    now = status([], [link(up=False), link(name="tcp", bandwidth=8000.0, bytes_out=3000)],
                 time=11.0)
    found = assess(now, before)
    assert [(level, name, message) for level, name, message, _ in found[:2]] == [
        (ERROR, "link udp", "down"),
        (WARN, "link tcp", "over budget: 16000 of 8000 bit/s")]
    assert found[1][3] == [("up", True), ("frames_out", 10), ("bytes_out", 3000),
                           ("frames_in", 0), ("bytes_in", 0), ("queue", 0), ("bandwidth", 8000.0)]
    # the first status has no rate yet: a link that is up is ok
    assert assess(now, None)[1][:3] == (OK, "link tcp", "up")
