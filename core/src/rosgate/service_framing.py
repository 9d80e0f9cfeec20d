"""Service framings: how calls travel when a service entry says ``framing: <name>`` other than
``rosgate`` — the call pattern of a device without rosgate's envelope (a microcontroller's
firmware), on a stream transport, in peer role.

A plugin subclasses :class:`ServiceFraming`, names it (``name`` is what ``framing:`` says) and
registers it through the ``rosgate_service_framings`` hook. The core keeps the entries, their
ROS side and the listening ports (with the bridge's limits on connections and sources); the
framing makes the two things that speak the device's pattern:

* ``direction: transmit``: :meth:`ServiceFraming.caller`, a service route whose
  ``on_request(request, respond)`` the proxy ROS server calls: it reaches the device at
  ``address`` over ``transport`` and answers every call, within the entry's ``timeout``.
* ``direction: receive``: :meth:`ServiceFraming.server`, a :class:`CallPort` per listening port,
  to which the core adds every serving route of that port and hands every accepted connection.

``rosgate-mcu-cvra`` (``framing: serial_datagram``, CVRA's firmware) is one.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any, ClassVar, Protocol

from .drops import LinkDrop
from .transport import Address, StreamConnection, StreamTransport


class CallPort(Protocol):
    """The calls of one listening port (direction receive), for every service on it."""

    name: str  # "<transport>:<port>", for logs and counters

    def add(self, route: Any) -> None:
        """A serving route of this port (a :class:`rosgate.services.ServerRoute`): its
        ``service`` entry (``remote``, ``timeout``, ``max_request``), its ``codec``, its
        ``serve(request, route.answering(settle))`` and its ``drop(reason, detail)``."""

    def accepted(self, connection: StreamConnection, peer: Address) -> None:
        """A connection the core accepted (within the bridge's limits): serve it and close it,
        without blocking the caller."""


class ServiceFraming(ABC):
    """A call pattern for service entries with ``framing: <name>``."""

    name: ClassVar[str]

    @classmethod
    @abstractmethod
    def caller(cls, *route_args: Any, transport: StreamTransport, address: Address) -> Any:
        """``direction: transmit``: a route made with ``route_args`` (the arguments of
        :class:`rosgate.services.ServiceRoute`, so subclass it) that calls the device at
        ``address``. The core serves the entry's ROS service with its ``on_request``, and calls
        its ``close()``, if it has one, when the route is removed."""

    @classmethod
    @abstractmethod
    def server(cls, name: str, link_drop: LinkDrop, idle_timeout: float) -> CallPort:
        """``direction: receive``: the calls of one listening port (``name``), for every service
        the core adds to it; what belongs to none of them is counted through ``link_drop``. A
        connection that falls silent for ``idle_timeout`` seconds
        (``bridge.limits.idle_timeout``) before a whole request is closed."""
