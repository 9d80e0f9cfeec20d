"""What keeps a stream link up: connects, and after every loss reconnects by itself, with
capped exponential backoff and jitter, filling a :class:`~rosgate.streamlink.slot.LinkSlot`.
"""

from __future__ import annotations

import logging
import random
import threading
from collections.abc import Callable
from dataclasses import dataclass

from ..config import LinkConfig
from ..errors import LinkError
from ..links.base import FrameHandler, LostHandler
from ..links.lifetime import Lifetime
from ..transport import Address, StreamConnection, StreamTransport, Transport
from .link import StreamLink
from .slot import LinkSlot

log = logging.getLogger("rosgate")

CONNECT_TIMEOUT = 5.0
#: seconds between two checks that a connection's local address is still this host's (a roam)
ADDRESS_CHECK = 0.25


@dataclass(frozen=True)
class Backoff:
    """Seconds between reconnection attempts: from ``min``, doubling up to ``max``, jittered."""

    min: float
    max: float

    def delay(self, failures: int) -> float:
        return min(self.min * 2 ** (failures - 1), self.max) * random.uniform(0.5, 1.0)


@dataclass(eq=False)
class Connector:
    """Keeps a stream connection up: connects, and after every loss reconnects by itself, with
    capped exponential backoff and jitter (a fleet of clients does not hammer a server that
    comes back); after a connection that worked is lost, at once. ``on_connected(link)`` may
    refuse a connection (a failed handshake: a failed attempt); ``on_lost(link)`` hears of
    every accepted connection that ended; ``on_closing(link)`` hears of every connection that
    starts closing (accepted or refused) at once, on the thread that closes it."""

    transport: Transport
    address: Address
    slot: LinkSlot
    on_frame: FrameHandler
    on_frame_lost: LostHandler
    life: Lifetime
    backoff: Backoff
    on_connected: Callable[[StreamLink], bool] | None = None
    on_lost: Callable[[StreamLink], None] | None = None
    secure: Callable[[StreamConnection], StreamConnection] | None = None
    budget: LinkConfig | None = None
    on_closing: Callable[[StreamLink], None] | None = None
    #: the main line's control frames (the others go to ``on_frame``)
    on_control: FrameHandler | None = None

    def __post_init__(self) -> None:
        self._last_failure = ""
        self._thread = threading.Thread(target=self._loop, name=f"connect-{self.slot.name}",
                                        daemon=True)
        self.life.closing(self)

    def start(self) -> None:
        self._thread.start()

    def _loop(self) -> None:
        stopping = self.life.stopping
        failures = 0
        while not stopping.is_set() and not self.slot.closed.is_set():
            link = self._connect()
            if link is None:
                failures += 1
                stopping.wait(self.backoff.delay(failures))
                continue
            failures = 0
            self._last_failure = ""
            self.slot.attach(link)
            gone = getattr(link.connection, "address_gone", None)
            while not link.closed.wait(ADDRESS_CHECK):
                if stopping.is_set() or self.slot.closed.is_set():
                    break
                if gone is not None and gone():  # it roamed: the connection is dead already
                    link.fail("this host no longer has the address it connected from")
            if stopping.is_set() and not self.slot.closed.is_set():
                return  # the role may have a last word (bye); closing the slot closes the link
            link.close()
            if self.on_lost is not None and not stopping.is_set():
                self.on_lost(link)

    def _connect(self) -> StreamLink | None:
        """One attempt: a connection its owner accepted, or None."""
        assert isinstance(self.transport, StreamTransport)
        try:
            connection = self.transport.connect(self.address, CONNECT_TIMEOUT)
        except (OSError, LinkError) as exc:
            log.debug("%s: connect failed: %s", self.slot.name, exc)
            return None
        if self.secure is not None:
            try:
                connection = self.secure(connection)
            except LinkError as exc:
                connection.close()
                self.failed(exc)
                return None
        link = self.life.closing(StreamLink(connection, self.slot.name, self.address,
                                            self.on_frame, self.on_frame_lost,
                                            on_close=self.life.forget,
                                            on_closing=self.on_closing, budget=self.budget,
                                            on_control=self.on_control))
        if self.on_connected is not None and not self.on_connected(link):
            link.close()
            return None
        return link

    def failed(self, exc: LinkError) -> None:
        """A connection that opened but was refused (its handshake failed): said once, until a
        connection works again."""
        if str(exc) != self._last_failure:
            self._last_failure = str(exc)
            log.warning("%s: %s", self.slot.name, exc)

    def close(self) -> None:
        self.slot.close()
        if self._thread.is_alive() and threading.current_thread() is not self._thread:
            self._thread.join(timeout=3)

