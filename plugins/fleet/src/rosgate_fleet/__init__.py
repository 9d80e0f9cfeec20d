"""rosgate's bus role ``fleet``: entries on a bus transport (zenoh, or any other that subclasses
:class:`FleetTransport`), wired for the peer role by key.

A bus transport plugin provides the network: :class:`FleetTransport` and the
:class:`BusSession` its ``open`` returns (publish and subscribe by key, queries, liveliness).
This distribution provides what every such bus shares, so a second one (MQTT, a DDS domain)
writes only its session:

* :class:`BusLink` — one per session: the inbound queue and the thread that drains it, and the
  outlets routes send through (:mod:`.link`);
* :class:`BusWiring` — the bus side of the peer role: keys, routes per entry, type
  announcements, liveliness tokens; ``{robot}`` placeholders and other systems' conventions
  through the bus's :class:`NameTemplates` and :class:`Dialect` (:mod:`.role`).

It registers :class:`BusWiring` through the core's ``rosgate_bus_roles`` hook, under the name
bus transports ask for by default (:attr:`rosgate.bus.BusTransport.role`).
"""

from __future__ import annotations

from typing import Any

from rosgate import hookimpl

from .link import BusAnswerer, BusCaller, BusLink, BusOutlet
from .role import BusWiring
from .session import (
    BusPublisher,
    BusQuery,
    BusSession,
    Dialect,
    FleetTransport,
    Handle,
    NameTemplates,
    check_key,
    is_template,
)

__all__ = ["BusAnswerer", "BusCaller", "BusLink", "BusOutlet", "BusPublisher", "BusQuery",
           "BusSession", "BusWiring", "Dialect", "FleetTransport", "Handle", "NameTemplates",
           "check_key", "is_template"]


@hookimpl
def rosgate_bus_roles(register: Any) -> None:
    register(BusWiring)
