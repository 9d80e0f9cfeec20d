"""The batch window (a topic's ``batch:``): its messages leave together, not one by one.

Without a window, the ROS executor wakes for every message and the route frames and sends it
at once: a thread switch and a system call per message on each side. With one, the first message
opens the window; the executor's thread then sleeps until the window closes (messages pile up
in the middleware meanwhile, no wake-up for any of them), and the route takes everything
waiting in one go, frames it, and hands it to its link as one call (one datagram, or one stream
write, as far as they fit). The far side receives that datagram in one wake and publishes every
message in it from there. A message waits at most the window for the ones after it: that is
the latency a topic opts into. A window of 0 is no window.

:class:`Batches` is the executor's side: one per ROS node, used only from its thread.
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


class Batches:
    """The windows open on one ROS node: when each closes, and the call that closes it.

    The executor's loop asks :meth:`close_due` before it waits for the next event: while a
    window is open it sleeps until the first one closes instead (see the module's docstring)."""

    __slots__ = ("_open",)

    def __init__(self) -> None:
        self._open: list[tuple[float, Callable[[], None]]] = []

    def open(self, closes: float, flush: Callable[[], None]) -> None:
        """A window that closes at ``closes`` (time.monotonic()); ``flush`` sends its batch."""
        self._open.append((closes, flush))

    def __bool__(self) -> bool:
        return bool(self._open)

    def close_due(self, now: float) -> float | None:
        """Close every window due by ``now`` (its flush runs here); the seconds until the next
        one closes, or None when none is open."""
        due = [entry for entry in self._open if entry[0] <= now]
        if due:
            self._open = [entry for entry in self._open if entry[0] > now]
            for _, flush in due:
                flush()
        return min(entry[0] for entry in self._open) - now if self._open else None
