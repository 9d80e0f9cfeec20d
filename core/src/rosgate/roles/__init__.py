"""Roles: which links a bridge opens and which routes go over them.

* :class:`~rosgate.roles.peer.PeerRole` — both files complete, no main line (static links and
  microcontrollers, whose CVRA wiring lives there too).
* :class:`~rosgate.roles.client.ClientRole` — connects a main line to a server and sends its
  topics in a handshake (:mod:`.mainline`).
* :class:`~rosgate.roles.server.ServerRole` — accepts many clients, a session each.

A role works with a :class:`Bridge`: the plan, the router, the bridge's lifetime — never with
the engine. :class:`Role` holds what the three share.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass

from ..config import BridgeConfig
from ..errors import ConfigError, LinkError
from ..links import (
    Acceptor,
    Backoff,
    DatagramLink,
    Lifetime,
    Link,
    LinkCounters,
    LinkSlot,
    QueueLimits,
    StreamLink,
)
from ..resolver import Plan, Resolver
from ..router import Router
from ..routes import BarePort
from ..transport import Address, StreamConnection, Transport
from ..wire import envelope

log = logging.getLogger("rosgate")

FrameHandler = Callable[[bytes, Link, Address], None]
#: (connection, peer, then): authenticate an accepted connection, then hand it to ``then``
Handshake = Callable[[StreamConnection, Address, Callable[[StreamConnection], None]], None]


@dataclass
class Bridge:
    """What a role works with."""

    config: BridgeConfig
    plan: Plan
    resolver: Resolver  # a server resolves the entries its clients send
    router: Router
    life: Lifetime

    def slot(self, name: str) -> LinkSlot:
        """A place for a stream link that reconnects; reliable frames wait in it while it is down."""
        return LinkSlot(name, QueueLimits(self.config.queue_frames, self.config.queue_bytes))

    @property
    def backoff(self) -> Backoff:
        return Backoff(self.config.reconnect_min, self.config.reconnect_max)

    def link_error(self, exc: LinkError, key: str) -> ConfigError:
        """A link that cannot be opened, located at the key that named it."""
        return self.config.error(key, str(exc), exc.fix or "free the port, or pick another one")


class Role:
    """What the three roles share: datagram links by local address, listening ports, and the
    control channel's drops."""

    def __init__(self, bridge: Bridge):
        self.bridge = bridge
        self.cfg = bridge.config
        self.router = bridge.router
        self.life = bridge.life
        self.datagram_links: dict[tuple[str, Address], DatagramLink] = {}
        self.bare_ports: dict[DatagramLink, BarePort] = {}
        self.listening: set[tuple[str, Address]] = set()
        self.control = Control(self.router)
        self._lock = threading.RLock()

    def start(self) -> None: ...

    def stop(self) -> None:
        for route in self.router.snapshot():
            self.router.remove(route)

    def datagram_link(self, transport: Transport, local: Address, key: str = "bridge",
                      bare_named: bool | None = None) -> DatagramLink:
        """The link bound at ``local`` (shared by every entry on that port). ``bare_named`` is
        not None for a port of ``framing: none`` topics: whether their datagrams carry names."""
        with self._lock:
            found = self.datagram_links.get((transport.name, local))
            if found is not None:
                return found
            try:
                endpoint = transport.bind(local)
            except LinkError as exc:
                raise self.bridge.link_error(exc, key) from None
            name = f"{transport.name}:{local[1]}" if local[1] else f"{transport.name}"
            if bare_named is None:
                link = DatagramLink(transport, endpoint, name, self.admit(self.router.on_frame),
                                    self.router.on_lost)
            else:
                port = self.router.bare_port(bare_named)
                link = DatagramLink(transport, endpoint, name, self.admit(port.on_frame),
                                    self.router.on_lost, bare=True)
                self.bare_ports[link] = port
            self.datagram_links[(transport.name, local)] = self.life.closing(link)
            return link

    def allowed(self, host: str) -> bool:
        """Whether ``bridge.allow`` (peer role) lets frames from ``host`` in; all without it."""
        if not self.cfg.allow:
            return True
        import ipaddress

        try:
            address = ipaddress.ip_address(host)
        except ValueError:
            return False
        return any(address in network for network in self.cfg.allow)

    def admit(self, handler: FrameHandler) -> FrameHandler:
        """``handler`` for frames from allowed addresses; the others dropped and counted."""
        if not self.cfg.allow:
            return handler

        def admitted(frame: bytes, link: Link, source: Address) -> None:
            if self.allowed(source[0]):
                handler(frame, link, source)
            else:
                self.router.link_drop(link, "not_allowed", f"from {source[0]}")
        return admitted

    def admitting(self, on_connection: Callable[[StreamConnection, Address], None]
                  ) -> Callable[[StreamConnection, Address], None]:
        """``on_connection`` for connections from allowed addresses; the others closed."""
        if not self.cfg.allow:
            return on_connection

        def admitted(connection: StreamConnection, peer: Address) -> None:
            if self.allowed(peer[0]):
                on_connection(connection, peer)
            else:
                connection.close()
                self.router.link_drop(None, "not_allowed", f"a connection from {peer[0]}")
        return admitted

    def accept_into(self, on_frame: FrameHandler, transport: Transport, port: int,
                    handshake: Handshake | None = None
                    ) -> Callable[[StreamConnection, Address], None]:
        """What to do with each connection accepted on a port: a link that feeds ``on_frame``
        and is forgotten by the bridge when it ends (after ``handshake``, when given)."""
        life, on_lost = self.life, self.router.on_lost

        def accepted(connection: StreamConnection, peer: Address) -> None:
            def link(ready: StreamConnection) -> None:
                life.closing(StreamLink(ready, f"{transport.name}:{port}<-{peer[0]}", peer,
                                        on_frame, on_lost, on_close=life.forget))
            if handshake is None:
                link(connection)
            else:
                handshake(connection, peer, link)

        return accepted

    def listen(self, transport: Transport, local: Address, on_frame: FrameHandler,
               key: str | None = None, handshake: Handshake | None = None) -> None:
        """Accept stream connections at ``local`` (once per address). A LinkError is located at
        ``key``; without one (a server listening for a client) it goes to the caller."""
        with self._lock:
            if (transport.name, local) in self.listening:
                return
            try:
                listener = transport.listen(local)
            except LinkError as exc:
                if key is None:
                    raise
                raise self.bridge.link_error(exc, key) from None
            self.listening.add((transport.name, local))
        self.life.closing(Acceptor(listener, f"{transport.name}:{local[1]}", self.admitting(
            self.accept_into(on_frame, transport, local[1], handshake))))


class Control:
    """The control channel (topic 0) as the sender of the frames it puts on links: hellos,
    pings, the handshake. A control frame that is dropped belongs to no topic."""

    topic_id = envelope.CONTROL_TOPIC
    reliable = False

    def __init__(self, router: Router):
        self.router = router

    def drop(self, reason: str, detail: str = "") -> None:
        self.router.link_drop(None, reason, detail or "a control frame on a link")


REFUSAL_EVERY = 60.0  # seconds between two log lines about one refusal


class Refusals:
    """Refusals said once per :data:`REFUSAL_EVERY` seconds each (an attacker retrying must not
    flood the log), with how many were held back."""

    def __init__(self, every: float = REFUSAL_EVERY):
        self.every = every
        self._last: dict[str, float] = {}
        self._held: Counter = Counter()
        self._lock = threading.Lock()

    def say(self, key: str, message: str, level: int = logging.WARNING) -> None:
        now = time.monotonic()
        with self._lock:
            if now - self._last.get(key, -self.every) < self.every:
                self._held[key] += 1
                return
            self._last[key] = now
            held = self._held.pop(key, 0)
        log.log(level, "%s%s", message, f" ({held} more since)" if held else "")


class NoLink(Link):
    """A receiving route's link: frames come in through the router, nothing goes out."""

    def __init__(self) -> None:
        self.name = "in"
        self.closed = threading.Event()
        self.counters = LinkCounters()

    def send_all(self, frames: list[bytes], sender: object, to: Address | None = None) -> int:
        return 0

    def close(self) -> None:
        pass
