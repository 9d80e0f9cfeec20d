"""What a route sends through and what frames are reported from: the :class:`Link`, the
:class:`Sender` of every frame (a frame dropped later is counted against it), the handlers a
link reports to, and the counters of what it carried."""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

from ..drops import Reason
from ..spec import Delivery
from ..transport import Address

#: what a link hands each frame it receives to: (the frame, the link, where it came from)
FrameHandler = Callable[[bytes, "Link", Address], None]
#: a loss on the receiving side: (topic id when known, reason)
LostHandler = Callable[[int | None, Reason], None]

POLL = 0.2  # seconds a receive waits before checking whether the link is closing


class Sender(Protocol):
    """What sends a frame: a route, a call, or a role's control channel."""

    @property
    def delivery(self) -> Delivery:
        """How the link carries its frames (read on every send: set once, never changed)."""

    @property
    def topic_id(self) -> int:
        """The id fragments of its frames carry (so a receiver counts a lost one against it)."""

    def drop(self, reason: Reason, detail: str = "") -> None:
        """Count one of its frames as dropped on the way out."""

    def on_wire(self, size: int, again: bool) -> None:
        """A packet of ``size`` bytes left on the link for it (``again``: a retransmission)."""


class Link:
    """What a route sends through and what frames are reported from."""

    name: str
    closed: threading.Event
    counters: LinkCounters
    #: datagram links need a destination for every send; stream links are connected
    datagram: bool = False
    #: while a frame is handed to its handler: when its datagram arrived (time.time_ns), 0: unknown
    arrived: int = 0

    # a link implements send or send_all (or both): each defaults to the other

    def send(self, frame: bytes, sender: Sender, to: Address | None = None) -> bool:
        """Hand ``frame`` to the link. False when it was dropped at once (counted against
        ``sender``); True when it was sent or queued — a queued frame that is lost later is
        counted against ``sender`` then."""
        return self.send_all([frame], sender, to) == 1

    def send_all(self, frames: list[bytes], sender: Sender, to: Address | None = None) -> int:
        """Hand several frames of one sender to the link at once (they may share a datagram or a
        write); how many were sent or queued, as :meth:`send` says for one."""
        return sum(self.send(frame, sender, to) for frame in frames)

    def queue_depth(self, sender: Sender) -> int:
        """Messages of ``sender`` waiting or being sent (a link without a queue: none)."""
        return 0

    def forget(self, sender: Sender) -> None:
        """A sender that is gone: drop what it queued, silently."""

    def close(self) -> None:
        raise NotImplementedError


@dataclass
class LinkCounters:
    """What a link carried, per direction: frames, the packets (datagrams, stream writes and
    reads) that carried them, and the frames that shared one with others (coalesced)."""

    frames_out: int = 0
    #: of frames_out, those sent from the caller's thread (the link was idle: no hand-off)
    inline_out: int = 0
    packets_out: int = 0
    coalesced_out: int = 0
    bytes_out: int = 0
    frames_in: int = 0
    packets_in: int = 0
    coalesced_in: int = 0
    bytes_in: int = 0

    def snapshot(self) -> dict[str, int]:
        return dict(vars(self))

    def line(self) -> str:
        return (f"out {self.frames_out} frames in {self.packets_out} packets "
                f"({self.coalesced_out} coalesced, {self.inline_out} inline, {self.bytes_out} B), "
                f"in {self.frames_in} frames in {self.packets_in} packets "
                f"({self.coalesced_in} coalesced, {self.bytes_in} B)")


class NoLink(Link):
    """A receiving route's link: frames come in through the router (or a bus role), nothing
    goes out."""

    def __init__(self) -> None:
        self.name = "in"
        self.closed = threading.Event()
        self.counters = LinkCounters()

    def send_all(self, frames: list[bytes], sender: object, to: Address | None = None) -> int:
        return 0

    def close(self) -> None:
        pass
