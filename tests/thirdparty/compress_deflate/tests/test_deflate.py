"""The deflate transform: the plugin kit's transform suite at two levels, and what it refuses."""

from __future__ import annotations

import zlib

import pytest
from rosgate_compress_deflate import DeflateTransform
from rosgate_testing import TransformConformance

from rosgate import OptionError, TransformError


class TestDeflateConformance(TransformConformance):
    transform = DeflateTransform


class TestFastestDeflateConformance(TransformConformance):
    transform = DeflateTransform
    options = {"level": 1}


def test_it_writes_a_zlib_stream():
    payload = b"odom " * 1000
    assert zlib.decompress(DeflateTransform({}, 1 << 20).encode(payload)) == payload


@pytest.mark.parametrize("data, message", [
    (zlib.compress(b"x" * 5000), "inflates to more than 1000 bytes"),
    (zlib.compress(b"x" * 500)[:-3], "not one whole deflate stream"),
    (zlib.compress(b"x" * 500) + b"more", "not one whole deflate stream"),
    (b"not deflate", "deflate: Error -3 while decompressing data: incorrect header check"),
])
def test_what_it_refuses(data, message):
    with pytest.raises(TransformError, match=message):
        DeflateTransform({}, 1000).decode(data)


def test_its_level_is_checked():
    with pytest.raises(OptionError) as error:
        DeflateTransform({"level": 10}, 1000)
    assert (error.value.key, error.value.message) == ("level", "expected an integer 1..9, got 10")
