"""A cipher that works in place (aead) seals a large payload straight into its frame and opens a
reassembled frame where it lies: the image that reaches the publisher is the very bytearray
the frame was reassembled in, and what went out is what ChaCha20-Poly1305 itself makes."""

from __future__ import annotations

import inspect
import os

import pytest
from cryptography.hazmat.primitives.ciphers.aead import ChaCha20Poly1305
from rosgate_crypto_aead import AeadCipher
from rosgate_testing import write_key

from rosgate.builtin import CdrCodec
from rosgate.config import TopicConfig
from rosgate.keyring import StaticKeys
from rosgate.routes import SEAL_IN_PLACE, EnvelopeFraming, ReceiveRoute, TransmitRoute, Warner
from rosgate.spec import Delivery
from rosgate.wire import envelope

pytestmark = pytest.mark.skipif(not AeadCipher.in_place,
                                reason="this cryptography has no encrypt_into/decrypt_into")

IMAGE = b"\x00\x01\x00\x00" + os.urandom(1024 * 1024)  # CDR-encapsulated, 1 MB
SECRET = os.urandom(32)


def topic() -> TopicConfig:
    fields = inspect.signature(TopicConfig).parameters
    return TopicConfig(**{name: None for name, p in fields.items() if p.default is p.empty})


class Link:
    datagram = True

    def __init__(self) -> None:
        self.frames: list[bytes] = []

    def send_all(self, frames, sender, to=None) -> int:
        self.frames += frames
        return len(frames)


def sender(cipher: AeadCipher) -> tuple[TransmitRoute, Link]:
    link = Link()
    route = TransmitRoute(topic(), 7, CdrCodec(None, {}), StaticKeys(cipher), Warner(), "/t",
                          Delivery(), framing=EnvelopeFraming(),
                          link=link,  # type: ignore[arg-type]
                          destination=lambda: ("127.0.0.1", 9))
    return route, link


def receiver(cipher: AeadCipher) -> tuple[ReceiveRoute, list]:
    codec = CdrCodec(None, {})
    route = ReceiveRoute(topic(), 7, codec, StaticKeys(cipher), Warner(), "/t", Delivery(),
                         decode=codec.decode)
    published: list = []
    route.publish = published.append
    return route, published


def static_cipher(tmp_path) -> AeadCipher:
    if not (tmp_path / "a.key").exists():
        write_key(tmp_path / "a.key", AeadCipher.generate_key())
    return AeadCipher({"key_file": "a.key"}, tmp_path)


def test_a_large_payload_is_sealed_into_its_frame_as_chacha20_poly1305_makes_it():
    route, link = sender(AeadCipher.from_secret(SECRET))
    route.on_message(IMAGE)
    (frame,) = link.frames
    assert type(frame) is bytearray and len(frame) == envelope.SIZE + len(IMAGE) + 16
    header = bytes(frame[:envelope.SIZE])
    unpacked = envelope.unpack(header)
    assert (unpacked.topic_id, unpacked.seq, unpacked.flags) == (7, 1, 0)
    plain = ChaCha20Poly1305(SECRET).decrypt(header[8:20], bytes(frame[envelope.SIZE:]), header)
    assert plain == IMAGE


def test_a_small_payload_stays_bytes_and_opens_the_same_way():
    route, link = sender(AeadCipher.from_secret(SECRET))
    small = IMAGE[:SEAL_IN_PLACE - 1]
    route.on_message(small)
    (frame,) = link.frames
    assert type(frame) is bytes
    header = frame[:envelope.SIZE]
    assert ChaCha20Poly1305(SECRET).decrypt(header[8:20], frame[envelope.SIZE:], header) == small


@pytest.mark.parametrize("keyed", ["session", "static"])
def test_a_reassembled_frame_is_opened_where_it_lies_and_published_without_a_copy(
        keyed, tmp_path):
    def cipher() -> AeadCipher:
        return AeadCipher.from_secret(SECRET) if keyed == "session" else static_cipher(tmp_path)

    out, link = sender(cipher())
    out.on_message(IMAGE)
    frame = bytearray(link.frames[0])  # as a reassembler hands it on: its own bytearray
    route, published = receiver(cipher())
    route.on_frame(envelope.unpack(frame), frame)  # type: ignore[arg-type]
    assert len(published) == 1 and published[0] is frame
    assert bytes(published[0]) == IMAGE
    assert route.counters.received == 1 and route.counters.drops == {}
    assert route.counters.bytes_received == envelope.SIZE + len(IMAGE) + (16 if keyed ==
                                                                          "session" else 28)


@pytest.mark.parametrize("where", ["header", "body", "tag"])
def test_a_tampered_frame_opened_in_place_is_dropped_and_counted(where):
    out, link = sender(AeadCipher.from_secret(SECRET))
    out.on_message(IMAGE)
    frame = bytearray(link.frames[0])
    at = {"header": 26, "body": envelope.SIZE + 500_000, "tag": len(frame) - 1}[where]
    frame[at] ^= 0x01
    route, published = receiver(AeadCipher.from_secret(SECRET))
    route.on_frame(envelope.unpack(frame), frame)  # type: ignore[arg-type]
    assert published == []
    assert route.counters.drops == {"auth_failed": 1} and route.counters.received == 0


def test_a_frame_too_short_for_its_tag_is_dropped_not_raised():
    frame = bytearray(envelope.pack(0, 7, 1, 1, 0) + b"short")
    route, published = receiver(AeadCipher.from_secret(SECRET))
    route.on_frame(envelope.unpack(frame), frame)  # type: ignore[arg-type]
    assert published == [] and route.counters.drops == {"auth_failed": 1}


def test_bytes_frames_still_open_through_open():
    """A frame that arrived whole (bytes, a view of nothing it owns) is not opened in place."""
    out, link = sender(AeadCipher.from_secret(SECRET))
    out.on_message(IMAGE[:1000])
    frame = link.frames[0]
    route, published = receiver(AeadCipher.from_secret(SECRET))
    route.on_frame(envelope.unpack(frame), frame)
    assert published == [IMAGE[:1000]] and type(published[0]) is bytes
