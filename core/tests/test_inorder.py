"""A reliable topic's frames put back in their sender's order (rosgate.inorder), within its
hold's time, bytes and frames."""

from rosgate.inorder import InOrder


def test_frames_after_a_gap_wait_for_the_missing_one_then_go_in_order():
    order = InOrder(hold=2.0)
    assert order.put(7, 1, "m1", 10, 0.0) == ["m1"]
    assert order.put(7, 3, "m3", 10, 0.1) == []
    assert order.put(7, 4, "m4", 10, 0.2) == []
    assert order.put(7, 4, "m4", 10, 0.2) == [] and order.copies == 1
    assert order.held_bytes == 20 and order.next_due() == 2.1
    assert order.put(7, 2, "m2", 10, 0.3) == ["m2", "m3", "m4"]
    assert len(order) == 0 and order.held_bytes == 0 and order.next_due() is None
    assert order.put(7, 2, "again", 10, 0.4) == ["again"]  # a copy: the replay window refuses it


def test_a_gap_is_given_up_after_the_hold_and_a_late_frame_still_goes():
    order = InOrder(hold=2.0)
    order.put(1, 1, "m1", 10, 0.0)
    order.put(1, 3, "m3", 10, 0.0)
    assert order.put(1, 2, "m2", 10, 0.0) == ["m2", "m3"]  # the sender repairs
    assert order.put(1, 5, "m5", 10, 0.5) == []
    assert order.put(1, 7, "m7", 10, 1.0) == []
    assert order.due(2.4) == []
    assert order.due(2.5) == ["m5"] and order.gaps == 1
    assert order.due(3.0) == ["m7"] and order.gaps == 2 and not order.unrepaired
    assert order.put(1, 4, "m4", 10, 3.1) == ["m4"]  # the replay window decides


def test_the_first_frames_of_an_epoch_are_waited_for_unless_it_is_heard_mid_stream():
    order = InOrder(hold=2.0)
    assert order.put(1, 2, "m2", 10, 0.0) == []  # m1 lost on the way: waited for
    assert order.put(1, 1, "m1", 10, 0.1) == ["m1", "m2"]
    # a new epoch, heard mid-stream: what comes in the first 0.3 s is gathered, then the newest
    # unbroken run goes (n880 and n895: repairs of what was sent before this side was there)
    assert order.put(2, 900, "n900", 10, 0.2) == []
    assert order.put(2, 880, "n880", 10, 0.25) == []
    assert order.put(2, 895, "n895", 10, 0.3) == []
    assert order.put(2, 901, "n901", 10, 0.35) == []
    assert order.next_due() == 0.5
    assert order.due(0.5) == ["n900", "n901"] and order.before == 2
    assert order.put(2, 880, "n880", 10, 0.6) == [] and order.before == 3  # not for this side
    assert order.put(2, 903, "n903", 10, 0.7) == []
    assert order.put(3, 1, "k1", 10, 0.8) == ["n903", "k1"]  # a new key: the old order goes


def test_what_overflows_the_bounds_gives_the_oldest_gap_up():
    order = InOrder(hold=2.0, max_bytes=25, max_frames=10)
    order.put(1, 1, "m1", 10, 0.0)
    assert order.put(1, 3, "m3", 10, 0.1) == []
    assert order.put(1, 4, "m4", 10, 0.1) == []
    assert order.put(1, 6, "m6", 10, 0.1) == ["m3", "m4"] and order.overflowed == 1
    assert order.held_bytes == 10
    assert order.put(1, 100_000, "far", 10, 0.2) == ["m6", "far"]  # a jump: the order restarts


def test_a_sender_that_never_repairs_is_found_out_at_its_first_gap_then_frames_go_as_they_come():
    order = InOrder(hold=2.0)
    order.put(1, 1, "m1", 10, 0.0)
    assert order.put(1, 3, "m3", 10, 0.1) == []
    assert order.due(2.1) == ["m3"] and order.unrepaired
    assert order.put(1, 5, "m5", 10, 2.2) == ["m5"]  # no hold any more
    assert order.put(1, 4, "m4", 10, 2.3) == ["m4"]


def test_a_sender_that_repaired_once_is_waited_for_at_its_next_gap_too():
    order = InOrder(hold=2.0)
    order.put(1, 1, "m1", 10, 0.0)
    order.put(1, 3, "m3", 10, 0.1)
    assert order.put(1, 2, "m2", 10, 0.2) == ["m2", "m3"] and order.filled == 1
    order.put(1, 5, "m5", 10, 0.3)
    assert order.due(2.4) == ["m5"] and not order.unrepaired  # given up, still ordered
    assert order.put(1, 7, "m7", 10, 2.4) == []
