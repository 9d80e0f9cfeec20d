"""What of a transmitting route's messages waits: while the far side is out of reach
(:mod:`rosgate.holdback`), sealed again under the keys of when they go, and how long a message
may wait in the bridge's own buffers (:func:`max_wait_ns`). Not the path of a message that
goes at once."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from ..config import TopicConfig
from ..holdback import Held, Holdback
from ..links.base import Link
from ..spec import Delivery
from ..transport import Address

# when a batch window closes, a route takes what waits up to this much (send_all cuts it)
BATCH_FRAMES = 512
BATCH_BYTES = 1_000_000


def max_wait_ns(topic: TopicConfig) -> int:
    """How long (ns) a message may wait in the bridge's own buffers before it is dropped
    ``too_late``: the topic's ``max_delay``; 0, none. Without it a best-effort topic's wait
    there is bounded only once the queue stands behind (:attr:`Route.backlog`): a short
    backlog waits for a bridge thread, which catches up with it; where the link is the
    bottleneck, frames wait in its queue instead, shed by latest-only, its ``max_delay`` and
    the scheduler."""
    return int(1e9 * topic.max_delay) if topic.max_delay is not None else 0


class Holding:
    """The part of a :class:`~rosgate.routes.TransmitRoute` for messages that wait for the far
    side."""

    hold: Holdback | None
    link: Link
    delivery: Delivery
    destination: Callable[[], Address | None]
    _hand: Callable[..., None]
    _encode: Callable[[Any], tuple[bytes, int, int] | None]
    _seal: Callable[[bytes, int, int], bytes | None]
    _drain: Callable[[list[Any], int, int], list[Any]]
    _send: Callable[[list[Any]], None]
    pending: list[Any]
    take: Callable[[], Any] | None
    entity: Any

    def _hold(self, hold: Holdback, messages: list[Any]) -> None:
        """The far side is out of reach: ``hold`` keeps a reliable topic's messages and says
        whether they go out now too (a datagram link's: the server may be up, only the main
        line lost; and anything once the far side is back)."""
        encoded = [got for got in map(self._encode, messages) if got is not None]
        route: Any = self  # a TransmitRoute
        if hold.take(route, encoded, self.delivery.reliable, self.link.datagram):
            self._hand(self._seal_all(encoded), self.destination())

    def send_again(self, held: list[Held], again: bool) -> None:
        """Messages that waited for the far side, sealed under the keys of now, sent in order
        (``again``: copies of them went out before, and were counted sent)."""
        self._hand(self._seal_all([(h.payload, h.flags, h.stamp) for h in held]),
                   self.destination(), again)

    def _seal_all(self, encoded: list[tuple[bytes, int, int]]) -> list[bytes]:
        return [frame for frame in (self._seal(*e) for e in encoded) if frame is not None]

    @property
    def queue_depth(self) -> int:
        """Its messages waiting in the link, or being sent, or for the far side, now."""
        route: Any = self  # a TransmitRoute
        held = self.hold.depth(route) if self.hold is not None and self.hold.down else 0
        return self.link.queue_depth(route) + held

    def flush(self) -> None:
        """The batch window closed: what came in it and everything waiting now leave together."""
        messages, self.pending = self.pending, []
        if self.take is not None and self.entity is not None:
            messages = self._drain(messages, BATCH_FRAMES, BATCH_BYTES)
        self._send(messages)

    def close(self) -> None:
        """The route is removed: what it queued goes (a message half sent is not finished)."""
        self.pending.clear()  # an open window closes with nothing to send
        route: Any = self  # a TransmitRoute
        self.link.forget(route)
        if self.hold is not None:
            self.hold.forget(route)
