"""What a route says of its entry on its link and hears of the far side's: announcements (its
type and the QoS found here, :mod:`rosgate.announce`), the type check, and the paced release of
frames held until the far side said its type. Not the data path: a route's messages never come
here."""

from __future__ import annotations

import itertools
import threading
import time
from collections.abc import Callable
from typing import Any

from .. import announce
from ..announce import Identity, TypeCheck
from ..drops import Drop
from ..keyring import Keys
from ..matching import PACE_EACH, PACE_FOR
from ..wire import envelope
from .counters import Counters


class Said:
    """The part of a :class:`~rosgate.routes.Route` that speaks of its entry, not its messages."""

    keys: Keys
    check: TypeCheck
    counters: Counters
    entity: Any
    qos_found: dict[str, Any] | None
    far_served: bool | None
    _announced: itertools.count
    _lock: threading.Lock
    replay: envelope.ReplayWindow
    _pace_until: float
    drop: Callable[..., None]
    seal: Callable[..., bytes]
    open: Callable[[bytes, int], bytes | None]

    def announcement(self) -> bytes:
        """An announcement frame of this entry (:mod:`rosgate.announce`), with the QoS found
        here. NoKey before a session has keys."""
        body = announce.encode(self.said())
        epoch = self.keys.epoch()
        return self.seal(envelope.FLAG_ANNOUNCE, epoch, next(self._announced), body)

    def said(self) -> dict[str, Any]:
        """What this side says of its entry (a hello's or a welcome's item, an announcement)."""
        return announce.item(self.check.mine, self.qos_found)

    def heard(self, header: envelope.Header,
              frame: bytes) -> tuple[Identity | None, dict[str, Any] | None] | None:
        """The far side's announcement frame of this entry: see :meth:`told`."""
        body = self.open(frame, header.epoch)
        return None if body is None else self.told(bytes(body))

    def told(self, said: Any) -> tuple[Identity | None, dict[str, Any] | None] | None:
        """What the far side says of this entry (an announcement's body, or a hello's or a
        welcome's item; None from an older rosgate), its type checked; None (counted) when
        it cannot be read."""
        try:
            identity, qos = (announce.parse_body(said) if isinstance(said, bytes)
                             else announce.read(said))
            self.far_served = announce.served(said)
        except ValueError as exc:
            self.drop(Drop.BAD_ANNOUNCEMENT, str(exc))
            return None
        self.check.far(identity)
        return identity, qos

    def refuse_type(self) -> None:
        """A frame dropped because the far side's type is not this side's."""
        self.counters.drops[self.check.reason] += 1
        self.check.say()

    def _pace_release(self, went: int) -> None:
        """Frames held for the far side's first word go on in a burst: after each history's
        depth of them, wait until the subscribers acknowledged (at most ``matching.PACE_FOR``
        in all), so a reliable keep-last publisher does not overwrite what a subscriber has not
        got (a 37-frame release through a depth-10 publisher lost 30 of them)."""
        from rclpy.qos import HistoryPolicy, ReliabilityPolicy

        profile = getattr(self.entity, "qos_profile", None)
        if profile is None or profile.reliability != ReliabilityPolicy.RELIABLE \
                or profile.history != HistoryPolicy.KEEP_LAST or went % max(1, profile.depth):
            return
        now = time.monotonic()
        if went == profile.depth:
            self._pace_until = now + PACE_FOR
        if now < self._pace_until:
            from rclpy.duration import Duration

            self.entity.wait_for_all_acked(Duration(nanoseconds=int(PACE_EACH * 1e9)))

    def taken(self) -> dict[int, int]:
        """What this route took of its far side: the newest sequence number per epoch."""
        with self._lock:
            return self.replay.newest()
