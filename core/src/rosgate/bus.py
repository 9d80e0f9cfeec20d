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
from typing import Any

from .config import ServiceConfig, TopicConfig
from .spec import ServiceSpec, TopicSpec
from .transport import Transport


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


class BusRole(ABC):
    """The bus side of a peer-role bridge. The resolver asks :meth:`key` of each bus entry; the
    peer role makes one instance per bridge (``cls(bridge)``, a :class:`rosgate.roles.Bridge`)
    and hands it each prepared bus entry as the bridge starts."""

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

    @abstractmethod
    def topic(self, spec: TopicSpec) -> None:
        """Make the routes of one bus topic."""

    @abstractmethod
    def service(self, spec: ServiceSpec) -> None:
        """Make the routes of one bus service."""
