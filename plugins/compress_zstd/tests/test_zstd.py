"""The zstd transform: the plugin kit's transform suite at its default level and at the extremes
of its range, and its option's limits."""

from __future__ import annotations

import pytest
from rosgate_compress_zstd import ZstdTransform
from rosgate_testing import TransformConformance

from rosgate import OptionError


class TestZstdConformance(TransformConformance):
    transform = ZstdTransform


class TestFastestZstdConformance(TransformConformance):
    transform = ZstdTransform
    options = {"level": -7}


class TestSmallestZstdConformance(TransformConformance):
    transform = ZstdTransform
    options = {"level": 22}


def test_a_payload_goes_out_as_a_zstd_frame_of_its_level():
    payload = b"abc" * 10_000
    fast, small = ZstdTransform({"level": 1}, 1 << 20), ZstdTransform({"level": 19}, 1 << 20)
    packed_fast, packed_small = fast.encode(payload), small.encode(payload)
    assert packed_fast is not None and packed_small is not None
    assert packed_fast[:4] == packed_small[:4] == b"\x28\xb5\x2f\xfd"  # zstd's magic
    assert len(packed_small) <= len(packed_fast)
    assert small.decode(packed_fast) == payload  # the level is the sender's alone


@pytest.mark.parametrize("options, message", [
    ({"level": 0}, "must not be 0 (zstd would take it for its default, 3)"),
    ({"level": 23}, "expected an integer -7..22, got 23"),
    ({"level": -8}, "expected an integer -7..22, got -8"),
    ({"level": "max"}, "expected an integer -7..22, got 'max'"),
])
def test_wrong_levels(options, message):
    with pytest.raises(OptionError) as error:
        ZstdTransform(options, 1 << 20)
    assert (error.value.key, error.value.message) == ("level", message)
