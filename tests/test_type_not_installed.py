"""A far side that announces a type this side does not have installed (a robot with a package of
its own messages the base lacks): this side says which package is missing, by the announced
type's name, refuses that entry alone, counts what its frames become (``type_not_installed``)
and keeps carrying everything else — on every role. Real ``rosgate run`` processes; the far side
is a plain socket or zenoh session that speaks rosgate's protocol and names a package no machine
has (``gadget_msgs``), as a bridge with that package installed would."""

from __future__ import annotations

import json
import socket
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import free_port, wait_until
from rclpy.serialization import serialize_message
from rosgate_top.client import StatusClient
from std_msgs.msg import String
from test_zenoh_fleet import Router, zenoh_plugin

from rosgate import runtime
from rosgate.rostypes import type_hash
from rosgate.wire import envelope

GADGET = "gadget_msgs/msg/Gadget"
GADGET_HASH = "RIHS01_" + "6a" * 32
PACKAGE = ("interface package 'gadget_msgs' is not installed (apt install "
           "ros-$ROS_DISTRO-gadget-msgs, or pip install ros-jazzy-gadget-msgs)")
#: what a receiving side says of the far side's type, after the entry's name
MISSING = f"the far side's type {GADGET} is not installed on this side: {PACKAGE}"
#: what a server says of a client's entry
SERVER_MISSING = f"/gadget: its type {GADGET} is not installed on the server: {PACKAGE}"


@pytest.fixture
def runtime_dir() -> Iterator[None]:
    """A socket folder of the test's own, which the bridge processes inherit."""
    with tempfile.TemporaryDirectory(prefix="rg", dir="/tmp") as folder, \
            pytest.MonkeyPatch.context() as patch:
        patch.setenv(runtime.RUNTIME_VARIABLE, str(Path(folder) / "run"))
        yield


def entry(bridge_name: str, name: str) -> dict[str, Any]:
    with StatusClient(bridge_name) as ask:
        return next(e for e in ask.status()["entries"] if e["name"] == name)


def said(bridge: Any, text: str) -> int:
    """How many lines of a bridge's log say ``text``."""
    return sum(text in line for line in bridge.log.splitlines())


def announcement(type_name: str, type_hash_: str | None) -> bytes:
    return json.dumps({"type": type_name, "hash": type_hash_}).encode()


def string_announcement() -> bytes:
    return announcement("std_msgs/msg/String", type_hash(String))


def frame(flags: int, topic_id: int, seq: int, body: bytes) -> bytes:
    return envelope.pack(flags, topic_id, 7, seq, time.time_ns()) + body


def test_a_peer_names_the_missing_package_counts_the_drops_and_goes_on(
        tmp_path, bridge, domain, ros_side, runtime_dir):
    d, port = domain(), free_port()
    path = tmp_path / "b.yaml"
    path.write_text(f"""bridge: {{name: b, role: peer, peer: 127.0.0.1, listen: 127.0.0.1}}
topics: [{{topic: /gadget, type: std_msgs/msg/String, direction: receive, port: {port}}}]""")
    b = bridge(path, d)
    inbox = ros_side(d, "b").listen("/gadget", String)
    topic_id = envelope.topic_id_for("/gadget")
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        send = lambda data: s.sendto(data, ("127.0.0.1", port))
        send(frame(envelope.FLAG_ANNOUNCE, topic_id, 1, announcement(GADGET, GADGET_HASH)))
        for seq in range(2, 7):  # five frames of the type this side lacks
            send(frame(0, topic_id, seq, b"\x00\x01\x00\x00gadget bytes"))
        assert wait_until(lambda: entry("b", "/gadget")["drops"] == {"type_not_installed": 5},
                          10), (entry("b", "/gadget"), b.log)
        assert b.wait_log(f"/gadget: refused, {MISSING}", 5), b.log
        # the same far side, now with the type this side has: its messages are published
        seq = 7
        while not inbox.wait_count(1, 0.2):
            assert seq < 100, (entry("b", "/gadget"), b.log)
            send(frame(envelope.FLAG_ANNOUNCE, topic_id, seq, string_announcement()))
            send(frame(0, topic_id, seq + 1, serialize_message(String(data="after"))))
            seq += 2
    assert {m.data for m in inbox.items} == {"after"}, "nothing of the gadget frames was published"
    assert entry("b", "/gadget")["drops"] == {"type_not_installed": 5}
    assert said(b, "gadget_msgs") == 1, "said once, not per frame"
    assert b.proc.poll() is None


def test_a_peer_answers_a_call_of_a_type_it_lacks_as_a_failure_naming_the_package(
        tmp_path, bridge, domain, ros_side, runtime_dir):
    """A serving peer: the caller's announcement names a service type not installed here; its
    call is answered as a failure that names the package, counted, and never served."""
    from std_srvs.srv import Trigger

    d, port = domain(), free_port()
    path = tmp_path / "b.yaml"
    path.write_text(f"""bridge: {{name: b, role: peer, peer: 127.0.0.1, listen: 127.0.0.1}}
services: [{{service: /gadget_srv, type: std_srvs/srv/Trigger, direction: receive,
             port: {port}}}]""")
    b = bridge(path, d)
    served: list[Any] = []
    ros_side(d, "b").ros.node.create_service(Trigger, "/gadget_srv",
                                             lambda q, r: served.append(q) or r)
    service_id = envelope.topic_id_for("/gadget_srv")
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.settimeout(10)
        s.sendto(frame(envelope.FLAG_ANNOUNCE, service_id, 1,
                       announcement("gadget_msgs/srv/Gadget", GADGET_HASH)), ("127.0.0.1", port))
        s.sendto(frame(envelope.FLAG_REQUEST, service_id, 2, b"\x00\x01\x00\x00gadget"),
                 ("127.0.0.1", port))
        answer, _ = s.recvfrom(65536)
    header = envelope.HEADER.unpack_from(answer)
    assert header[2] == envelope.FLAG_REPLY | envelope.FLAG_FAILED, header
    assert answer[envelope.SIZE:].decode() == (
        "/gadget_srv: refused, the far side's type gadget_msgs/srv/Gadget is not installed on "
        "this side: interface package 'gadget_msgs' is not installed (apt install "
        "ros-$ROS_DISTRO-gadget-msgs, or pip install ros-jazzy-gadget-msgs), so its frames are "
        "dropped")
    assert entry("b", "/gadget_srv")["drops"] == {"type_not_installed": 1}
    assert served == [] and b.proc.poll() is None


def test_zenoh_names_the_missing_package_counts_the_drops_and_goes_on(
        tmp_path, bridge, domain, ros_side, runtime_dir):
    import zenoh

    router = Router()
    try:
        d = domain()
        path = tmp_path / "b.yaml"
        path.write_text(f"bridge: {{name: b, role: peer, defaults: {{transport: zenoh}}}}\n"
                        f"{zenoh_plugin(router)}topics: [{{topic: /gadget, type: "
                        "std_msgs/msg/String, direction: receive, remote: fleet/gadget}]\n")
        b = bridge(path, d)
        inbox = ros_side(d, "b").listen("/gadget", String)
        config = zenoh.Config()
        config.insert_json5("mode", '"client"')
        config.insert_json5("connect/endpoints", f'["{router.endpoint}"]')
        topic_id = envelope.topic_id_for("fleet/gadget")
        with zenoh.open(config) as session:
            publisher = session.declare_publisher("fleet/gadget")
            seq = 0
            # until the bridge's subscription is matched: it refuses the type
            while not b.wait_log("/gadget: refused", 0.2):
                seq += 1
                assert seq < 100, b.log
                publisher.put(frame(envelope.FLAG_ANNOUNCE, topic_id, seq,
                                    announcement(GADGET, GADGET_HASH)))
            assert b.wait_log(f"/gadget: refused, {MISSING}", 5), b.log
            for i in range(5):
                publisher.put(frame(0, topic_id, seq + 1 + i, b"\x00\x01\x00\x00gadget"))
            assert wait_until(lambda: entry("b", "/gadget")["drops"] ==
                              {"type_not_installed": 5}, 10), entry("b", "/gadget")
            seq += 6
            while not inbox.wait_count(1, 0.2):
                assert seq < 200, (entry("b", "/gadget"), b.log)
                publisher.put(frame(envelope.FLAG_ANNOUNCE, topic_id, seq, string_announcement()))
                publisher.put(frame(0, topic_id, seq + 1, serialize_message(String(data="after"))))
                seq += 2
        assert {m.data for m in inbox.items} == {"after"}
        assert entry("b", "/gadget")["drops"] == {"type_not_installed": 5}
        assert said(b, "gadget_msgs") == 1, "said once, not per frame"
        assert b.proc.poll() is None
    finally:
        router.stop()


class MainLine:
    """A client's main line to an insecure server, spoken by hand."""

    def __init__(self, port: int):
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=10)

    def send(self, data: bytes) -> None:
        self.sock.sendall(len(data).to_bytes(4, "big") + data)

    def control(self, message: dict[str, Any]) -> None:
        self.send(envelope.pack(envelope.FLAG_CONTROL, envelope.CONTROL_TOPIC, 0, 0,
                                time.time_ns()) + json.dumps(message).encode())

    def receive(self) -> dict[str, Any]:
        """The next control message (heartbeats and announcements skipped)."""
        while True:
            size = int.from_bytes(self._exactly(4), "big")
            data = self._exactly(size)
            if data[3] & envelope.FLAG_CONTROL:
                message = json.loads(data[envelope.SIZE:])
                if message.get("type") in ("welcome", "refused"):
                    return message

    def _exactly(self, n: int) -> bytes:
        data = b""
        while len(data) < n:
            more = self.sock.recv(n - len(data))
            assert more, "the server closed the main line"
            data += more
        return data

    def close(self) -> None:
        self.sock.close()


def test_a_server_refuses_the_entry_whose_type_it_lacks_and_serves_the_rest(
        tmp_path, bridge, domain, ros_side, runtime_dir):
    """A client whose hello asks for a type the server does not have: that entry is refused
    with the missing package named, in the welcome and the server's log; the client's other
    entries are served."""
    d, port = domain(), free_port()
    path = tmp_path / "base.yaml"
    path.write_text(f"bridge: {{name: base, role: server, server: '127.0.0.1:{port}', "
                    "insecure: true}\n")
    base = bridge(path, d)
    inbox = ros_side(d, "base").listen("/chatter", String)
    line = MainLine(port)
    try:
        line.control({
            "type": "hello", "protocol": 1, "name": "robot9",
            "topics": [{"topic": "/gadget", "type": GADGET, "direction": "transmit"},
                       {"topic": "/chatter", "type": "std_msgs/msg/String",
                        "direction": "transmit"}],
            "services": [], "actions": [],
            "entries": [{"type": GADGET, "hash": GADGET_HASH},
                        {"type": "std_msgs/msg/String", "hash": type_hash(String)}]})
        welcome = line.receive()
        assert welcome["type"] == "welcome", welcome
        gadget_id, chatter_id = welcome["topic_ids"]
        assert gadget_id == 0 and chatter_id != 0
        assert welcome["refused"] == [{"entry": "topics[0] (/gadget)", "error": SERVER_MISSING}]
        assert base.wait_log(SERVER_MISSING, 5), base.log
        seq = 1
        while not inbox.wait_count(1, 0.2):  # the other entry is served
            assert seq < 100, base.log
            line.send(frame(0, chatter_id, seq, serialize_message(String(data="served"))))
            seq += 1
        assert {m.data for m in inbox.items} == {"served"}
    finally:
        line.close()
    assert base.proc.poll() is None
    assert said(base, "gadget_msgs") == 1, base.log


# -- the check itself --------------------------------------------------------------------------
def test_the_check_tells_a_type_not_installed_from_another_type(caplog):
    from rosgate.announce import Identity, TypeCheck
    from rosgate.drops import Drop

    mine = Identity("std_msgs/msg/String", type_hash(String))
    # a label of its own: what is said is said once a minute per label, for the whole process
    check = TypeCheck("/installed_or_not", mine)
    check.far(Identity(GADGET, GADGET_HASH))
    assert check.reason is Drop.TYPE_NOT_INSTALLED
    assert check.mismatch == f"/installed_or_not: refused, {MISSING}, so its frames are dropped"
    check.far(Identity("geometry_msgs/msg/Point", "RIHS01_" + "69" * 32))  # installed, another
    assert check.reason is Drop.TYPE_MISMATCH
    assert check.mismatch is not None and "not installed" not in check.mismatch
    check.far(Identity("std_msgs/msg/String", "RIHS01_" + "5e" * 32))  # another version
    assert check.reason is Drop.TYPE_MISMATCH
    check.far(Identity("not a type", GADGET_HASH))  # junk from the network: said, never raised
    assert check.reason is Drop.TYPE_NOT_INSTALLED and "'not a type' is not an interface name" \
        in str(check.mismatch)
    check.far(mine)
    assert check.mismatch is None
