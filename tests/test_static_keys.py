"""Peers keyed by a key file (no identities, no handshake): frames captured on the way and sent
again after the receiving bridge restarts publish nothing, and the pair carries on whichever
side restarts, or when the receiver's record of its peer is lost. Real ``rosgate run``
processes, a relay that keeps what it forwards, a raw UDP socket for the replay."""

from __future__ import annotations

import base64
import json
import os
import re
import socket
import subprocess
import time
from pathlib import Path

import pytest
from conftest import ROSGATE, Bridge, cross, free_port, settle, wait_until
from faults import FaultProxy
from geometry_msgs.msg import Twist
from std_srvs.srv import SetBool
from test_services import DEEP, Caller

from rosgate.builtin import NoCipher
from rosgate.keyring import ReplayRecord, StaticKeys
from rosgate.wire import envelope

FAST = "heartbeat: 0.2, peer_timeout: 0.8"
WARMUP = -1.0
S = 1_000_000_000  # ns
TWIST = "topic: /cmd_vel, type: geometry_msgs/msg/Twist"


def twist(i: int | None) -> Twist:
    message = Twist()
    message.linear.x = WARMUP if i is None else float(i)
    message.angular.z = 0.5
    return message


def is_warmup(m: Twist) -> bool:
    return m.linear.x == WARMUP


def keyed_pair(folder: Path, send_to: int, listen_on: int, section: str = "topics",
               entry: str = TWIST, recovery: str = "none") -> tuple[Path, Path]:
    """Files of a (sends ``entry`` to ``send_to``) and b (takes what reaches ``listen_on``),
    keyed by one aead key file, as ``rosgate check``'s fix for an open peer entry says.
    ``recovery: none`` by default: each datagram is then one envelope frame, one message
    (``""``: the topic's default, retransmit for a reliable topic, whose packets the attacker
    replays as they are)."""
    key = folder / "aead.key"
    key.write_bytes(base64.b64encode(os.urandom(32)))  # what rosgate keygen aead writes
    key.chmod(0o600)
    files = []
    for name, direction, port in (("a", "transmit", send_to), ("b", "receive", listen_on)):
        path = folder / f"{name}.yaml"
        path.write_text(f"""
bridge: {{name: {name}, role: peer, peer: 127.0.0.1, listen: 127.0.0.1, {FAST}, insecure: false}}
plugins: {{aead: {{key_file: {key}}}}}
{section}:
  - {{{entry}, direction: {direction}, port: {port}, cipher: aead{
      f", recovery: {recovery}" if recovery and section == "topics" else ""}}}
""")
        files.append(path)
    return files[0], files[1]


def data_frames(captured: list[tuple[bool, bytes]], flag: int = 0) -> list[bytes]:
    """The datagrams a sent towards b that carry messages (``flag``: calls), not
    announcements."""
    return [d for up, d in captured if up and d[:2] == envelope.MAGIC
            and not d[3] & envelope.FLAG_ANNOUNCE and d[3] & flag == flag]


def replayed_count(b: Bridge) -> int:
    """What a stopped bridge counted ``replayed`` (its route's line at stop)."""
    found = re.search(r"drops: .*\breplayed=(\d+)", b.log)
    return int(found.group(1)) if found else 0


def kill(b: Bridge) -> None:
    """The receiving robot loses power: no orderly stop, nothing written on the way out."""
    b.proc.kill()
    b.proc.wait()


@pytest.mark.parametrize("recovery", ["none", ""], ids=["bare frames", "retransmit packets"])
def test_frames_captured_before_the_receiver_restarts_publish_nothing(recovery, tmp_path, domain,
                                                                      ros_side, bridge):
    """The review's attack 2: 25 datagrams of Twists captured on the way, sent again after the
    receiving bridge restarted. Measured on the code before the replay record: 25 of 25
    published (the restarted receiver's replay window is empty, and the sender's epoch still
    runs). Now: 0, each counted ``replayed``."""
    da, db = domain(), domain()
    port = free_port()
    proxy = FaultProxy(free_port(), port)
    try:
        a_yaml, b_yaml = keyed_pair(tmp_path, proxy.port, port, recovery=recovery)
        bridge(a_yaml, da)
        first = Bridge(b_yaml, db)
        talker = ros_side(da, "a").publisher("/cmd_vel", Twist)
        inbox = ros_side(db, "b").listen("/cmd_vel", Twist)
        cross(talker, inbox, twist, is_warmup, 0)
        mark = len(proxy.udp.captured)
        got = cross(talker, inbox, twist, is_warmup, 25)
        assert sorted(m.linear.x for m in got) == [float(i) for i in range(25)]
        # bare: the 25 frames; repaired: every packet a sent (messages, probes, batches)
        frames = data_frames(proxy.udp.captured[mark:]) if recovery else \
            [d for up, d in proxy.udp.captured[mark:] if up]
        assert len(frames) >= (25 if recovery else 1), len(frames)  # warm-ups may cross too
        kill(first)

        second = bridge(b_yaml, db)
        cross(talker, inbox, twist, is_warmup, 0)  # the sender's new frames cross: no lockout
        start = len(inbox.items)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
            for frame in frames[-25:] if recovery else frames:
                udp.sendto(frame, ("127.0.0.1", port))
        talker.publish(twist(1000))
        assert inbox.wait_for(lambda items: any(m.linear.x == 1000 for m in items[start:]), 10)
        settle(inbox)
        published = [m.linear.x for m in inbox.items[start:] if 0 <= m.linear.x < 25]
        assert published == []
        second.stop()
        # and the sender's first after the restart
        assert replayed_count(second) >= (25 if recovery else 1), second.log
    finally:
        proxy.close()


def test_frames_of_a_sender_start_the_receiver_has_forgotten_publish_nothing(tmp_path, domain,
                                                                           ros_side, bridge):
    """Within one run of the receiver: its replay window keeps the sender's last 8 starts, so
    frames captured 9 sender starts ago once opened a window of their own and were published
    (on the code before: 10 of 10). Now they are refused by their send time: 0."""
    da, db = domain(), domain()
    port = free_port()
    proxy = FaultProxy(free_port(), port)
    try:
        a_yaml, b_yaml = keyed_pair(tmp_path, proxy.port, port)
        b = bridge(b_yaml, db)
        inbox = ros_side(db, "b").listen("/cmd_vel", Twist)
        side_a = ros_side(da, "a")
        talker = side_a.publisher("/cmd_vel", Twist)
        frames: list[bytes] = []
        for start in range(10):
            a = Bridge(a_yaml, da)
            cross(talker, inbox, twist, is_warmup, 0)  # b has heard this start
            if start == 0:
                mark = len(proxy.udp.captured)
                got = cross(talker, inbox, twist, is_warmup, 10)
                assert sorted(m.linear.x for m in got) == [float(i) for i in range(10)]
                frames = data_frames(proxy.udp.captured[mark:])[-10:]
            kill(a)
        a = Bridge(a_yaml, da)
        try:
            cross(talker, inbox, twist, is_warmup, 0)
            start = len(inbox.items)
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
                for frame in frames:
                    udp.sendto(frame, ("127.0.0.1", port))
            talker.publish(twist(1000))
            assert inbox.wait_for(lambda items: any(m.linear.x == 1000 for m in items[start:]),
                                  10)
            settle(inbox)
            assert [m.linear.x for m in inbox.items[start:] if 0 <= m.linear.x < 10] == []
        finally:
            assert a.stop() == 0, a.log
        b.stop()
        assert replayed_count(b) >= 10, b.log
    finally:
        proxy.close()


def ready(caller: Caller, timeout: float = 30.0) -> None:
    """Call until a call is answered by the far side's ROS server (not by a bridge that is not
    ready yet), then let the service's timeout pass, so an answer lost in DDS discovery cannot
    land among the test's own."""
    deadline = time.monotonic() + timeout
    while caller.call(SetBool.Request(data=False)).message.startswith("rosgate: "):
        assert time.monotonic() < deadline, "the bridges never got ready"
        time.sleep(0.1)  # pacing the retries; each answer is waited on


def test_calls_captured_before_the_server_restarts_are_not_served(tmp_path, domain, ros_side,
                                                                 bridge):
    """The same attack on a service (a command too): 5 captured calls sent again after the
    serving bridge restarted. Before the replay record: served again. Now: 0 served."""
    da, db = domain(), domain()
    port = free_port()
    proxy = FaultProxy(free_port(), port)
    served: list[bool] = []

    def serve(request: SetBool.Request, response: SetBool.Response) -> SetBool.Response:
        served.append(request.data)
        response.success = True
        return response

    try:
        a_yaml, b_yaml = keyed_pair(tmp_path, proxy.port, port, "services",
                                    "service: /arm, type: std_srvs/srv/SetBool, timeout: 2")
        bridge(a_yaml, da)
        first = Bridge(b_yaml, db)
        ros_side(db, "b").ros.node.create_service(SetBool, "/arm", serve, qos_profile=DEEP)
        caller = Caller(ros_side(da, "a"), SetBool, "/arm")
        ready(caller)
        mark = len(proxy.udp.captured)
        for _ in range(5):
            assert caller.call(SetBool.Request(data=True)).success
        frames = data_frames(proxy.udp.captured[mark:], envelope.FLAG_REQUEST)
        assert len(frames) == 5 and served.count(True) == 5
        kill(first)

        second = bridge(b_yaml, db)
        ready(caller)  # the restarted server is found again
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
            for frame in frames:
                udp.sendto(frame, ("127.0.0.1", port))
        assert not caller.call(SetBool.Request(data=False)).message  # after the replays
        assert not wait_until(lambda: served.count(True) > 5, 1.0), served
        second.stop()
        assert replayed_count(second) >= 5, second.log
    finally:
        proxy.close()


def test_the_pair_carries_on_whichever_side_restarts_or_loses_its_record(tmp_path, domain,
                                                                          ros_side):
    """No lockout: the sender restarting (its new frames are stamped after its old ones), the
    receiver restarting, both in either order, and the receiver's record removed (it says so,
    and takes its peer's frames again)."""
    da, db = domain(), domain()
    port = free_port()
    a_yaml, b_yaml = keyed_pair(tmp_path, port, port)
    record = Path(os.environ["ROSGATE_STATE_DIR"]) / "b.replay"
    running: dict[str, Bridge] = {}

    def up(*names: str) -> None:
        for name in names:
            running[name] = Bridge(a_yaml if name == "a" else b_yaml, da if name == "a" else db)

    def down(*names: str) -> None:
        for name in names:
            kill(running.pop(name))

    try:
        up("a", "b")
        talker = ros_side(da, "a").publisher("/cmd_vel", Twist)
        inbox = ros_side(db, "b").listen("/cmd_vel", Twist)
        steps = [("a restarts", ("a",), ("a",)), ("b restarts", ("b",), ("b",)),
                 ("both down, a up first", ("a", "b"), ("a", "b")),
                 ("both down, b up first", ("a", "b"), ("b", "a"))]
        for what, stopped, started in [("first start", (), ()), *steps]:
            down(*stopped)
            up(*started)
            got = cross(talker, inbox, twist, is_warmup, 10)
            assert sorted(m.linear.x for m in got) == [float(i) for i in range(10)], what
        assert record.exists()
        assert "no record of what peer" not in "\n".join(running["b"].lines)
        down("b")
        record.unlink()
        up("b")
        assert running["b"].wait_log(f"no record of what peer 127.0.0.1 sent before this start "
                                     f"({record}, a first start, or it was lost)", 10)
        got = cross(talker, inbox, twist, is_warmup, 10)
        assert sorted(m.linear.x for m in got) == [float(i) for i in range(10)]
        twin_yaml = tmp_path / "twin.yaml"  # another bridge named b, on a port of its own
        twin_yaml.write_text(b_yaml.read_text().replace(f"port: {port}", f"port: {free_port()}"))
        twin = subprocess.run([ROSGATE, "run", str(twin_yaml)], capture_output=True, text=True,
                              timeout=60, env=dict(os.environ, ROS_DOMAIN_ID=str(db)))
        assert twin.returncode == 2 and f"another bridge keeps its replay record in {record}" \
            in twin.stderr, twin.stderr
    finally:
        for b in running.values():
            assert b.stop() == 0 and "Traceback" not in b.log, b.log


def marks(path: Path) -> dict[str, int]:
    """What a record's file says."""
    return json.loads(path.read_text())


def test_a_restarted_sender_stamps_after_its_old_frames_even_with_its_clock_set_back(tmp_path):
    """The record alone, on real files: the receiver refuses what it may have taken before its
    restart and takes what follows; a sender whose clock went back a minute across its restart
    still stamps after its old frames and after the receiver's mark, so it is not locked out."""
    sender, receiver = ReplayRecord(tmp_path / "a.replay"), ReplayRecord(tmp_path / "b.replay")
    assert not sender.known and not receiver.known
    sent = [sender.stamp(1000 * S + i * S // 100) for i in range(300)]  # 3 s of frames
    assert sent == sorted(sent) and sent[0] == 1000 * S
    assert all(map(receiver.fresh, sent))
    assert receiver.fresh(1)  # a first start refuses nothing (known is False)

    del sender, receiver  # both crash: their locks go, as a killed process's do
    sender, receiver = ReplayRecord(tmp_path / "a.replay"), ReplayRecord(tmp_path / "b.replay")
    assert sender.known and receiver.known
    assert not any(map(receiver.fresh, sent))  # every frame it took, and any frame before them
    assert not receiver.fresh(sent[-1] + 1)  # within the mark's second ahead: maybe taken
    after = sender.stamp(940 * S)  # its clock a minute behind
    assert after > max(sent) and receiver.fresh(after)
    assert sender.stamp(941 * S) >= after  # held up until its clock passes it


def test_the_record_is_written_about_once_a_second_of_frames_not_per_frame(tmp_path):
    path = tmp_path / "a.replay"
    record = ReplayRecord(path)
    record.stamp(1000 * S)
    written = path.read_text()
    for i in range(1000):  # a second of frames at 1 kHz, sent and heard
        record.fresh(record.stamp(1000 * S + i * S // 1000))
    assert path.read_text() != written  # heard: marked once
    written = path.read_text()
    for i in range(1000):
        record.fresh(record.stamp(1000 * S + i * S // 1000))
    assert path.read_text() == written
    record.stamp(1002 * S)
    assert path.read_text() != written


def test_one_record_serves_one_bridge_at_a_time(tmp_path):
    """Two bridges of one name and one state folder would each overwrite the other's marks."""
    record = ReplayRecord(tmp_path / "b.replay")
    with pytest.raises(OSError, match="another bridge keeps its replay record in"):
        ReplayRecord(tmp_path / "b.replay")
    record.close()
    ReplayRecord(tmp_path / "b.replay").close()


def test_an_unreadable_record_is_taken_as_lost_and_said(tmp_path):
    path = tmp_path / "b.replay"
    path.write_text("{not json")
    record = ReplayRecord(path)
    assert not record.known and "JSONDecodeError" in record.unreadable
    assert record.fresh(1)
    assert marks(path) == {"sent": 0, "heard": 1 + ReplayRecord.AHEAD}  # whole again


def test_the_refusal_of_an_open_peer_entry_ranks_identities_first_and_says_what_a_key_file_leaves(
        tmp_path):
    """Before, the fix offered a key file as equal to identities ("identities ... or this entry a
    cipher keyed from a file"). Now identities come first, and the key file after what it leaves
    open: theft from either machine, and a lost state folder."""
    path = tmp_path / "robot1.yaml"
    path.write_text("bridge: {name: robot1, role: peer, peer: 127.0.0.1, listen: 127.0.0.1}\n"
                    "topics: [{topic: /cmd_vel, type: geometry_msgs/msg/Twist, "
                    "direction: receive, port: 12002}]\n")
    refused = subprocess.run([ROSGATE, "check", str(path)], capture_output=True, text=True)
    assert refused.returncode == 2, refused.stderr
    fix = refused.stderr.split("fix: ", 1)[1]
    assert fix.startswith("give both peers identities (bridge.identity, peer_key, "
                          "handshake_port: docs/security.md); less safe, a cipher keyed from a "
                          "file"), fix
    for limit in ("from either machine", "writes to both sides", "loses its state folder",
                  "insecure: true"):
        assert limit in fix, fix


def test_a_record_that_cannot_be_written_is_said_once_and_frames_go_on(tmp_path, caplog):
    record = ReplayRecord(tmp_path / "b.replay")
    (tmp_path / "b.replay.new").mkdir()  # where the next file is written: not a file
    with caplog.at_level("ERROR", logger="rosgate"):
        assert all(record.fresh(1000 * S + i * 2 * S) for i in range(3))  # a mark each
    said = [r.getMessage() for r in caplog.records if "cannot write" in r.getMessage()]
    assert said == [f"cannot write {tmp_path / 'b.replay'} (Is a directory): frames taken now "
                    "could be replayed after a restart"]
    assert not (tmp_path / "b.replay").exists()


def test_a_frame_of_a_sender_start_the_window_forgot_is_refused(tmp_path):
    """Within one run of the receiver: the replay window keeps a sender's last 8 starts, and a
    frame of a start before them once opened a window of its own, as new. Now its send time is
    not after the latest one taken in the start forgotten: refused."""
    keys = StaticKeys(NoCipher({}, tmp_path), ReplayRecord(tmp_path / "b.replay"))
    first = [(1, 1000 * S + i) for i in range(3)]  # the sender's first start: epoch 1
    assert all(keys.fresh(*frame) for frame in first)
    for start in range(2, 10):  # eight starts more, each stamping later
        assert keys.fresh(start, (1000 + start) * S)
        assert keys.fresh(start - 1, (1000 + start - 1) * S + 1)  # late, across the restart
    assert not any(keys.fresh(*frame) for frame in first)
    assert keys.fresh(9, 1010 * S)  # the sender's own frames go on
