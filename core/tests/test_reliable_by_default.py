"""A topic's QoS decides its link's guarantee: a reliable topic on a datagram link is repaired
(retransmit) unless its entry says otherwise, a best-effort one is not; what a reliable topic
gives up without repairs is said at start-up (``rosgate check`` and ``rosgate run``)."""

from __future__ import annotations

import logging

import pytest

from rosgate.config import loads, topic_from_mapping, topic_to_mapping
from rosgate.engine import Engine
from rosgate.plugins import DISABLE_VARIABLE, Plugins

HEAD = "bridge: {name: robot1, role: peer, peer: 127.0.0.2, insecure: true}\nplugins: {}\n"


def recovery_of(entry: str, plugins: Plugins | None = None) -> str | None:
    engine = Engine(loads(HEAD + "topics:\n  - {topic: /t, type: std_msgs/msg/String, "
                          f"direction: transmit, port: 9, {entry}}}\n"), plugins).prepare()
    assert engine.plan is not None
    packetizer = engine.plan.topics[0].delivery.packetizer
    return packetizer.name if packetizer is not None else None


@pytest.mark.parametrize(("entry", "recovery"), [
    ("qos: 10", "retransmit"),                       # ROS's default QoS: reliable
    ("qos: {reliability: reliable, depth: 5}", "retransmit"),
    ("qos: sensor_data", None),                      # best effort stays fresh
    ("qos: {reliability: best_effort}", None),
    ("qos: sensor_data, recovery: fec", "fec"),      # the entry's own choice
    ("qos: 10, recovery: fec", "fec"),
    ("qos: 10, transport: tcp", None),               # a stream delivers whole and in order
    ("qos: 10, framing: none, codec: msgpack", None),  # a microcontroller answers nothing
])
def test_the_qos_decides_the_recovery(entry, recovery):
    assert recovery_of(entry) == recovery


def test_an_entry_without_qos_is_repaired_as_ros_s_default_qos_is_reliable():
    assert recovery_of("remote: /t") == "retransmit"


def test_recovery_none_on_a_reliable_topic_is_allowed_and_said(caplog):
    with caplog.at_level(logging.WARNING, logger="rosgate"):
        assert recovery_of("recovery: none") is None
    said = [r.getMessage() for r in caplog.records]
    assert any("/t (topics[0]): reliable QoS on udp with recovery: none: a datagram lost on "
               "the way loses its message" in line for line in said), said
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="rosgate"):
        assert recovery_of("qos: sensor_data, recovery: none") is None
    assert not caplog.records  # best effort gives nothing up


def test_without_the_recovery_plugin_a_reliable_topic_runs_unrepaired_and_says_the_fix(
        caplog, monkeypatch):
    monkeypatch.setenv(DISABLE_VARIABLE, "recovery")
    plugins = Plugins.discover()
    with caplog.at_level(logging.WARNING, logger="rosgate"):
        assert recovery_of("qos: 10", plugins) is None
    said = " ".join(r.getMessage() for r in caplog.records)
    assert "reliable QoS on udp, where the packetizer 'retransmit' would repair" in said, said
    assert "rosgate-recovery" in said and "recovery: none to accept it" in said, said


def test_a_client_s_hello_leaves_an_unset_recovery_to_the_server_and_says_none():
    unset, none = loads(HEAD + """topics:
  - {topic: /a, type: std_msgs/msg/String, direction: transmit, port: 9}
  - {topic: /b, type: std_msgs/msg/String, direction: transmit, port: 9, recovery: none}
""").topics
    assert "recovery" not in topic_to_mapping(unset)
    assert topic_to_mapping(none)["recovery"] == "none"
    assert topic_from_mapping(topic_to_mapping(unset), {}, "client robot1").recovery is None
    assert topic_from_mapping(topic_to_mapping(none), {}, "client robot1").recovery == "none"
