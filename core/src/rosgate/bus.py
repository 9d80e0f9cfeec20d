"""Buses: the third kind of link, for pub/sub and query networks addressed by key (Eclipse Zenoh).

A bus moves whole frames by **key**, and discovers, reconnects and fragments by itself. A bus
plugin subclasses :class:`BusTransport` (registered through ``rosgate_transports``); its entries
(peer role, no ``port:``, no ``peer:``) are wired by the :class:`BusRole` its
:attr:`~BusTransport.role` names, registered through ``rosgate_bus_roles``. rosgate's own is
``fleet`` (distribution ``rosgate-fleet``), which defines the session :meth:`BusTransport.open`
returns.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any

from .config import ServiceConfig, TopicConfig
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
    peer role makes one instance per bridge (``cls(bridge)``: the bridge is the core's own, not
    part of the plugin API) and hands it each prepared bus entry as the bridge starts."""

    name: str = ""

    def __init__(self, bridge: Any) -> None:
        self.bridge = bridge

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
