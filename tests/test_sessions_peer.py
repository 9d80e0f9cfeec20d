"""Peers with identities: the same Noise handshake as client/server on a line of its own, one
side initiating (the one whose public key sorts first), every envelope entry keyed from the
session. Real ``rosgate run`` processes and real sockets."""

from __future__ import annotations

import socket
from pathlib import Path

import pytest
from conftest import cross, free_port
from faults import FaultProxy
from std_msgs.msg import String
from std_srvs.srv import SetBool
from test_services import DEEP, Caller, echo_set_bool

from rosgate import identity

FAST = "heartbeat: 0.2, peer_timeout: 0.8, reconnect: {min: 0.05, max: 0.5}"


def text(i: int | None) -> String:
    return String(data="warmup" if i is None else f"m{i}")


def is_warmup(m: String) -> bool:
    return m.data == "warmup"


def identities(folder: Path, a_initiates: bool) -> dict[str, tuple[Path, str]]:
    """Keys for peers a and b, ordered so that a initiates (or b does)."""
    keys = sorted((identity.generate() for _ in range(2)), key=identity.public_of)
    if not a_initiates:
        keys.reverse()
    made = {}
    for name, key in zip("ab", keys, strict=True):
        path = folder / f"{name}.key"
        identity.write_private(path, key)
        made[name] = (path, identity.encode(identity.public_of(key)))
    return made


def peer_file(folder: Path, name: str, key: Path, peer_key: str, handshake: int,
              entries: str) -> Path:
    path = folder / f"{name}.yaml"
    path.write_text(f"""
bridge: {{name: {name}, role: peer, peer: 127.0.0.1, listen: 127.0.0.1, {FAST},
          identity: {key}, peer_key: {peer_key}, handshake_port: {handshake}}}
{entries}""")
    return path


@pytest.mark.parametrize("a_initiates", [True, False], ids=["a-initiates", "b-initiates"])
def test_authenticated_peers_carry_topics_and_calls(tmp_path, domain, ros_side, bridge,
                                                    a_initiates):
    da, db = domain(), domain()
    keys = identities(tmp_path, a_initiates)
    handshake, topic_port, call_port = free_port(), free_port(), free_port()
    call = (f"{{service: /set, type: std_srvs/srv/SetBool, port: {call_port}, timeout: 2")
    a = bridge(peer_file(tmp_path, "a", keys["a"][0], keys["b"][1], handshake, f"""
topics: [{{topic: /chatter, type: std_msgs/msg/String, direction: transmit, port: {topic_port}}}]
services: [{call}, direction: transmit}}]"""), da)
    b = bridge(peer_file(tmp_path, "b", keys["b"][0], keys["a"][1], handshake, f"""
topics: [{{topic: /chatter, type: std_msgs/msg/String, direction: receive, port: {topic_port}}}]
services: [{call}, direction: receive}}]"""), db)
    for side in (a, b):
        assert side.wait_log("up (authenticated)", 10), side.log
    side_a, side_b = ros_side(da, "a"), ros_side(db, "b")
    got = cross(side_a.publisher("/chatter", String), side_b.listen("/chatter", String), text,
                is_warmup, 20)
    assert sorted(m.data for m in got) == sorted(f"m{i}" for i in range(20))
    side_b.ros.node.create_service(SetBool, "/set", echo_set_bool, qos_profile=DEEP)
    caller = Caller(side_a, SetBool, "/set")
    assert caller.warm_up(SetBool.Request(data=True))[0].message == "data=True"


def test_a_peer_with_another_key_is_refused_and_nothing_crosses(tmp_path, domain, ros_side,
                                                               bridge):
    da, db = domain(), domain()
    keys = identities(tmp_path, a_initiates=True)
    b_public = identity.decode_public(keys["b"][1])
    # b expects a stranger that sorts before it, so b responds, as a real b would
    stranger = next(k for k in (identity.public_of(identity.generate()) for _ in range(100))
                    if k < b_public)
    stranger_text = identity.encode(stranger)
    handshake, port = free_port(), free_port()
    a = bridge(peer_file(tmp_path, "a", keys["a"][0], keys["b"][1], handshake, f"""
topics: [{{topic: /chatter, type: std_msgs/msg/String, direction: transmit, port: {port}}}]"""),
               da)
    b = bridge(peer_file(tmp_path, "b", keys["b"][0], stranger_text, handshake, f"""
topics: [{{topic: /chatter, type: std_msgs/msg/String, direction: receive, port: {port}}}]"""), db)
    assert b.wait_log("refused a handshake from 127.0.0.1: its key is not peer_key", 10), b.log
    inbox = ros_side(db, "b").listen("/chatter", String)
    talker = ros_side(da, "a").publisher("/chatter", String)
    for _ in range(20):
        talker.publish(String(data="let me in"))
        if inbox.wait_count(1, 0.1):
            break
    assert inbox.items == []
    assert not any("up (authenticated)" in x for x in a.lines + b.lines)
    assert len([x for x in b.lines if "refused a handshake" in x]) == 1


def test_a_frame_captured_between_peers_is_not_published_after_a_restart(tmp_path, domain,
                                                                        ros_side, bridge):
    """Before sessions, a peer topic with a static key accepted a frame captured before its
    receiver restarted (a fresh replay window). With identities, the restarted peer makes a new
    handshake: the captured frame names a key it never had."""
    from conftest import Bridge

    da, db = domain(), domain()
    keys = identities(tmp_path, a_initiates=True)
    handshake, port = free_port(), free_port()
    proxy = FaultProxy(free_port(), port)
    try:
        bridge(peer_file(tmp_path, "a", keys["a"][0], keys["b"][1], handshake, f"""
topics: [{{topic: /goal, type: std_msgs/msg/String, direction: transmit, port: {proxy.port}}}]"""),
               da)
        b_yaml = peer_file(tmp_path, "b", keys["b"][0], keys["a"][1], handshake, f"""
topics: [{{topic: /goal, type: std_msgs/msg/String, direction: receive, port: {port}}}]""")
        first = Bridge(b_yaml, db)
        talker = ros_side(da, "a").publisher("/goal", String)
        inbox = ros_side(db, "b").listen("/goal", String)
        cross(talker, inbox, text, is_warmup, 0)
        talker.publish(String(data="drive to dock"))
        assert inbox.wait_for(lambda items: any(m.data == "drive to dock" for m in items), 5)
        frames = [d for up, d in list(proxy.udp.captured) if up and d[:2] == b"RG"]
        first.proc.kill()
        first.proc.wait()
        second = bridge(b_yaml, db)
        assert second.wait_log("up (authenticated)", 10)
        cross(talker, inbox, text, is_warmup, 0)
        before = sum(1 for m in inbox.items if m.data == "drive to dock")
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
            for f in frames:
                udp.sendto(f, ("127.0.0.1", port))
        talker.publish(String(data="after"))
        assert inbox.wait_for(lambda items: any(m.data == "after" for m in items), 10)
        assert not inbox.wait_for(
            lambda items: sum(1 for m in items if m.data == "drive to dock") > before, 1.0)
    finally:
        proxy.close()
