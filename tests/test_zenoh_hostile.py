"""Bad input on a bus: whatever a zenoh session puts on a bridge's keys is dropped and counted by
reason, nothing bad is published, and good frames keep flowing. An engine in this process (its
counters are read directly) and a plain zenoh session throwing frames at it through a router."""

from __future__ import annotations

import json
import time

import pytest
import zenoh
from conftest import wait_until
from rclpy.serialization import serialize_message
from std_msgs.msg import String
from test_zenoh_fleet import Router

from rosgate.wire import envelope
from rosgate.wire.envelope import topic_id_for


@pytest.fixture
def router():
    r = Router()
    yield r
    r.stop()


@pytest.fixture
def plain(router):
    session = zenoh.open(zenoh.Config.from_json5(json.dumps({
        "mode": "client", "connect": {"endpoints": [router.endpoint]},
        "scouting": {"multicast": {"enabled": False}}})))
    yield session
    session.close()


def frame(key: str, payload: bytes, flags: int = 0, seq: int = 1,
          topic: str | None = None) -> bytes:
    header = envelope.pack(flags, topic_id_for(topic or key), 7, seq, time.time_ns())
    return header + payload


def test_bad_frames_on_a_bus_are_counted_by_reason_and_good_ones_still_flow(
        router, plain, engines, domain, ros_side):
    d = domain()
    base = engines(f"""
bridge: {{name: base, role: peer, defaults: {{transport: zenoh}}}}
plugins: {{zenoh: {{mode: client, connect: [{router.endpoint}]}}}}
topics:
  - {{topic: /r1/cmd, type: std_msgs/msg/String, direction: receive, remote: fleet/r1/cmd}}
  - {{topic: '/{{robot}}/scan', type: std_msgs/msg/String, direction: receive,
      remote: 'fleet/{{robot}}/scan'}}
  - {{topic: /raw, type: std_msgs/msg/String, direction: receive, framing: none}}
services:
  - {{service: /reset, type: std_srvs/srv/Trigger, direction: receive, remote: fleet/r1/reset,
      timeout: 1}}
""", d)
    side = ros_side(d, "base")
    cmd, raw = side.listen("/r1/cmd", String), side.listen("/raw", String)
    good = serialize_message(String(data="good"))
    put = lambda key, data: plain.put(key, data)
    # the subscriptions take a moment to spread: until a good frame crosses
    deadline = time.monotonic() + 20
    seq = 0
    while not cmd.wait_count(1, 0.2):
        assert time.monotonic() < deadline
        seq += 1
        put("fleet/r1/cmd", frame("fleet/r1/cmd", good, seq=seq))
    while not raw.wait_count(1, 0.2):
        assert time.monotonic() < deadline
        put("raw", good)
    time.sleep(0.3)  # the warm-up frames still on their way
    routes = {r.label: r for r in base.routes()}
    before = {label: dict(r.counters.drops) for label, r in routes.items()}
    received = len(cmd.items), len(raw.items)

    bad_cdr = b"\x00\x01\x00\x00\xff\xff\xff\x7f"  # a string longer than the frame
    put("fleet/r1/cmd", b"RG")                                             # truncated
    put("fleet/r1/cmd", b"XX" + bytes(40))                                  # foreign
    put("fleet/r1/cmd", frame("fleet/r1/cmd", good, seq=seq + 1, topic="fleet/r2/cmd"))  # moved
    put("fleet/r1/cmd", frame("fleet/r1/cmd", good, envelope.FLAG_REQUEST, seq + 2))  # a call?
    put("fleet/r1/cmd", frame("fleet/r1/cmd", bad_cdr, seq=seq + 3))        # not a String
    put("fleet/r1/cmd", frame("fleet/r1/cmd", good, seq=seq))               # replayed
    put("raw", bad_cdr)                                                     # bare, not a String
    put("fleet/robot-9/scan", frame("fleet/robot-9/scan", good))            # not a ROS name
    replies: list = []
    plain.get("fleet/r1/reset", zenoh.handlers.Callback(replies.append, indirect=False),
              payload=b"RG", timeout=0.5)                                  # a truncated call
    put("fleet/r1/cmd", frame("fleet/r1/cmd", good, seq=seq + 10))          # and a good one
    put("raw", good)

    assert cmd.wait_count(received[0] + 1, 10) and raw.wait_count(received[1] + 1, 10)
    expected = {
        "/r1/cmd": {"truncated_frame": 1, "foreign_frame": 1, "unexpected_frame": 2,
                    "decode_error": 1, "duplicate": 1},
        "/raw": {"decode_error": 1},
        "/reset": {"truncated_frame": 1},
    }

    def drops() -> dict:
        return {label: {k: v - before[label].get(k, 0) for k, v in r.counters.drops.items()
                        if v != before[label].get(k, 0)} for label, r in routes.items()}

    assert wait_until(lambda: drops() == expected, 10), drops()
    assert wait_until(lambda: base.link_drops.get("unknown_topic") == 1, 5), base.link_drops
    assert [m.data for m in cmd.items[received[0]:]] == ["good"]
    assert [m.data for m in raw.items[received[1]:]] == ["good"]
    assert side.ros.node.count_publishers("/robot_9/scan") == 0
    assert not any("robot-9" in r.label for r in base.routes())
    assert replies == [] or all(r.ok is None for r in replies)


def test_a_sealed_topic_crosses_and_a_frame_sealed_with_another_key_is_refused(
        router, plain, engines, domain, ros_side, tmp_path):
    from rosgate_crypto_nacl import NaclCipher
    from rosgate_testing import write_key

    write_key(tmp_path / "fleet.key", NaclCipher.generate_key())
    write_key(tmp_path / "other.key", NaclCipher.generate_key())
    def bridge_file(name: str, key: str, direction: str) -> str:
        return (f"bridge: {{name: {name}, role: peer, defaults: {{transport: zenoh, "
                f"cipher: nacl}}}}\nplugins: {{zenoh: {{mode: client, connect: "
                f"[{router.endpoint}]}}, nacl: {{key_file: {key}}}}}\ntopics: [{{topic: /t, "
                f"type: std_msgs/msg/String, direction: {direction}, remote: s/t}}]\n")

    da, db, dc = domain(), domain(), domain()
    engines(bridge_file("a", "fleet.key", "transmit"), da, tmp_path)
    b = engines(bridge_file("b", "fleet.key", "receive"), db, tmp_path)
    engines(bridge_file("c", "other.key", "transmit"), dc, tmp_path)
    inbox = ros_side(db, "b").listen("/t", String)
    good, bad = ros_side(da, "a").publisher("/t", String), ros_side(dc, "c").publisher("/t", String)
    deadline = time.monotonic() + 20
    while not inbox.wait_count(1, 0.2):
        assert time.monotonic() < deadline
        good.publish(String(data="sealed"))
    route = b.routes()[0]
    deadline = time.monotonic() + 20
    while not route.counters.drops.get("auth_failed"):
        assert time.monotonic() < deadline
        bad.publish(String(data="forged"))
        time.sleep(0.1)
    assert {m.data for m in inbox.items} == {"sealed"}
