"""Bytes from the network never crash the bridge, never reach ROS as a message, and every drop is
counted by reason. Two engines run in this process, each with its own rclpy context and DDS
domain; garbage comes from plain sockets."""

from __future__ import annotations

import random
import socket
import time
from pathlib import Path

import pytest
from conftest import cross, free_port, wait_until
from rclpy.serialization import serialize_message
from std_msgs.msg import String

from rosgate.wire import envelope
from rosgate.wire.framing import FRAGMENT


def peer_pair(engines, domain, transport: str = "udp", cipher_a: str = "none",
              cipher_b: str = "none", plugins_a: str = "{}", plugins_b: str = "{}",
              base_dir: Path | None = None):
    da, db, port = domain(), domain(), free_port()
    common = f"transport: {transport}, port: {port}, type: std_msgs/msg/String, topic: /chatter"
    a = engines(f"""
bridge: {{name: a, role: peer, peer: 127.0.0.1, listen: 127.0.0.1}}
plugins: {plugins_a}
topics: [{{{common}, direction: transmit, cipher: {cipher_a}}}]
""", da, base_dir)
    b = engines(f"""
bridge: {{name: b, role: peer, peer: 127.0.0.1, listen: 127.0.0.1}}
plugins: {plugins_b}
topics: [{{{common}, direction: receive, cipher: {cipher_b}}}]
""", db, base_dir)
    return a, b, da, db, port


def text(i: int | None) -> String:
    return String(data="warmup" if i is None else f"real-{i}")


def test_garbage_datagrams_counted_by_reason_and_never_published(engines, domain, ros_side):
    a, b, da, db, port = peer_pair(engines, domain)
    inbox = ros_side(db, "listener").listen("/chatter", String)
    talker = ros_side(da, "talker").publisher("/chatter", String)
    assert [m.data for m in cross(talker, inbox, text, lambda m: m.data == "warmup", 5)] == \
        [f"real-{i}" for i in range(5)]
    route = b.routes()[0]

    rng = random.Random(7)
    garbage: list[bytes] = [b""]
    while len(garbage) < 101:
        junk = rng.randbytes(rng.randint(envelope.SIZE, 300))
        if junk[:2] not in (b"RG", b"RF"):
            garbage.append(junk)  # foreign: 100
    # truncated: 10 (+ b"")
    garbage += [b"RG" + rng.randbytes(rng.randint(0, 20)) for _ in range(10)]
    header = lambda topic, seq: envelope.pack(0, topic, 1, seq, 0)
    garbage.append(envelope.HEADER.pack(b"RG", 99, 0, route.topic_id, 1, 1, 0) + b"x")  # version
    garbage.append(header(route.topic_id ^ 0xFFFF, 1) + serialize_message(text(1)))  # unknown topic
    garbage.append(header(route.topic_id, 1) + b"\x00\x01\x00\x00" + b"\xff" * 12)  # bad CDR
    garbage.append(header(route.topic_id, 2) + b"not cdr at all")  # bad CDR
    garbage += [b"RF" + rng.randbytes(3) for _ in range(5)]  # malformed fragments
    lone = FRAGMENT.pack(b"RF", 0, 3, route.topic_id, 77) + b"part"  # its siblings never come
    dup = header(route.topic_id, 3) + serialize_message(String(data="dup"))

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        for datagram in garbage + [lone, dup, dup]:
            s.sendto(datagram, ("127.0.0.1", port))

    expected_link = {"foreign_frame": 100, "truncated_frame": 11, "version_frame": 1,
                     "unknown_topic": 1, "bad_fragment": 5}
    assert wait_until(lambda: b.stats()["link_drops"] == expected_link), b.stats()
    assert wait_until(lambda: route.counters.drops == {"decode_error": 2, "duplicate": 1,
                                                       "fragment_lost": 1}), route.counters
    # the one well-formed frame among them was published once; nothing else was
    assert inbox.wait_for(lambda items: any(m.data == "dup" for m in items), 5)

    # and the link still carries real traffic
    again = cross(talker, inbox, lambda i: text(None if i is None else 100 + i),
                  lambda m: m.data == "warmup", 5)
    published = {m.data for m in inbox.items}
    assert published <= {"warmup", "dup"} | {f"real-{i}" for i in [*range(5), *range(100, 105)]}
    assert [m.data for m in again if m.data != "dup"] == [f"real-{100 + i}" for i in range(5)]


def test_wrong_key_is_rejected_and_counted(tmp_path, engines, domain, ros_side):
    from cryptography.fernet import Fernet

    (tmp_path / "a.key").write_bytes(Fernet.generate_key())
    (tmp_path / "b.key").write_bytes(Fernet.generate_key())
    a, b, da, db, port = peer_pair(engines, domain, cipher_a="fernet", cipher_b="fernet",
                                   plugins_a="{fernet: {key_file: a.key}}",
                                   plugins_b="{fernet: {key_file: b.key}}", base_dir=tmp_path)
    inbox = ros_side(db, "listener").listen("/chatter", String)
    talker = ros_side(da, "talker").publisher("/chatter", String)
    route, sent = b.routes()[0], a.routes()[0].counters
    deadline = time.monotonic() + 20
    # every message is refused, and so are the entry's type announcements (sealed the same way)
    while sent.sent < 10 or route.counters.drops["auth_failed"] < sent.sent:
        assert time.monotonic() < deadline, (route.counters, sent)
        if sent.sent < 10:
            talker.publish(String(data="secret"))
        time.sleep(0.02)  # pacing the talker
    assert route.counters.received == 0
    assert inbox.items == []
    assert set(route.counters.drops) == {"auth_failed"}


def test_garbage_on_a_tcp_link_closes_that_connection_only(engines, domain, ros_side):
    a, b, da, db, port = peer_pair(engines, domain, transport="tcp")
    inbox = ros_side(db, "listener").listen("/chatter", String)
    talker = ros_side(da, "talker").publisher("/chatter", String)
    cross(talker, inbox, text, lambda m: m.data == "warmup", 3)

    with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
        s.sendall(b"\xff\xff\xff\xff" + b"junk")  # a length no frame can have
        assert s.recv(10) == b""  # the bridge closed this connection
    with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
        s.sendall(b"\x00\x00\x00\x05hello")  # well framed, but not an envelope
    assert wait_until(lambda: b.stats()["link_drops"] == {"bad_length": 1, "truncated_frame": 1})

    again = cross(talker, inbox, lambda i: text(None if i is None else 50 + i),
                  lambda m: m.data == "warmup", 5)
    assert [m.data for m in again][-5:] == [f"real-{50 + i}" for i in range(5)]


@pytest.mark.parametrize("insecure", [False, True], ids=["authenticated", "insecure"])
def test_garbage_on_the_main_line_leaves_the_server_serving(engines, domain, ros_side, insecure):
    """Authenticated, the server parses nothing but a Noise handshake: both connections fail it
    at their first bytes. Insecure, the main line's own framing and control checks catch them."""
    ds, dc, port = domain(), domain(), free_port()
    mode = ", insecure: true" if insecure else ""
    server = engines(f"bridge: {{name: base, role: server, server: 127.0.0.1:{port}{mode}}}", ds)
    with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
        s.sendall(b"GET / HTTP/1.1\r\nHost: x\r\n\r\n")  # "GET " as a length: far too long
        assert s.recv(10) == b""
    with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
        frame = envelope.pack(envelope.FLAG_CONTROL, 0, 0, 0, 0) + b"{not json"
        s.sendall(len(frame).to_bytes(4, "big") + frame)
        data_frame = envelope.pack(0, 5, 1, 1, 0) + b"x"
        s.sendall(len(data_frame).to_bytes(4, "big") + data_frame)
        if insecure:
            assert wait_until(lambda: server.stats()["link_drops"].get("before_handshake") == 1)
        else:
            assert s.recv(10) == b""
    if insecure:
        assert server.stats()["link_drops"] == {"bad_length": 1, "bad_control": 1,
                                                "before_handshake": 1}
    else:
        assert wait_until(lambda: server.stats()["link_drops"] == {"bad_handshake": 2})

    engines(f"""
bridge: {{name: robot1, role: client, server: 127.0.0.1:{port}{mode}}}
topics: [{{topic: /chatter, type: std_msgs/msg/String, direction: transmit}}]
""", dc)
    inbox = ros_side(ds, "listener").listen("/chatter", String)
    got = cross(ros_side(dc, "talker").publisher("/chatter", String), inbox, text,
                lambda m: m.data == "warmup", 5)
    assert sorted(m.data for m in got) == [f"real-{i}" for i in range(5)]


def test_compressed_frames_that_lie_are_counted_and_never_published(engines, domain, ros_side):
    """FLAG_COMPRESSED on a link without a cipher: anyone can send such a frame. A bomb (64 MiB of
    zeros in a few kB, over the 64 MiB a frame may hold once the message's CDR is around it) is
    refused before anything is allocated; garbage and damaged zstd frames, a transform id no
    installed transform has and a flagged frame without a payload are counted."""
    import zstandard

    a, b, da, db, port = peer_pair(engines, domain)
    inbox = ros_side(db, "listener").listen("/chatter", String)
    talker = ros_side(da, "talker").publisher("/chatter", String)
    cross(talker, inbox, text, lambda m: m.data == "warmup", 1)
    route = b.routes()[0]
    header = lambda seq: envelope.pack(envelope.FLAG_COMPRESSED, route.topic_id, 5, seq, 0)
    bomb = zstandard.ZstdCompressor(level=19).compress(bytes((64 << 20) + 1))
    unsized = zstandard.ZstdCompressor(write_content_size=False).compress(b"a" * 100)
    good = zstandard.ZstdCompressor().compress(serialize_message(String(data="squeezed " * 20)))
    damaged = bytearray(good)
    damaged[-5] ^= 0xFF
    zstd = bytes([1])  # the wire id of the zstd transform, in front of what it made
    frames = [header(1) + zstd + bomb, header(2) + zstd + unsized, header(3) + zstd + b"not zstd",
              header(4) + zstd + bytes(damaged), header(5) + zstd + good,
              header(6) + bytes([0x99]) + good, header(7)]  # no such transform; no payload
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        for frame in frames:
            s.sendto(frame, ("127.0.0.1", port))
    assert wait_until(lambda: route.counters.drops == {"decompression_error": 6}), route.counters
    assert inbox.wait_for(lambda items: any(m.data.startswith("squeezed") for m in items), 5)
    assert {m.data for m in inbox.items} <= {"warmup", "real-0", "squeezed " * 20}
