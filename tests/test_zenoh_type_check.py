"""The type check over zenoh: each bus entry's sending side announces its type (name and RIHS01
hash) on the entry's key, at once and again every few seconds; a receiving side whose type
differs publishes nothing, counts ``type_mismatch`` and says so once a minute. And what else a
key carries besides messages: compressed ones. Real ``rosgate router`` and ``rosgate run``
processes, real rclpy on both sides, each in a DDS domain of its own.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Any

import pytest
from conftest import wait_until
from geometry_msgs.msg import Point, Vector3
from rosgate_top.client import StatusClient
from std_srvs.srv import SetBool, Trigger
from test_services import DEEP
from test_type_check_and_qos import POINT_HASH, VECTOR3_HASH
from test_zenoh_fleet import Router, zenoh_plugin

from rosgate import runtime


@pytest.fixture
def router():
    r = Router()
    yield r
    r.stop()


@pytest.fixture
def runtime_dir(monkeypatch):
    """A socket folder of the test's own, which the bridge processes inherit."""
    with tempfile.TemporaryDirectory(prefix="rg", dir="/tmp") as folder:
        monkeypatch.setenv(runtime.RUNTIME_VARIABLE, str(Path(folder) / "run"))
        yield


def peer_file(tmp: Path, name: str, router: Router, entries: str) -> Path:
    path = tmp / f"{name}.yaml"
    path.write_text(f"bridge: {{name: {name}, role: peer, defaults: {{transport: zenoh}}}}\n"
                    f"{zenoh_plugin(router)}{entries}")
    return path


def counters(bridge_name: str, entry: str) -> dict[str, Any]:
    with StatusClient(bridge_name) as ask:
        return next(e for e in ask.status()["entries"] if e["name"] == entry)


@pytest.mark.parametrize("receiver_first", [True, False], ids=["receiver first",
                                                              "sender first"])
def test_point_sent_as_vector3_over_zenoh_is_refused_counted_and_said(
        tmp_path, router, bridge, domain, ros_side, runtime_dir, receiver_first):
    """Receiver first: the sender's first announcement, before its first message, reaches it.
    Sender first: the receiver hears one of its re-announcements (every 2 s)."""
    da, db = domain(), domain()
    start = {
        "b": lambda: bridge(peer_file(tmp_path, "b", router, "topics: [{topic: /mm, type: "
                                      "geometry_msgs/msg/Vector3, direction: receive, "
                                      "remote: fleet/mm}]\n"), db),
        "a": lambda: bridge(peer_file(tmp_path, "a", router, "topics: [{topic: /mm, type: "
                                      "geometry_msgs/msg/Point, direction: transmit, "
                                      "remote: fleet/mm}]\n"), da)}
    first, second = ("b", "a") if receiver_first else ("a", "b")
    started = {first: start[first]()}
    started[second] = start[second]()
    a, b = started["a"], started["b"]
    if not receiver_first:  # before anything is published: it heard a re-announcement
        assert b.wait_log("/mm: refused, the far side's type", 10), b.log
    inbox = ros_side(db, "b").listen("/mm", Vector3)
    talker = ros_side(da, "a").publisher("/mm", Point)
    deadline = time.monotonic() + 20
    while counters("b", "/mm")["drops"].get("type_mismatch", 0) < 20:
        assert time.monotonic() < deadline, counters("b", "/mm")
        talker.publish(Point(x=1.0, y=2.0, z=3.0))
        time.sleep(0.02)  # paces the talker; the loop waits on the counter
    got = counters("b", "/mm")
    assert got["received"] == 0 and set(got["drops"]) == {"type_mismatch"}
    assert counters("a", "/mm")["sent"] >= 20
    assert inbox.items == []
    sentence = (f"/mm: refused, the far side's type is geometry_msgs/msg/Point ({POINT_HASH}) "
                f"and this side's is geometry_msgs/msg/Vector3 ({VECTOR3_HASH}), so its frames "
                "are dropped")
    assert b.wait_log(sentence, 5)
    assert b.log.count("refused, the far side's type") == 1  # once a minute, not per frame
    assert "refused" not in a.log


def test_a_service_of_another_type_over_zenoh_is_answered_as_a_failure_never_served(
        tmp_path, router, bridge, domain, ros_side, runtime_dir):
    """The caller's bridge announces its type to the serving bridge (a query of its own); the
    server refuses calls of another type, and says why in the answer."""
    da, db = domain(), domain()
    b = bridge(peer_file(tmp_path, "b", router, "services: [{service: /set, type: "
                         "std_srvs/srv/SetBool, direction: receive, remote: fleet/set, "
                         "timeout: 2}]\n"), db)
    bridge(peer_file(tmp_path, "a", router, "services: [{service: /set, type: "
                     "std_srvs/srv/Trigger, direction: transmit, remote: fleet/set, "
                     "timeout: 2}]\n"), da)
    served: list[Any] = []
    ros_side(db, "b").ros.node.create_service(
        SetBool, "/set", lambda q, a: served.append(q) or a, qos_profile=DEEP)
    caller = ros_side(da, "a").ros.node.create_client(Trigger, "/set")
    assert caller.wait_for_service(timeout_sec=15)
    assert b.wait_log("/set: refused, the far side's type is std_srvs/srv/Trigger", 10)
    future = caller.call_async(Trigger.Request())
    assert wait_until(future.done, 5)
    answer = future.result()
    assert not answer.success
    assert answer.message.startswith("rosgate: /set: refused, the far side's type is "
                                     "std_srvs/srv/Trigger (RIHS01_")
    assert served == []
    assert counters("b", "/set")["drops"] == {"type_mismatch": 1}


def test_an_older_sender_that_says_no_hash_is_accepted_and_said_once(
        tmp_path, router, bridge, domain, ros_side, runtime_dir):
    """A zenoh session that writes rosgate's envelopes on the key as an older rosgate would:
    its announcements name the type without a hash. Its messages are published, and the
    unchecked type is said once."""
    import zenoh
    from rclpy.serialization import serialize_message

    from rosgate.wire import envelope

    d = domain()
    b = bridge(peer_file(tmp_path, "b", router, "topics: [{topic: /mm, type: "
                         "geometry_msgs/msg/Vector3, direction: receive, remote: fleet/mm}]\n"), d)
    inbox = ros_side(d, "b").listen("/mm", Vector3)
    config = zenoh.Config()
    config.insert_json5("mode", '"client"')
    config.insert_json5("connect/endpoints", f'["{router.endpoint}"]')
    topic_id = envelope.topic_id_for("fleet/mm")
    with zenoh.open(config) as session:
        publisher = session.declare_publisher("fleet/mm")
        frame = lambda flags, seq, body: envelope.pack(flags, topic_id, 7, seq, time.time_ns()) \
            + body
        seq = 0
        while not inbox.wait_count(1, 0.2):  # until the subscription is matched
            seq += 1
            assert seq < 100, counters("b", "/mm")
            publisher.put(frame(envelope.FLAG_ANNOUNCE, seq,
                                b'{"type":"geometry_msgs/msg/Vector3"}'))
            publisher.put(frame(0, seq, serialize_message(Vector3(x=-1.0))))
        for i in range(5):
            publisher.put(frame(envelope.FLAG_ANNOUNCE, seq + 1 + i,
                                b'{"type":"geometry_msgs/msg/Vector3"}'))
            publisher.put(frame(0, seq + 1 + i, serialize_message(Vector3(x=float(i)))))
        assert inbox.wait_for(lambda items: [m.x for m in items][-5:] == [0.0, 1.0, 2.0, 3.0, 4.0],
                              10), inbox.items
    assert counters("b", "/mm")["drops"] == {}
    assert b.log.count("/mm: the far side gives no type hash (an older rosgate, or a ROS before "
                       "Iron): its type is not checked") == 1


def test_a_compressed_topic_crosses_zenoh(tmp_path, router, bridge, domain, ros_side,
                                          runtime_dir):
    """Beside messages and announcements, a key carries messages its sender compressed (the
    envelope says so per frame): they are published as they were sent."""
    from conftest import cross
    from std_msgs.msg import String

    da, db = domain(), domain()
    bridge(peer_file(tmp_path, "b", router, "topics: [{topic: /log, type: std_msgs/msg/String, "
                     "direction: receive, remote: fleet/log}]\n"), db)
    bridge(peer_file(tmp_path, "a", router, "topics: [{topic: /log, type: std_msgs/msg/String, "
                     "direction: transmit, remote: fleet/log, compression: zstd}]\n"), da)
    text = lambda i: String(data="warm" if i is None else f"{i}:" + "all quiet here. " * 500)
    got = cross(ros_side(da, "a").publisher("/log", String), ros_side(db, "b").listen(
        "/log", String), text, lambda m: m.data == "warm", 5)
    assert [m.data for m in got] == [text(i).data for i in range(5)]
    assert counters("b", "/log")["drops"] == {}
    assert counters("a", "/log")["bytes_sent"] < 5 * 8000 / 10  # they went compressed
