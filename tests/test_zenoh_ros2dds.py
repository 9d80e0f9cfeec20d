"""Interoperation with zenoh-bridge-ros2dds: ``framing: none`` + ``codec: cdr`` on a zenoh topic
speaks its convention, checked against a plain zenoh publisher and subscriber that follow it.

The convention, from zenoh-plugin-ros2dds (``ros2_utils.rs`` ``ros2_name_to_key_expr``,
``route_publisher.rs``, ``route_subscriber.rs``): the key is the ROS name without its leading
slash, under the bridge's ``namespace`` when that is not ``/`` (``/bot1`` + ``/cmd_vel`` ->
``bot1/cmd_vel``); the payload is the serialized sample as DDS carries it, CDR with its 4-byte
encapsulation header — what ``rclpy.serialization.serialize_message`` gives — with no encoding
and no attachment."""

from __future__ import annotations

import json
import random
import threading
import time
from pathlib import Path

import pytest
import zenoh
import zenoh.ext
from action_msgs.msg import GoalInfo, GoalStatus, GoalStatusArray
from action_msgs.srv import CancelGoal
from conftest import wait_until
from geometry_msgs.msg import Twist
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import Image
from std_msgs.msg import String
from std_srvs.srv import SetBool
from test_actions import ActionSide, Goal, fibonacci, settled, warmed_up
from test_msgs.action import Fibonacci
from test_services import DEEP, Caller, echo_set_bool
from test_zenoh_fleet import Router, zenoh_plugin
from unique_identifier_msgs.msg import UUID

TIMEOUT = 20.0


@pytest.fixture
def router():
    r = Router()
    yield r
    r.stop()


@pytest.fixture
def plain(router):
    """A plain zenoh session, as a zenoh-bridge-ros2dds base would have one."""
    session = zenoh.open(zenoh.Config.from_json5(json.dumps({
        "mode": "client", "connect": {"endpoints": [router.endpoint]},
        "scouting": {"multicast": {"enabled": False}},
        "timestamping": {"enabled": True}})))  # as that bridge has it: its caches need it
    yield session
    session.close()  # a session with callbacks must be closed, or the process may hang


def twist() -> Twist:
    t = Twist()
    t.linear.x, t.linear.y, t.angular.z = 1.5, -0.25, 0.75
    return t


def image() -> Image:
    rng = random.Random(7)
    return Image(height=480, width=640, encoding="rgb8", is_bigendian=0, step=640 * 3,
                 data=rng.randbytes(640 * 480 * 3))


@pytest.fixture
def bot1(tmp_path, router, bridge, domain):
    d = domain()
    path = tmp_path / "bot1.yaml"
    path.write_text(f"""\
bridge: {{name: bot1, role: peer, defaults: {{transport: zenoh, codec: cdr}}}}
{zenoh_plugin(router, ", namespace: /bot1")}topics:
  - {{topic: /cmd_vel, type: geometry_msgs/msg/Twist, direction: transmit, framing: none}}
  - {{topic: /camera/image_raw, type: sensor_msgs/msg/Image, direction: transmit, framing: none}}
  - {{topic: /cmd_vel_in, type: geometry_msgs/msg/Twist, direction: receive, framing: none}}
  - {{topic: /image_in, type: sensor_msgs/msg/Image, direction: receive, framing: none}}
""")
    bridge(path, d)
    return d


@pytest.mark.parametrize("topic, key, make", [
    ("/cmd_vel", "bot1/cmd_vel", twist),
    ("/camera/image_raw", "bot1/camera/image_raw", image),
], ids=["Twist", "Image 640x480"])
def test_rosgate_feeds_a_ros2dds_base_byte_for_byte(bot1, plain, ros_side, topic, key, make):
    message = make()
    expected = serialize_message(message)
    got: list[tuple[str, bytes]] = []
    arrived = threading.Event()

    def sample(s: zenoh.Sample) -> None:
        got.append((str(s.key_expr), s.payload.to_bytes()))
        arrived.set()

    subscriber = plain.declare_subscriber(key, zenoh.handlers.Callback(sample, indirect=False))
    publisher = ros_side(bot1, "robot").publisher(topic, type(message))
    deadline = time.monotonic() + TIMEOUT
    while not arrived.wait(0.2):  # ROS discovery and the subscription's spread take a moment
        assert time.monotonic() < deadline, "nothing arrived on the key"
        # the serialized bytes themselves: rclpy leaves CDR padding bytes uninitialised, so two
        # serializations of one message may differ there (README, Security)
        publisher.publish(expected)
    subscriber.undeclare()
    assert got[0][0] == key
    assert got[0][1] == expected
    assert expected[:4] in (b"\x00\x01\x00\x00", b"\x00\x00\x00\x00")  # the CDR header is kept


@pytest.mark.parametrize("topic, key, make", [
    ("/cmd_vel_in", "bot1/cmd_vel_in", twist),
    ("/image_in", "bot1/image_in", image),
], ids=["Twist", "Image 640x480"])
def test_a_ros2dds_base_feeds_rosgate_byte_for_byte(bot1, plain, ros_side, topic, key, make):
    message = make()
    payload = serialize_message(message)
    got: list[bytes] = []
    side = ros_side(bot1, "robot")
    side.ros.subscribe(type(message), topic, 10, got.append, raw=True)
    publisher = plain.declare_publisher(key)
    deadline = time.monotonic() + TIMEOUT
    while not wait_until(lambda: bool(got), 0.2):
        assert time.monotonic() < deadline, "nothing was published on the ROS side"
        publisher.put(payload)
    publisher.undeclare()
    assert got[0] == payload


# -- as an equal: speak: ros2dds ------------------------------------------------------------------
# zenoh-bridge-ros2dds and rosgate as equals (plugins: {zenoh: {speak: ros2dds}}), checked against
# a peer written from that bridge's sources (zenoh-plugin-ros2dds: liveliness_mgt.rs for the
# tokens, route_publisher.rs / route_subscriber.rs for the publication cache and the querying
# subscriber of transient_local topics, route_service_*.rs and ros2_utils.rs for service calls
# and their request-header attachment). What the peer declares and reads is written out here.

LATCHED = QoSProfile(depth=3, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                     reliability=ReliabilityPolicy.RELIABLE)


def bot1_file(tmp: Path, router) -> Path:
    path = tmp / "bot1.yaml"
    path.write_text(f"""\
bridge: {{name: bot1, role: peer, defaults: {{transport: zenoh, codec: cdr}}}}
{zenoh_plugin(router, ", namespace: /bot1, speak: ros2dds")}topics:
  - {{topic: /cmd_vel, type: geometry_msgs/msg/Twist, direction: transmit, framing: none}}
  - {{topic: /map, type: std_msgs/msg/String, direction: transmit, framing: none,
      qos: {{durability: transient_local, depth: 3}}}}
  - {{topic: /cmd_in, type: geometry_msgs/msg/Twist, direction: receive, framing: none,
      qos: {{reliability: best_effort, depth: 5}}}}
services:
  - {{service: /set, type: std_srvs/srv/SetBool, direction: receive, remote: bot1/set}}
  - {{service: /zb_set, type: std_srvs/srv/SetBool, direction: transmit, remote: bot1/zb_set}}
""")
    return path


@pytest.fixture
def equal(tmp_path, router, bridge, domain):
    d = domain()
    return bridge(bot1_file(tmp_path, router), d), d


def tokens_of(session: zenoh.Session) -> list[str]:
    """Every zenoh-bridge-ros2dds token there is, as that bridge's liveliness subscriber
    (``@/*/@ros2_lv/**``) sees them."""
    return [str(r.ok.key_expr) for r in session.liveliness().get("@/*/@ros2_lv/**", timeout=5)
            if r.ok is not None]


def test_the_peer_sees_every_route_by_its_token_before_any_data(equal, plain):
    def routes() -> set[str]:
        return {"/".join(t.split("/")[3:]) for t in tokens_of(plain) if t.count("/") > 2}

    expected = {
        # kind / key with '§' for '/' / type with '§' / [K]:reliability:durability:history,depth
        "MP/bot1§cmd_vel/geometry_msgs§msg§Twist/:1:0:0,10",
        "MP/bot1§map/std_msgs§msg§String/:1:1:0,3",
        "MS/bot1§cmd_in/geometry_msgs§msg§Twist/:0:0:0,5",
        "SS/bot1§set/std_srvs§srv§SetBool",
        "SC/bot1§zb_set/std_srvs§srv§SetBool",
    }
    assert wait_until(lambda: routes() == expected, TIMEOUT), routes()
    zids = {t.split("/")[1] for t in tokens_of(plain)}
    assert len(zids) == 1, "every token is the bridge session's own"
    assert f"@/{zids.pop()}/@ros2_lv" in tokens_of(plain), "the bridge token is declared too"


def test_a_late_joiner_gets_the_last_transient_local_samples(equal, plain, ros_side):
    _bridge, d = equal
    publisher = ros_side(d, "robot").publisher("/map", String, LATCHED)
    live: list[bytes] = []
    plain.declare_subscriber("bot1/map", zenoh.handlers.Callback(
        lambda s: live.append(s.payload.to_bytes()), indirect=False))
    assert wait_until(lambda: publisher.get_subscription_count() >= 1, TIMEOUT)
    sent = [f"map {n}" for n in range(5)]
    for text in sent:
        publisher.publish(String(data=text))

    def texts(samples: list[bytes]) -> list[str]:  # CDR padding bytes are not compared
        return [deserialize_message(s, String).data for s in samples]

    # what DDS hands the bridge: all five, or (its subscription matching the publisher mid-way)
    # some, then the publisher's own history of three
    assert wait_until(lambda: texts(live)[-3:] == sent[-3:], TIMEOUT), texts(live)

    late: list[bytes] = []
    # route_subscriber.rs: a transient_local route is an advanced subscriber that queries the
    # history of every publisher it detects, up to the reader's depth
    subscriber = zenoh.ext.declare_advanced_subscriber(
        plain, "bot1/map", zenoh.handlers.Callback(lambda s: late.append(s.payload.to_bytes()),
                                                   indirect=False),
        history=zenoh.ext.HistoryConfig(detect_late_publishers=True, max_samples=10))
    assert wait_until(lambda: len(late) >= 3, TIMEOUT), late
    time.sleep(0.5)  # a fourth sample would be a bug: give it the chance to show
    subscriber.undeclare()
    assert texts(late) == sent[-3:], "the cache keeps the topic's depth (3), in order"
    assert late == live[-3:], "byte for byte as they were published on the key"


def test_rosgate_queries_the_history_of_a_transient_local_topic_on_start(
        tmp_path, router, plain, bridge, domain, ros_side):
    # route_publisher.rs: a transient_local route is an advanced publisher with a cache and
    # publisher detection; its samples exist before rosgate starts
    publisher = zenoh.ext.declare_advanced_publisher(
        plain, "bot2/latched", cache=zenoh.ext.CacheConfig(max_samples=5),
        publisher_detection=True)
    sent = [serialize_message(String(data=f"latched {n}")) for n in range(2)]
    for payload in sent:
        publisher.put(payload)
    d = domain()
    path = tmp_path / "bot2.yaml"
    path.write_text(f"""\
bridge: {{name: bot2, role: peer, defaults: {{transport: zenoh, codec: cdr}}}}
{zenoh_plugin(router, ", speak: ros2dds")}topics:
  - {{topic: /latched, type: std_msgs/msg/String, direction: receive, framing: none,
      remote: bot2/latched, qos: {{durability: transient_local, depth: 5}}}}
""")
    bridge(path, d)
    got: list[bytes] = []
    ros_side(d, "robot").ros.subscribe(
        String, "/latched", QoSProfile(depth=5, durability=DurabilityPolicy.TRANSIENT_LOCAL),
        got.append, raw=True)
    assert wait_until(lambda: len(got) >= 2, TIMEOUT), got
    # DDS may pad the serialized sample to a 4-byte boundary: compare what it says
    assert [deserialize_message(g, String).data for g in got] == ["latched 0", "latched 1"]
    assert [g[:len(s)] for g, s in zip(got, sent, strict=True)] == sent
    publisher.undeclare()


def test_the_peer_calls_a_service_rosgate_bridges(equal, plain, ros_side):
    _bridge, d = equal
    ros_side(d, "robot").ros.node.create_service(SetBool, "/set", echo_set_bool, qos_profile=DEEP)
    # route_service_cli.rs: the query's payload is the request's CDR; its attachment the
    # request header: b"rqh", the client's GUID (8 bytes), the sequence number (8), endianness
    header = b"rqh" + bytes(range(8)) + (7).to_bytes(8, "little") + b"\x01"
    deadline = time.monotonic() + TIMEOUT
    while True:  # until the bridge's ROS client has found the server
        replies = [r for r in plain.get("bot1/set", payload=serialize_message(
            SetBool.Request(data=True)), attachment=header, timeout=5) if r.ok is not None]
        if replies:
            break
        assert time.monotonic() < deadline, "the service never answered"
        time.sleep(0.2)
    assert len(replies) == 1
    answer = deserialize_message(replies[0].ok.payload.to_bytes(), SetBool.Response)
    assert (answer.success, answer.message) == (True, "data=True")
    assert str(replies[0].ok.key_expr) == "bot1/set"


def test_rosgate_calls_a_service_the_peer_serves(equal, plain, ros_side):
    _bridge, d = equal
    seen: list[tuple[bytes, bytes | None]] = []

    def serve(query: zenoh.Query) -> None:  # route_service_srv.rs, seen from outside
        request = query.payload.to_bytes() if query.payload is not None else b""
        attachment = query.attachment.to_bytes() if query.attachment is not None else None
        seen.append((request, attachment))
        data = deserialize_message(request, SetBool.Request).data
        query.reply("bot1/zb_set", serialize_message(
            SetBool.Response(success=not data, message=f"peer got {data}")))

    queryable = plain.declare_queryable("bot1/zb_set", zenoh.handlers.Callback(
        serve, indirect=False))
    caller = Caller(ros_side(d, "robot"), SetBool, "/zb_set")
    answers = caller.call_many([SetBool.Request(data=False), SetBool.Request(data=True)], 10)
    queryable.undeclare()
    assert [(a.success, a.message) for a in answers] == [(True, "peer got False"),
                                                         (False, "peer got True")]
    assert [deserialize_message(r, SetBool.Request).data for r, _ in seen] == [False, True]
    for _request, attachment in seen:
        assert attachment is not None and attachment[:3] == b"rqh" and len(attachment) == 20
        assert attachment[19] == 1  # little endian, as the CDR it goes with
    assert {a[3:11] for _r, a in seen if a} .__len__() == 1, "one client id for one route"
    assert sorted(int.from_bytes(a[11:19], "little") for _r, a in seen if a) == [1, 2]


def test_rosgate_learns_a_ros2dds_robot_from_its_tokens(tmp_path, router, plain, bridge,
                                                        domain, ros_side):
    d = domain()
    path = tmp_path / "base.yaml"
    path.write_text(f"""\
bridge: {{name: base, role: peer, defaults: {{transport: zenoh, codec: cdr}}, fleet_timeout: 30}}
{zenoh_plugin(router, ", speak: ros2dds")}topics:
  - {{topic: "/{{robot}}/cmd", remote: "fleet/{{robot}}/cmd", type: std_msgs/msg/String,
      direction: transmit, framing: none}}
  - {{topic: "/{{robot}}/odom", remote: "fleet/{{robot}}/odom", type: std_msgs/msg/String,
      direction: receive, framing: none}}
""")
    base = bridge(path, d)
    zid = str(plain.zid())
    got: list[bytes] = []
    arrived = threading.Event()

    def sample(s: zenoh.Sample) -> None:
        got.append(s.payload.to_bytes())
        arrived.set()

    subscriber = plain.declare_subscriber("fleet/zb7/cmd", zenoh.handlers.Callback(
        sample, indirect=False))
    # the tokens a zenoh-bridge-ros2dds robot declares for a ROS subscriber of /cmd and a ROS
    # publisher of /odom behind it (liveliness_mgt.rs), and nothing else: no frame at all
    tokens = [plain.liveliness().declare_token(f"@/{zid}/@ros2_lv/{kind}/fleet§zb7§{name}/"
                                               "std_msgs§msg§String/:1:0:0,10")
              for kind, name in (("MS", "cmd"), ("MP", "odom"))]
    assert base.wait_log("fleet: robot zb7 joined", TIMEOUT), base.log
    assert base.wait_log("fleet: publishing /zb7/odom for robot zb7", TIMEOUT), base.log
    publisher = ros_side(d, "base").publisher("/zb7/cmd", String, 10)
    payload = serialize_message(String(data="go"))
    deadline = time.monotonic() + TIMEOUT
    while not arrived.wait(0.2):
        assert time.monotonic() < deadline, "nothing reached the robot's key"
        publisher.publish(payload)
    assert got[0][:len(payload)] == payload  # DDS may pad it to a 4-byte boundary
    assert deserialize_message(got[0], String).data == "go"
    for token in tokens:
        token.undeclare()
    assert base.wait_log("fleet: robot zb7 left", TIMEOUT), base.log
    subscriber.undeclare()


# -- actions in zenoh-bridge-ros2dds's layout -----------------------------------------------------
# route_action_srv.rs / route_action_cli.rs: an action keyed <key> is three services and two topics
# under <key>/_action/ (ros2_utils.rs, KE_SUFFIX_ACTION_*), served and called as any service and
# topic, status transient_local (a publication cache, a querying subscriber); one liveliness token
# per action, AS or AC on <key> with the action's type (liveliness_mgt.rs), none for its parts.
# The peers below are those two routes, seen from the bus.

SEND_GOAL, GET_RESULT = Fibonacci.Impl.SendGoalService, Fibonacci.Impl.GetResultService
FEEDBACK = Fibonacci.Impl.FeedbackMessage


@pytest.fixture
def action_bot(tmp_path, router, bridge, domain):
    """A bridge serving /fib to the bus (AS) and calling /zb_fib on it (AC), ZB's layout; and a
    ROS side in its domain (rclpy's multi-threaded executor, as actions need)."""
    d = domain()
    path = tmp_path / "bot1.yaml"
    path.write_text(f"""\
bridge: {{name: bot1, role: peer, defaults: {{transport: zenoh, codec: cdr}}}}
{zenoh_plugin(router, ", namespace: /bot1, speak: ros2dds")}actions:
  - {{action: /fib, type: test_msgs/action/Fibonacci, direction: receive, remote: bot1/fib}}
  - {{action: /zb_fib, type: test_msgs/action/Fibonacci, direction: transmit,
      remote: bot1/zb_fib, timeout: 3}}
""")
    bridge(path, d)
    side = ActionSide(d, "bot1_ros")
    yield side
    side.close()


def route_tokens(session: zenoh.Session) -> set[str]:
    return {"/".join(t.split("/")[3:]) for t in tokens_of(session) if t.count("/") > 2}


def uuid(goal_id: bytes) -> UUID:
    return UUID(uuid=list(goal_id))


def request_header(seq: int) -> bytes:
    return b"rqh" + bytes(range(8)) + seq.to_bytes(8, "little") + b"\x01"


def test_the_peer_sends_goals_to_an_action_rosgate_serves(action_bot, plain):
    """The peer as zenoh-bridge-ros2dds's action client route: goals, feedback, status, a
    cancel and results, each a query or a sample on <key>/_action/..., in bare CDR."""
    keep = action_bot.fibonacci_server("/fib")
    assert wait_until(lambda: route_tokens(plain) == {
        "AS/bot1§fib/test_msgs§action§Fibonacci",
        "AC/bot1§zb_fib/test_msgs§action§Fibonacci"}, TIMEOUT), route_tokens(plain)
    feedback: list[bytes] = []
    plain.declare_subscriber("bot1/fib/_action/feedback", zenoh.handlers.Callback(
        lambda s: feedback.append(s.payload.to_bytes()), indirect=False))
    calls = iter(range(1, 1000))

    def call(part: str, request, answer_type, timeout: float = 5.0):
        replies = [r.ok for r in plain.get(f"bot1/fib/_action/{part}",
                                           payload=serialize_message(request),
                                           attachment=request_header(next(calls)),
                                           timeout=timeout) if r.ok is not None]
        assert all(str(r.key_expr) == f"bot1/fib/_action/{part}" for r in replies)
        return [deserialize_message(r.payload.to_bytes(), answer_type) for r in replies]

    def send(order: int) -> bytes:
        deadline = time.monotonic() + TIMEOUT
        while True:  # until the bridge's ROS client has found the action server
            goal_id = random.randbytes(16)
            answers = call("send_goal", SEND_GOAL.Request(goal_id=uuid(goal_id),
                                                          goal=Fibonacci.Goal(order=order)),
                           SEND_GOAL.Response)
            if answers and answers[0].accepted:
                assert len(answers) == 1
                return goal_id
            assert time.monotonic() < deadline, "no goal was ever accepted"
            time.sleep(0.2)

    def sequences(goal_id: bytes) -> list[list[int]]:
        found = [deserialize_message(f, FEEDBACK) for f in list(feedback)]
        return [list(f.feedback.sequence) for f in found if bytes(f.goal_id.uuid) == goal_id]

    goal_id = send(20)
    (result,) = call("get_result", GET_RESULT.Request(goal_id=uuid(goal_id)), GET_RESULT.Response,
                     timeout=30)
    assert result.status == GoalStatus.STATUS_SUCCEEDED
    assert list(result.result.sequence) == fibonacci(21)
    got = sequences(goal_id)
    assert len(got) >= 15, got
    assert got == [fibonacci(len(s) - 1) for s in got]
    assert [len(s) for s in got] == sorted({len(s) for s in got})  # in order

    # a late joiner's querying subscriber gets the last status from the publication cache
    statuses: list[bytes] = []
    late = zenoh.ext.declare_advanced_subscriber(
        plain, "bot1/fib/_action/status", zenoh.handlers.Callback(
            lambda s: statuses.append(s.payload.to_bytes()), indirect=False),
        history=zenoh.ext.HistoryConfig(detect_late_publishers=True, max_samples=10))

    def status_of(goal: bytes) -> int | None:
        for sample in reversed(statuses):
            for status in deserialize_message(sample, GoalStatusArray).status_list:
                if bytes(status.goal_info.goal_id.uuid) == goal:
                    return status.status
        return None

    assert wait_until(lambda: status_of(goal_id) == GoalStatus.STATUS_SUCCEEDED, TIMEOUT), \
        statuses

    goal_id = send(200)
    assert wait_until(lambda: len(sequences(goal_id)) >= 5, TIMEOUT)
    (cancel,) = call("cancel_goal", CancelGoal.Request(goal_info=GoalInfo(goal_id=uuid(goal_id))),
                     CancelGoal.Response)
    assert cancel.return_code == CancelGoal.Response.ERROR_NONE
    assert [bytes(g.goal_id.uuid) for g in cancel.goals_canceling] == [goal_id]
    (result,) = call("get_result", GET_RESULT.Request(goal_id=uuid(goal_id)), GET_RESULT.Response,
                     timeout=30)
    assert result.status == GoalStatus.STATUS_CANCELED
    assert 5 <= len(result.result.sequence) < 200
    assert wait_until(lambda: status_of(goal_id) == GoalStatus.STATUS_CANCELED, TIMEOUT)
    late.undeclare()
    del keep


class ZbActionServer:
    """zenoh-bridge-ros2dds's action server route for bot1/zb_fib, seen from the bus: three
    queryables, a feedback publisher and a status publisher with a cache; Fibonacci served
    here, a step every 50 ms. Every query's payload and attachment is kept."""

    def __init__(self, session: zenoh.Session):
        self.session = session
        self.key = "bot1/zb_fib/_action"
        self.queries: dict[str, list[tuple[bytes, bytes | None]]] = {
            "send_goal": [], "cancel_goal": [], "get_result": []}
        self.results: dict[bytes, tuple[int, list[int]]] = {}  # goal -> (status, sequence)
        self.waiting: dict[bytes, list[zenoh.Query]] = {}
        self.canceled: set[bytes] = set()
        self.lock = threading.Lock()
        self.declared = [session.declare_queryable(f"{self.key}/{part}", zenoh.handlers.Callback(
            lambda q, part=part: self._query(part, q), indirect=False)) for part in self.queries]
        self.feedback = session.declare_publisher(f"{self.key}/feedback")
        self.status = zenoh.ext.declare_advanced_publisher(
            session, f"{self.key}/status", cache=zenoh.ext.CacheConfig(max_samples=10),
            publisher_detection=True)
        self.token = session.liveliness().declare_token(
            f"@/{session.zid()}/@ros2_lv/AS/bot1§zb_fib/test_msgs§action§Fibonacci")

    def _query(self, part: str, query: zenoh.Query) -> None:
        payload = query.payload.to_bytes() if query.payload is not None else b""
        attachment = query.attachment.to_bytes() if query.attachment is not None else None
        self.queries[part].append((payload, attachment))
        key = f"{self.key}/{part}"
        if part == "send_goal":
            request = deserialize_message(payload, SEND_GOAL.Request)
            goal_id = bytes(request.goal_id.uuid)
            query.reply(key, serialize_message(SEND_GOAL.Response(accepted=True)))
            threading.Thread(target=self._work, args=(goal_id, request.goal.order),
                             daemon=True).start()
        elif part == "cancel_goal":
            goal_id = bytes(deserialize_message(payload, CancelGoal.Request).goal_info.goal_id.uuid)
            self.canceled.add(goal_id)
            query.reply(key, serialize_message(CancelGoal.Response(
                return_code=CancelGoal.Response.ERROR_NONE,
                goals_canceling=[GoalInfo(goal_id=uuid(goal_id))])))
        else:
            goal_id = bytes(deserialize_message(payload, GET_RESULT.Request).goal_id.uuid)
            with self.lock:
                if goal_id not in self.results:
                    self.waiting.setdefault(goal_id, []).append(query)
                    return  # answered when the goal ends
            self._answer(query, goal_id)
            return
        query.drop()

    def _answer(self, query: zenoh.Query, goal_id: bytes) -> None:
        status, sequence = self.results[goal_id]
        query.reply(f"{self.key}/get_result", serialize_message(GET_RESULT.Response(
            status=status, result=Fibonacci.Result(sequence=sequence))))
        query.drop()

    def _status(self, goal_id: bytes, status: int) -> None:
        self.status.put(serialize_message(GoalStatusArray(status_list=[GoalStatus(
            goal_info=GoalInfo(goal_id=uuid(goal_id)), status=status)])))

    def _work(self, goal_id: bytes, order: int) -> None:
        self._status(goal_id, GoalStatus.STATUS_EXECUTING)
        sequence, status = [0, 1], GoalStatus.STATUS_SUCCEEDED
        for _ in range(order):
            if goal_id in self.canceled:
                status = GoalStatus.STATUS_CANCELED
                break
            sequence.append(sequence[-1] + sequence[-2])
            self.feedback.put(serialize_message(FEEDBACK(
                goal_id=uuid(goal_id), feedback=Fibonacci.Feedback(sequence=sequence))))
            time.sleep(0.05)  # the action's work: it takes a while
        self._status(goal_id, status)
        with self.lock:
            self.results[goal_id] = (status, sequence)
            waiting = self.waiting.pop(goal_id, [])
        for query in waiting:
            self._answer(query, goal_id)

    def close(self) -> None:
        for declared in self.declared:
            declared.undeclare()
        self.feedback.undeclare()
        self.status.undeclare()
        self.token.undeclare()


def test_rosgate_sends_goals_to_an_action_the_peer_serves(router, plain, tmp_path, bridge,
                                                          domain):
    """rclpy's ActionClient behind rosgate, the peer as zenoh-bridge-ros2dds's action server
    route: each query's payload is the request's CDR byte for byte, with the request header."""
    peer = ZbActionServer(plain)
    side = None
    try:
        d = domain()
        path = tmp_path / "bot1.yaml"
        path.write_text(f"""\
bridge: {{name: bot1, role: peer, defaults: {{transport: zenoh, codec: cdr}}}}
{zenoh_plugin(router, ", speak: ros2dds")}actions:
  - {{action: /zb_fib, type: test_msgs/action/Fibonacci, direction: transmit,
      remote: bot1/zb_fib, timeout: 3}}
""")
        bridge(path, d)
        side = ActionSide(d, "bot1_ros")
        client = warmed_up(side.client(Fibonacci, "/zb_fib"), Fibonacci.Goal(order=1))
        goal = Goal(client, Fibonacci.Goal(order=20))
        assert goal.handle.accepted
        answer = goal.result()
        assert answer.status == GoalStatus.STATUS_SUCCEEDED
        assert list(answer.result.sequence) == fibonacci(21)
        got = [list(f.sequence) for f in goal.feedback]
        assert len(got) >= 15, got
        assert got == [fibonacci(len(s) - 1) for s in got]
        assert [len(s) for s in got] == sorted({len(s) for s in got})

        goal_id = bytes(goal.handle.goal_id.uuid)
        sent = {part: [(p, a) for p, a in peer.queries[part] if p[4:20] == goal_id]
                for part in ("send_goal", "get_result")}
        assert [p for p, _ in sent["send_goal"]] == [serialize_message(SEND_GOAL.Request(
            goal_id=uuid(goal_id), goal=Fibonacci.Goal(order=20)))]
        assert [p for p, _ in sent["get_result"]] == [serialize_message(GET_RESULT.Request(
            goal_id=uuid(goal_id)))]
        for _payload, attachment in [*sent["send_goal"], *sent["get_result"]]:
            assert attachment is not None and attachment[:3] == b"rqh" and len(attachment) == 20
            assert attachment[19] == 1

        goal = Goal(client, Fibonacci.Goal(order=200))
        assert goal.handle.accepted and goal.wait_feedback(5, 10)
        cancel = settled(goal.handle.cancel_goal_async(), 10)
        goal_id = bytes(goal.handle.goal_id.uuid)
        assert cancel.return_code == CancelGoal.Response.ERROR_NONE
        assert [bytes(g.goal_id.uuid) for g in cancel.goals_canceling] == [goal_id]
        assert [p for p, _ in peer.queries["cancel_goal"]] == [serialize_message(
            CancelGoal.Request(goal_info=GoalInfo(goal_id=uuid(goal_id))))]
        answer = goal.result()
        assert answer.status == GoalStatus.STATUS_CANCELED
        assert 5 <= len(answer.result.sequence) < 200
    finally:
        if side is not None:
            side.close()
        peer.close()


def test_a_base_declares_the_tokens_of_each_robots_routes_and_calls_it_bare(
        tmp_path, router, plain, bridge, domain, ros_side):
    """Fleet entries speak zenoh-bridge-ros2dds too: each robot's routes hold the tokens that
    bridge declares (so a zenoh-bridge-ros2dds robot makes its DDS writer for the base's
    /{robot}/cmd), a fleet service is called with bare CDR, and the tokens go with the robot."""
    d = domain()
    path = tmp_path / "base.yaml"
    path.write_text(f"""\
bridge: {{name: base, role: peer, defaults: {{transport: zenoh, codec: cdr}}, fleet_timeout: 2}}
{zenoh_plugin(router, ", speak: ros2dds")}topics:
  - {{topic: "/{{robot}}/cmd", remote: "fleet/{{robot}}/cmd", type: std_msgs/msg/String,
      direction: transmit, framing: none}}
  - {{topic: "/{{robot}}/odom", remote: "fleet/{{robot}}/odom", type: std_msgs/msg/String,
      direction: receive, framing: none}}
services:
  - {{service: "/{{robot}}/set", remote: "fleet/{{robot}}/set", type: std_srvs/srv/SetBool,
      direction: transmit, timeout: 3}}
""")
    base = bridge(path, d)
    zid = str(plain.zid())
    seen: list[tuple[bytes, bytes | None]] = []

    def serve(query: zenoh.Query) -> None:
        request = query.payload.to_bytes() if query.payload is not None else b""
        seen.append((request, query.attachment.to_bytes() if query.attachment else None))
        query.reply("fleet/zb7/set", serialize_message(SetBool.Response(success=True,
                                                                        message="zb7 set")))

    queryable = plain.declare_queryable("fleet/zb7/set", zenoh.handlers.Callback(
        serve, indirect=False))
    # robot zb7 as a zenoh-bridge-ros2dds robot announces its ROS subscriber of /cmd, publisher
    # of /odom and server of /set (liveliness_mgt.rs)
    tokens = [plain.liveliness().declare_token(f"@/{zid}/@ros2_lv/{route}") for route in (
        "MS/fleet§zb7§cmd/std_msgs§msg§String/:1:0:0,10",
        "MP/fleet§zb7§odom/std_msgs§msg§String/:1:0:0,10",
        "SS/fleet§zb7§set/std_srvs§srv§SetBool")]

    def base_routes() -> set[str]:
        return {"/".join(t.split("/")[3:]) for t in tokens_of(plain)
                if t.count("/") > 2 and t.split("/")[1] != zid}

    expected = {"MP/fleet§zb7§cmd/std_msgs§msg§String/:1:0:0,10",
                "MS/fleet§zb7§odom/std_msgs§msg§String/:1:0:0,10",
                "SC/fleet§zb7§set/std_srvs§srv§SetBool"}
    assert wait_until(lambda: base_routes() == expected, TIMEOUT), base_routes()
    caller = Caller(ros_side(d, "base"), SetBool, "/zb7/set")
    (answer,) = caller.call_many([SetBool.Request(data=True)], 10)
    assert (answer.success, answer.message) == (True, "zb7 set")
    assert [request for request, _ in seen] == [serialize_message(SetBool.Request(data=True))]
    assert seen[0][1] is not None and seen[0][1][:3] == b"rqh"

    for token in tokens:
        token.undeclare()
    queryable.undeclare()
    assert base.wait_log("fleet: robot zb7 dropped", TIMEOUT), base.log
    assert wait_until(lambda: base_routes() == set(), TIMEOUT), base_routes()
