"""A peer's patterns, both ways, against real bridges and real rclpy nodes, each side in its own
domain: names that appear under a transmit pattern after both peers are up cross, field by
field, and the far peer takes only what its own receive patterns take (mapped by ``remote:``,
within ``max_routes``); a name published on both sides crosses once each way and never echoes
back (each echo refused and counted); a name whose publishers went is gone from the far side
after the grace; a server found on one side is called from the other; forged announcements are
counted by reason and make nothing."""

from __future__ import annotations

import json
import socket
import time
from typing import Any

from conftest import free_port, settle, wait_until
from interfaces import differences, fill
from std_msgs.msg import String
from std_srvs.srv import Trigger
from test_msgs.msg import Arrays
from test_services import DEEP, Caller

from rosgate.roles.peer_patterns import ROSTER_ID
from rosgate.wire import envelope

PEER = """
bridge: {{name: {name}, role: peer, peer: 127.0.0.1, listen: 127.0.0.1, pattern_grace: 1}}
topics:
  - {{topic: /**, direction: transmit, port: {send}}}
{receive}
services:
  - {{service: /x/**, direction: {calls}, port: {calls_port}}}
"""
#: a takes everything b sends; b takes two of a's /a/** as /from_a/**, and the rest but /hidden/**
A_TAKES = "  - {{topic: /**, direction: receive, port: {port}}}"
B_TAKES = """
  - {{topic: /from_a/**, remote: /a/**, direction: receive, port: {port}, max_routes: 2}}
  - {{topic: /**, direction: receive, port: {port}, deny: [/a/**, /hidden/**]}}"""


def first_crossing(publisher: Any, inbox: Any, message: Any, timeout: float = 20.0) -> None:
    """Publish ``message`` every 50 ms until one arrives."""
    deadline = time.monotonic() + timeout
    while not inbox.wait_count(1, 0.05):
        assert time.monotonic() < deadline, "nothing crossed"
        publisher.publish(message)


def published(side: Any, name: str) -> bool:
    return bool(side.ros.node.get_publishers_info_by_topic(name))


def drops(engine: Any, name: str, direction: str) -> dict[str, int]:
    return next((e["drops"] for e in engine.status()["entries"]
                 if e["name"] == name and e["direction"] == direction), {})


def roster(seq: int, body: bytes) -> bytes:
    """A roster of names as anyone on a link without a cipher could send it."""
    return envelope.pack(envelope.FLAG_ANNOUNCE, ROSTER_ID, 7, seq, 0) + body


def names(link: str, names: dict[str, Any]) -> bytes:
    return json.dumps({"link": link, "kind": "topics", "names": names}).encode()


def test_two_peers_with_patterns_both_ways_carry_each_message_once(engines, domain, ros_side,
                                                                   logs):
    da, db, p1, p2 = domain(), domain(), free_port(), free_port()
    p3 = free_port()  # a serves its /x/** servers, b calls them
    a = engines(PEER.format(name="a", send=p1, receive=A_TAKES.format(port=p2), calls="receive",
                            calls_port=p3), da)
    b = engines(PEER.format(name="b", send=p2, receive=B_TAKES.format(port=p1),
                            calls="transmit", calls_port=p3), db)
    here, there = ros_side(da, "here"), ros_side(db, "there")
    # names only one side publishes: a's under /a/** reach b as /from_a/**, exact
    arrays = fill(Arrays, "high")
    inbox = there.listen("/from_a/arrays", Arrays)
    talker = here.publisher("/a/arrays", Arrays)
    first_crossing(talker, inbox, arrays)
    assert differences(arrays, inbox.items[0]) == []
    # a third name under b's pattern of two routes is refused, counted, never on b's graph
    more = [here.publisher(f"/a/m{i}", String) for i in (1, 2)]
    assert wait_until(lambda: b.role.discovery.status()["refused"] == {"too_many_names": 1})
    assert sum(published(there, f"/from_a/m{i}") for i in (1, 2)) == 1 and more
    b_chat, a_got = there.publisher("/b/chat", String), here.listen("/b/chat", String)
    first_crossing(b_chat, a_got, String(data="warm"))
    hidden = here.publisher("/hidden/x", String)
    # one name published on both sides: each side's listener hears its own and the far one's
    both_a, both_b = here.publisher("/both", String), there.publisher("/both", String)
    heard_a, heard_b = here.listen("/both", String), there.listen("/both", String)
    first_crossing(both_a, heard_b, String(data="warm"))
    first_crossing(both_b, heard_a, String(data="warm"))
    for inbox_ in (inbox, a_got, heard_a, heard_b):
        settle(inbox_)
    marks = {id(i): len(i.items) for i in (a_got, heard_a, heard_b)}
    for n in range(20):
        both_a.publish(String(data=f"a{n}"))
        both_b.publish(String(data=f"b{n}"))
        b_chat.publish(String(data=f"c{n}"))
        hidden.publish(String(data="never"))
        time.sleep(0.01)
    for inbox_ in (a_got, heard_a, heard_b):
        settle(inbox_, quiet=1.0)
    got = {id(i): sorted(m.data for m in i.items[marks[id(i)]:]) for i in (a_got, heard_a,
                                                                           heard_b)}
    every = sorted([f"a{n}" for n in range(20)] + [f"b{n}" for n in range(20)])
    assert got[id(a_got)] == sorted(f"c{n}" for n in range(20))
    assert got[id(heard_a)] == every and got[id(heard_b)] == every  # once each: no echo
    # what each bridge published of /both came back to its own subscription: refused, counted
    for side in (a, b):
        assert wait_until(lambda side=side: drops(side, "/both", "transmit").get("echo", 0)
                          >= 20), side.status()["entries"]
    # seconds later: what b publishes for a, its own /** never finds (bridges' nodes are left
    # out), so it never goes back to a
    assert "/from_a/arrays" not in b.role.discovery.discovery.status()["found"]
    assert not published(here, "/from_a/arrays")
    # never on b's graph: a's name under its remote head, and what b's patterns leave out
    names_b = {name for name, _ in there.ros.node.get_topic_names_and_types()}
    assert not names_b & {"/a/arrays", "/hidden/x"}
    assert "/hidden/x" in a.role.discovery.status()["found"]
    # a's publisher goes: b's is gone after the grace
    here.ros.destroy(talker)
    assert wait_until(lambda: not published(there, "/from_a/arrays"), 10)
    assert "/from_a/arrays" not in b.role.discovery.status()["found"]
    # a's server, found by a's receive pattern, is called from b through the proxy b made
    server = here.ros.node.create_service(Trigger, "/x/ping", lambda request, response: (
        setattr(response, "message", "from a"), response)[1], qos_profile=DEEP)
    caller = Caller(there, Trigger, "/x/ping")
    assert caller.warm_up(Trigger.Request())[0].message == "from a"
    here.ros.node.destroy_service(server)  # gone here: b's proxy goes after the grace
    assert wait_until(lambda: not caller.client.service_is_ready(), 10)
    # rosters no peer sent: each refusal counted by reason, nothing made, the bridge serves on
    string = {"type": "std_msgs/msg/String"}
    forged = [b"not json", names("x", {"no name": string, "/x/y": {**string, "hash": 5}}),
              names("y", {f"/hidden/n{i}": string for i in range(1001)}),
              names("z", {"/c/x": {"type": "nope_pkg/msg/X"}})]
    before = dict(b.status()["link_drops"])
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        for seq, body in enumerate(forged, 1):
            s.sendto(roster(seq, body), ("127.0.0.1", p1))
    grown = {"bad_announcement": 3, "too_many_names": 1, "type_not_installed": 1}
    assert wait_until(lambda: {k: v - before.get(k, 0) for k, v in b.status()["link_drops"]
                               .items() if v != before.get(k, 0)} == grown), b.status()
    assert logs.wait("interface package 'nope_pkg' is not installed")
    assert not any(published(there, name) for name in ("/c/x", "/hidden/n0", "/x/y"))


def test_authenticated_peers_announce_and_carry_found_names(tmp_path, domain, ros_side, bridge):
    """With identities, names are announced and carried under the session's keys."""
    from test_sessions_peer import identities, peer_file

    da, db, port = domain(), domain(), free_port()
    keys = identities(tmp_path, a_initiates=True)
    handshake = free_port()
    a = bridge(peer_file(tmp_path, "a", keys["a"][0], keys["b"][1], handshake,
                         f"topics: [{{topic: /a/**, direction: transmit, port: {port}}}]"), da)
    b = bridge(peer_file(tmp_path, "b", keys["b"][0], keys["a"][1], handshake,
                         f"topics: [{{topic: /**, direction: receive, port: {port}}}]"), db)
    for side in (a, b):
        assert side.wait_log("up (authenticated)", 20), side.log
    arrays = fill(Arrays, "low")
    inbox = ros_side(db, "there").listen("/a/deep/arrays", Arrays)
    first_crossing(ros_side(da, "here").publisher("/a/deep/arrays", Arrays), inbox, arrays)
    assert differences(arrays, inbox.items[0]) == []
    assert b.wait_log("the peer announces /a/deep/arrays (test_msgs/msg/Arrays): bridged", 5)
