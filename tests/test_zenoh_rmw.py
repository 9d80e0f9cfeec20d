"""rmw_zenoh as an equal (``plugins: {zenoh: {speak: rmw_zenoh}}``): a real ``rosgate run``
bridging a real rclpy node, checked against a publisher and a subscriber that do what a ROS 2
node running rmw_zenoh_cpp does on the wire.

No rmw_zenoh binary installs here, so that node is written out below from rmw_zenoh's sources
(ros2/rmw_zenoh, ``rmw_zenoh_cpp/src/detail/``, the Jazzy format of 0.2.4 to 0.2.10): a plain
zenoh session that declares a node token and one token per entity (``liveliness_utils.cpp``:
``@ros2_lv/<domain>/<zid>/<nid>/<id>/<NN|MP|MS>/<enclave>/<namespace>/<node>[/<topic>/<type>/<hash>/<qos>]``,
'/' inside a part written '%'), reads the graph with a liveliness query on
``@ros2_lv/<domain>/**``, keys its data ``<domain>/<name>/<pkg::msg::dds_::Name_>/<RIHS01 hash>``
(``TopicInfo``), computes an entity's GID as the XXH3-128 of its token, and puts and reads
the attachment of ``attachment_helpers.cpp`` (int64 sequence number from 1, int64 source
timestamp in ns, the 16-byte GID as a zenoh-ext array). Its token
parsing and attachment decoding are written here again, not taken from rosgate."""

from __future__ import annotations

import json
import struct
import threading
import time
from pathlib import Path

import pytest
import xxhash
import zenoh
import zenoh.ext
from conftest import wait_until
from geometry_msgs.msg import Twist
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from rclpy.serialization import deserialize_message, serialize_message
from std_msgs.msg import String
from std_srvs.srv import SetBool
from test_cli import rosgate, user_error
from test_services import DEEP, Caller, echo_set_bool
from test_zenoh_fleet import Router, zenoh_plugin

TIMEOUT = 20.0
STRING = ("std_msgs::msg::dds_::String_",
          "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18")
SETBOOL = ("std_srvs::srv::dds_::SetBool_",
           "RIHS01_abe9e4bb6b41b40e6789712c00ec8871923e089af3f667a79992a428cff2da0a")
TWIST = ("geometry_msgs::msg::dds_::Twist_",
         "RIHS01_9c45bf16fe0983d80e3cfe750d6835843d265a9a6c46bd2e609fcddde6fb8d2a")
LATCHED = QoSProfile(depth=3, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                     reliability=ReliabilityPolicy.RELIABLE)


class RmwNode:
    """What a ROS 2 node running rmw_zenoh puts on zenoh, written from its sources."""

    def __init__(self, router: Router, domain: int, name: str = "listener"):
        self.domain = domain
        self.session = zenoh.open(zenoh.Config.from_json5(json.dumps({
            "mode": "client", "connect": {"endpoints": [router.endpoint]},
            "scouting": {"multicast": {"enabled": False}}})))
        self.zid = str(self.session.zid())
        self.name = name
        self.ids = iter(range(1, 1000))
        self.held = [self.token(0, "NN")]
        self.seq = 0
        self.closed = False

    def token(self, entity: int, kind: str, rest: str = "") -> zenoh.LivelinessToken:
        key = f"@ros2_lv/{self.domain}/{self.zid}/0/{entity}/{kind}/%/%/{self.name}" + rest
        return self.session.liveliness().declare_token(key)

    def key(self, name: str, type_and_hash: tuple[str, str]) -> str:
        return f"{self.domain}/{name.strip('/')}/{type_and_hash[0]}/{type_and_hash[1]}"

    def announce(self, kind: str, name: str, type_and_hash: tuple[str, str], qos: str) -> None:
        self.held.append(self.token(next(self.ids), kind, f"/{name.replace('/', '%')}/"
                                    f"{type_and_hash[0]}/{type_and_hash[1]}/{qos}"))

    def graph(self) -> list[list[str]]:
        """Every token of the domain, split into its parts (the node's own left out)."""
        replies = self.session.liveliness().get(f"@ros2_lv/{self.domain}/**", timeout=5)
        return [str(r.ok.key_expr).split("/") for r in replies
                if r.ok is not None and str(r.ok.key_expr).split("/")[2] != self.zid]

    def attachment(self) -> bytes:
        self.seq += 1
        return struct.pack("<qqB", self.seq, time.time_ns(), 16) + bytes(range(16))

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self.session.close()


def read_attachment(data: bytes) -> tuple[int, int, bytes]:
    """``AttachmentData(const zenoh::Bytes &)``: int64, int64, then a 16-element array."""
    assert len(data) == 33, data
    seq, stamp, length = struct.unpack_from("<qqB", data)
    assert length == 16, "the GID is a zenoh-ext sequence of 16 bytes"
    return seq, stamp, data[17:]


def gid_of(token: str) -> bytes:
    """``Entity::Entity``: the token's XXH3-128 (seed 0), low 64 bits then high, little endian."""
    return xxhash.xxh3_128_intdigest(token.encode()).to_bytes(16, "little")


@pytest.fixture
def router():
    r = Router()
    yield r
    r.stop()


def bot1_file(tmp: Path, router: Router, more: str = "", options: str = "") -> Path:
    """An rmw_zenoh router takes any session (no TLS): the file says it accepts that."""
    path = tmp / "bot1.yaml"
    path.write_text(f"""\
bridge: {{name: bot1, role: peer, defaults: {{transport: zenoh, codec: cdr}}, insecure: true}}
{zenoh_plugin(router, ", speak: rmw_zenoh" + options)}topics:
  - {{topic: /chatter, type: std_msgs/msg/String, direction: transmit, framing: none,
      qos: {{depth: 10}}}}
  - {{topic: /cmd_vel, type: geometry_msgs/msg/Twist, direction: receive, framing: none,
      remote: /robot1/cmd_vel, qos: {{reliability: best_effort, depth: 5}}}}
  - {{topic: /map, type: std_msgs/msg/String, direction: transmit, framing: none,
      qos: {{durability: transient_local, depth: 3}}}}
""" + more + """\
services:
  - {service: /set, type: std_srvs/srv/SetBool, direction: receive, remote: /robot1/set}
  - {service: /rmw_set, type: std_srvs/srv/SetBool, direction: transmit, remote: /rmw_set}
""")
    return path


@pytest.fixture
def bot1(tmp_path, router, bridge, domain):
    d = domain()
    return bridge(bot1_file(tmp_path, router), d), d


@pytest.fixture
def rmw_node(router, bot1):
    node = RmwNode(router, bot1[1])
    yield node
    node.close()  # a session with callbacks must be closed, or the process may hang


def test_an_rmw_zenoh_node_sees_rosgate_in_its_graph_before_any_data(bot1, rmw_node):
    expected_entities = {
        # kind, topic (mangled), type, hash, QoS as qos_to_keyexpr writes it
        # (each field empty where it is qos.cpp's default: reliable, volatile since 0.2.3)
        ("MP", "%chatter", *STRING, "::,10:,:,:,,"),  # reliable, volatile, keep last 10
        ("MS", "%robot1%cmd_vel", *TWIST, "2::,5:,:,:,,"),  # best effort, volatile, 5
        ("MP", "%map", *STRING, ":1:,3:,:,:,,"),  # reliable, transient local, 3
        ("SS", "%robot1%set", *SETBOOL, "::,10:,:,:,,"),  # ROS's services profile
        ("SC", "%rmw_set", *SETBOOL, "::,10:,:,:,,"),
    }

    def entities() -> set[tuple[str, ...]]:
        return {(p[5], *p[9:]) for p in rmw_node.graph() if len(p) == 13}

    assert wait_until(lambda: entities() == expected_entities, TIMEOUT), rmw_node.graph()
    tokens = rmw_node.graph()
    nodes = [p for p in tokens if p[5] == "NN"]
    assert len(nodes) == 1 and len(nodes[0]) == 9, tokens
    node = nodes[0]
    assert node[0] == "@ros2_lv" and node[1] == str(bot1[1])
    assert node[3] == node[4], "a node's entity id is its node id"
    assert node[6:] == ["%", "%", "rosgate_bot1"], "enclave /, namespace /, the bridge's node"
    for parts in tokens:
        assert parts[:4] == node[:4], "every entity is the bridge's node's, in its domain"
        assert parts[6:9] == node[6:9]
    entity_ids = [p[4] for p in tokens if p[5] != "NN"]
    assert len(set(entity_ids)) == 5 and node[4] not in entity_ids


def test_a_message_from_rclpy_reaches_an_rmw_zenoh_subscriber_with_its_attachment(
        bot1, rmw_node, ros_side):
    _bridge, d = bot1
    got: list[tuple[str, bytes, bytes | None]] = []
    arrived = threading.Condition()

    def sample(s: zenoh.Sample) -> None:
        with arrived:
            got.append((str(s.key_expr), s.payload.to_bytes(),
                        s.attachment.to_bytes() if s.attachment is not None else None))
            arrived.notify_all()

    key = rmw_node.key("/chatter", STRING)
    subscriber = rmw_node.session.declare_subscriber(key, zenoh.handlers.Callback(
        sample, indirect=False))
    rmw_node.announce("MS", "/chatter", STRING, "::,10:,:,:,,")
    publisher = ros_side(d, "talker").publisher("/chatter", String, 10)
    before = time.time_ns()
    deadline = time.monotonic() + TIMEOUT
    warmup = serialize_message(String(data="warm up"))
    with arrived:
        while not got:  # ROS discovery and the subscription's spread take a moment
            assert time.monotonic() < deadline, "nothing arrived on the rmw_zenoh key"
            publisher.publish(warmup)
            arrived.wait(0.2)
    start = len(got)
    sent = [serialize_message(String(data=f"hello {n}")) for n in range(5)]
    for payload in sent:
        publisher.publish(payload)
    # a warm-up published before the first one arrived may still arrive after it: not counted
    hellos = lambda: [p for _, p, _ in got[start:] if p != warmup]
    with arrived:
        assert arrived.wait_for(lambda: len(hellos()) >= 5, TIMEOUT), got
    subscriber.undeclare()
    assert {k for k, _, _ in got} == {key}
    assert hellos() == sent, "the CDR, header and all, byte for byte"
    assert sent[0][:4] in (b"\x00\x01\x00\x00", b"\x00\x00\x00\x00")
    read = [read_attachment(a) for _, _, a in got if a is not None]
    assert len(read) == len(got), "every sample carries an attachment"
    numbers = [seq for seq, _, _ in read]
    assert numbers[0] >= 1 and numbers == list(range(numbers[0], numbers[0] + len(numbers))), \
        "sequence numbers go up by one per sample"
    assert all(before - 10**9 <= stamp <= time.time_ns() for _, stamp, _ in read)
    assert len({gid for _, _, gid in read}) == 1, "one publisher, one GID"
    # the GID rmw_zenoh's graph computes for the bridge's publisher from its token
    publishers = ["/".join(p) for p in rmw_node.graph() if p[5] == "MP" and p[9] == "%chatter"]
    assert len(publishers) == 1, publishers
    assert read[0][2] == gid_of(publishers[0]), "the attachment's GID is the token's XXH3-128"


def test_a_message_from_an_rmw_zenoh_publisher_reaches_rclpy_field_by_field(
        bot1, rmw_node, ros_side):
    bridge_, d = bot1
    inbox = ros_side(d, "listener").listen("/cmd_vel", Twist, qos_profile_sensor_data)
    rmw_node.announce("MP", "/robot1/cmd_vel", TWIST, "2::,5:,:,:,,")
    publisher = rmw_node.session.declare_publisher(rmw_node.key("/robot1/cmd_vel", TWIST))
    message = Twist()
    message.linear.x, message.linear.y, message.linear.z = 1.5, -0.25, 3.0
    message.angular.x, message.angular.y, message.angular.z = 0.125, 0.0, -0.75
    payload = serialize_message(message)
    deadline = time.monotonic() + TIMEOUT
    while not inbox.wait_count(1, 0.2):
        assert time.monotonic() < deadline, "nothing was published on the ROS side"
        publisher.put(payload, attachment=rmw_node.attachment())
    got = inbox.items[0]
    assert (got.linear.x, got.linear.y, got.linear.z) == (1.5, -0.25, 3.0)
    assert (got.angular.x, got.angular.y, got.angular.z) == (0.125, 0.0, -0.75)
    # rmw_zenoh drops a sample without its attachment ("Unable to obtain attachment"): so does
    # rosgate, and counts it
    count = len(inbox.items)
    publisher.put(serialize_message(Twist()), attachment=None)
    publisher.put(serialize_message(Twist()), attachment=b"\x01" * 20)
    key = rmw_node.key("/robot1/cmd_vel", TWIST)
    assert bridge_.wait_log(f"dropped (bad_attachment): on {key}: no attachment", TIMEOUT), \
        bridge_.log
    publisher.put(payload, attachment=rmw_node.attachment())
    assert inbox.wait_count(count + 1, TIMEOUT)
    assert all(m.linear.x == 1.5 for m in inbox.items[count:]), "the two bad samples never came"
    publisher.undeclare()
    bridge_.stop()  # its counters, in its log as it stops
    assert "bad_attachment=2" in bridge_.log, bridge_.log


def test_a_late_rmw_zenoh_subscriber_gets_the_last_transient_local_samples(
        bot1, rmw_node, ros_side):
    _bridge, d = bot1
    publisher = ros_side(d, "mapper").publisher("/map", String, LATCHED)
    key = rmw_node.key("/map", STRING)
    live: list[bytes] = []
    rmw_node.session.declare_subscriber(key, zenoh.handlers.Callback(
        lambda s: live.append(s.payload.to_bytes()), indirect=False))
    assert wait_until(lambda: publisher.get_subscription_count() >= 1, TIMEOUT)
    sent = [f"map {n}" for n in range(5)]
    for text in sent:
        publisher.publish(String(data=text))

    def texts(samples: list[bytes]) -> list[str]:  # CDR padding bytes are not compared
        return [deserialize_message(s, String).data for s in samples]

    assert wait_until(lambda: texts(live)[-3:] == sent[-3:], TIMEOUT), texts(live)
    late: list[tuple[bytes, bytes | None]] = []
    # rmw_subscription_data.cpp: a transient_local subscription is an advanced subscriber that
    # detects late publishers and queries their history, up to its depth
    subscriber = zenoh.ext.declare_advanced_subscriber(
        rmw_node.session, key, zenoh.handlers.Callback(
            lambda s: late.append((s.payload.to_bytes(), s.attachment.to_bytes()
                                   if s.attachment is not None else None)), indirect=False),
        history=zenoh.ext.HistoryConfig(detect_late_publishers=True, max_samples=3))
    rmw_node.announce("MS", "/map", STRING, ":1:,3:,:,:,,")
    assert wait_until(lambda: len(late) >= 3, TIMEOUT), late
    time.sleep(0.5)  # a fourth sample would be a bug: give it the chance to show
    subscriber.undeclare()
    assert texts([p for p, _ in late]) == sent[-3:], "the cache keeps the topic's depth (3)"
    numbers = [read_attachment(a)[0] for _, a in late if a is not None]
    assert len(numbers) == 3 and numbers == sorted(numbers), "kept with their attachments"


def test_rosgate_logs_the_rmw_zenoh_nodes_it_sees(bot1, rmw_node):
    bridge_, _d = bot1
    rmw_node.announce("MS", "/chatter", STRING, "::,10:,:,:,,")
    assert bridge_.wait_log(f"rmw_zenoh {rmw_node.zid}: /listener", TIMEOUT), bridge_.log
    assert bridge_.wait_log(f"rmw_zenoh {rmw_node.zid}: subscriber on /chatter "
                            "[std_msgs/msg/String] of listener", TIMEOUT), bridge_.log
    rmw_node.close()
    assert bridge_.wait_log(f"rmw_zenoh {rmw_node.zid}: /listener is gone", TIMEOUT), \
        bridge_.log


def test_check_says_which_entries_speak_rmw_zenoh(tmp_path, router):
    path = bot1_file(tmp_path, router, "  - {topic: /status, type: std_msgs/msg/String, "
                     "direction: transmit}\n")
    result = rosgate("check", str(path))
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert "  /chatter -> chatter  [std_msgs/msg/String] zenoh cdr none  (rmw_zenoh)" in lines
    assert ("  /cmd_vel <- robot1/cmd_vel  [geometry_msgs/msg/Twist] zenoh cdr none  (rmw_zenoh)"
            in lines)
    assert "  /status -> rosgate/bot1/status  [std_msgs/msg/String] zenoh cdr none" in lines, \
        "an entry with rosgate's envelope stays rosgate's"
    assert "  /set <- robot1/set  [std_srvs/srv/SetBool] zenoh cdr none  (rmw_zenoh)" in lines
    assert "  /rmw_set -> rmw_set  [std_srvs/srv/SetBool] zenoh cdr none  (rmw_zenoh)" in lines


def test_check_refuses_a_key_that_is_no_ros_name(tmp_path, router):
    path = bot1_file(tmp_path, router, "  - {topic: /odom, type: std_msgs/msg/String, "
                     "direction: transmit, framing: none, remote: /robot-1/odom}\n")
    text = user_error(rosgate("check", str(path)))
    assert f"{path}:11: topics[3].remote: 'robot-1/odom' is not a ROS name" in text, text
    assert "e.g. remote: /robot1/cmd_vel" in text


def test_an_rmw_zenoh_client_calls_a_service_rosgate_bridges(bot1, rmw_node, ros_side):
    bridge_, d = bot1
    ros_side(d, "server").ros.node.create_service(SetBool, "/set", echo_set_bool,
                                                  qos_profile=DEEP)
    rmw_node.announce("SC", "/robot1/set", SETBOOL, "::,10:,:,:,,")
    key = rmw_node.key("/robot1/set", SETBOOL)

    def call(data: bool, attachment: bytes | None) -> list[zenoh.Reply]:
        # rmw_send_request: the request's CDR, the call's attachment, every complete queryable
        return [r for r in rmw_node.session.get(
            key, payload=serialize_message(SetBool.Request(data=data)), attachment=attachment,
            target=zenoh.QueryTarget.ALL_COMPLETE, timeout=5) if r.ok is not None]

    deadline = time.monotonic() + TIMEOUT
    while not (replies := call(True, rmw_node.attachment())):
        assert time.monotonic() < deadline, "the service never answered"  # ROS discovery
        time.sleep(0.2)
    asked = rmw_node.seq
    assert len(replies) == 1 and str(replies[0].ok.key_expr) == key
    answer = deserialize_message(replies[0].ok.payload.to_bytes(), SetBool.Response)
    assert (answer.success, answer.message) == (True, "data=True")
    assert replies[0].ok.attachment is not None
    seq, stamp, gid = read_attachment(replies[0].ok.attachment.to_bytes())
    assert (seq, gid) == (asked, bytes(range(16))), "the call's number and the caller's GID"
    assert abs(stamp - time.time_ns()) < 30 * 10**9
    replies = call(False, rmw_node.attachment())
    assert read_attachment(replies[0].ok.attachment.to_bytes())[0] == asked + 1
    answer = deserialize_message(replies[0].ok.payload.to_bytes(), SetBool.Response)
    assert (answer.success, answer.message) == (True, "data=False")
    assert call(True, None) == [], "a call without its attachment gets no answer"
    assert bridge_.wait_log(f"dropped (bad_attachment): a call on {key}: no attachment",
                            TIMEOUT), bridge_.log


def test_rosgate_calls_a_service_an_rmw_zenoh_node_serves(bot1, rmw_node, ros_side):
    _bridge, d = bot1
    key = rmw_node.key("/rmw_set", SETBOOL)
    seen: list[tuple[bool, bytes | None]] = []

    def serve(query: zenoh.Query) -> None:  # rmw_service_data.cpp, seen from outside
        attachment = query.attachment.to_bytes() if query.attachment is not None else None
        data = deserialize_message(query.payload.to_bytes(), SetBool.Request).data
        seen.append((data, attachment))
        seq, _stamp, gid = read_attachment(attachment or b"")
        query.reply(key, serialize_message(SetBool.Response(
            success=not data, message=f"rmw node got {data}")),
            attachment=struct.pack("<qqB", seq, time.time_ns(), 16) + gid)

    queryable = rmw_node.session.declare_queryable(
        key, zenoh.handlers.Callback(serve, indirect=False), complete=True)
    rmw_node.announce("SS", "/rmw_set", SETBOOL, "::,10:,:,:,,")
    caller = Caller(ros_side(d, "client"), SetBool, "/rmw_set")
    answers = caller.call_many([SetBool.Request(data=False), SetBool.Request(data=True)], 10)
    queryable.undeclare()
    assert [(a.success, a.message) for a in answers] == [(True, "rmw node got False"),
                                                         (False, "rmw node got True")]
    assert sorted(data for data, _ in seen) == [False, True]
    calls = [read_attachment(a) for _, a in seen if a is not None]
    assert len(calls) == 2, "every call carries rmw_zenoh's attachment"
    assert sorted(seq for seq, _, _ in calls) == [1, 2], "numbered from 1, one up per call"
    assert len({gid for _, _, gid in calls}) == 1, "one client, one GID"


def test_check_wants_the_name_of_a_service_on_the_rmw_zenoh_side(tmp_path, router):
    path = bot1_file(tmp_path, router)
    path.write_text(path.read_text() + (
        "  - {service: /reset, type: std_srvs/srv/SetBool, direction: receive}\n"))
    text = user_error(rosgate("check", str(path)))
    assert f"{path}:14: services[2].service: a service rmw_zenoh nodes " \
           "call or serve needs remote:" in text, text
    assert "add remote: /reset to this entry" in text


def test_the_rmw_zenoh_side_may_have_a_domain_of_its_own(tmp_path, router, bridge, domain,
                                                         ros_side):
    d = domain()  # the bridge's DDS side; the rmw_zenoh nodes are in domain 42
    bridge(bot1_file(tmp_path, router, options=", domain: 42"), d)
    node = RmwNode(router, 42)
    try:
        assert wait_until(lambda: len(node.graph()) == 6, TIMEOUT), node.graph()
        assert {p[1] for p in node.graph()} == {"42"}
        got: list[bytes] = []
        node.session.declare_subscriber(node.key("/chatter", STRING), zenoh.handlers.Callback(
            lambda s: got.append(s.payload.to_bytes()), indirect=False))
        publisher = ros_side(d, "talker").publisher("/chatter", String, 10)
        payload = serialize_message(String(data="to domain 42"))
        deadline = time.monotonic() + TIMEOUT
        while not wait_until(lambda: bool(got), 0.2):
            assert time.monotonic() < deadline, "nothing arrived on 42/chatter/..."
            publisher.publish(payload)
        assert got[0][:len(payload)] == payload  # DDS may pad it to a 4-byte boundary
        assert deserialize_message(got[0], String).data == "to domain 42"
    finally:
        node.close()
