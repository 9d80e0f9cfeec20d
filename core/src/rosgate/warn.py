"""Rate-limited warnings: a flood of bad frames from a peer costs a few log lines, never one
each. :class:`Warner` says one warning per subject and reason per window, then how many were
held back; :data:`BUGS` one traceback of an unexpected error per reason per minute.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter

log = logging.getLogger("rosgate")

WARN_EVERY = 5.0  # seconds between two warnings of one kind for one subject
TRACEBACK_EVERY = 60.0  # seconds between two tracebacks for one reason


class Warner:
    """Rate-limited warnings: the first at once, then at most one per ``every`` seconds per
    (subject, reason), saying how many were held back."""

    def __init__(self, every: float = WARN_EVERY):
        self.every = every
        self._last: dict[tuple[str, str], float] = {}
        self._held: Counter = Counter()
        self._lock = threading.Lock()

    def due(self, subject: str, reason: str) -> int | None:
        """None when a warning of this kind was said within the window (it is counted as held
        back); else how many were held back since the last one (it is said now)."""
        key = (subject, reason)
        now = time.monotonic()
        with self._lock:
            if now - self._last.get(key, -self.every) < self.every:
                self._held[key] += 1
                return None
            if len(self._last) > 10_000:  # subjects come from the network: keep them bounded
                self._last.clear()
                self._held.clear()
            self._last[key] = now
            return self._held.pop(key, 0)

    def warn(self, subject: str, reason: str, detail: str) -> None:
        held = self.due(subject, reason)
        if held is not None:
            more = f" ({held} more since the last warning)" if held else ""
            log.warning("%s: dropped (%s): %s%s", subject, reason, detail, more)

    def bug(self, reason: str, message: str) -> None:
        """Log ``message`` with the traceback being handled, at most once per window for
        ``reason``; the caller counts every occurrence itself."""
        held = self.due("bug", reason)
        if held is not None:
            more = f" ({held} more since the last one, not shown)" if held else ""
            log.error("%s%s", message, more, exc_info=True)


#: tracebacks of unexpected errors, process-wide
BUGS = Warner(TRACEBACK_EVERY)
