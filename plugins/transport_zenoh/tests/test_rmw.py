"""rmw_zenoh's keys, tokens, QoS and attachments, byte for byte.

The expected values are worked out by hand from ros2/rmw_zenoh's sources
(``rmw_zenoh_cpp/src/detail/``): ``liveliness_utils.cpp`` (``TopicInfo``: the data key with the
name's slashes stripped at both ends; ``Entity``: the token's thirteen parts, ``mangle_name``
writing '/' as '%'; ``qos_to_keyexpr``: each QoS field empty where it equals the default),
``qos.cpp`` (the defaults: reliable, transient local, keep last 42, infinite durations, automatic
liveliness; ``best_available_qos``: depth 0 becomes 42, durations left at 0 become infinite),
``attachment_helpers.cpp`` (``AttachmentData::serialize_to_zbytes``: int64, int64, then the GID
as an array, which zenoh-cpp's serializer writes with its length) and
``type_support_common.cpp`` (``pkg::msg::dds_::Name_``). zenoh's own serializer
(``zenoh.ext.z_serialize``, the Rust code zenoh-cpp calls through zenoh-c) checks the bytes."""

from __future__ import annotations

import pytest
from rclpy.duration import Duration
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    LivelinessPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)
from rosgate_transport_zenoh import rmw
from rosgate_transport_zenoh.rmw import Entity, Kind, Node, Qos
from zenoh.ext import Int64, z_serialize

STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
ZID = "26f163a320e95b83d877a2c32706d88a"
NODE = Node(7, ZID, "0", "rosgate_bot1")


# -- data keys ------------------------------------------------------------------------------------
@pytest.mark.parametrize("name, key", [
    ("/chatter", f"0/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"),
    ("/robot1/cmd_vel", f"0/robot1/cmd_vel/std_msgs::msg::dds_::String_/{STRING_HASH}"),
    ("/robot1/cmd_vel/", f"0/robot1/cmd_vel/std_msgs::msg::dds_::String_/{STRING_HASH}"),
    ("chatter", f"0/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"),
])
def test_the_data_key_strips_the_name_and_keeps_its_inner_slashes(name, key):
    assert rmw.topic_key(0, name, "std_msgs/msg/String", STRING_HASH) == key


def test_type_names_are_the_dds_ones_both_ways():
    assert rmw.dds_type("geometry_msgs/msg/Twist") == "geometry_msgs::msg::dds_::Twist_"
    assert rmw.dds_type("std_srvs/srv/SetBool") == "std_srvs::srv::dds_::SetBool_"
    assert rmw.ros_type("geometry_msgs::msg::dds_::Twist_") == "geometry_msgs/msg/Twist"
    for bad in ("geometry_msgs/msg/Twist", "a::b::c::D_", "a::msg::dds_::Twist", "a::msg::dds_::_"):
        with pytest.raises(ValueError):
            rmw.ros_type(bad)


# -- QoS ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("profile, chunk", [
    (QoSProfile(depth=10), ":2:,10:,:,:,,"),  # rclpy's default: volatile, keep last 10
    (qos_profile_sensor_data, "2:2:,5:,:,:,,"),  # best effort, volatile, keep last 5
    (QoSProfile(depth=42, durability=DurabilityPolicy.TRANSIENT_LOCAL), "::,:,:,:,,"),
    (QoSProfile(depth=0, durability=DurabilityPolicy.TRANSIENT_LOCAL), "::,:,:,:,,"),  # 0 -> 42
    (QoSProfile(depth=3, durability=DurabilityPolicy.SYSTEM_DEFAULT,
                reliability=ReliabilityPolicy.SYSTEM_DEFAULT), "::,3:,:,:,,"),
    (QoSProfile(depth=1, history=HistoryPolicy.KEEP_ALL), ":2:2,1:,:,:,,"),
    (QoSProfile(depth=10, deadline=Duration(seconds=1, nanoseconds=500_000_000),
                lifespan=Duration(seconds=2)), ":2:,10:1,500000000:2,0:,,"),
    (QoSProfile(depth=10, liveliness=LivelinessPolicy.MANUAL_BY_TOPIC,
                liveliness_lease_duration=Duration(seconds=3)), ":2:,10:,:,:3,3,0"),
])
def test_a_profile_becomes_the_token_qos_rmw_zenoh_writes(profile, chunk):
    assert Qos.of(profile).chunk() == chunk
    assert Qos.parse(chunk) == Qos.of(profile)


def test_a_qos_part_is_read_field_by_field():
    qos = Qos.parse("2:2:2,5:1,2:3,4:3,5,6")
    assert (qos.reliability, qos.durability, qos.history, qos.depth) == (2, 2, 2, 5)
    assert (qos.deadline, qos.lifespan, qos.liveliness, qos.lease) == ((1, 2), (3, 4), 3, (5, 6))
    assert not qos.reliable and not qos.transient_local and qos.keep_all
    assert Qos.parse("::,:,:,:,,") == Qos()
    assert Qos().deadline == (9223372036, 854775807)  # RMW_DURATION_INFINITE


@pytest.mark.parametrize("chunk", ["", "1:2", "::,:,:,:,", "::,:,:,:", "x::,:,:,:,,",
                                   "::1:,:,:,:,,", "::-1,:,:,:,,"])
def test_a_qos_part_that_is_not_one_is_refused(chunk):
    with pytest.raises(ValueError):
        Qos.parse(chunk)


# -- tokens ---------------------------------------------------------------------------------------
def test_a_node_token_has_nine_parts_with_the_node_id_twice():
    assert NODE.token() == f"@ros2_lv/7/{ZID}/0/0/NN/%/%/rosgate_bot1"
    spaced = Node(0, ZID, "3", "driver", namespace="/robots/a", enclave="/secure")
    assert spaced.token() == f"@ros2_lv/0/{ZID}/3/3/NN/%secure/%robots%a/driver"
    assert rmw.parse(spaced.token()) == spaced


def test_an_entity_token_holds_its_topic_type_hash_and_qos():
    entity = Entity(NODE, "1", Kind.PUBLISHER, "/robot1/chatter", "std_msgs/msg/String",
                    STRING_HASH, Qos.of(QoSProfile(depth=10)))
    assert entity.token() == (f"@ros2_lv/7/{ZID}/0/1/MP/%/%/rosgate_bot1/%robot1%chatter/"
                              f"std_msgs::msg::dds_::String_/{STRING_HASH}/:2:,10:,:,:,,")
    assert entity.key() == f"7/robot1/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
    assert rmw.parse(entity.token()) == entity
    subscriber = Entity(NODE, "2", Kind.SUBSCRIBER, "/chatter", "std_msgs/msg/String",
                        STRING_HASH, Qos.of(qos_profile_sensor_data))
    parts = subscriber.token().split("/")
    assert len(parts) == 13 and parts[5] == "MS" and parts[12] == "2:2:,5:,:,:,,"


def test_tokens_other_nodes_declare_are_read():
    token = (f"@ros2_lv/0/{ZID}/5/9/MS/%/%ns/listener/%ns%chatter/"
             f"std_msgs::msg::dds_::String_/{STRING_HASH}/2::,5:,:,:,,")
    found = rmw.parse(token)
    assert isinstance(found, Entity)
    assert (found.node.domain, found.node.zid, found.node.nid, found.id) == (0, ZID, "5", "9")
    assert (found.node.namespace, found.node.name, found.node.enclave) == ("/ns", "listener", "/")
    assert (found.kind, found.name, found.type, found.hash) == (
        Kind.SUBSCRIBER, "/ns/chatter", "std_msgs/msg/String", STRING_HASH)
    assert found.qos == Qos(reliability=2, depth=5)


@pytest.mark.parametrize("token", [
    f"@ros2_lv/0/{ZID}/0/0/NN/%/%",  # too few parts
    f"@ros2_lv/0/{ZID}/0/0/NN/%/%/node/extra",
    f"@ros2_lv/0/{ZID}/0/1/MP/%/%/node",  # an entity without its topic
    f"@ros2_lv/0/{ZID}/0/1/MP/%/%/node/%t/std_msgs::msg::dds_::String_/{STRING_HASH}/bad",
    f"@ros2_lv/0/{ZID}/0/1/MP/%/%/node/%t/std_msgs/{STRING_HASH}/::,:,:,:,,",
    f"@ros2_lv/0/{ZID}/0/1/XX/%/%/node/%t/std_msgs::msg::dds_::String_/{STRING_HASH}/::,:,:,:,,",
    f"@ros2_lv/zero/{ZID}/0/0/NN/%/%/node",
    f"@other/0/{ZID}/0/0/NN/%/%/node",
    f"@/{ZID}/@ros2_lv/MP/chatter/std_msgs§msg§String/:1:0:0,10",  # zenoh-bridge-ros2dds's
])
def test_a_token_that_is_not_rmw_zenohs_is_ignored(token):
    assert rmw.parse(token) is None


def test_each_entity_has_a_gid_of_its_own():
    one = Entity(NODE, "1", Kind.PUBLISHER, "/a", "std_msgs/msg/String", STRING_HASH)
    two = Entity(NODE, "2", Kind.PUBLISHER, "/a", "std_msgs/msg/String", STRING_HASH)
    assert len(one.gid()) == 16 and one.gid() == rmw.gid(one.token())
    assert one.gid() != two.gid()
    assert rmw.everything(7) == "@ros2_lv/7/**"


# -- attachments ----------------------------------------------------------------------------------
GID = bytes(range(16))
STAMP = 1_764_620_000_123_456_789


def test_the_attachment_is_two_int64_and_a_16_byte_array():
    data = rmw.attachment(1, STAMP, GID)
    assert data == ((1).to_bytes(8, "little") + STAMP.to_bytes(8, "little") + b"\x10" + GID)
    assert len(data) == 33
    assert data == z_serialize((Int64(1), Int64(STAMP), GID)).to_bytes()
    assert rmw.read_attachment(data) == rmw.Attachment(1, STAMP, GID)
    with pytest.raises(ValueError):
        rmw.attachment(1, STAMP, GID[:8])


def test_the_keyed_attachment_of_rmw_zenoh_before_0_2_4_is_read_too():
    keyed = z_serialize(("sequence_number", Int64(42), "source_timestamp", Int64(STAMP),
                         "source_gid", GID)).to_bytes()
    assert keyed[:16] == b"\x0fsequence_number"
    assert rmw.read_attachment(keyed) == rmw.Attachment(42, STAMP, GID)


@pytest.mark.parametrize("data", [
    None, b"", b"\x01" * 32, b"\x01" * 34, (1).to_bytes(8, "little") * 2 + b"\x08" + GID,
    z_serialize(("sequence_number", Int64(1), "source_time", Int64(2), "source_gid",
                 GID)).to_bytes(),
    z_serialize(("sequence_number", Int64(1), "source_timestamp", Int64(2), "source_gid",
                 GID[:4])).to_bytes(),
    b"\x0fsequence_number\x01",
], ids=["none", "empty", "short", "long", "gid length", "wrong key", "short gid", "cut"])
def test_an_attachment_that_is_not_rmw_zenohs_is_refused(data):
    with pytest.raises(ValueError):
        rmw.read_attachment(data)


# -- the graph rosgate reads ----------------------------------------------------------------------
def test_the_graph_counts_other_nodes_entities_and_ignores_its_own_and_junk(caplog):
    from rosgate_transport_zenoh.rmw_dialect import Graph

    other = Node(7, "aa11", "0", "listener", namespace="/ns")
    sub = Entity(other, "1", Kind.SUBSCRIBER, "/chatter", "std_msgs/msg/String", STRING_HASH)
    mine = Entity(NODE, "1", Kind.PUBLISHER, "/chatter", "std_msgs/msg/String", STRING_HASH)
    graph = Graph(ZID)
    with caplog.at_level("INFO", logger="rosgate"):
        for token in (other.token(), sub.token(), sub.token(), mine.token(), NODE.token(),
                      "@ros2_lv/7/aa11/0/1/MS/%/%", "@ros2_lv/7/aa11/0/1/MS/%/%/x/%t/y/z/q"):
            graph.changed(token, True)
    assert dict(graph.counts) == {"node": 1, "subscriber": 1}, "its own and junk are not counted"
    assert graph.known == {other.token(): other, sub.token(): sub}
    assert "rmw_zenoh aa11: /ns/listener" in caplog.text
    assert "rmw_zenoh aa11: subscriber on /chatter [std_msgs/msg/String] of listener" in caplog.text
    with caplog.at_level("INFO", logger="rosgate"):
        graph.changed(sub.token(), False)
        graph.changed(sub.token(), False)  # a second departure changes nothing
    assert dict(graph.counts) == {"node": 1, "subscriber": 0}
    assert "subscriber on /chatter [std_msgs/msg/String] of listener is gone" in caplog.text
