"""Fleets: one entry for any number of robots, ``topic: /{robot}/scan`` with ``remote:
fleet/{robot}/scan`` (:mod:`.placeholders`), the zenoh transport's
:class:`rosgate_fleet.NameTemplates`.

* A receiving fleet topic is one wildcard subscription (``fleet/*/scan``); the first frame from
  a robot makes its route (the ROS publisher ``/robot7/scan``), logged once.
* A transmitting fleet topic, or a fleet service (``/{robot}/reset``, transmit only: each robot
  serves it), gets a route per robot the bridge knows, from the liveliness tokens it watches
  (``<prefix>/*/@alive``) or the frames it received.
* A robot whose token goes is logged once; its routes are dropped after ``bridge.fleet_timeout``
  seconds unless it returns (a robot known by its frames only: after that long without any).
* With ``speak: ros2dds``, a robot's routes of entries that speak it are made as
  zenoh-bridge-ros2dds makes them (:mod:`.dialect`: bare service calls, cached transient_local
  topics) and hold its tokens (``MP``, ``MS``, ``SC`` on the robot's keys), which go with the
  robot's routes.

Everything here runs on the bus link's thread (routes are made and dropped in one thread) but
the sweeper, which only queues a look at departed robots there.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from rosgate_fleet import BusLink, BusWiring

from rosgate import (
    ConfigError,
    Direction,
    Drop,
    ReceiveRoute,
    Route,
    ServiceConfig,
    ServiceSpec,
    TopicConfig,
    TopicSpec,
)

from . import placeholders
from .dialect import NAME, Ros2dds
from .placeholders import Template
from .ros2dds import Announced, Kind

if TYPE_CHECKING:
    from rosgate_fleet import FleetTransport, Handle

log = logging.getLogger("rosgate")

SWEEP_EVERY = 0.5  # seconds between looks at departed robots
_KEY_EXAMPLE = "remote: fleet/{robot}/scan"

Prepared = TopicSpec | ServiceSpec


class Fleets:
    """What the zenoh transport does with entries that hold placeholders."""

    def __init__(self, transport: FleetTransport):
        self.transport = transport

    def check(self, entry: TopicConfig | ServiceConfig, key: str) -> None:
        """The same known placeholders in the ROS name and in remote; a fleet service is called
        here; the key's wildcard form a zenoh key expression."""
        service = isinstance(entry, ServiceConfig)
        name_key, name = (("service", entry.service) if isinstance(entry, ServiceConfig)
                          else ("topic", entry.topic))
        try:
            found = placeholders.check(name)
        except ValueError as exc:
            raise ConfigError(str(exc), key=name_key, fix=f"e.g. {name_key}: /{{robot}}/scan") \
                from None
        if found and "remote" not in entry.lines:
            raise ConfigError("an entry with placeholders needs remote: with the same "
                              "placeholders (the key every robot uses)", key=name_key,
                              fix=f"add e.g. {_KEY_EXAMPLE}")
        try:
            in_remote = placeholders.check(key)
        except ValueError as exc:
            raise ConfigError(str(exc), key="remote", fix=f"e.g. {_KEY_EXAMPLE}") from None
        if sorted(found) != sorted(in_remote):
            raise ConfigError(f"{name_key} and remote must hold the same placeholders "
                              f"({_listed(found)} in {name_key}, {_listed(in_remote)} in remote)",
                              key="remote", fix=f"e.g. topic: /{{robot}}/scan with {_KEY_EXAMPLE}")
        if service and entry.direction is Direction.RECEIVE:
            raise ConfigError("a fleet service (with {robot}) is called here and served by each "
                              "robot, so its direction is transmit", key="direction",
                              fix="use direction: transmit, or name the service without "
                                  "placeholders")
        try:
            self.transport.check_key(Template(key).wildcard())
        except ValueError as exc:
            raise ConfigError(str(exc), key="remote", fix="write remote: as parts separated by "
                              f"single '/', e.g. {_KEY_EXAMPLE}") from None

    def start(self, wiring: BusWiring, link: BusLink) -> Callable[[Prepared], None]:
        fleet = Fleet(wiring, link)
        fleet.start()
        return fleet.add


def _listed(names: list[str]) -> str:
    return ", ".join("{" + n + "}" for n in names) or "none"


@dataclass
class Member:
    """A robot the fleet knows."""

    name: str
    token: bool = False  # its liveliness token is there now
    had_token: bool = False
    last_seen: float = field(default_factory=time.monotonic)
    gone_since: float | None = None
    #: (section, index, name) -> its route; the name tells an action's five parts apart
    routes: dict[tuple[str, int, str], Route] = field(default_factory=dict)
    #: the zenoh-bridge-ros2dds tokens its routes hold (speak: ros2dds)
    tokens: list[Handle] = field(default_factory=list)


class Fleet:
    """The fleet entries of one bus link, and the robots they were filled for."""

    def __init__(self, wiring: BusWiring, link: BusLink):
        self.wiring = wiring
        self.link = link
        self.name = wiring.config.name
        self.timeout = wiring.config.fleet_timeout
        self.alive = Template(link.transport.alive_key("{robot}"))
        self.transmit: list[tuple[Prepared, Template, Template]] = []
        self.receive: list[tuple[TopicSpec, Template, Template]] = []
        self.announced: list[Announced] = []  # zenoh-bridge-ros2dds routes seen
        self.members: dict[str, Member] = {}
        self._stop = wiring.stopping
        self._thread = threading.Thread(target=self._sweeper, name=f"fleet-{link.name}",
                                        daemon=True)

    def start(self) -> None:
        self.link.watch(self.alive.wildcard(), self._token)
        dialect = self.link.transport.dialect
        if isinstance(dialect, Ros2dds):  # zenoh-bridge-ros2dds robots are members too
            dialect.graph(self.link).listen(self._announced)
        self._thread.start()

    def add(self, p: Prepared) -> None:
        """A fleet entry: a receiving topic subscribes now; a transmitting topic or a service
        (which the base calls) gets a route per robot, now and as robots come."""
        assert p.key is not None
        names, keys = Template(p.name), Template(p.key)
        if p.config.direction is Direction.TRANSMIT or isinstance(p, ServiceSpec):
            self.transmit.append((p, names, keys))
            for member in list(self.members.values()):
                self.link.call_later(self._transmit_for, member, p, names, keys)
            return
        assert isinstance(p, TopicSpec)
        self.receive.append((p, names, keys))
        for announced in self.announced:
            self.link.call_later(self._announced, announced, True)
        self.link.subscribe(keys.wildcard(), lambda key, frame: self._frame(p, names, keys, key,
                                                                            frame),
                            lambda key, reason: self.link.link_drop(self.link, reason,
                                                                    f"a frame on {key}"))

    # -- on the link's thread ---------------------------------------------------------------------
    def _announced(self, route: Announced, alive: bool) -> None:
        """A zenoh-bridge-ros2dds route: a robot whose publisher, subscriber or service fits a
        fleet entry's key joins as by its liveliness token (a receiving route is made before any
        frame), and leaves when the last of its routes is gone."""
        robots = {values["robot"] for values in self._fits(route)} - {self.name}
        if not alive:
            if route in self.announced:
                self.announced.remove(route)
            for robot in robots:
                if not any(robot in self._robots(other) for other in self.announced):
                    self._token(self.link.transport.alive_key(robot), False)
            return
        if route not in self.announced:
            self.announced.append(route)
        for robot in robots:
            member = self._member(robot, f"its {NAME} {route.kind.words} on {route.key}")
            member.token = member.had_token = True
        if route.kind is Kind.PUBLISHER:
            for p, names, keys in self.receive:
                values = keys.match(route.key)
                if values is not None and values["robot"] in robots:
                    self._receiver_for(self.members[values["robot"]], p, names, keys, values)

    def _fits(self, route: Announced) -> list[dict[str, str]]:
        """The placeholder values of each fleet entry ``route`` fits (by direction)."""
        entries = self.receive if route.kind is Kind.PUBLISHER else (
            self.transmit if route.kind in (Kind.SUBSCRIBER, Kind.SERVER) else [])
        found = (keys.match(route.key) for _p, _names, keys in entries)
        return [values for values in found if values is not None]

    def _robots(self, route: Announced) -> set[str]:
        return {values["robot"] for values in self._fits(route)}

    def _receiver_for(self, member: Member, p: TopicSpec, names: Template, keys: Template,
                      values: dict[str, str]) -> ReceiveRoute:
        slot = ("topics", p.index, p.name)
        route = member.routes.get(slot)
        if route is None:
            filled = _filled(p, names, keys, values)
            assert isinstance(filled, TopicSpec)
            route = self.wiring.receiver(filled)
            member.routes[slot] = route
            dialect = self._speaking(filled)
            if dialect is not None:  # its frames come through the fleet's subscription
                member.tokens.append(self.link.token(dialect.topic_token(self.link, filled)))
            log.info("fleet: publishing %s for robot %s (frames on %s)", filled.config.topic,
                     member.name, filled.key)
        assert isinstance(route, ReceiveRoute)
        return route

    def _frame(self, p: TopicSpec, names: Template, keys: Template, key: str,
               frame: bytes) -> None:
        values = keys.match(key)
        if values is None:
            self.link.link_drop(self.link, Drop.UNKNOWN_TOPIC, f"{key} does not fit {keys.text}")
            return
        member = self._member(values["robot"], f"a frame on {key}")
        member.last_seen = time.monotonic()
        self.wiring.dispatch(self._receiver_for(member, p, names, keys, values), key, frame)

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

    def _transmit_for(self, member: Member, p: Prepared, names: Template,
                      keys: Template) -> None:
        """A transmitting topic's route, or a service's caller, for one robot."""
        slot = ("topics" if isinstance(p, TopicSpec) else "services", p.index, p.name)
        if slot in member.routes or member.name not in self.members:
            return
        filled = _filled(p, names, keys, {"robot": member.name})
        dialect = self._speaking(filled)
        if dialect is not None:  # as zenoh-bridge-ros2dds would route it, with its token
            member.routes[slot], token = dialect.route(self.wiring, self.link, filled)
            if token is not None:
                member.tokens.append(token)
        if isinstance(filled, TopicSpec):
            if dialect is None:
                member.routes[slot] = self.wiring.transmitter(self.link, filled)
            log.info("fleet: sending %s to robot %s on %s", filled.name, member.name, filled.key)
            return
        if dialect is None:
            member.routes[slot] = self.wiring.caller(self.link, filled)
        log.info("fleet: offering %s, served by robot %s on %s", filled.name, member.name,
                 filled.key)

    def _speaking(self, filled: Prepared) -> Ros2dds | None:
        """The dialect, when a robot's route speaks it (``speak: ros2dds``, bare CDR)."""
        dialect = self.link.transport.dialect
        if isinstance(dialect, Ros2dds) and dialect.name(filled.config) is not None:
            return dialect
        return None

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
                self.wiring.remove(route)
            for token in member.tokens:
                self.link.release(token)
            log.warning("fleet: robot %s dropped (%s %.0f s ago): %d route(s) removed",
                        member.name, why, silent, len(member.routes))

    def _sweeper(self) -> None:
        while not self._stop.wait(SWEEP_EVERY):
            self.link.call_later(self._sweep)


def _filled(p: Prepared, names: Template, keys: Template, values: dict[str, str]) -> Prepared:
    """An entry with the placeholders filled: one robot's route."""
    name, key = names.fill(values), keys.fill(values)
    if isinstance(p, TopicSpec):
        return dataclasses.replace(p, key=key, config=dataclasses.replace(
            p.config, topic=name, remote=key))
    return dataclasses.replace(p, key=key, config=dataclasses.replace(
        p.config, service=name, remote=key))
