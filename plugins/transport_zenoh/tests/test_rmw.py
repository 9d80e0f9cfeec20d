"""rmw_zenoh's keys, tokens, QoS and attachments, byte for byte.

The expected values are worked out by hand from ros2/rmw_zenoh's sources
(``rmw_zenoh_cpp/src/detail/``): ``liveliness_utils.cpp`` (``TopicInfo``: the data key with the
name's slashes stripped at both ends; ``Entity``: the token's thirteen parts, ``mangle_name``
writing '/' as '%'; ``qos_to_keyexpr``: each QoS field empty where it equals the default),
``qos.cpp`` (the defaults: reliable, volatile since 0.2.3, keep last 42, infinite durations,
automatic liveliness; ``best_available_qos``: depth 0 becomes 42, durations left at 0 become
infinite),
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
    (QoSProfile(depth=10), "::,10:,:,:,,"),  # rclpy's default: volatile, keep last 10
    (qos_profile_sensor_data, "2::,5:,:,:,,"),  # best effort, volatile, keep last 5
    (QoSProfile(depth=42, durability=DurabilityPolicy.VOLATILE), "::,:,:,:,,"),
    (QoSProfile(depth=0), "::,:,:,:,,"),  # depth 0 -> 42
    (QoSProfile(depth=3, durability=DurabilityPolicy.TRANSIENT_LOCAL), ":1:,3:,:,:,,"),
    (QoSProfile(depth=3, durability=DurabilityPolicy.SYSTEM_DEFAULT,
                reliability=ReliabilityPolicy.SYSTEM_DEFAULT), "::,3:,:,:,,"),
    (QoSProfile(depth=1, history=HistoryPolicy.KEEP_ALL), "::2,1:,:,:,,"),
    (QoSProfile(depth=10, deadline=Duration(seconds=1, nanoseconds=500_000_000),
                lifespan=Duration(seconds=2)), "::,10:1,500000000:2,0:,,"),
    (QoSProfile(depth=10, liveliness=LivelinessPolicy.MANUAL_BY_TOPIC,
                liveliness_lease_duration=Duration(seconds=3)), "::,10:,:,:3,3,0"),
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
    assert Qos().durability == 2 and not Qos().transient_local, "volatile since rmw_zenoh 0.2.3"
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
                              f"std_msgs::msg::dds_::String_/{STRING_HASH}/::,10:,:,:,,")
    assert entity.key() == f"7/robot1/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
    assert rmw.parse(entity.token()) == entity
    subscriber = Entity(NODE, "2", Kind.SUBSCRIBER, "/chatter", "std_msgs/msg/String",
                        STRING_HASH, Qos.of(qos_profile_sensor_data))
    parts = subscriber.token().split("/")
    assert len(parts) == 13 and parts[5] == "MS" and parts[12] == "2::,5:,:,:,,"


def test_tokens_other_nodes_declare_are_read():
    token = (f"@ros2_lv/0/{ZID}/5/9/MS/%/%ns/listener/%ns%chatter/"
             f"std_msgs::msg::dds_::String_/{STRING_HASH}/2::,5:,:,:,,")  # best effort
    found = rmw.parse(token)
    assert isinstance(found, Entity)
    assert (found.node.domain, found.node.zid, found.node.nid, found.id) == (0, ZID, "5", "9")
    assert (found.node.namespace, found.node.name, found.node.enclave) == ("/ns", "listener", "/")
    assert (found.kind, found.name, found.type, found.hash) == (
        Kind.SUBSCRIBER, "/ns/chatter", "std_msgs/msg/String", STRING_HASH)
    assert found.qos == Qos(reliability=2, depth=5)


# Tokens as rmw_zenoh's Jazzy release writes them, verbatim from ros2/rmw_zenoh docs/design.md
# ("Graph Cache": demo_nodes_cpp's listener, talker and add_two_ints in domain 2), which
# rmw_zenoh_cpp 0.2.10 (Jazzy) writes: Entity::Entity and qos_to_keyexpr in
# src/detail/liveliness_utils.cpp, the defaults in src/detail/qos.cpp (volatile since 0.2.3).
# The demos' QoS: reliable, volatile, keep last 10 (listener, services) and 7 (talker).
ADD_TWO_INTS_HASH = "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a"
RELEASE_TOKENS = {
    "listener": "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener",
    "subscription": "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/10/MS/%/%/listener/%chatter/"
                    "std_msgs::msg::dds_::String_/RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1"
                    "288021743503259e948f6b1a18/::,10:,:,:,,",
    "publisher": "@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/"
                 "std_msgs::msg::dds_::String_/RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288"
                 "021743503259e948f6b1a18/::,7:,:,:,,",
    "server": "@ros2_lv/2/f9980ee0495eaafb3e38f0d19e2eae12/0/10/SS/%/%/add_two_ints_server/"
              "%add_two_ints/example_interfaces::srv::dds_::AddTwoInts_/RIHS01_e118de6bf5eeb66a2"
              "491b5bda11202e7b68f198d6f67922cf30364858239c81a/::,10:,:,:,,",
    "client": "@ros2_lv/2/e1dc8d1b45ae8717fce78689cc655685/0/10/SC/%/%/add_two_ints_client/"
              "%add_two_ints/example_interfaces::srv::dds_::AddTwoInts_/RIHS01_e118de6bf5eeb66a2"
              "491b5bda11202e7b68f198d6f67922cf30364858239c81a/::,10:,:,:,,",
}


def test_the_releases_tokens_are_read_field_by_field_with_volatile_as_the_default():
    sub = rmw.parse(RELEASE_TOKENS["subscription"])
    assert isinstance(sub, Entity)
    assert (sub.node.domain, sub.node.zid, sub.node.nid, sub.id, sub.kind) == (
        2, "aac3178e146ba6f1fc6e6a4085e77f21", "0", "10", Kind.SUBSCRIBER)
    assert (sub.node.enclave, sub.node.namespace, sub.node.name) == ("/", "/", "listener")
    assert (sub.name, sub.type, sub.hash) == ("/chatter", "std_msgs/msg/String", STRING_HASH)
    assert (sub.qos.reliability, sub.qos.durability, sub.qos.history, sub.qos.depth) == (
        1, 2, 1, 10), "reliable, VOLATILE, keep last 10"
    assert not sub.qos.transient_local, "an empty durability field is volatile since 0.2.3"
    talker = rmw.parse(RELEASE_TOKENS["publisher"])
    assert isinstance(talker, Entity) and talker.kind is Kind.PUBLISHER
    assert (talker.node.name, talker.qos.depth, talker.qos.transient_local) == ("talker", 7, False)
    for kind, which in ((Kind.SERVER, "server"), (Kind.CLIENT, "client")):
        found = rmw.parse(RELEASE_TOKENS[which])
        assert isinstance(found, Entity)
        assert (found.kind, found.name, found.type, found.hash) == (
            kind, "/add_two_ints", "example_interfaces/srv/AddTwoInts", ADD_TWO_INTS_HASH)
        assert found.qos == Qos(depth=10)
    listener = rmw.parse(RELEASE_TOKENS["listener"])
    assert listener == Node(2, "aac3178e146ba6f1fc6e6a4085e77f21", "0", "listener")


def test_rosgate_writes_the_releases_tokens_exactly():
    listener = Node(2, "aac3178e146ba6f1fc6e6a4085e77f21", "0", "listener")
    talker = Node(2, "8b20917502ee955ac4476e0266340d5c", "0", "talker")
    server = Node(2, "f9980ee0495eaafb3e38f0d19e2eae12", "0", "add_two_ints_server")
    client = Node(2, "e1dc8d1b45ae8717fce78689cc655685", "0", "add_two_ints_client")
    made = {
        "listener": listener.token(),
        "subscription": Entity(listener, "10", Kind.SUBSCRIBER, "/chatter", "std_msgs/msg/String",
                               STRING_HASH, Qos.of(QoSProfile(depth=10))).token(),
        "publisher": Entity(talker, "10", Kind.PUBLISHER, "/chatter", "std_msgs/msg/String",
                            STRING_HASH, Qos.of(QoSProfile(depth=7))).token(),
        "server": Entity(server, "10", Kind.SERVER, "/add_two_ints",
                         "example_interfaces/srv/AddTwoInts", ADD_TWO_INTS_HASH,
                         Qos.of(QoSProfile(depth=10))).token(),
        "client": Entity(client, "10", Kind.CLIENT, "/add_two_ints",
                         "example_interfaces/srv/AddTwoInts", ADD_TWO_INTS_HASH,
                         Qos.of(QoSProfile(depth=10))).token(),
    }
    assert made == RELEASE_TOKENS


def test_a_transient_local_entity_says_so_in_its_token():
    latched = Qos.of(QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL))
    assert latched.chunk() == ":1:,1:,:,:,,"
    assert Qos.parse(":1:,1:,:,:,,").transient_local


# The GID rmw_zenoh_cpp 0.2.10 (Jazzy) gives an entity: Entity::Entity in
# src/detail/liveliness_utils.cpp hashes the whole token with simplified_XXH3_128bits
# (src/detail/simplified_xxhash3.cpp: XXH3 with its default secret, seed 0) and copies low64 then
# high64 into the 16 bytes (little endian, as on every machine ROS 2 Jazzy supports). The hash
# below is the reference xxHash's XXH3-128 of the talker's token, written out once.
TALKER_XXH3_128 = 0x1C7D90177A6DD80C_FFD9DCEA310F17AC


def test_an_entitys_gid_is_rmw_zenohs_xxh3_128_of_its_token():
    import xxhash

    # the library is the reference algorithm: XXH3-128 of nothing, from xxHash's own tests
    assert xxhash.xxh3_128_hexdigest(b"") == "99aa06d3014798d86001c324468d497f"
    token = RELEASE_TOKENS["publisher"]
    assert xxhash.xxh3_128_intdigest(token.encode()) == TALKER_XXH3_128
    low, high = TALKER_XXH3_128 & (2**64 - 1), TALKER_XXH3_128 >> 64
    expected = low.to_bytes(8, "little") + high.to_bytes(8, "little")
    assert rmw.gid(token) == expected
    talker = rmw.parse(token)
    assert isinstance(talker, Entity) and talker.gid() == expected, "parsed and written back"


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


def test_the_graph_names_the_package_of_a_type_not_installed_here(caplog):
    from rosgate_transport_zenoh.rmw_dialect import Graph

    other = Node(7, "aa11", "0", "talker")
    gadget = Entity(other, "1", Kind.PUBLISHER, "/gadget", "gadget_msgs/msg/Gadget",
                    "RIHS01_" + "6a" * 32)
    chatter = Entity(other, "2", Kind.PUBLISHER, "/chatter", "std_msgs/msg/String", STRING_HASH)
    graph = Graph(ZID)
    with caplog.at_level("INFO", logger="rosgate"):
        for token in (other.token(), gadget.token(), chatter.token()):
            graph.changed(token, True)
    lines = {r.getMessage() for r in caplog.records}
    assert ("rmw_zenoh aa11: publisher on /gadget [gadget_msgs/msg/Gadget] of talker (its type "
            "is not installed on this side: interface package 'gadget_msgs' is not installed "
            "(apt install ros-$ROS_DISTRO-gadget-msgs, or pip install ros-jazzy-gadget-msgs))"
            ) in lines
    assert "rmw_zenoh aa11: publisher on /chatter [std_msgs/msg/String] of talker" in lines
    assert dict(graph.counts) == {"node": 1, "publisher": 2}

