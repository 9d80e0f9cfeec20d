"""Pattern entries in bringup.yaml: a glob for a name, no type, deny:, remote: that keeps the
wildcards, max_routes; every mistake located at its file, line and key with a fix."""

from __future__ import annotations

import pytest

from rosgate.config import loads, topic_from_mapping, topic_to_mapping
from rosgate.config.patterns import DENY_DEFAULT, denied, far_name, matches
from rosgate.errors import ConfigError
from rosgate.plugins import Plugins
from rosgate.resolver.plan import Resolver

HEAD = "bridge: {name: robot1, role: client, server: 127.0.0.1:12000, insecure: true}\n"


def error(text: str) -> ConfigError:
    with pytest.raises(ConfigError) as info:
        loads(HEAD + text, file="bringup.yaml")
    return info.value


def test_a_pattern_entry_needs_no_type_and_keeps_every_other_key() -> None:
    cfg = loads(HEAD + "topics:\n"
                "  - {topic: /robot1/**, direction: transmit, remote: /fleet/robot1/**,\n"
                "     deny: [/robot1/camera/**], max_routes: 50, max_rate: 20, qos: 5}\n")
    (t,) = cfg.topics
    assert (t.topic, t.type, t.remote, t.deny, t.max_routes, t.max_rate, t.qos, t.pattern) == (
        "/robot1/**", "", "/fleet/robot1/**", ("/robot1/camera/**",), 50, 20, 5, True)
    assert cfg.deny == DENY_DEFAULT
    resolver = Resolver(cfg, Plugins.discover())
    plan = resolver.plan()
    assert plan.topics == [] and len(plan.patterns) == 1  # a template, not a route
    spec = resolver.found(plan.patterns[0], "/robot1/arm/joints",
                                                   "sensor_msgs/msg/JointState")
    c = spec.config
    assert (c.topic, c.remote, c.type, c.max_rate, c.qos, c.pattern) == (
        "/robot1/arm/joints", "/fleet/robot1/arm/joints", "sensor_msgs/msg/JointState", 20, 5,
        False)
    sent = topic_to_mapping(c)  # what a client tells its server: a listed entry
    assert "deny" not in sent and "max_routes" not in sent and sent["type"] == c.type


def test_globs_as_the_policy_reads_them() -> None:
    assert matches("/r/**", "/r/a/b") and matches("/r/*", "/r/a") and not matches("/r/*", "/r/a/b")
    assert not matches("/r/**", "/rx/a") and matches("/**", "/rosout")
    assert denied("/rosout", DENY_DEFAULT) == "/rosout"
    assert denied("/robot1/get_parameters", DENY_DEFAULT) == "/**/get_parameters"
    assert denied("/robot1/scan", DENY_DEFAULT) is None
    assert far_name("/robot1/**", "/fleet/robot1/**", "/robot1/a/b") == "/fleet/robot1/a/b"
    assert far_name("/**", "/base/**", "/scan") == "/base/scan"


def test_bridge_deny_replaces_the_default() -> None:
    cfg = loads(HEAD.replace("insecure: true", "insecure: true, deny: [/secret/**]")
                + "topics:\n  - {topic: /**, direction: transmit}\n")
    assert cfg.deny == ("/secret/**",)


@pytest.mark.parametrize(("entry", "key", "says", "fix"), [
    ("{topic: /a, direction: transmit}", "topics[0].type", "missing required key 'type'",
     "add type: std_msgs/msg/String"),
    ("{topic: /r/a**, direction: transmit}", "topics[0].topic", "segment 'a**'", "'**' only"),
    ("{topic: 'r/**', direction: transmit}", "topics[0].topic", "starts with '/'",
     "topic: /robot1/**"),
    ("{topic: /r/**, direction: transmit, remote: /f/r}", "topics[0].remote",
     "does not keep the pattern's wildcards (/**)", "end remote with /**"),
    ("{topic: /r/**, direction: transmit, deny: [x/y]}", "topics[0].deny", "does not start",
     "[/x/y]"),
    ("{topic: /a, type: std_msgs/msg/String, direction: transmit, deny: [/a]}",
     "topics[0].deny", "deny is for pattern entries", "make topic: a pattern"),
    ("{topic: /r/**, direction: transmit, max_routes: 0}", "topics[0].max_routes", "", ""),
])
def test_mistakes_name_file_line_key_and_fix(entry: str, key: str, says: str, fix: str) -> None:
    found = error(f"topics:\n  - {entry}\n")
    assert (found.file, found.line, found.key) == ("bringup.yaml", 3, key)
    assert says in found.message and fix in (found.fix or "")


def test_a_bare_framing_pattern_off_a_bus_is_refused_at_its_framing() -> None:
    """``framing: none`` on a pattern is a bus's (zenoh's CDR on ROS names): on udp the resolver,
    which knows the transport, refuses it at its key with the fix."""
    cfg = loads(HEAD + "topics:\n  - {topic: /r/**, direction: transmit, framing: none, "
                "cipher: none}\n", file="bringup.yaml")
    with pytest.raises(ConfigError) as info:
        Resolver(cfg, Plugins.discover()).plan()
    assert (info.value.file, info.value.line, info.value.key) == ("bringup.yaml", 3,
                                                                  "topics[0].framing")
    assert "finds ROS names as they appear" in info.value.message
    assert "list each name" in (info.value.fix or "")


PEER = "bridge: {name: a, role: peer, peer: 127.0.0.1, insecure: true}\n"


@pytest.mark.parametrize(("text", "key", "says"), [
    ("actions:\n  - {action: /robot1/*, direction: transmit, port: 12001}\n",
     "actions[0].action", "a peer lists each action by its name"),
    ("topics:\n  - {topic: /a, type: std_msgs/msg/String, direction: transmit, port: 12002}\n"
     "actions:\n  - {action: /robot1/**, direction: receive, port: 12001}\n",
     "actions[0].action", "a peer lists each action by its name"),
])
def test_what_patterns_do_not_find_is_refused_at_start(text: str, key: str, says: str) -> None:
    """A client's actions may be patterns; a peer's may not (its patterns find topics and
    services)."""
    cfg = loads(PEER + text, file="bringup.yaml")
    with pytest.raises(ConfigError) as info:
        Resolver(cfg, Plugins.discover()).plan()
    assert info.value.key == key and says in info.value.message
    assert info.value.fix and "as an entry of its own" in info.value.fix



def test_a_peer_finds_topics_and_services_on_the_links_that_can() -> None:
    plan = Resolver(loads(PEER + "topics:\n  - {topic: /r/**, direction: transmit, port: 12001}\n"
                          "services:\n  - {service: /s/**, direction: receive, port: 12002}\n"),
                    Plugins.discover()).plan()
    assert [(p.section, p.name) for p in plan.patterns] == [("topics", "/r/**"),
                                                            ("services", "/s/**")]
    cfg = loads(PEER + "services:\n  - {service: /s/**, direction: receive, port: 12002, "
                "transport: tcp}\n", file="bringup.yaml")
    with pytest.raises(ConfigError) as info:
        Resolver(cfg, Plugins.discover()).plan()
    assert (info.value.line, info.value.key) == (3, "services[0].transport")
    assert "cannot find names over tcp" in info.value.message and "udp" in (info.value.fix or "")


def test_a_peer_pattern_anyone_could_write_through_is_an_open_door() -> None:
    from rosgate.engine import open_entries

    plan = Resolver(loads(PEER + "topics:\n  - {topic: /r/**, direction: receive, port: 12001}\n"
                          "  - {topic: /t/**, direction: transmit, port: 12002}\n"
                          "services:\n  - {service: /s/**, direction: transmit, port: 12003}\n"),
                    Plugins.discover()).plan()
    assert [(door.key, door.name) for door in open_entries(plan)] == [
        ("topics[0].cipher", "/r/**"), ("services[0].cipher", "/s/**")]


def test_a_client_sends_names_never_patterns() -> None:
    with pytest.raises(ConfigError) as info:
        topic_from_mapping({"topic": "/r/**", "direction": "transmit"}, {}, "client x", index=2)
    assert (info.value.file, info.value.key) == ("client x", "topics[2]")
