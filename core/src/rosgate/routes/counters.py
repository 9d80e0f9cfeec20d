"""What a route counts (:class:`Counters`: a route's every message, byte and drop, by reason),
and the sender of its frames that are not its messages (:class:`SideSender`)."""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from typing import Any

from ..drops import Drop
from ..spec import Delivery

# reasons that say something is wrong (a warning); the others are routine and only counted
QUIET_REASONS = {Drop.RATE_LIMIT, Drop.DUPLICATE, Drop.SUPERSEDED, Drop.ECHO}

@dataclass
class Counters:
    sent: int = 0
    received: int = 0
    bytes_sent: int = 0
    bytes_received: int = 0
    lost: int = 0  # sequence numbers skipped by the sender and never filled in
    drops: Counter = field(default_factory=Counter)
    # sender, the link's view: every byte put on it for this topic (compressed, with fragment
    # headers, repairs and retransmissions), and the packets a receiver asked for again
    bytes_on_wire: int = 0
    retransmitted: int = 0
    recovered: int = 0  # receiver: frames whole only thanks to fec or retransmit
    # compression (sender): payload bytes before and after; payloads it did not make smaller
    bytes_before_compression: int = 0
    bytes_after_compression: int = 0
    not_compressed: int = 0

    def snapshot(self) -> dict[str, Any]:
        """Every counter, the drops as a plain mapping."""
        return {**{f.name: getattr(self, f.name) for f in fields(self)}, "drops": dict(self.drops)}

@dataclass(slots=True, eq=False)
class SideSender:
    """Frames of a route that are not its messages, as the link's sender: an announcement (in
    the control class, never waiting out a link loss: the next one comes soon) or a service
    call (whose drop fails the call). Their bytes are not the route's data."""

    route: Any  # the Route whose frames these are
    delivery: Delivery
    drop: Callable[..., None]  # (reason, detail="")

    @property
    def topic_id(self) -> int:
        return self.route.topic_id

    def on_wire(self, size: int, again: bool) -> None:
        pass
