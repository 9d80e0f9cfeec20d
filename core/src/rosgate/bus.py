"""Buses: the third kind of link, for pub/sub and query networks addressed by key (Eclipse Zenoh).

A bus moves whole frames by **key**, and discovers, reconnects and fragments by itself. A bus
plugin subclasses :class:`BusTransport` (registered through ``rosgate_transports``); its entries
(peer role, no ``port:``, no ``peer:``) are wired by the :class:`BusRole` its
:attr:`~BusTransport.role` names, registered through ``rosgate_bus_roles``. rosgate's own is
``fleet`` (distribution ``rosgate-fleet``), which defines the session :meth:`BusTransport.open`
returns.
"""

from __future__ import annotations

import threading
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any

from .config import ServiceConfig, TopicConfig
from .drops import Reason
from .errors import ConfigError, LinkError
from .spec import ServiceSpec, TopicSpec
from .transport import Transport


@dataclass(frozen=True)
class Unauthenticated:
    """What lets anyone who reaches a bus write to a bridge's entries on it: ``option``, the
    plugin's option where the fix goes (dotted, ``connect.endpoints``; None: the plugin's table
    as a whole), ``why`` in a few words, and the ``fix``."""

    option: str | None
    why: str
    fix: str


class BusTransport(Transport):
    """Base class of bus plugins. Set :attr:`name`; implement :meth:`open`. A bus for the
    ``fleet`` role subclasses :class:`rosgate_fleet.FleetTransport`, which adds its keys."""

    #: the bus role that wires this bus's entries (a plugin of kind ``bus_role``)
    role: str = "fleet"

    @abstractmethod
    def open(self, name: str) -> Any:
        """Open a session for the bridge called ``name``, of the interface the bus role expects
        (``fleet``: :class:`rosgate_fleet.BusSession`). Raise :class:`rosgate.LinkError` when it
        cannot be opened (no router where one is required, a port in use)."""

    def unauthenticated(self) -> Unauthenticated | None:
        """Whether a stranger could send on this bus as its options stand: None when every link
        the session has, or can get, authenticates the far side (mutual TLS with the fleet's
        CA, say), else what leaves it open. ``rosgate check`` and ``rosgate run`` refuse an
        entry that takes frames from an open bus (a receiving topic, a service, an action)
        unless a keyed cipher seals it or the file says ``insecure: true``. A bus that does not
        answer is open."""
        return Unauthenticated(None, f"{self.name} does not say it authenticates who sends on "
                               "it", f"ask the author of {self.name} to judge its links")


class BusRole(ABC):
    """The bus side of a peer-role bridge. The resolver asks :meth:`key` of each bus entry; the
    peer role makes one instance per bridge (``cls(bridge)``) and hands it each prepared bus
    entry as the bridge starts. The bridge itself is the core's own: a bus role makes its routes
    and reaches the bridge through the methods below, the plugin API's bus facade."""

    name: str = ""

    def __init__(self, bridge: Any) -> None:
        self.bridge = bridge

    # -- the bus facade: what the bridge lends its bus role ------------------------------------
    @property
    def config(self) -> Any:
        """The file's ``bridge:`` table as read: one attribute per key of
        docs/configuration.md (``name``, ``pattern_grace``, ``fleet_timeout`` ...)."""
        return self.bridge.config

    @property
    def stopping(self) -> threading.Event:
        """Set when the bridge stops: a bus role's own threads end on it."""
        return self.bridge.life.stopping

    def closing(self, item: Any) -> Any:
        """``item`` (a link, a session: anything with ``close()``), closed when the bridge
        stops; returned, so it reads ``link = self.closing(MyLink(...))``."""
        return self.bridge.life.closing(item)

    def link_error(self, exc: LinkError, key: str) -> ConfigError:
        """The error that stops the bridge when a bus cannot be opened: ``exc`` said at the
        entry's ``key`` (``topics[2].transport``), with its fix."""
        return self.bridge.link_error(exc, key)

    def topic_route(self, spec: TopicSpec, topic_id: int, link: Any, *,
                    bare_names: bool = True) -> Any:
        """Make the route of a bus topic, with its ROS side, and add it to the bridge: a
        :class:`rosgate.TransmitRoute` sending through ``link`` (a :class:`rosgate.Link`) or a
        :class:`rosgate.ReceiveRoute` (``link``: a :class:`rosgate.NoLink`) that the bus role
        hands each frame. ``topic_id``: :func:`rosgate.topic_id_for` of the key;
        ``bare_names=False``: a bare frame carries no name in front (a bus key says it)."""
        return self.bridge.router.topic(spec, topic_id, spec.name, link, bare_names=bare_names)

    def service_route(self, spec: ServiceSpec, service_id: int, link: Any, *,
                      announce: bool = True) -> Any:
        """Make the route of a bus service and add it to the bridge: a
        :class:`rosgate.ServerRoute` (``receive``; ``link`` None, each call handed to its
        ``on_request``) or a :class:`rosgate.CallerRoute` (``transmit``) calling through
        ``link``. ``announce=False``: its calls carry no envelope, so it says nothing of its
        type."""
        return self.bridge.router.service(spec, service_id, spec.name, link, announce=announce)

    def answered(self, frame: bytes, link: Any, source: Any) -> None:
        """A frame a bus link received for a route rather than a key (a call's answer): found
        by its envelope's id and handed to its route, or counted as a drop."""
        self.bridge.router.on_frame(frame, link, source)

    def link_drop(self, link: Any, reason: Reason, detail: str) -> None:
        """A frame on ``link`` that belongs to no route: counted per bridge, warned about per
        link."""
        self.bridge.router.link_drop(link, reason, detail)

    def follow_qos(self, route: Any, qos: dict[str, Any] | None) -> None:
        """A receiving route's publisher takes the QoS its far side announced (``heard``),
        unless the entry sets its own."""
        self.bridge.router.follow_qos(route, qos)

    def routes_of(self, entry: TopicConfig | ServiceConfig) -> list[Any]:
        """The routes the bridge holds for ``entry``."""
        return [r for r in self.bridge.router.snapshot() if r.entry is entry]

    def remove_route(self, route: Any) -> None:
        """Take a route away from the bridge (its ROS side too), its counters logged."""
        router = self.bridge.router
        router.log_stats([route])
        router.remove(route)

    def domain_id(self) -> int:
        """The ROS domain of the bridge's node."""
        return int(self.bridge.router.ros.context.get_domain_id())

    @staticmethod
    @abstractmethod
    def key(transport: BusTransport, entry: TopicConfig | ServiceConfig, bridge: str) -> str:
        """The key ``entry`` is carried on (bridge: this bridge's name). Refuse what the bus
        cannot carry with a :class:`rosgate.ConfigError` whose ``key`` is the entry's field."""

    @staticmethod
    def speaks(transport: BusTransport, entry: TopicConfig | ServiceConfig) -> str | None:
        """The convention ``entry`` follows, in a few words for ``rosgate check``; None:
        rosgate's own."""
        return None

    @staticmethod
    def finds(transport: BusTransport) -> bool:
        """Whether it finds the topics ``transport``, as its options stand, announces: a peer's
        receiving topic pattern on it (``topic: /robot1/**``) is then handed to
        :meth:`pattern`; else such an entry is refused at its line."""
        return False

    @abstractmethod
    def topic(self, spec: TopicSpec) -> None:
        """Make the routes of one bus topic."""

    @abstractmethod
    def service(self, spec: ServiceSpec) -> None:
        """Make the routes of one bus service."""

    def pattern(self, pattern: Any) -> None:
        """Watch the bus for the topics announced under a receiving pattern entry, a
        :class:`rosgate.BusPattern` (called only when :meth:`finds`): hand each announced name
        and type to its ``take``, and make the route of the spec it gives as :meth:`topic`
        makes a listed entry's."""
        raise NotImplementedError(f"{self.name} says it finds topics but takes no pattern")
