"""Authenticated sessions, piece by piece: identities, the Noise handshake and secure stream over
real sockets, the key schedule (generations, handshakes, expiry), session keys for routes, sealed
hellos, the policy, and type names from peers."""

from __future__ import annotations

import os
import socket
import sys
import threading
from pathlib import Path

import pytest
from rosgate_crypto_aead import AeadCipher

from rosgate import CipherError, identity
from rosgate.config import ClientPolicy, Rule, TopicConfig, service_from_mapping
from rosgate.policy import matches, refusal
from rosgate.rostypes import TypeNotFound, resolve_type
from rosgate.secure import (
    GRACE,
    HandshakeError,
    KeySchedule,
    SessionKeys,
    UnknownKey,
    initiate,
    open_hello,
    respond,
    seal_hello,
)
from rosgate.transport import SocketConnection
from rosgate.wire import envelope


# -- identities -------------------------------------------------------------------------------
def test_identity_files_are_0600_base64_and_refused_when_others_can_read(tmp_path: Path):
    key = identity.generate()
    path = tmp_path / "robot1.key"
    identity.write_private(path, key)
    assert path.stat().st_mode & 0o777 == 0o600
    assert len(path.read_text().strip()) == 44
    assert identity.load_private(path) == key
    with pytest.raises(FileExistsError):
        identity.write_private(path, identity.generate())
    path.chmod(0o644)
    with pytest.raises(identity.IdentityError) as info:
        identity.load_private(path)
    assert "can be read by other users (mode 644)" in str(info.value)
    assert info.value.fix == f"chmod 600 {path}"
    assert identity.encode(key) not in str(info.value)


@pytest.mark.parametrize("text", ["", "abc", "A" * 44, None, 7])
def test_a_public_key_that_is_not_one_is_refused(text):
    with pytest.raises(identity.IdentityError):
        identity.decode_public(text)


# -- the handshake, over real sockets -------------------------------------------------------------
def pair() -> tuple[SocketConnection, SocketConnection]:
    a, b = socket.socketpair()
    return SocketConnection(a), SocketConnection(b)


def handshake(client_key: bytes, server_key: bytes, known: set[bytes], server_public: bytes):
    c, s = pair()
    result: dict[str, object] = {}

    def serve() -> None:
        try:
            result["server"] = respond(s, server_key, lambda k: k in known, timeout=2)
        except HandshakeError as exc:
            result["server"] = exc
            s.close()

    thread = threading.Thread(target=serve)
    thread.start()
    try:
        result["client"] = initiate(c, client_key, server_public, timeout=2)
    except HandshakeError as exc:
        result["client"] = exc
    thread.join()
    return result["client"], result["server"]


@pytest.fixture
def keys():
    server, client = identity.generate(), identity.generate()
    return server, client, identity.public_of(server), identity.public_of(client)


def test_handshake_authenticates_both_sides_and_the_stream_carries_any_size(keys):
    server, client, server_public, client_public = keys
    c, s = handshake(client, server, {client_public}, server_public)
    assert c.peer_key == server_public and s.peer_key == client_public
    assert c.handshake_hash == s.handshake_hash
    data = os.urandom(200_000)  # several Noise messages
    c.send(data)
    got = b""
    while len(got) < len(data):
        got += s.receive(1 << 20, 2) or b""
    assert got == data
    s.send(b"back")
    assert c.receive(100, 2) == b"back"
    c.close()
    s.close()


def test_a_key_the_server_does_not_list_gets_no_answer(keys):
    server, client, server_public, _ = keys
    c, s = handshake(client, server, set(), server_public)
    assert isinstance(s, UnknownKey) and s.key == identity.public_of(client)
    assert isinstance(c, HandshakeError) and "closed during the handshake" in str(c)


def test_a_client_with_a_wrong_server_key_fails_on_both_sides(keys):
    server, client, _, client_public = keys
    wrong = identity.public_of(identity.generate())
    c, s = handshake(client, server, {client_public}, wrong)
    assert isinstance(s, HandshakeError) and not isinstance(s, UnknownKey)
    assert isinstance(c, HandshakeError)


@pytest.mark.parametrize("garbage, says", [
    (b"GET / HTTP/1.1\r\n\r\n", "not a handshake"),
    (b"\x00\x05hello", "not a handshake"),
    (b"", "no handshake in time"),
])
def test_the_server_parses_nothing_but_a_handshake(keys, garbage, says):
    server, _, _, _ = keys
    c, s = pair()
    c.send(garbage)
    with pytest.raises(HandshakeError, match=says):
        respond(s, server, lambda k: True, timeout=0.5)
    c.close()
    s.close()


def test_a_tampered_record_ends_the_secure_stream(keys):
    server, client, server_public, client_public = keys
    c, s = handshake(client, server, {client_public}, server_public)
    sealed = c.noise.encrypt(b"hello")
    c.raw.send(len(sealed).to_bytes(2, "big") + sealed[:-1] + bytes([sealed[-1] ^ 1]))
    with pytest.raises(OSError, match="does not verify"):
        s.receive(100, 2)


# -- the key schedule -----------------------------------------------------------------------------
class Clock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def schedules(rekey: float = 10.0):
    clock = Clock()
    secret, digest = os.urandom(32), os.urandom(32)
    a, b = KeySchedule(rekey, clock), KeySchedule(rekey, clock)
    a.install(7, secret, digest)
    b.install(7, secret, digest)
    return a, b, clock


def route_keys(a: KeySchedule, b: KeySchedule):
    sender = SessionKeys(a, AeadCipher, "topic c2s /t", "topic s2c /t")
    receiver = SessionKeys(b, AeadCipher, "topic s2c /t", "topic c2s /t")
    return sender, receiver


def frame(keys: SessionKeys, seq: int, epoch: int | None = None) -> tuple[int, bytes, bytes]:
    epoch = keys.epoch() if epoch is None else epoch
    header = envelope.pack(0, 5, epoch, seq, 0)
    return epoch, header, keys.sealer(epoch).seal(header, b"payload")


def test_two_sides_derive_the_same_keys_per_direction_and_generation():
    a, b, clock = schedules()
    sender, receiver = route_keys(a, b)
    epoch, header, body = frame(sender, 1)
    assert epoch == 7 << 24
    assert receiver.opener(epoch).open(header, body) == b"payload"
    # the other direction's key does not open it
    backwards = SessionKeys(b, AeadCipher, "topic c2s /t", "topic s2c /t")
    with pytest.raises(CipherError):
        backwards.opener(epoch).open(header, body)
    clock.now += 10  # the next generation: a new key and epoch
    epoch2, header2, body2 = frame(sender, 1)
    assert epoch2 == 7 << 24 | 1
    assert receiver.opener(epoch2).open(header2, body2) == b"payload"
    with pytest.raises(CipherError):
        receiver.opener(epoch2).open(header, body)


def test_generations_overlap_by_one_and_older_ones_never_open():
    a, b, clock = schedules()
    sender, receiver = route_keys(a, b)
    epoch, header, body = frame(sender, 1)
    clock.now += 10  # one generation on: still opens (the two clocks may straddle a turn)
    assert receiver.opener(epoch).open(header, body) == b"payload"
    clock.now += 10  # two on: that key is gone
    assert receiver.opener(epoch) is None
    assert receiver.opener(epoch + 5) is None  # nor a generation from the future


def test_a_new_handshake_keeps_the_old_root_for_a_grace_period_then_erases_it():
    a, b, clock = schedules()
    sender, receiver = route_keys(a, b)
    old_epoch, header, body = frame(sender, 1)
    secret, digest = os.urandom(32), os.urandom(32)
    a.install(8, secret, digest)
    b.install(8, secret, digest)
    new_epoch, header2, body2 = frame(sender, 1)
    assert new_epoch >> 24 == 8
    assert receiver.opener(new_epoch).open(header2, body2) == b"payload"
    assert receiver.opener(old_epoch).open(header, body) == b"payload"  # queued frames
    clock.now += GRACE + 1
    assert receiver.opener(old_epoch) is None


def test_a_reused_key_id_is_a_new_root_not_a_cached_cipher():
    """A restarted server may pick the key id its predecessor had."""
    a, b, _ = schedules()
    sender, receiver = route_keys(a, b)
    epoch, header, body = frame(sender, 1)
    secret, digest = os.urandom(32), os.urandom(32)
    a.install(7, secret, digest)
    b.install(7, secret, digest)
    assert receiver.opener(epoch) is not None
    with pytest.raises(CipherError):
        receiver.opener(epoch).open(header, body)  # the old root's frame
    epoch2, header2, body2 = frame(sender, 2)
    assert epoch2 == epoch and receiver.opener(epoch2).open(header2, body2) == b"payload"


def test_a_server_seals_under_the_old_root_until_the_client_is_ready():
    server, _, _ = schedules()
    server.install(8, os.urandom(32), os.urandom(32), seal_now=False)
    assert server.epoch() >> 24 == 7
    server.seal_with(8)
    assert server.epoch() >> 24 == 8


def test_an_offered_secret_keys_both_sides_and_the_next_offer_is_the_next_key_id():
    clock, digest = Clock(), os.urandom(32)
    responder, initiator = KeySchedule(10.0, clock), KeySchedule(10.0, clock)
    offer = responder.offer(digest)
    assert sorted(offer) == ["key_id", "rekey", "secret"] and offer["rekey"] == 10.0
    assert len(bytes.fromhex(offer["secret"])) == 32 and 0 <= offer["key_id"] < 256
    assert responder.epoch() >> 24 == offer["key_id"]  # the first offer seals at once
    assert initiator.accept(offer, digest) == offer["key_id"]
    sender, receiver = route_keys(responder, initiator)
    epoch, header, body = frame(sender, 1)
    assert receiver.opener(epoch).open(header, body) == b"payload"
    again = responder.offer(os.urandom(32))
    assert again["key_id"] == (offer["key_id"] + 1) % 256 and again["secret"] != offer["secret"]
    assert responder.epoch() >> 24 == offer["key_id"]  # until the initiator is ready
    responder.seal_with("not a key id")
    responder.seal_with([again["key_id"]])
    assert responder.epoch() >> 24 == offer["key_id"]
    responder.seal_with(again["key_id"])
    assert responder.epoch() >> 24 == again["key_id"]


@pytest.mark.parametrize("offer", [
    {"secret": "00" * 31, "key_id": 1}, {"secret": "00" * 32, "key_id": 256},
    {"secret": "00" * 32, "key_id": -1}, {"secret": "zz", "key_id": 1}, {"key_id": 1},
    {"secret": "00" * 32, "key_id": "x"}, {"secret": 5, "key_id": 1}])
def test_an_offer_without_a_session_secret_is_refused_and_installs_nothing(offer):
    schedule = KeySchedule(10.0, Clock())
    with pytest.raises((ValueError, KeyError, TypeError)):
        schedule.accept(offer, os.urandom(32))
    with pytest.raises(LookupError):
        schedule.epoch()


def test_a_forgotten_schedule_opens_and_seals_nothing():
    a, b, _ = schedules()
    sender, receiver = route_keys(a, b)
    epoch, _, _ = frame(sender, 1)
    b.forget()
    assert receiver.opener(epoch) is None
    with pytest.raises(LookupError):
        b.epoch()


def test_hellos_are_sealed_in_the_session():
    a, b, _ = schedules()
    hello = seal_hello(a, 3, 1)
    header = envelope.unpack(hello)
    assert header.flags == envelope.FLAG_HELLO and header.topic_id == 3
    assert open_hello(b, header, hello)
    assert not open_hello(b, header, hello[:-1] + bytes([hello[-1] ^ 1]))
    forged = envelope.pack(envelope.FLAG_HELLO, 3, header.epoch, 1, 0) + bytes(16)
    assert not open_hello(b, envelope.unpack(forged), forged)
    other, _, _ = schedules()
    assert not open_hello(other, header, hello)


# -- policy ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("pattern, name, expected", [
    ("/robot1/**", "/robot1/scan", True), ("/robot1/**", "/robot1/arm/joint", True),
    ("/robot1/*", "/robot1/arm/joint", False), ("/robot1/*", "/robot1/scan", True),
    ("/robot1/**", "/robot10/scan", False), ("/robot?/scan", "/robot2/scan", True),
    ("/**", "/anything/at/all", True), ("std_msgs/msg/*", "std_msgs/msg/String", True),
    ("std_msgs/*", "std_msgs/msg/String", False), ("/a.b", "/aXb", False),
])
def test_globs(pattern, name, expected):
    assert matches(pattern, name) is expected


def topic(remote: str, direction: str = "transmit", **kw) -> TopicConfig:
    fields = {"type": "std_msgs/msg/String", "cipher": "aead", **kw}
    return TopicConfig(topic="/local", direction=direction, remote=remote,  # type: ignore[arg-type]
                       **fields)


POLICY = ClientPolicy("robot1", bytes(32), topics=(
    Rule("/robot1/**", "transmit", types=("std_msgs/msg/*",)),
    Rule("/robot1/cmd", "receive", ciphers=("aead", "none")),
    Rule("/robot1/cam/*", "both", ports=((12010, 12019),)),
), services=(Rule("/robot1/ping", "transmit"),))


@pytest.mark.parametrize("entry, says", [
    (topic("/robot1/x"), None),
    (topic("/robot1/cmd", "receive", cipher="none"), None),
    (topic("/robot1/cam/a", port=12012), None),
    (topic("/cmd_vel"), "robot1 may not transmit /cmd_vel (policy for robot1 allows /robot1/**, "
                        "/robot1/cam/*)"),
    (topic("/robot1/x", "receive"), "robot1 may not receive /robot1/x (policy for robot1 allows "
                                    "/robot1/cmd, /robot1/cam/*)"),
    (topic("/robot1/x", type="geometry_msgs/msg/Twist"),
     "robot1 may not transmit /robot1/x with type geometry_msgs/msg/Twist (policy for robot1 "
     "allows types std_msgs/msg/* for /robot1/**)"),
    (topic("/robot1/x", cipher="none"),
     "robot1 may not transmit /robot1/x with cipher none (policy for robot1 allows ciphers "
     "keyed by the session (not none) for /robot1/**)"),
    (topic("/robot1/x", port=12001),
     "robot1 may not transmit /robot1/x with port 12001 (policy for robot1 allows ports none but "
     "the main port for /robot1/**)"),
    (topic("/robot1/cam/a", "receive", port=13000),
     "robot1 may not receive /robot1/cam/a with port 13000 (policy for robot1 allows ports "
     "12010-12019 for /robot1/cam/*)"),
    (topic("/robot1/cmd", "receive", cipher="fernet"),
     "robot1 may not receive /robot1/cmd with cipher fernet (policy for robot1 allows ciphers "
     "aead, none for /robot1/cmd)"),
])
def test_policy_refusals_name_the_client_the_entry_and_the_rule(entry, says):
    assert refusal(POLICY, entry, {"none"}) == says


def test_policy_for_services():
    call = service_from_mapping({"service": "/reset", "type": "std_srvs/srv/Trigger",
                                 "direction": "transmit", "cipher": "aead"}, {}, "x")
    assert refusal(POLICY, call, {"none"}) == ("robot1 may not transmit service /reset (policy "
                                              "for robot1 allows /robot1/ping)")
    served = service_from_mapping({"service": "/robot1/ping", "type": "std_srvs/srv/Trigger",
                                   "direction": "receive", "cipher": "aead"}, {}, "x")
    assert refusal(POLICY, served, {"none"}) == ("robot1 may not receive service /robot1/ping "
                                                "(policy for robot1 allows no services it "
                                                "receives)")


def test_no_rules_refuse_everything():
    empty = ClientPolicy("robot9", bytes(32))
    assert refusal(empty, topic("/x"), set()) == (
        "robot9 may not transmit /x (policy for robot9 allows no topics it transmits)")


# -- type names from peers ------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["this/msg/Foo", "antigravity/msg/Foo", "os/msg/Path",
                                  "rosgate/msg/Foo", "pytest/srv/X"])
def test_a_type_name_never_imports_a_module_that_is_not_an_interface_package(name):
    package = name.split("/")[0]
    was_loaded = package in sys.modules
    with pytest.raises(TypeNotFound, match="is not installed"):
        resolve_type(name)
    assert (package in sys.modules) == was_loaded


def test_interface_packages_still_resolve():
    assert resolve_type("std_msgs/msg/String").__name__ == "String"
    assert resolve_type("std_srvs/srv/Trigger").__name__ == "Trigger"


def test_a_route_holds_its_ciphers_only_while_its_keys_are_the_same():
    """A route keeps the cipher it seals with and the one it last opened with, and asks its
    keys again when a generation turns, a handshake installs a root, or a key id is reused."""
    import inspect

    from rosgate.keyring import NoKey
    from rosgate.routes import Route, Warner

    a, b, clock = schedules()
    sender_keys, receiver_keys = route_keys(a, b)
    fields = inspect.signature(TopicConfig).parameters
    topic = TopicConfig(**{n: None for n, p in fields.items() if p.default is p.empty})
    sender = Route(topic, 5, None, sender_keys, Warner(), "/t (sender)")
    receiver = Route(topic, 5, None, receiver_keys, Warner(), "/t (receiver)")

    def crosses(seq: int) -> tuple[int, bytes | None]:
        epoch, sealer = sender.sealing()
        assert epoch == sender_keys.epoch()
        frame = sender.seal(0, epoch, seq, b"payload %d" % seq, 0, sealer)
        # sealed under what the keys seal with now, not a cipher held too long
        opener = receiver_keys.opener(epoch)
        assert opener is not None
        assert opener.open(frame[:envelope.SIZE], frame[envelope.SIZE:]) == b"payload %d" % seq
        return epoch, receiver.open(frame, epoch)

    assert crosses(1) == (7 << 24, b"payload 1")
    assert crosses(2) == (7 << 24, b"payload 2")  # the held ciphers
    clock.now += 10  # a new generation
    assert crosses(3) == (7 << 24 | 1, b"payload 3")
    secret, digest = os.urandom(32), os.urandom(32)
    a.install(8, secret, digest)
    b.install(8, secret, digest)
    assert crosses(4) == (8 << 24 | 0, b"payload 4")  # the new root's at once
    secret, digest = os.urandom(32), os.urandom(32)
    a.install(8, secret, digest)  # a restarted server reusing key id 8: same epoch, new root
    b.install(8, secret, digest)
    assert crosses(5) == (8 << 24 | 0, b"payload 5")
    a.forget()
    with pytest.raises(NoKey):
        sender.sealing()
    assert receiver.counters.drops == {}
