"""Frames of one sender put back in its order: a receiving route of a reliable topic whose link
repairs losses (``retransmit``) holds what comes after a gap until the missing frame arrives,
sent again, and then publishes them all in sequence, as a DDS reliable reader does.

The hold is bounded in time (the packetizer's ``resends_within``: after that the missing frame
cannot come any more, and its gap is given up), in bytes and in frames (what overflows gives the
oldest gap up at once). A frame older than the next one expected (its gap given up, or a copy)
is handed on as it comes: the replay window after this refuses copies and what is older than its
window, and takes (out of order) a repaired frame a little too late. A receiver that takes a
sender up mid-stream (a first sequence number past :data:`START`) gathers what comes for
:data:`SETTLE` seconds and starts at the newest unbroken run: what the sender still repairs of
what it sent before the receiver was there is not for it, and is ignored. Sequence numbers are
per epoch (a session's
key generation): a new epoch releases what the old one held. :class:`InOrder` reads no clock
and takes no lock (times are passed in); :class:`Ordered` puts a route's frames through it.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from typing import Any

from .drops import Drop

log = logging.getLogger("rosgate")

#: a new epoch whose first frame is at most this far from 1 is waited for from 1 (its first
#: frames were lost on the way); a later one is a sender heard mid-stream, taken from there
START = 64
#: seconds a receiver that takes a sender up mid-stream gathers its frames before it starts at
#: the newest unbroken run of them: a sender's repairs of what it sent before the receiver was
#: there come in that time, scattered (a probe comes 0.21 s after its frame, unanswered)
SETTLE = 0.3
#: a frame this far past the next one expected is a sender that jumped (or a forged header
#: where no cipher vouches for it): what is held goes, and the order starts again from it
JUMP = 4096
MAX_HELD_BYTES = 16 * 1024 * 1024
MAX_HELD_FRAMES = 4096


@dataclass(slots=True)
class _Held:
    item: Any
    size: int
    since: float  # when it came (a gap before it is given up ``hold`` seconds after)


class InOrder:
    """One sender's frames in sequence order. :meth:`put` takes a frame and returns what can
    be published now, in order; :meth:`due` gives up the gaps waited for too long."""

    def __init__(self, hold: float, max_bytes: int = MAX_HELD_BYTES,
                 max_frames: int = MAX_HELD_FRAMES):
        self.hold = hold
        self.max_bytes = max_bytes
        self.max_frames = max_frames
        self.epoch: int | None = None
        self.next = 1  # the sequence number to publish next
        self.first = 1  # of the epoch: where this side took its frames up
        self.settling: float | None = None  # a sender taken up mid-stream: until when
        self._held: dict[int, _Held] = {}
        self.held_bytes = 0
        #: gaps given up for time (the sender gave up too) and for the bounds (``overflowed``)
        self.gaps = 0
        self.overflowed = 0
        self.copies = 0  # frames held already, given again
        self.filled = 0  # gaps a repaired frame filled
        #: a gap given up before any was ever filled: its sender does not repair (its file says
        #: recovery: none, or an older rosgate): frames go as they come from then on
        self.unrepaired = False
        #: frames sent before the first this side took (a sender still repairing what it sent
        #: before this side was there): history a volatile subscriber never had, ignored
        self.before = 0

    def __len__(self) -> int:
        return len(self._held)

    def put(self, epoch: int, seq: int, item: Any, size: int, now: float) -> list[Any]:
        """Take frame ``seq`` of ``epoch``; what is ready, in order (maybe nothing)."""
        if self.unrepaired:
            return [item]
        if seq == self.next and epoch == self.epoch and not self._held \
                and self.settling is None:  # the next one, nothing waiting: the common case
            self.next += 1
            return [item]
        out: list[Any] = []
        if epoch != self.epoch:
            out += self._release_all()
            self.epoch, self.next = epoch, 1 if seq <= START else seq
            self.first = self.next
            self.settling = None if seq <= START else now + SETTLE
        if self.settling is not None:
            if now < self.settling:
                if seq in self._held:
                    self.copies += 1
                elif len(self._held) < self.max_frames:
                    self._held[seq] = _Held(item, size, now)
                    self.held_bytes += size
                return out
            out += self._settle()
        if seq < self.first:  # sent before this side took the sender's frames up: not for it
            self.before += 1
            return out
        if seq < self.next:
            out.append(item)  # late (its gap given up) or a copy: the replay window decides
            return out
        if seq - self.next > JUMP:
            out += self._release_all()
            self.next = seq
        if seq in self._held:
            self.copies += 1
            return out
        if seq == self.next and self._held:  # the frame a gap waited for
            self.filled += 1
        self._held[seq] = _Held(item, size, now)
        self.held_bytes += size
        out += self._ready()
        while self._held and (self.held_bytes > self.max_bytes
                              or len(self._held) > self.max_frames):
            self.overflowed += 1
            out += self._skip()
        return out

    def due(self, now: float) -> list[Any]:
        """What waited past the hold for a frame that did not come: its gap given up, the frames
        after it released in order (and after them, any later gap's that is due too)."""
        if self.settling is not None:
            return self._settle() if now >= self.settling else []
        out: list[Any] = []
        while self._held and now - self._oldest().since >= self.hold:
            self.gaps += 1
            out += self._skip()
            if not self.filled:  # nothing was ever repaired: a sender that does not repair
                self.unrepaired = True
                return out + self._release_all()
        return out

    def next_due(self) -> float | None:
        """When :meth:`due` has a gap to give up, or a start to settle (None: nothing held)."""
        if self.settling is not None:
            return self.settling
        return self._oldest().since + self.hold if self._held else None

    def _settle(self) -> list[Any]:
        """A sender taken up mid-stream: start at the newest unbroken run of what came while
        settling. What came before its gap was sent before this side was there (a repair of
        it, or a frame that came before this side's route did): not for it."""
        self.settling = None
        if self._held:
            start = max(self._held)
            while start - 1 in self._held:
                start -= 1
            for seq in [seq for seq in self._held if seq < start]:
                self.held_bytes -= self._held.pop(seq).size
                self.before += 1
            self.first = self.next = start
        return self._ready()

    def _oldest(self) -> _Held:
        """The first frame after the first gap: it has waited longest."""
        return self._held[min(self._held)]

    def _skip(self) -> list[Any]:
        """Give the first gap up: publish from the first frame held."""
        self.next = min(self._held)
        return self._ready()

    def _ready(self) -> list[Any]:
        out = []
        while (held := self._held.pop(self.next, None)) is not None:
            self.held_bytes -= held.size
            out.append(held.item)
            self.next += 1
        return out

    def _release_all(self) -> list[Any]:
        out = []
        for seq in sorted(self._held):
            out.append(self._held[seq].item)
            self.next = seq + 1
        self._held.clear()
        self.held_bytes = 0
        return out


class Ordered:
    """A receiving route's frames through an :class:`InOrder`: opened by the route's cipher
    first (a sequence number counts once it is authenticated), then put in order, then past
    the route's replay window to be published. Its lock keeps the order from the link's
    thread and its timer's; the timer gives up a gap that is due."""

    def __init__(self, route: Any, hold: float):
        self.route = route  # a rosgate.routes.ReceiveRoute (open, replayed, admitted, drop)
        self.stage = InOrder(hold)
        self._lock = threading.Lock()
        self._timer: threading.Timer | None = None
        self._closed = False

    def on_frame(self, header: Any, frame: bytes, arrived: int) -> bool:
        """Take a frame; whether it opened and was published now, new to the replay window (a
        genuine, new frame of the far side: one held for a gap, or a copy, is not yet one)."""
        route, size = self.route, len(frame)  # before it is opened: maybe where it lies
        payload = route.open(frame, header.epoch)
        if payload is None:
            return False
        stage, item = self.stage, (header, payload, size, arrived)
        with self._lock:
            overflowed = stage.overflowed
            genuine = self._publish(stage.put(header.epoch, header.seq, item, size,
                                              time.monotonic()), item)
            if stage.overflowed != overflowed:
                route.drop(Drop.ORDER_OVERFLOW, f"over {stage.max_frames} frames or "
                           f"{stage.max_bytes // 2**20} MiB held for a missing one")
            if stage._held or stage.settling is not None:  # (nothing held: no timer to set)
                self._arm()
        return genuine

    def _publish(self, ready: list[Any], mine: Any = None) -> bool:
        """Publish what is ready, in order; whether ``mine`` was among it and new."""
        route, genuine = self.route, False
        for item in ready:
            header, payload, size, arrived = item
            payload = route.replayed(header, payload)
            genuine = genuine or (item is mine and payload is not None)
            route.admitted(header, payload, size, arrived)
        return genuine

    def _arm(self) -> None:
        if self._timer is not None or self._closed:  # (before next_due: a min over what is held)
            return
        due = self.stage.next_due()
        if due is None:
            return
        self._timer = threading.Timer(max(0.0, due - time.monotonic()) + 0.01, self._expire)
        self._timer.daemon = True
        self._timer.start()

    def _expire(self) -> None:
        with self._lock:
            self._timer = None
            if self._closed:
                return
            self._publish(self.stage.due(time.monotonic()))
            if self.stage.unrepaired:
                log.warning("%s: a lost frame was waited for %.0f s and never sent again: its "
                            "sender does not repair what is lost (recovery: none on its side, or "
                            "an older rosgate); frames are published as they come, out of order "
                            "after a loss. Give both sides the same qos: and recovery:",
                            self.route.label, self.stage.hold)
                return
            self._arm()

    def close(self) -> None:
        with self._lock:
            self._closed = True
            if self._timer is not None:
                self._timer.cancel()
