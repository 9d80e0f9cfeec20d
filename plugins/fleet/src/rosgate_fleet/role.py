"""The ``fleet`` bus role: entries on a bus (zenoh), wired for the peer role. Each file is
complete and the bus finds the others, so there is no main line, no ``peer:`` and no ``port:``.

* An entry's key is its ``remote``, or :meth:`rosgate_fleet.FleetTransport.default_key`.

* A topic is published on its key; a receiving topic subscribes to its key and is found by it
  (the envelope's topic id must be the key's: a frame moved to another key is refused).
* A service is a queryable on its key (``receive``) or one query per call (``transmit``).
* The sending side of each entry announces its type on the entry's key (:mod:`rosgate.announce`):
  a topic beside its messages, a service's caller as a query that servers close unanswered.
* Each bridge holds a liveliness token (:meth:`rosgate_fleet.FleetTransport.alive_key`).
* An entry whose name holds placeholders (``/{robot}/scan``) is the bus's own
  (:attr:`rosgate_fleet.FleetTransport.templates`, the zenoh plugin's fleets): it makes its routes
  with the methods of :class:`BusWiring` as the bus finds robots.

Everything a bus delivers is handled on its link's thread (:class:`rosgate_fleet.BusLink`),
templated entries' bookkeeping included, so routes are made and dropped in one thread.
"""

from __future__ import annotations

import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from rosgate import (
    FLAG_ANNOUNCE,
    FLAG_COMPRESSED,
    FLAG_REQUEST,
    BusPattern,
    BusRole,
    BusTransport,
    ConfigError,
    Direction,
    Drop,
    EnvelopeError,
    Framing,
    Link,
    LinkError,
    NoLink,
    ReceiveRoute,
    Route,
    ServerRoute,
    ServiceConfig,
    ServiceSpec,
    TopicConfig,
    TopicSpec,
    TransmitRoute,
    topic_id_for,
    unpack_envelope,
)

from .link import BusLink
from .session import FleetTransport, Handle, is_template

SWEEP_EVERY = 0.25  # seconds between looks at the names a pattern's publishers left

#: what a topic's frame on its key may say besides being a message: an announcement of the
#: entry, or a payload its sender transformed (compressed)
_TOPIC_FLAGS = FLAG_ANNOUNCE | FLAG_COMPRESSED


class BusWiring(BusRole):
    """The bus entries of a peer-role bridge: one :class:`BusLink` per bus transport. Its public
    methods are what a bus's :class:`rosgate_fleet.NameTemplates` makes routes with."""

    name = "fleet"

    @dataclass(frozen=True)
    class Options:
        """None: each bus transport has its own."""

    def __init__(self, bridge: Any):
        super().__init__(bridge)
        self.links: dict[str, BusLink] = {}
        self._templates: dict[str, Callable[[Any], None]] = {}

    @staticmethod
    def key(transport: BusTransport, entry: TopicConfig | ServiceConfig, bridge: str) -> str:
        """An entry's key: its remote, or the transport's default key; with placeholders, the
        bus's templates check it, in another convention its dialect."""
        if not isinstance(transport, FleetTransport):
            raise ConfigError(f"{transport.name} asks for the bus role fleet but is no "
                              "rosgate_fleet.FleetTransport, whose keys that role uses",
                              key="transport", fix=f"report it to the authors of the "
                              f"{transport.name} plugin, or use another transport")
        kind = "topic" if isinstance(entry, TopicConfig) else "service"
        name = entry.topic if isinstance(entry, TopicConfig) else entry.service
        given = "remote" in entry.lines
        key = (entry.remote.removeprefix("/") if given
               else transport.default_key(bridge, name, entry.framing is Framing.NONE))
        if is_template(name) or is_template(key):
            if transport.templates is None:
                raise ConfigError(f"{entry.transport} takes no placeholders such as {{robot}}",
                                  key=kind, fix="write the robot's name, or use a bus that "
                                  "takes them")
            transport.templates.check(entry, key)
            return key
        try:
            transport.check_key(key)
        except ValueError as exc:
            raise ConfigError(str(exc), key="remote" if given else kind,
                              fix="write remote: as parts separated by single '/', e.g. "
                              "remote: fleet/robot1/scan") from None
        dialect = transport.dialect
        if dialect is not None and dialect.name(entry) is not None:
            dialect.check(entry, key)
        return key

    @staticmethod
    def finds(transport: BusTransport) -> bool:
        """Its bus announces topics it can find: a convention (:class:`rosgate_fleet.Dialect`,
        the zenoh plugin's ``speak:``) whose graph it reads."""
        return isinstance(transport, FleetTransport) and transport.dialect is not None

    @staticmethod
    def speaks(transport: BusTransport, entry: TopicConfig | ServiceConfig) -> str | None:
        dialect = transport.dialect if isinstance(transport, FleetTransport) else None
        return dialect.name(entry) if dialect is not None else None

    def link(self, p: TopicSpec | ServiceSpec) -> BusLink:
        transport = p.transport
        assert isinstance(transport, FleetTransport)
        found = self.links.get(transport.name)
        if found is not None:
            return found
        try:
            session = transport.open(self.config.name)
        except LinkError as exc:
            kind = "topics" if isinstance(p, TopicSpec) else "services"
            raise self.link_error(exc, f"{kind}[{p.index}].transport") from None
        link = self.closing(BusLink(transport, session, transport.name, self.link_drop))
        link.token(transport.alive_key(self.config.name))
        self.links[transport.name] = link
        return link

    def _templated(self, link: BusLink, p: TopicSpec | ServiceSpec) -> None:
        add = self._templates.get(link.name)
        if add is None:
            templates = link.transport.templates
            assert templates is not None, "the resolver lets no template reach a bus without"
            add = self._templates[link.name] = templates.start(self, link)
        add(p)

    def _dialect(self, link: BusLink, p: TopicSpec | ServiceSpec) -> bool:
        """An entry in another system's convention is the bus's own to wire."""
        dialect = link.transport.dialect
        if dialect is None or dialect.name(p.config) is None:
            return False
        dialect.wire(self, link, p)
        return True

    # -- topics ----------------------------------------------------------------------------------
    def topic(self, p: TopicSpec) -> None:
        link = self.link(p)
        if is_template(p.config.topic):
            self._templated(link, p)
        elif self._dialect(link, p):
            return
        elif p.config.direction is Direction.TRANSMIT:
            self.transmitter(link, p)
        else:
            assert p.key is not None
            route = self.receiver(p)
            link.subscribe(p.key, lambda key, frame: self.dispatch(route, key, frame),
                           lambda key, reason: route.drop(reason))

    def pattern(self, pattern: BusPattern) -> None:
        """A receiving topic pattern: a route for each publisher its bus's convention announces
        under it, made as a listed entry's (on the link's thread, where the graph is read), and
        removed with what it declared on the bus once the name's last publisher has been gone
        for ``bridge.pattern_grace`` seconds."""
        link = self.link(pattern.spec)
        dialect = link.transport.dialect
        assert dialect is not None, "the resolver lets no pattern reach a bus without one"
        found = _Found(self, link, pattern)
        link.call_later(dialect.publishers, self, link, found.announced)
        threading.Thread(target=found.sweeper, name=f"pattern-{link.name}", daemon=True).start()

    # -- services --------------------------------------------------------------------------------
    def service(self, p: ServiceSpec) -> None:
        link, s = self.link(p), p.config
        assert p.key is not None
        if is_template(s.service):
            self._templated(link, p)
            return
        if self._dialect(link, p):
            return
        service_id = topic_id_for(p.key)
        if s.direction is Direction.RECEIVE:
            route = self.service_route(p, service_id, None)
            assert isinstance(route, ServerRoute)
            link.serve(p.key, lambda frame, answerer, source: self._request(
                route, link, frame, answerer, source), s.timeout + 1.0)
            return
        self.caller(link, p)

    def _request(self, route: ServerRoute, link: BusLink, frame: bytes, answerer: Link,
                 source: tuple[str, int]) -> None:
        """A query's payload must be a call of this service (its id, the REQUEST flag), or its
        caller's announcement, which is heard and closed without an answer."""
        try:
            header = unpack_envelope(frame)
        except EnvelopeError as exc:
            route.drop(exc.reason, f"a query on {source[0]}")
            return
        if header.topic_id == route.topic_id and header.flags == FLAG_ANNOUNCE:
            query = link.take(source[1])
            if query is not None:
                query.close()
            route.heard(header, frame)
            return
        if not header.flags & FLAG_REQUEST or header.topic_id != route.topic_id:
            route.drop(Drop.UNEXPECTED_FRAME, f"a query on {source[0]} that is not a call of it")
            return
        route.on_request(header, frame, answerer, source)

    # -- routes, one per key ---------------------------------------------------------------------
    def transmitter(self, link: BusLink, p: TopicSpec) -> Route:
        """A topic published on its key."""
        assert p.key is not None
        outlet = link.outlet(p.key, p.delivery.reliable, p.delivery.priority)
        return self.topic_route(p, topic_id_for(p.key), outlet, bare_names=False)

    def caller(self, link: BusLink, p: ServiceSpec) -> Route:
        """A service called here and served on the bus: each call one query on its key."""
        assert p.key is not None
        outlet = link.caller(p.key, p.config.timeout)
        outlet.on_answer = self.answered
        return self.service_route(p, topic_id_for(p.key), outlet)

    def receiver(self, p: TopicSpec) -> ReceiveRoute:
        """A topic received from its key: frames reach it through :meth:`dispatch`."""
        assert p.key is not None
        route = self.topic_route(p, topic_id_for(p.key), NoLink())
        assert isinstance(route, ReceiveRoute)
        return route

    def dispatch(self, route: ReceiveRoute, key: str, frame: bytes) -> None:
        """A frame from the route's key: bare, or an envelope that names this key's topic: a
        message, or the sender's announcement of the entry (its type checked, its QoS
        followed)."""
        if route.topic.framing is Framing.NONE:
            route.deliver(frame, len(frame))
            return
        try:
            header = unpack_envelope(frame)
        except EnvelopeError as exc:
            route.drop(exc.reason, f"{len(frame)} bytes on {key}")
            return
        if header.flags & ~_TOPIC_FLAGS or header.topic_id != route.topic_id:
            route.drop(Drop.UNEXPECTED_FRAME,
                       f"on {key}: not a frame of this topic (flags {header.flags:#x}, "
                       f"topic id {header.topic_id})")
            return
        if header.flags & FLAG_ANNOUNCE:
            heard = route.heard(header, frame)
            if heard is not None:
                self.follow_qos(route, heard[1])
            return
        route.on_frame(header, frame)

    def remove(self, route: Route) -> None:
        """Take a route away: its counters logged, and its publisher on the bus closed."""
        self.remove_route(route)
        if isinstance(route, TransmitRoute):
            route.link.close()


class _Found:
    """The routes one pattern made on one bus link, and the publishers each name has there."""

    def __init__(self, wiring: BusWiring, link: BusLink, pattern: BusPattern):
        self.wiring, self.link, self.pattern = wiring, link, pattern
        self.publishers: Counter[str] = Counter()  # name on the bus -> tokens alive
        self.made: dict[str, tuple[list[Route], list[Handle]]] = {}
        self.gone_since: dict[str, float] = {}

    def announced(self, name: str, type_name: str, alive: bool) -> None:
        self.publishers[name] += 1 if alive else -1
        if self.publishers[name] > 0:
            self.gone_since.pop(name, None)
        elif name in self.made:
            self.gone_since.setdefault(name, time.monotonic())
        spec = self.pattern.take(name, type_name) if alive else None
        if spec is not None:
            handles = self.link.declared_by(lambda: self.wiring.topic(spec))
            routes = self.wiring.routes_of(spec.config)
            self.made[name] = routes, handles

    def sweep(self) -> None:
        now, grace = time.monotonic(), self.wiring.config.pattern_grace
        for name, since in list(self.gone_since.items()):
            if now - since >= grace:
                del self.gone_since[name]
                routes, handles = self.made.pop(name)
                for route in routes:
                    self.wiring.remove(route)
                for handle in handles:
                    self.link.release(handle)
                self.pattern.forget(name)

    def sweeper(self) -> None:
        while not self.wiring.stopping.wait(SWEEP_EVERY):
            self.link.call_later(self.sweep)
