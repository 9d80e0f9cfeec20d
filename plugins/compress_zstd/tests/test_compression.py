"""zstd compression of payloads: round trips, the skip when nothing shrinks, and the bound that
keeps a hostile frame from decompressing into more than a frame may hold."""

from __future__ import annotations

import os

import pytest
import zstandard
from rosgate_compress_zstd import CompressionError, Compressor, Decompressor


@pytest.mark.parametrize("level", [-7, 1, 3, 19])
def test_round_trip_at_every_kind_of_level(level):
    payload = b"\xff" * 100_000 + bytes(range(256)) * 40 + b"\x00" * 5000
    packed = Compressor(level).compress(payload)
    assert packed is not None and len(packed) < len(payload) // 10
    assert Decompressor(1 << 20).decompress(packed) == payload


def test_what_does_not_shrink_is_left_as_it_is():
    compressor = Compressor(3)
    assert compressor.compress(os.urandom(5000)) is None  # noise
    assert compressor.compress(b"x") is None              # smaller than zstd's own header
    assert compressor.compress(b"") is None


def test_a_frame_that_states_more_than_the_limit_is_refused_before_it_is_decompressed():
    bomb = zstandard.ZstdCompressor(level=19).compress(bytes(64 << 20))
    assert len(bomb) < 4000  # 64 MiB of zeros
    with pytest.raises(CompressionError, match=r"decompress to 67108864 bytes, over the limit "
                                               r"of 1048576"):
        Decompressor(1 << 20).decompress(bomb)


def test_a_frame_that_does_not_state_its_size_is_refused():
    # zstandard's own max_output_size does not bound a frame that states its size, and a frame
    # that does not would need streaming: rosgate's senders always state it
    quiet = zstandard.ZstdCompressor(write_content_size=False).compress(b"a" * 1000)
    with pytest.raises(CompressionError, match="does not state its size"):
        Decompressor(1 << 20).decompress(quiet)


@pytest.mark.parametrize("data, reason", [
    (b"", "not a zstd frame"),
    (b"hello world", "not a zstd frame"),
    (b"\x28\xb5\x2f\xfd", "bad header"),
])
def test_garbage_is_an_error_not_a_crash(data, reason):
    with pytest.raises(CompressionError, match=reason):
        Decompressor(1 << 20).decompress(data)


def test_a_damaged_frame_is_an_error():
    packed = bytearray(Compressor(3).compress(b"abc" * 10_000) or b"")
    packed[len(packed) // 2] ^= 0xFF
    packed[-3] ^= 0xFF
    with pytest.raises(CompressionError):
        Decompressor(1 << 20).decompress(bytes(packed))
