"""The batch window (a topic's ``batch:``, see docs/real-links.md): the first message opens it,
the executor's thread sleeps until it closes (no wake-up per message), then the route takes
everything waiting and hands it to its link in one call: one datagram or stream write as far
as they fit, on each side a thread switch and a system call for all of them.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from typing import Any

#: the longest window a topic may ask for, seconds
WINDOW_MAX = 0.1
_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "µs": 1e-6}
_DURATION = re.compile(r"^\s*(\d+(?:\.\d*)?|\.\d+)\s*(s|ms|us|µs)?\s*$")


def window(key: Any, value: Any) -> float:
    """seconds, or a duration with its unit: `2ms`, `500us`, `0.002` (0: no window, at most
    0.1 s)"""
    fix = f"write a duration up to {WINDOW_MAX * 1e3:g} ms, e.g. {key.name}: 2ms"
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        seconds = float(value)
    elif isinstance(value, str) and (found := _DURATION.match(value)):
        seconds = float(found.group(1)) * _UNITS[found.group(2) or "s"]
    else:
        raise key.error(f"expected a duration such as 2ms, got {value!r}", fix=fix)
    if not 0 <= seconds <= WINDOW_MAX:
        raise key.error(f"a window of {seconds * 1e3:g} ms is outside 0..{WINDOW_MAX * 1e3:g} ms",
                        fix=fix)
    return seconds


class Batches(list[tuple[float, Callable[[], None]]]):
    """The windows open on one ROS node (when each closes, the call that closes it), used only
    from its executor's thread: it asks :meth:`close_due` before it waits for the next event."""

    def open(self, closes: float, flush: Callable[[], None]) -> None:
        """A window that closes at ``closes`` (time.monotonic()); ``flush`` sends its batch."""
        self.append((closes, flush))

    def close_due(self, now: float) -> float | None:
        """Close every window due by ``now`` (its flush runs here); the seconds until the next
        one closes, or None when none is open."""
        due = [entry for entry in self if entry[0] <= now]
        if due:
            self[:] = [entry for entry in self if entry[0] > now]
            for _, flush in due:
                flush()
        return min(entry[0] for entry in self) - now if self else None
