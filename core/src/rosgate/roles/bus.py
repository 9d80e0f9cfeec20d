"""Entries on a bus (zenoh), wired for the peer role: each file is complete and the bus finds
the others, so there is no main line, no ``peer:`` and no ``port:``.

* A topic is published on its key; a receiving topic subscribes to its key and is found by it
  (the envelope's topic id must be the key's: a frame moved to another key is refused).
* A service is a queryable on its key (``receive``) or one query per call (``transmit``).
  A fleet service (``/{robot}/reset``, transmit only) is offered for each robot known.
* Each bridge holds a liveliness token, ``<prefix>/<name>/@alive``.
* **Fleet entries** (placeholders, :mod:`rosgate.placeholders`) belong to a :class:`Fleet`: a
  receiving one is one wildcard subscription, and the first frame from a robot makes its route
  (the ROS publisher), logged once; a transmitting one gets a route per robot the bridge knows,
  from the liveliness tokens it watches or the frames it received. A robot whose token goes is
  logged once; its routes are dropped after ``bridge.fleet_timeout`` seconds unless it returns
  (a robot known by its frames only: after that long without any).

Everything a bus delivers is handled on its link's thread (:class:`rosgate.buslink.BusLink`),
fleet bookkeeping included, so routes are made and dropped in one thread.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from dataclasses import dataclass, field

from ..bus import BusTransport
from ..buslink import BusLink
from ..config import Direction, Framing
from ..errors import LinkError
from ..links import Link
from ..placeholders import Template, has_placeholders
from ..resolver import PreparedService, PreparedTopic
from ..routes import ReceiveRoute, Route, TransmitRoute
from ..services import ServerRoute
from ..wire import envelope
from ..wire.envelope import topic_id_for
from . import Bridge, NoLink

log = logging.getLogger("rosgate")

SWEEP_EVERY = 0.5  # seconds between looks at departed robots


class BusWiring:
    """The bus entries of a peer-role bridge: one :class:`BusLink` per bus transport."""

    def __init__(self, bridge: Bridge):
        self.bridge = bridge
        self.cfg = bridge.config
        self.router = bridge.router
        self.links: dict[str, BusLink] = {}
        self.fleets: dict[str, Fleet] = {}

    def link(self, p: PreparedTopic | PreparedService) -> BusLink:
        transport = p.transport
        assert isinstance(transport, BusTransport)
        found = self.links.get(transport.name)
        if found is not None:
            return found
        try:
            session = transport.open(self.cfg.name)
        except LinkError as exc:
            kind = "topics" if isinstance(p, PreparedTopic) else "services"
            raise self.bridge.link_error(exc, f"{kind}[{p.index}].transport") from None
        link = self.bridge.life.closing(BusLink(transport, session, transport.name,
                                                self.router.link_drop))
        link.token(transport.alive_key(self.cfg.name))
        self.links[transport.name] = link
        return link

    def fleet(self, link: BusLink) -> Fleet:
        if link.name not in self.fleets:
            fleet = Fleet(self.bridge, link)
            self.fleets[link.name] = fleet
            fleet.start()
        return self.fleets[link.name]

    # -- topics ----------------------------------------------------------------------------------
    def topic(self, p: PreparedTopic) -> None:
        link = self.link(p)
        if has_placeholders(p.config.topic):
            self.fleet(link).add(p)
        elif p.config.direction is Direction.TRANSMIT:
            transmitter(self.bridge, link, p, p.config.topic)
        else:
            assert p.key is not None
            route = receiver(self.bridge, p, p.config.topic)
            link.subscribe(p.key, lambda key, frame: dispatch(route, key, frame),
                           lambda key, reason: route.drop(reason))

    # -- services --------------------------------------------------------------------------------
    def service(self, p: PreparedService) -> None:
        link, s = self.link(p), p.config
        assert p.key is not None
        if has_placeholders(s.service):
            self.fleet(link).add(p)
            return
        service_id = topic_id_for(p.key)
        if s.direction is Direction.RECEIVE:
            route = self.router.service(p, service_id, s.service, None)
            assert isinstance(route, ServerRoute)
            link.serve(p.key, lambda frame, answerer, source: self._request(
                route, link, frame, answerer, source), s.timeout + 1.0)
            return
        caller(self.bridge, link, p)

    def _request(self, route: ServerRoute, link: BusLink, frame: bytes, answerer: Link,
                 source: tuple[str, int]) -> None:
        """A query's payload must be a call of this service (its id, the REQUEST flag)."""
        try:
            header = envelope.unpack(frame)
        except envelope.EnvelopeError as exc:
            route.drop(f"{exc}_frame", f"a query on {source[0]}")
            return
        if not header.flags & envelope.FLAG_REQUEST or header.topic_id != route.topic_id:
            route.drop("unexpected_frame", f"a query on {source[0]} that is not a call of it")
            return
        route.on_request(header, frame, answerer, source)


def transmitter(bridge: Bridge, link: BusLink, p: PreparedTopic, label: str) -> Route:
    assert p.key is not None
    outlet = link.outlet(p.key, p.reliable, p.priority)
    return bridge.router.topic(p, topic_id_for(p.key), label, outlet, bare_names=False)


def caller(bridge: Bridge, link: BusLink, p: PreparedService) -> Route:
    """A service called here and served on the bus: each call one query on its key."""
    assert p.key is not None
    outlet = link.caller(p.key, p.config.timeout)
    outlet.on_answer = bridge.router.on_frame
    return bridge.router.service(p, topic_id_for(p.key), p.name, outlet)


def receiver(bridge: Bridge, p: PreparedTopic, label: str) -> ReceiveRoute:
    assert p.key is not None
    route = bridge.router.topic(p, topic_id_for(p.key), label, NoLink())
    assert isinstance(route, ReceiveRoute)
    return route


def dispatch(route: ReceiveRoute, key: str, frame: bytes) -> None:
    """A frame from the route's key: bare, or an envelope that names this key's topic."""
    if route.topic.framing is Framing.NONE:
        route.deliver(frame, len(frame))
        return
    try:
        header = envelope.unpack(frame)
    except envelope.EnvelopeError as exc:
        route.drop(f"{exc}_frame", f"{len(frame)} bytes on {key}")
        return
    if header.flags or header.topic_id != route.topic_id:
        route.drop("unexpected_frame", f"on {key}: not a frame of this topic "
                                       f"(flags {header.flags:#x}, topic id {header.topic_id})")
        return
    route.on_frame(header, frame)


@dataclass
class Member:
    """A robot the fleet knows."""

    name: str
    token: bool = False  # its liveliness token is there now
    had_token: bool = False
    last_seen: float = field(default_factory=time.monotonic)
    gone_since: float | None = None
    routes: dict[tuple[str, int], Route] = field(default_factory=dict)  # (section, index) ->


class Fleet:
    """The fleet entries of one bus link, and the robots they were filled for."""

    def __init__(self, bridge: Bridge, link: BusLink):
        self.bridge = bridge
        self.link = link
        self.name = bridge.config.name
        self.timeout = bridge.config.fleet_timeout
        assert isinstance(link.transport, BusTransport)
        self.alive = Template(link.transport.alive_key("{robot}"))
        self.transmit: list[tuple[PreparedTopic | PreparedService, Template, Template]] = []
        self.members: dict[str, Member] = {}
        self._stop = bridge.life.stopping
        self._thread = threading.Thread(target=self._sweeper, name=f"fleet-{link.name}",
                                        daemon=True)

    def start(self) -> None:
        self.link.watch(self.alive.wildcard(), self._token)
        self._thread.start()

    def add(self, p: PreparedTopic | PreparedService) -> None:
        """A fleet entry: a receiving topic subscribes now; a transmitting topic or a service
        (which the base calls) gets a route per robot, now and as robots come."""
        assert p.key is not None
        names, keys = Template(p.name), Template(p.key)
        if p.config.direction is Direction.TRANSMIT or isinstance(p, PreparedService):
            self.transmit.append((p, names, keys))
            for member in list(self.members.values()):
                self.link.call_later(self._transmit_for, member, p, names, keys)
            return
        assert isinstance(p, PreparedTopic)
        self.link.subscribe(keys.wildcard(), lambda key, frame: self._frame(p, names, keys, key,
                                                                            frame),
                            lambda key, reason: self.link.link_drop(self.link, reason,
                                                                    f"a frame on {key}"))

    # -- on the link's thread ---------------------------------------------------------------------
    def _frame(self, p: PreparedTopic, names: Template, keys: Template, key: str,
               frame: bytes) -> None:
        values = keys.match(key)
        if values is None:
            self.link.link_drop(self.link, "unknown_topic", f"{key} does not fit {keys.text}")
            return
        member = self._member(values["robot"], f"a frame on {key}")
        member.last_seen = time.monotonic()
        route = member.routes.get(("topics", p.index))
        if route is None:
            filled = self._filled(p, names, keys, values)
            assert isinstance(filled, PreparedTopic)
            route = receiver(self.bridge, filled, filled.config.topic)
            member.routes[("topics", p.index)] = route
            log.info("fleet: publishing %s for robot %s (frames on %s)", filled.config.topic,
                     member.name, filled.key)
        assert isinstance(route, ReceiveRoute)
        dispatch(route, key, frame)

    def _token(self, key: str, alive: bool) -> None:
        values = self.alive.match(key)
        if values is None or values["robot"] == self.name:
            return
        robot = values["robot"]
        if alive:
            member = self._member(robot, "its liveliness token")
            member.token = member.had_token = True
            member.last_seen = time.monotonic()
            return
        known = self.members.get(robot)
        if known is None or not known.token:
            return
        known.token = False
        known.gone_since = time.monotonic()
        log.warning("fleet: robot %s left (its liveliness token is gone); its %d route(s) go in "
                    "%g s unless it returns", robot, len(known.routes), self.timeout)

    def _member(self, robot: str, how: str) -> Member:
        member = self.members.get(robot)
        if member is None:
            member = self.members[robot] = Member(robot)
            log.info("fleet: robot %s joined (%s)", robot, how)
            for p, names, keys in self.transmit:
                self._transmit_for(member, p, names, keys)
        elif member.gone_since is not None:
            member.gone_since = None
            log.info("fleet: robot %s is back (%s)", robot, how)
        return member

    def _transmit_for(self, member: Member, p: PreparedTopic | PreparedService, names: Template,
                      keys: Template) -> None:
        """A transmitting topic's route, or a service's caller, for one robot."""
        slot = ("topics" if isinstance(p, PreparedTopic) else "services", p.index)
        if slot in member.routes or member.name not in self.members:
            return
        filled = self._filled(p, names, keys, {"robot": member.name})
        if isinstance(filled, PreparedTopic):
            member.routes[slot] = transmitter(self.bridge, self.link, filled, filled.name)
            log.info("fleet: sending %s to robot %s on %s", filled.name, member.name, filled.key)
            return
        member.routes[slot] = caller(self.bridge, self.link, filled)
        log.info("fleet: offering %s, served by robot %s on %s", filled.name, member.name,
                 filled.key)

    @staticmethod
    def _filled(p: PreparedTopic | PreparedService, names: Template, keys: Template,
                values: dict[str, str]) -> PreparedTopic | PreparedService:
        name, key = names.fill(values), keys.fill(values)
        if isinstance(p, PreparedTopic):
            return dataclasses.replace(p, key=key, config=dataclasses.replace(
                p.config, topic=name, remote=key))
        return dataclasses.replace(p, key=key, config=dataclasses.replace(
            p.config, service=name, remote=key))

    def _sweep(self) -> None:
        now = time.monotonic()
        for member in list(self.members.values()):
            if member.gone_since is not None:
                silent, why = now - member.gone_since, "its liveliness token went"
            elif not member.had_token:
                silent, why = now - member.last_seen, "no frames"
            else:
                continue
            if silent < self.timeout:
                continue
            del self.members[member.name]
            for route in member.routes.values():
                self.bridge.router.log_stats([route])
                self.bridge.router.remove(route)
                if isinstance(route, TransmitRoute):
                    route.link.close()  # its publisher on the robot's key
            log.warning("fleet: robot %s dropped (%s %.0f s ago): %d route(s) removed",
                        member.name, why, silent, len(member.routes))

    def _sweeper(self) -> None:
        while not self._stop.wait(SWEEP_EVERY):
            self.link.call_later(self._sweep)
