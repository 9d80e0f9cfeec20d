"""Waiting for state nothing signals: a link's counters, which its own thread moves after the
kernel has taken the packets (so the far side may hold a frame before they do), or a
retransmit store."""

import time


def settles(condition, timeout: float = 20.0) -> bool:
    """Whether ``condition()`` holds within ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True
