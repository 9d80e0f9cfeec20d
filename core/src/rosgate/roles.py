"""What every role shares, and the peer role.

A role turns the engine's prepared topics into routes over links:

* :class:`PeerRole` — both files complete, no main line. A topic's id on the wire is derived
  from its link name (``remote``), so both sides agree without talking. Receiving topics bind
  ``listen:port``; transmitting topics send (or connect) to ``peer:port``.
* ``ClientRole`` (client.py) and ``ServerRole`` (server.py) — a main line and a handshake.
"""

from __future__ import annotations

import logging
import random
import threading
from typing import TYPE_CHECKING, Callable

from . import services
from .envelope import Header, topic_id_for
from .errors import LinkError
from .links import Acceptor, DatagramLink, Link, LinkSlot, StreamLink
from .routes import ReceiveRoute, Route, TransmitRoute
from .transport import Address, StreamConnection, Transport

if TYPE_CHECKING:
    from .engine import Engine, Prepared

log = logging.getLogger("rosgate")

CONNECT_TIMEOUT = 5.0


class Role:
    """What the three roles share: datagram links by local address, and route bookkeeping."""

    def __init__(self, engine: Engine):
        self.engine = engine
        self.cfg = engine.config
        self.datagram_links: dict[tuple[str, Address], DatagramLink] = {}
        self.listening: set[tuple[str, Address]] = set()
        self.bare_routes: dict[DatagramLink, dict[str | None, ReceiveRoute]] = {}
        self._routes: list[Route] = []
        self._lock = threading.RLock()

    def start(self) -> None: ...

    def on_hello(self, header: Header, frame: bytes, link: Link, source: Address) -> None:
        """Only a server takes hellos; elsewhere a hello is a damaged or foreign frame."""
        self.engine.link_drop(link, "unexpected_hello", f"from {source}")

    def stop(self) -> None:
        for route in self._routes:
            self.engine.remove_route(route)
        self._routes.clear()

    def routes(self) -> list[Route]:
        with self._lock:
            return list(self._routes)

    def bare_receivers(self) -> list[ReceiveRoute]:
        with self._lock:
            return [r for routes in self.bare_routes.values() for r in routes.values()]

    def transmitter(self, topic_id: int) -> Route | None:
        with self._lock:
            return next((r for r in self._routes
                         if r.topic_id == topic_id and isinstance(r, TransmitRoute)), None)

    def add(self, route: Route) -> Route:
        with self._lock:
            self._routes.append(route)
        return route

    def datagram_link(self, transport: Transport, local: Address, bare: bool = False,
                      key: str = "bridge") -> DatagramLink:
        """The link bound at ``local`` (shared by every topic on that port)."""
        with self._lock:
            found = self.datagram_links.get((transport.name, local))
            if found is not None:
                return found
            try:
                endpoint = transport.bind(local)
            except LinkError as exc:
                raise self.engine.bind_error(exc, key) from None
            name = f"{transport.name}:{local[1]}" if local[1] else f"{transport.name}"
            if bare:
                link = DatagramLink(transport, endpoint, name,
                                    lambda d, l, s: self.engine.on_bare(self.bare_routes[l], d, l, s),
                                    self.engine.on_drop, bare=True)
                self.bare_routes[link] = {}
            else:
                link = DatagramLink(transport, endpoint, name, self.engine.on_frame,
                                    self.engine.on_drop)
            self.datagram_links[(transport.name, local)] = self.engine.closing(link)
            return link


    def accept_into(self, on_frame: Callable[[bytes, Link, Address], None], transport: Transport,
                    port: int) -> Callable[[StreamConnection, Address], None]:
        """What to do with each connection accepted on a port: a link that feeds ``on_frame``
        and is forgotten by the engine when it ends."""
        engine = self.engine

        def accepted(connection: StreamConnection, peer: Address) -> None:
            engine.closing(StreamLink(connection, f"{transport.name}:{port}<-{peer[0]}", peer,
                                      on_frame, engine.on_drop, on_close=engine.forget))

        return accepted


class PeerRole(Role):
    """Both sides configured; no main line."""

    def start(self) -> None:
        engine, cfg = self.engine, self.cfg
        listen = cfg.listen or "0.0.0.0"
        for p in engine.topics:
            t = p.config
            key = f"topics[{p.index}].port"
            label = t.topic
            assert t.port is not None
            if p.transport.stream:
                self._start_stream(p, key)
                continue
            if t.direction == "receive":
                link = self.datagram_link(p.transport, p.address, t.framing == "none", key)
                route = engine.make_route(p, topic_id_for(t.remote), label, link)
                if t.framing == "none":
                    for name in {t.topic, t.remote}:
                        self.bare_routes[link][name] = route  # type: ignore[assignment]
                    if not p.codec_cls.names_bare_frames:
                        self.bare_routes[link] = {None: route}  # type: ignore[assignment]
                elif t.topic != t.remote:
                    engine.receivers[topic_id_for(t.topic)] = route  # type: ignore[assignment]
            else:
                link = self.datagram_link(p.transport, (listen, 0), False, key)
                route = engine.make_route(p, topic_id_for(t.remote), label, link,
                                          lambda to=p.address: to)
            self.add(route)
        services.start_peer(self)

    def _start_stream(self, p: Prepared, key: str) -> None:
        t = p.config
        if t.direction == "receive":
            route = self.engine.make_route(p, topic_id_for(t.remote), t.topic, _NoLink())
            if t.topic != t.remote:
                self.engine.receivers[topic_id_for(t.topic)] = route  # type: ignore[assignment]
            self.add(route)
            self._listen(p.transport, p.address, key)
        else:
            slot = self.engine.slot(f"{t.transport}->{self.cfg.peer}:{t.port}")
            route = self.add(self.engine.make_route(p, topic_id_for(t.remote), t.topic, slot))
            slot.reliable = [route] if p.reliable else []
            Connector(self.engine, p.transport, p.address, slot, self.engine.on_frame).start()

    def _listen(self, transport: Transport, local: Address, key: str) -> None:
        if (transport.name, local) in self.listening:
            return
        try:
            listener = transport.listen(local)
        except LinkError as exc:
            raise self.engine.bind_error(exc, key) from None
        self.listening.add((transport.name, local))
        self.engine.closing(Acceptor(listener, f"{transport.name}:{local[1]}",
                                     self.accept_into(self.engine.on_frame, transport, local[1])))

class _NoLink(Link):
    """A receive route's link: frames come in through the engine, nothing goes out."""

    def __init__(self) -> None:
        self.name = "in"
        self.closed = threading.Event()

    def send(self, frame: bytes, topic_id: int, to: Address | None = None) -> bool:
        return False

    def close(self) -> None:
        pass


class Connector:
    """Keeps a stream connection up: connects, and after every loss reconnects by itself.

    Attempts are spaced by capped exponential backoff with jitter (``bridge.reconnect``: from
    ``min`` seconds, doubling up to ``max``), so a fleet of clients does not hammer a server that
    comes back. After a connection that worked is lost, the next attempt is immediate.
    ``on_connected(link)`` may refuse a connection (a failed handshake), which counts as a failed
    attempt; ``on_lost(link)`` hears of every accepted connection that ended.
    """

    def __init__(self, engine: Engine, transport: Transport, address: Address, slot: LinkSlot,
                 on_frame: Callable[[bytes, Link, Address], None],
                 on_connected: Callable[[StreamLink], bool] | None = None,
                 on_lost: Callable[[StreamLink], None] | None = None):
        self.engine = engine
        self.transport = transport
        self.address = address
        self.slot = slot
        self.on_frame = on_frame
        self.on_connected = on_connected
        self.on_lost = on_lost
        self.connected = threading.Event()
        self._thread = threading.Thread(target=self._loop, name=f"connect-{slot.name}", daemon=True)
        engine.closing(self)

    def start(self) -> None:
        self._thread.start()

    def _loop(self) -> None:
        cfg = self.engine.config
        stopping = self.engine.stopping
        failures = 0
        while not stopping.is_set() and not self.slot.closed.is_set():
            link = self._connect()
            if link is None:
                failures += 1
                delay = min(cfg.reconnect_min * 2 ** (failures - 1), cfg.reconnect_max)
                stopping.wait(delay * random.uniform(0.5, 1.0))
                continue
            failures = 0
            self.slot.attach(link)
            self.connected.set()
            while not link.closed.wait(0.5):
                if stopping.is_set() or self.slot.closed.is_set():
                    break
            self.connected.clear()
            link.close()
            if self.on_lost is not None and not stopping.is_set():
                self.on_lost(link)

    def _connect(self) -> StreamLink | None:
        """One attempt: a connection its owner accepted, or None."""
        try:
            connection = self.transport.connect(self.address, CONNECT_TIMEOUT)
        except (OSError, LinkError) as exc:
            log.debug("%s: connect failed: %s", self.slot.name, exc)
            return None
        link = StreamLink(connection, self.slot.name, self.address, self.on_frame,
                          self.engine.on_drop, on_close=self.engine.forget)
        if self.on_connected is not None and not self.on_connected(link):
            link.close()
            return None
        return link

    def close(self) -> None:
        self.slot.close()
        if self._thread.is_alive() and threading.current_thread() is not self._thread:
            self._thread.join(timeout=3)
