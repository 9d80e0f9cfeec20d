"""Serial datagram framing against the shared vectors, byte for byte, and every bad frame."""

from __future__ import annotations

import zlib
from pathlib import Path

import pytest
from rosgate_mcu_cvra import serial_datagram as sd

VECTORS = Path(__file__).resolve().parent / "vectors" / "serial_datagram.txt"


def vectors() -> list[tuple[bytes, bytes]]:
    pairs = []
    for line in VECTORS.read_text().splitlines():
        if line.startswith("#") or "->" not in line:
            continue
        payload, frame = (part.strip() for part in line.split("->"))
        pairs.append((b"" if payload == "(empty)" else bytes.fromhex(payload),
                      bytes.fromhex(frame)))
    return pairs


def decode_all(data: bytes, chunk: int | None = None, max_frame: int = 64 * 1024):
    errors: list[str] = []
    decoder = sd.Decoder(lambda reason, detail: errors.append(reason), max_frame)
    step = chunk or max(len(data), 1)
    frames = [f for i in range(0, len(data), step) for f in decoder.feed(data[i:i + step])]
    return frames, errors


def test_the_file_has_the_three_vectors():
    assert len(vectors()) == 3


@pytest.mark.parametrize("payload,frame", vectors())
def test_encode_matches_every_vector(payload, frame):
    assert sd.encode(payload) == frame


@pytest.mark.parametrize("payload,frame", vectors())
def test_decode_matches_every_vector_whole_and_byte_by_byte(payload, frame):
    assert decode_all(frame) == ([payload], [])
    assert decode_all(frame, chunk=1) == ([payload], [])


def test_frames_back_to_back_and_every_byte_value():
    payloads = [bytes(range(256)), b"\xc0\xdb\xc0", b"x" * 1000]
    data = b"".join(map(sd.encode, payloads))
    assert decode_all(data, chunk=7) == (payloads, [])


def test_bad_frames_are_reported_and_the_next_frame_still_decodes():
    good = sd.encode(b"ok")
    bad_crc = bytearray(sd.encode(b"hello"))
    bad_crc[0] ^= 1
    cases = [
        (b"\x01\x02\x03\xc0", "too_short"),
        (b"\xc0", "too_short"),
        (bytes(bad_crc), "bad_crc"),
        (b"ab\xdb\x41cdef\xc0", "bad_escape"),  # ESC followed by neither ESC_END nor ESC_ESC
        (b"abcdef\xdb\xc0", "bad_escape"),      # ESC right before END
    ]
    for data, reason in cases:
        assert decode_all(data + good) == ([b"ok"], [reason]), data


def test_a_frame_over_the_limit_is_dropped_once_and_skipped_to_its_end():
    big = sd.encode(b"y" * 101)
    frames, errors = decode_all(big + sd.encode(b"z" * 100), chunk=16, max_frame=100)
    assert (frames, errors) == ([b"z" * 100], ["too_long"])


def test_memory_stays_bounded_on_an_endless_frame():
    decoder = sd.Decoder(lambda *a: None, max_frame=100)
    for _ in range(100):
        list(decoder.feed(b"\x00" * 1000))
    assert decoder.pending <= 104


def test_crc_is_big_endian_zlib_crc32():
    assert sd.encode(b"abc")[-5:-1] == zlib.crc32(b"abc").to_bytes(4, "big")
