"""What the two sides of an entry agree on before anything is published: the type (name and
RIHS01 hash: a mismatch is refused, counted and said), and, for a topic without a qos, the QoS
its publishers use (a latched topic reaches a late subscriber on the far side)."""

from __future__ import annotations

import logging
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import Inbox, free_port, wait_until
from geometry_msgs.msg import Point
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rosgate_top.client import StatusClient
from std_msgs.msg import String

from rosgate import runtime
from rosgate.announce import HOLD_FOR, Identity, TypeCheck, parse_body, qos_of, read
from rosgate.router import Router

LATCHED = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                     reliability=ReliabilityPolicy.RELIABLE)
POINT_HASH = "RIHS01_6963084842a9b04494d6b2941d11444708d892da2f4b09843b9c43f42a7f6881"
VECTOR3_HASH = "RIHS01_cc12fe83e4c02719f1ce8070bfd14aecd40f75a96696a67a2a1f37f7dbb0765d"
OTHER_VERSION = "RIHS01_" + "5e" * 32


def latched_publishers(side: Any, topic: str, texts: list[str]) -> list[Any]:
    """One transient_local publisher per text, each having published its text once."""
    publishers = []
    for text in texts:
        publisher = side.publisher(topic, String, LATCHED)
        publisher.publish(String(data=text))
        publishers.append(publisher)
    return publishers


def late_listener(side: Any, topic: str) -> Inbox:
    inbox = Inbox()
    side.ros.subscribe(String, topic, QoSProfile(depth=10, durability=DurabilityPolicy
                                                 .TRANSIENT_LOCAL), inbox.put, raw=False)
    return inbox


def route(engine: Any, label: str) -> Any:
    return next(r for r in engine.routes() if r.label.startswith(label))


def publisher_durability(side: Any, topic: str, bridge: str) -> set[Any]:
    """The durability of the publishers ``bridge`` has on ``topic``, as ``side`` sees them."""
    return {info.qos_profile.durability for info in side.ros.node.get_publishers_info_by_topic(
        topic) if info.node_name == f"rosgate_{bridge}"}


# -- QoS found from the publishers -----------------------------------------------------------
def test_a_latched_topic_with_two_publishers_reaches_a_late_subscriber_client_server(
        engines, domain, ros_side):
    """No qos in either file: each side's bridge finds transient_local from the publishers it
    discovers, the far side publishes so too, and a subscriber that joins after everything
    crossed gets both publishers' messages, both ways."""
    ds, dc, main = domain(), domain(), free_port()
    base, robot = ros_side(ds, "base"), ros_side(dc, "robot")
    keep = [latched_publishers(robot, "/up_static", ["robot frame a", "robot frame b"]),
            latched_publishers(base, "/down_static", ["base frame a", "base frame b"])]
    server = engines(f"bridge: {{name: base, role: server, server: '127.0.0.1:{main}'}}", ds)
    client = engines(f"""
bridge: {{name: robot1, role: client, server: '127.0.0.1:{main}'}}
topics:
  - {{topic: /up_static, type: std_msgs/msg/String, direction: transmit}}
  - {{topic: /down_static, type: std_msgs/msg/String, direction: receive}}
""", dc)
    assert wait_until(lambda: len(server.routes()) == 2 and len(client.routes()) == 2)
    up, down = route(server, "/up_static"), route(client, "/down_static")
    # everything crossed before anyone listens on the far sides
    assert wait_until(lambda: up.counters.received >= 2 and down.counters.received >= 2, 20), \
        (up.counters, down.counters)
    for receiving in (up, down):
        assert receiving.qos_in_use == {"reliability": "reliable",
                                        "durability": "transient_local", "depth": 10}
    got_up, got_down = late_listener(base, "/up_static"), late_listener(robot, "/down_static")
    assert got_up.wait_for(lambda items: {m.data for m in items} ==
                           {"robot frame a", "robot frame b"}, 10), got_up.items
    assert got_down.wait_for(lambda items: {m.data for m in items} ==
                             {"base frame a", "base frame b"}, 10), got_down.items
    assert wait_until(lambda: publisher_durability(base, "/up_static", "base") ==
                      {DurabilityPolicy.TRANSIENT_LOCAL})
    assert not up.counters.drops and not down.counters.drops
    del keep


def test_a_latched_topic_reaches_a_late_subscriber_over_a_peer_link_and_follows_a_change(
        engines, domain, ros_side):
    da, db, port = domain(), domain(), free_port()
    entry = f"topic: /static, type: std_msgs/msg/String, port: {port}"
    b = engines(f"""bridge: {{name: b, role: peer, peer: 127.0.0.1, listen: 127.0.0.1}}
topics: [{{{entry}, direction: receive}}]""", db)
    side_a, side_b = ros_side(da, "a"), ros_side(db, "b")
    keep = latched_publishers(side_a, "/static", ["peer frame a", "peer frame b"])
    a = engines(f"""bridge: {{name: a, role: peer, peer: 127.0.0.1, listen: 127.0.0.1}}
topics: [{{{entry}, direction: transmit}}]""", da)
    receiving = route(b, "/static")
    assert wait_until(lambda: receiving.counters.received >= 2, 20), receiving.counters
    inbox = late_listener(side_b, "/static")
    assert inbox.wait_for(lambda items: {m.data for m in items} ==
                          {"peer frame a", "peer frame b"}, 10), inbox.items
    assert wait_until(lambda: publisher_durability(side_b, "/static", "b") ==
                      {DurabilityPolicy.TRANSIENT_LOCAL})
    # a volatile publisher joins: the topic is latched no longer, on both sides
    keep.append(side_a.publisher("/static", String, 10))
    assert wait_until(lambda: route(a, "/static").qos_found["durability"] == "volatile", 10)
    assert wait_until(lambda: publisher_durability(side_b, "/static", "b") ==
                      {DurabilityPolicy.VOLATILE}, 10)
    assert receiving.qos_in_use == {"reliability": "reliable", "durability": "volatile",
                                    "depth": 10}


def test_a_files_qos_wins_over_the_one_found(engines, domain, ros_side):
    da, db, port = domain(), domain(), free_port()
    entry = f"topic: /static, type: std_msgs/msg/String, port: {port}"
    b = engines(f"""bridge: {{name: b, role: peer, peer: 127.0.0.1, listen: 127.0.0.1}}
topics: [{{{entry}, direction: receive, qos: {{durability: volatile, depth: 5}}}}]""", db)
    side_a, side_b = ros_side(da, "a"), ros_side(db, "b")
    keep = latched_publishers(side_a, "/static", ["one", "two"])
    engines(f"""bridge: {{name: a, role: peer, peer: 127.0.0.1, listen: 127.0.0.1}}
topics: [{{{entry}, direction: transmit}}]""", da)
    receiving = route(b, "/static")
    assert wait_until(lambda: receiving.counters.received >= 2, 20), receiving.counters
    assert receiving.qos_in_use is None
    assert wait_until(lambda: publisher_durability(side_b, "/static", "b") ==
                      {DurabilityPolicy.VOLATILE})
    del keep


# -- the type check ----------------------------------------------------------------------------
def test_point_sent_as_vector3_is_refused_counted_and_said_once_a_minute(
        engines, domain, ros_side, logs):
    da, db, port = domain(), domain(), free_port()
    # the receiver first: the sender's first announcement, at its start, reaches it
    b = engines(f"""bridge: {{name: b, role: peer, peer: 127.0.0.1, listen: 127.0.0.1}}
topics: [{{topic: /mm, type: geometry_msgs/msg/Vector3, direction: receive, port: {port}}}]""",
                db)
    engines(f"""bridge: {{name: a, role: peer, peer: 127.0.0.1, listen: 127.0.0.1}}
topics: [{{topic: /mm, type: geometry_msgs/msg/Point, direction: transmit, port: {port}}}]""", da)
    from geometry_msgs.msg import Vector3

    inbox = ros_side(db, "b").listen("/mm", Vector3)
    talker = ros_side(da, "a").publisher("/mm", Point)
    receiving = route(b, "/mm")
    deadline = time.monotonic() + 20
    while receiving.counters.drops["type_mismatch"] < 20:
        assert time.monotonic() < deadline, receiving.counters
        talker.publish(Point(x=1.0, y=2.0, z=3.0))
        time.sleep(0.02)  # paces the talker; the loop waits on the counter
    assert receiving.counters.received == 0 and inbox.items == []
    said = logs.having("refused, the far side's type")
    assert said == [f"/mm: refused, the far side's type is geometry_msgs/msg/Point ({POINT_HASH})"
                    f" and this side's is geometry_msgs/msg/Vector3 ({VECTOR3_HASH}), so its "
                    "frames are dropped"]
    assert set(receiving.counters.drops) == {"type_mismatch"}


class Talker:
    """Publishes ``make(n)`` for n = 1, 2, ... at ``rate`` Hz in a thread of its own."""

    def __init__(self, publisher: Any, make: Callable[[int], Any], rate: float = 50):
        self.publisher, self.make, self.rate = publisher, make, rate
        self.count = 0
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self.stop.wait(1 / self.rate):  # paces the talker; nothing waits on it
            self.count += 1
            self.publisher.publish(self.make(self.count))

    def close(self) -> None:
        self.stop.set()
        self.thread.join(5)


@pytest.fixture
def status_dir(monkeypatch) -> Iterator[Path]:
    """The bridges' status sockets, in a folder of the test's own (AF_UNIX: a short path)."""
    with tempfile.TemporaryDirectory(prefix="rg", dir="/tmp") as folder:
        path = Path(folder) / "run"
        monkeypatch.setenv(runtime.RUNTIME_VARIABLE, str(path))
        yield path


def entry_status(bridge_name: str, topic: str) -> dict[str, Any]:
    with StatusClient(bridge_name) as client:
        status = client.status()
    [entry] = [e for e in status["entries"] if e["name"] == topic]
    return entry


def late_receiver(tmp_path: Path, bridge, domain, ros_side, sent: type, received: type,
                  make: Callable[[int], Any]) -> tuple[Any, Inbox, Talker]:
    """A sending peer (``sent``) whose talker runs, past its young announcements; then a
    receiving peer (``received``) started late, in processes of their own, its listener there
    before it: what the receiver publishes from its first frame on is in the inbox."""
    da, db, port = domain(), domain(), free_port()
    kind = lambda t: f"{t.__module__.split('.')[0]}/msg/{t.__name__}"
    sender = tmp_path / "a.yaml"
    sender.write_text(f"""bridge: {{name: a, role: peer, peer: 127.0.0.1, listen: 127.0.0.1}}
topics: [{{topic: /late, type: {kind(sent)}, direction: transmit, port: {port}}}]""")
    receiver = tmp_path / "b.yaml"
    receiver.write_text(f"""bridge: {{name: b, role: peer, peer: 127.0.0.1, listen: 127.0.0.1}}
topics: [{{topic: /late, type: {kind(received)}, direction: receive, port: {port}}}]""")
    a = bridge(sender, da)
    talker = Talker(ros_side(da, "a").publisher("/late", sent), make)
    inbox = ros_side(db, "b").listen("/late", received)
    # 3 s of messages: the sender is past its young announcements (every 0.5 s for 2 s), its
    # next comes up to 2 s after the receiver starts
    assert wait_until(lambda: entry_status("a", "/late")["sent"] >= 150, 20), a.log
    return bridge(receiver, db), inbox, talker


def test_a_peer_receiver_started_after_its_sender_publishes_nothing_of_another_type(
        tmp_path, bridge, domain, ros_side, status_dir):
    """Its frames wait for the sender's next announcement, then go as type_mismatch."""
    from geometry_msgs.msg import Vector3

    b, inbox, talker = late_receiver(tmp_path, bridge, domain, ros_side, Point, Vector3,
                                     lambda n: Point(x=float(n), y=2.0, z=3.0))
    assert wait_until(lambda: entry_status("b", "/late")["drops"].get("type_mismatch", 0)
                      >= 100, 30), (entry_status("b", "/late"), b.log)
    talker.close()
    entry = entry_status("b", "/late")
    assert entry["received"] == 0 and set(entry["drops"]) == {"type_mismatch"}, entry
    assert inbox.items == []
    assert [line for line in b.log.splitlines() if "refused, the far side's type" in line] \
        and "far side said nothing" not in b.log


def test_a_peer_receiver_started_after_its_sender_loses_nothing_of_its_own_type(
        tmp_path, bridge, domain, ros_side, status_dir):
    """Its first frames are held until the announcement says the types agree, then
    published in order: from the first message on, none is missing."""
    b, inbox, talker = late_receiver(tmp_path, bridge, domain, ros_side, String, String,
                                     lambda n: String(data=str(n)))
    assert inbox.wait_count(100, 30), (inbox.items, b.log)
    talker.close()
    assert inbox.wait_for(lambda items: items[-1].data == str(talker.count), 10)
    got = [int(m.data) for m in inbox.items]
    assert got == list(range(got[0], talker.count + 1)), got  # in order, no gap, to the last
    entry = entry_status("b", "/late")
    # every frame that reached the bridge was published (the listener may miss the first few
    # while DDS matches it with the bridge's new publisher: not the bridge's loss)
    assert not entry["drops"] and entry["lost"] == 0, entry
    assert entry["received"] >= len(got), entry


def test_a_peer_server_started_after_its_caller_serves_no_call_of_another_type(
        engines, domain, ros_side):
    """Its first calls wait for the caller's next announcement, then are answered as failures."""
    from std_srvs.srv import SetBool, Trigger

    da, db, port = domain(), domain(), free_port()
    peer = "bridge: {name: %s, role: peer, peer: 127.0.0.1, listen: 127.0.0.1}"
    entry = f"service: /set, port: {port}, timeout: 5"
    engines(f"{peer % 'a'}\nservices: [{{{entry}, type: std_srvs/srv/SetBool, "
            "direction: transmit}]", da)
    served: list[Any] = []
    ros_side(db, "b").ros.node.create_service(Trigger, "/set",
                                              lambda q, r: served.append(q) or r)
    caller = ros_side(da, "a").ros.node.create_client(SetBool, "/set")
    assert caller.wait_for_service(timeout_sec=10)
    b = engines(f"{peer % 'b'}\nservices: [{{{entry}, type: std_srvs/srv/Trigger, "
                "direction: receive}]", db)
    answers: list[Any] = []
    deadline = time.monotonic() + 30
    while not any("refused, the far side's type" in a.message for a in answers):
        assert time.monotonic() < deadline, [a.message for a in answers]
        future = caller.call_async(SetBool.Request(data=True))
        assert wait_until(future.done, 10)
        answers.append(future.result())
    assert served == [] and not any(a.success for a in answers)
    route = b.routes()[0]
    assert route.counters.drops["type_mismatch"] >= 1 and route.counters.received == 0


@pytest.fixture
def client_hashes_another_version(monkeypatch):
    """robot1's bridge says another hash for every type: the same names, another version."""
    real = Router.hash_of

    def hash_of(self: Router, interface: type) -> str | None:
        return OTHER_VERSION if "robot1" in self.ros.node.get_name() else real(self, interface)

    monkeypatch.setattr(Router, "hash_of", hash_of)


def test_two_versions_of_one_message_are_refused_both_ways_client_server(
        engines, domain, ros_side, logs, client_hashes_another_version):
    ds, dc, main = domain(), domain(), free_port()
    server = engines(f"bridge: {{name: base, role: server, server: '127.0.0.1:{main}'}}", ds)
    client = engines(f"""
bridge: {{name: robot1, role: client, server: '127.0.0.1:{main}'}}
topics:
  - {{topic: /up, type: std_msgs/msg/String, direction: transmit}}
  - {{topic: /down, type: std_msgs/msg/String, direction: receive}}
services:
  - {{service: /set, type: std_srvs/srv/SetBool, direction: transmit, timeout: 2}}
""", dc)
    base, robot = ros_side(ds, "base"), ros_side(dc, "robot")
    got_up, got_down = base.listen("/up", String), robot.listen("/down", String)
    up_talker, down_talker = robot.publisher("/up", String), base.publisher("/down", String)
    assert wait_until(lambda: len(server.routes()) == 3 and len(client.routes()) == 3)
    up, down = route(server, "/up"), route(client, "/down")
    deadline = time.monotonic() + 20
    while up.counters.drops["type_mismatch"] < 5 or down.counters.drops["type_mismatch"] < 5:
        assert time.monotonic() < deadline, (up.counters, down.counters)
        up_talker.publish(String(data="up"))
        down_talker.publish(String(data="down"))
        time.sleep(0.02)  # paces the talkers; the loop waits on the counters
    assert got_up.items == [] and got_down.items == []
    assert up.counters.received == down.counters.received == 0
    from rosgate.rostypes import type_hash

    mine = type_hash(String)
    assert logs.having("/up (from robot1): refused") == [
        f"/up (from robot1): refused, the far side's type is std_msgs/msg/String "
        f"({OTHER_VERSION}) and this side's is std_msgs/msg/String ({mine}), so its frames are "
        "dropped"]
    assert logs.having("/down (from base): refused") == [
        f"/down (from base): refused, the far side's type is std_msgs/msg/String ({mine}) and "
        f"this side's is std_msgs/msg/String ({OTHER_VERSION}), so its frames are dropped"]
    # a call of a service whose type differs is answered as a failure, never served
    from std_srvs.srv import SetBool

    served: list[bool] = []
    base.ros.node.create_service(SetBool, "/set", lambda q, a: served.append(q.data) or a)
    caller = robot.ros.node.create_client(SetBool, "/set")
    assert caller.wait_for_service(timeout_sec=10)
    future = caller.call_async(SetBool.Request(data=True))
    assert wait_until(future.done, 5)
    answer = future.result()
    assert not answer.success and "refused, the far side's type" in answer.message
    assert served == []
    assert route(client, "/set").counters.drops["type_mismatch"] == 1


# -- the parts --------------------------------------------------------------------------------
class Verdicts:
    """What became of held frames: (n, True) published, (n, False) refused; and the drops."""

    def __init__(self) -> None:
        self.given: list[tuple[int, bool]] = []
        self.drops: list[str] = []

    def frame(self, n: int) -> Callable[[bool], None]:
        return lambda agreed: self.given.append((n, agreed))

    def drop(self, reason: str, detail: str) -> None:
        self.drops.append(reason)


MINE = Identity("std_msgs/msg/String", "RIHS01_" + "aa" * 32)


def test_held_frames_are_published_in_order_once_the_far_side_agrees():
    check, verdicts = TypeCheck("/t", MINE), Verdicts()
    assert not check.hold(10, verdicts.frame(0))  # nothing awaited: it goes on now
    check.expect(verdicts.drop)
    assert all(check.hold(10, verdicts.frame(n)) for n in range(1, 4))
    assert verdicts.given == []
    check.far(MINE)
    assert verdicts.given == [(1, True), (2, True), (3, True)]
    assert not check.awaiting and not check.hold(10, verdicts.frame(4))
    assert verdicts.drops == [] and check.heard_at is not None


def test_held_frames_are_refused_when_the_far_side_differs(caplog):
    check, verdicts = TypeCheck("/t", MINE), Verdicts()
    check.expect(verdicts.drop)
    assert check.hold(10, verdicts.frame(1)) and check.hold(10, verdicts.frame(2))
    with caplog.at_level(logging.ERROR, logger="rosgate"):
        check.far(Identity("std_msgs/msg/String", "RIHS01_" + "bb" * 32))
    assert verdicts.given == [(1, False), (2, False)]
    assert check.mismatch is not None and check.mismatch in caplog.text


def test_what_is_held_is_bounded_and_the_oldest_go_counted():
    from rosgate.announce import HOLD_BYTES, HOLD_FRAMES

    check, verdicts = TypeCheck("/t", MINE), Verdicts()
    check.expect(verdicts.drop)
    for n in range(HOLD_FRAMES + 5):
        assert check.hold(1, verdicts.frame(n))
    assert verdicts.drops == ["type_unheard"] * 5
    assert check.hold(HOLD_BYTES, verdicts.frame(-1))  # one frame the size of the whole bound
    assert verdicts.drops == ["type_unheard"] * (5 + HOLD_FRAMES)
    check.far(MINE)
    assert verdicts.given == [(-1, True)]


def test_a_far_side_that_never_announces_is_published_unchecked_after_a_while(caplog):
    """An older rosgate: what was held goes on after HOLD_FOR seconds, said once."""
    check, verdicts = TypeCheck("/t", MINE), Verdicts()
    check.expect(verdicts.drop)
    assert check.hold(10, verdicts.frame(1))
    now = time.monotonic()
    check.expire(now + HOLD_FOR - 0.5)
    assert verdicts.given == [] and check.awaiting
    with caplog.at_level(logging.WARNING, logger="rosgate"):
        check.expire(now + HOLD_FOR + 0.5)
    assert verdicts.given == [(1, True)] and not check.awaiting
    assert not check.hold(10, verdicts.frame(2))
    assert [r.getMessage() for r in caplog.records] == [
        f"/t: the far side said nothing of its type in {HOLD_FOR:g} s (an older rosgate?): its "
        "type is not checked until it does"]


def test_a_far_side_without_a_hash_is_accepted_and_said_once(caplog):
    check = TypeCheck("/t", Identity("std_msgs/msg/String", "RIHS01_" + "aa" * 32))
    with caplog.at_level(logging.WARNING, logger="rosgate"):
        check.far(None)
        check.far(None)
        check.far(Identity("std_msgs/msg/String", None))
    assert check.mismatch is None
    assert [r.getMessage() for r in caplog.records] == [
        "/t: the far side gives no type hash (an older rosgate, or a ROS before Iron): its "
        "type is not checked"]
    check.far(Identity("std_msgs/msg/String", "RIHS01_" + "bb" * 32))
    assert check.mismatch is not None
    check.far(Identity("std_msgs/msg/String", "RIHS01_" + "aa" * 32))  # it was fixed
    assert check.mismatch is None


@pytest.mark.parametrize("body, why", [
    (b"[]", "not an object"),
    (b'{"type": 5}', "not a string"),
    (b'{"type": "a/msg/B", "qos": {"reliability": "sometimes", "durability": "volatile", '
     b'"depth": 1}}', "reliability"),
    (b'{"type": "a/msg/B", "qos": {"reliability": "reliable", "durability": "volatile", '
     b'"depth": 100000}}', "depth"),
    (b'{"type": "a/msg/B", "qos": {"reliability": "reliable", "durability": "volatile", '
     b'"depth": true}}', "depth"),
    (b"\xff", "not JSON"),
])
def test_unreadable_announcements_are_refused_with_a_reason(body, why):
    with pytest.raises(ValueError, match=why):
        parse_body(body)


def test_announcements_read_back():
    assert read(None) == (None, None)
    qos = {"reliability": "best_effort", "durability": "transient_local", "depth": 3}
    assert parse_body(b'{"type": "a/msg/B", "hash": "RIHS01_x", "qos": ' +
                      str(qos).replace("'", '"').encode() + b"}") == \
        (Identity("a/msg/B", "RIHS01_x"), qos)
    assert qos_of(None) is None
