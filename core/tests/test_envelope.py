"""The envelope header, byte for byte, and the replay window that refuses duplicated and stale
frames."""

from __future__ import annotations

import random

import pytest

from rosgate.wire import envelope
from rosgate.wire.envelope import EnvelopeError, Header, ReplayWindow

# --- pack / unpack -------------------------------------------------------------------------------

# flags 0x03, topic 0x01020304, epoch 0xA0B0C0D0, seq 0x1122334455667788, stamp 0x0102030405060708
PACKED = (b"RG"                                  # magic
          b"\x01"                                # version
          b"\x03"                                # flags
          b"\x01\x02\x03\x04"                    # topic_id
          b"\xa0\xb0\xc0\xd0"                    # epoch
          b"\x11\x22\x33\x44\x55\x66\x77\x88"    # seq
          b"\x01\x02\x03\x04\x05\x06\x07\x08")   # stamp


def test_pack_is_the_documented_28_byte_big_endian_layout():
    packed = envelope.pack(0x03, 0x01020304, 0xA0B0C0D0, 0x1122334455667788, 0x0102030405060708)
    assert packed == PACKED
    assert len(packed) == envelope.SIZE == 28


def test_pack_of_small_values_puts_them_in_the_low_bytes():
    assert envelope.pack(envelope.FLAG_CONTROL, 0, 1, 2, 3) == (
        b"RG\x01\x01" + b"\x00" * 4 + b"\x00\x00\x00\x01" + b"\x00" * 7 + b"\x02" + b"\x00" * 7
        + b"\x03")
    assert envelope.pack(envelope.FLAG_HELLO, 7, 0, 0, 0)[3] == 0x02


def test_unpack_reads_the_fields_back():
    assert envelope.unpack(PACKED) == Header(flags=3, topic_id=0x01020304, epoch=0xA0B0C0D0,
                                             seq=0x1122334455667788, stamp=0x0102030405060708)


@pytest.mark.parametrize("fields", [
    (0, 0, 0, 0, 0),
    (0xFF, 0xFFFFFFFF, 0xFFFFFFFF, 0xFFFFFFFFFFFFFFFF, 0xFFFFFFFFFFFFFFFF),
    (0x02, 12, 0xDEADBEEF, 1, 1_700_000_000_123_456_789),
])
def test_round_trip_of_extreme_values(fields):
    assert envelope.unpack(envelope.pack(*fields)) == Header(*fields)


def test_unpack_ignores_the_body_and_takes_a_memoryview():
    frame = PACKED + b"body bytes"
    assert envelope.unpack(memoryview(frame)) == envelope.unpack(frame) == envelope.unpack(PACKED)


@pytest.mark.parametrize("frame", [b"", b"R", b"RG", PACKED[:27]], ids=["empty", "1", "2", "27"])
def test_truncated(frame):
    with pytest.raises(EnvelopeError) as info:
        envelope.unpack(frame)
    assert info.value.args == ("truncated",)


@pytest.mark.parametrize("magic", [b"XX", b"GR", b"rg", b"RF", b"\x00\x00"])
def test_foreign_magic(magic):
    with pytest.raises(EnvelopeError) as info:
        envelope.unpack(magic + PACKED[2:])
    assert info.value.args == ("foreign",)


@pytest.mark.parametrize("version", [0, 2, 255])
def test_other_version(version):
    frame = PACKED[:2] + bytes([version]) + PACKED[3:]
    with pytest.raises(EnvelopeError) as info:
        envelope.unpack(frame)
    assert info.value.args == ("version",)


def test_foreign_is_reported_before_version():
    with pytest.raises(EnvelopeError, match="^foreign$"):
        envelope.unpack(b"XX\x09" + PACKED[3:])


def test_envelope_error_is_a_value_error():
    assert issubclass(EnvelopeError, ValueError)


# --- replay window -------------------------------------------------------------------------------

EPOCH = 0x5EED


def accept_all(window: ReplayWindow, seqs, epoch: int = EPOCH) -> list[str | None]:
    return [window.accept(epoch, s) for s in seqs]


def test_in_order_frames_are_all_accepted():
    window = ReplayWindow()
    assert accept_all(window, range(1, 1001)) == [None] * 1000


def test_duplicate_of_the_newest_and_of_an_older_frame():
    window = ReplayWindow()
    assert accept_all(window, [1, 2, 3, 4, 5]) == [None] * 5
    assert window.accept(EPOCH, 5) == "duplicate"
    assert window.accept(EPOCH, 1) == "duplicate"
    assert window.accept(EPOCH, 3) == "duplicate"
    assert window.accept(EPOCH, 6) is None


def test_first_frame_of_an_epoch_is_remembered():
    window = ReplayWindow()
    assert window.accept(EPOCH, 42) is None
    assert window.accept(EPOCH, 42) == "duplicate"


def test_reordered_within_the_window_accepted_exactly_once():
    # seqs 1..1024 shuffled within blocks of 32: no frame arrives more than 63 behind the newest
    rng = random.Random(1)
    order: list[int] = []
    for start in range(1, 1025, 32):
        block = list(range(start, start + 32))
        rng.shuffle(block)
        order += block
    window = ReplayWindow()
    assert accept_all(window, order) == [None] * 1024
    # everything again: the newest 64 are duplicates, anything older is outside the window
    replay = accept_all(window, range(1, 1025))
    assert replay == ["stale"] * (1024 - 64) + ["duplicate"] * 64


def test_window_edges_63_behind_accepted_64_behind_stale():
    window = ReplayWindow()
    assert window.accept(EPOCH, 100) is None
    assert window.accept(EPOCH, 36) == "stale"      # 64 behind
    assert window.accept(EPOCH, 37) is None         # 63 behind
    assert window.accept(EPOCH, 37) == "duplicate"
    assert accept_all(window, range(38, 100)) == [None] * 62
    assert accept_all(window, range(37, 101)) == ["duplicate"] * 64


def test_advance_by_63_keeps_the_old_newest_in_the_window():
    window = ReplayWindow()
    assert window.accept(EPOCH, 1) is None
    assert window.accept(EPOCH, 64) is None
    assert window.accept(EPOCH, 1) == "duplicate"
    assert window.accept(EPOCH, 2) is None


def test_advance_by_exactly_the_window_pushes_the_old_newest_out():
    window = ReplayWindow()
    assert window.accept(EPOCH, 1) is None
    assert window.accept(EPOCH, 65) is None
    assert window.accept(EPOCH, 1) == "stale"
    assert window.accept(EPOCH, 2) is None  # 63 behind, never seen


def test_jump_larger_than_the_window():
    window = ReplayWindow()
    assert accept_all(window, range(1, 11)) == [None] * 10
    assert window.accept(EPOCH, 1010) is None
    assert accept_all(window, range(1, 11)) == ["stale"] * 10
    assert window.accept(EPOCH, 1010) == "duplicate"
    # frames in the gap that are still within the window were never seen: accepted once
    assert window.accept(EPOCH, 1009) is None
    assert window.accept(EPOCH, 947) is None   # 63 behind
    assert window.accept(EPOCH, 946) == "stale"
    assert accept_all(window, [1009, 947]) == ["duplicate", "duplicate"]


def test_huge_jump_does_not_leave_old_bits_behind():
    window = ReplayWindow()
    assert accept_all(window, range(1, 65)) == [None] * 64
    assert window.accept(EPOCH, 2**63) is None
    # every seq from 2**63 - 63 to 2**63 - 1 is new
    assert accept_all(window, range(2**63 - 63, 2**63)) == [None] * 63


def test_a_new_epoch_starts_afresh():
    window = ReplayWindow()
    assert accept_all(window, range(1, 101)) == [None] * 100
    restarted = EPOCH + 1
    # the restarted sender counts from 1 again: nothing is stale or a duplicate
    assert accept_all(window, range(1, 101), restarted) == [None] * 100
    assert window.accept(restarted, 100) == "duplicate"
    assert window.accept(restarted, 36) == "stale"


def test_a_new_epoch_may_start_anywhere():
    window = ReplayWindow()
    assert window.accept(EPOCH, 5000) is None
    assert window.accept(0, 7) is None
    assert window.accept(0, 6) is None      # reordered in the new epoch
    assert window.accept(0, 7) == "duplicate"


def test_a_frame_of_an_earlier_epoch_is_not_accepted_twice():
    window = ReplayWindow()
    old, new = 0xAAAA, 0xBBBB
    assert accept_all(window, [1, 2, 3], old) == [None] * 3
    assert accept_all(window, [1, 2], new) == [None] * 2   # the sender restarted
    # replays of frames already accepted: the class promises each (epoch, seq) once
    assert window.accept(old, 2) is not None
    assert window.accept(new, 1) is not None


def test_a_forged_epoch_does_not_lock_out_the_real_sender():
    # on an unauthenticated link anyone can send a frame with a new epoch; the real sender's
    # following frames must still be accepted, and its earlier ones still refused
    window = ReplayWindow()
    real, forged = 0x1111, 0x2222
    assert accept_all(window, [1, 2, 3], real) == [None] * 3
    assert window.accept(forged, 1) is None
    assert accept_all(window, [4, 5], real) == [None, None]
    assert window.accept(real, 5) == "duplicate"


def test_only_the_last_epochs_are_remembered():
    window = ReplayWindow()
    for epoch in range(ReplayWindow.EPOCHS + 1):
        assert window.accept(epoch, 1) is None
    assert window.accept(ReplayWindow.EPOCHS, 1) == "duplicate"
    assert window.accept(0, 1) is None  # forgotten: a matter for an authenticated handshake


def test_topic_of_reads_the_topic_from_the_first_8_bytes_only():
    frame = envelope.pack(0, 0xDEADBEEF, 1, 2, 3) + b"body"
    assert envelope.topic_of(frame[:8]) == 0xDEADBEEF
    assert envelope.topic_of(frame[:7]) is None
    assert envelope.topic_of(b"XX" + frame[2:8]) is None


# --- replay window on an unauthenticated route (cipher none): issue 10, attack 9 ---------------

def open_window() -> ReplayWindow:
    return ReplayWindow(authenticated=False)


def test_unauthenticated_in_order_duplicates_and_stale_as_before():
    window = open_window()
    assert accept_all(window, range(1, 1001)) == [None] * 1000
    assert window.accept(EPOCH, 1000) == "duplicate"
    assert window.accept(EPOCH, 937) == "duplicate"   # 63 behind
    assert window.accept(EPOCH, 936) == "stale"       # 64 behind
    assert window.accept(EPOCH, 1) == "stale"
    assert window.lost == 0


def test_one_forged_frame_far_ahead_does_not_lock_out_the_real_sender():
    window = open_window()
    assert accept_all(window, range(1, 101)) == [None] * 100
    assert window.accept(EPOCH, 2**63) is None        # forged: a window of its own
    assert accept_all(window, range(101, 201)) == [None] * 100
    assert window.accept(EPOCH, 150) == "duplicate"
    assert window.accept(EPOCH, 2**63) == "duplicate"
    assert window.lost == 0


def test_a_forged_frame_a_little_ahead_merges_when_the_sender_catches_up():
    window = open_window()
    assert accept_all(window, range(1, 11)) == [None] * 10
    assert window.accept(EPOCH, 110) is None          # 100 ahead: its own window
    assert accept_all(window, range(11, 110)) == [None] * 99  # the sender carries on, merged
    assert window.accept(EPOCH, 110) == "duplicate"
    assert accept_all(window, range(111, 121)) == [None] * 10
    assert window.accept(EPOCH, 50) == "stale"  # 70 behind the merged window


def test_a_real_jump_over_lost_frames_carries_on_in_the_new_window():
    window = open_window()
    assert accept_all(window, range(1, 11)) == [None] * 10
    assert accept_all(window, range(1011, 1111)) == [None] * 100  # 1000 frames lost on the way
    assert window.lost == 1000
    assert window.accept(EPOCH, 1100) == "duplicate"
    assert window.accept(EPOCH, 5) == "duplicate"  # the old window is still remembered
    assert accept_all(window, range(10_000_000, 10_000_010)) == [None] * 10  # a very long outage
    assert window.lost == 1000  # a jump past JUMP is not counted: it may have been forged


def test_forged_frames_everywhere_cost_at_most_the_tracks():
    window = open_window()
    assert accept_all(window, range(1, 11)) == [None] * 10
    for i in range(1, 100):
        assert window.accept(EPOCH, i * 10**9) is None
        assert window.accept(EPOCH, 10 + i) is None    # the real sender, between the forgeries
    assert len(window._windows[EPOCH]) <= ReplayWindow.TRACKS
