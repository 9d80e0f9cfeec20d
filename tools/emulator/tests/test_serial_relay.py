"""The serial line of rosgate_emulator.serial: bytes cross between the two stable names no
faster than the baud rate, impaired as its profile says and counted, and the devices vanish
and come back under new paths."""

from __future__ import annotations

import os
import random
import select
import time

import pytest
from rosgate_emulator.serial import LineProfile, PtyRelay


def opened(path: str) -> int:
    return os.open(path, os.O_RDWR | os.O_NOCTTY)


def read_exactly(fd: int, size: int, timeout: float = 10.0) -> bytes:
    data, deadline = b"", time.monotonic() + timeout
    while len(data) < size and time.monotonic() < deadline:
        if select.select([fd], [], [], 0.1)[0]:
            data += os.read(fd, size - len(data))
    return data


def read_until_quiet(fd: int, quiet: float = 0.5) -> bytes:
    data = b""
    while select.select([fd], [], [], quiet)[0]:
        data += os.read(fd, 65536)
    return data


def hung_up(fd: int) -> bool:
    """A read says the device is gone: end of file, or EIO."""
    try:
        return os.read(fd, 1) == b""
    except OSError:
        return True


def test_bytes_cross_both_ways_exact_and_no_faster_than_the_baud_rate(tmp_path):
    with PtyRelay(tmp_path, LineProfile(baud=57_600)) as relay:
        a, b = opened(relay.a), opened(relay.b)
        try:
            payload = bytes(random.Random(1).randrange(256) for _ in range(2880))
            start = time.monotonic()
            os.write(a, payload)
            assert read_exactly(b, len(payload)) == payload
            # 2,880 bytes of 10 bits at 57,600 baud take 0.5 s on the line
            assert time.monotonic() - start >= 0.45
            os.write(b, b"back")
            assert read_exactly(a, 4) == b"back"
            assert (relay.up.bytes, relay.down.bytes) == (2880, 4)
        finally:
            os.close(a)
            os.close(b)


@pytest.mark.parametrize("profile", [LineProfile(baud=1_000_000, flip=0.01, seed=5),
                                     LineProfile(baud=1_000_000, drop=0.01, seed=6),
                                     LineProfile(baud=1_000_000, duplicate=0.01, seed=7)],
                         ids=["flip", "drop", "duplicate"])
def test_impairments_are_what_the_counters_say(tmp_path, profile):
    with PtyRelay(tmp_path, profile) as relay:
        a, b = opened(relay.a), opened(relay.b)
        try:
            payload = bytes(range(256)) * 40
            os.write(a, payload)
            got = read_until_quiet(b)
        finally:
            os.close(a)
            os.close(b)
        c = relay.up
        assert 40 < c.flipped + c.dropped + c.duplicated < 200, c  # about 1 % of 10,240
        assert len(got) == len(payload) - c.dropped + c.duplicated
        if profile.flip:
            diffs = [i for i, (x, y) in enumerate(zip(payload, got, strict=True)) if x != y]
            assert diffs == c.flipped_at
            assert all(bin(payload[i] ^ got[i]).count("1") == 1 for i in diffs)


def test_unplugged_devices_vanish_and_return_under_new_paths(tmp_path):
    relay = PtyRelay(tmp_path, LineProfile(baud=1_000_000))
    try:
        first = [os.path.realpath(relay.a), os.path.realpath(relay.b)]
        a = opened(relay.a)
        relay.unplug()
        assert not os.path.exists(relay.a) and not os.path.exists(relay.b)
        assert hung_up(a)  # the device is gone under the program that had it
        os.close(a)
        relay.replug()
        again = [os.path.realpath(relay.a), os.path.realpath(relay.b)]
        assert not set(again) & set(first), (first, again)
        a, b = opened(relay.a), opened(relay.b)
        os.write(a, b"hello")
        assert read_exactly(b, 5) == b"hello"
        os.close(a)
        os.close(b)
    finally:
        relay.close()
