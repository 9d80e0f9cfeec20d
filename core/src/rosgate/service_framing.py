"""Service framings: the call pattern of a device without rosgate's envelope (a
microcontroller's firmware), for service entries with ``framing: <name>`` (peer role, a stream
transport). A plugin subclasses :class:`ServiceFraming` and registers it through the
``rosgate_service_framings`` hook (docs/plugins.md, "Service framings"); the core keeps the ROS
side and the listening ports with their limits. ``rosgate-mcu-cvra`` is one.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any, ClassVar, Protocol

from .drops import LinkDrop
from .transport import Address, DatagramTransport, StreamConnection, StreamTransport


class CallPort(Protocol):
    """The calls of one listening port (direction receive), for every service on it."""

    name: str  # "<transport>:<port>", for logs and counters

    def add(self, route: Any) -> None:
        """A serving route of this port (a :class:`rosgate.ServerRoute`): its
        ``service`` entry (``remote``, ``timeout``, ``max_request``), its ``codec``, its
        ``serve(request, route.answering(settle))`` and its ``drop(reason, detail)``."""

    def accepted(self, connection: StreamConnection, peer: Address) -> None:
        """A connection the core accepted (within the bridge's limits): serve it and close it,
        without blocking the caller."""


class LineCallPort(Protocol):
    """The calls arriving on one serial line's port (direction receive), for every service on
    it; it reads the line itself, until closed."""

    name: str

    def add(self, route: Any) -> None:
        """A serving route, as for :meth:`CallPort.add`."""

    def close(self) -> None: ...


class ServiceFraming(ABC):
    """A call pattern for service entries with ``framing: <name>``."""

    name: ClassVar[str]
    #: whether its calls also go over a serial line (a datagram transport that is one line):
    #: then :meth:`caller` takes that transport, and :meth:`line_server` serves
    on_a_line: ClassVar[bool] = False

    @classmethod
    @abstractmethod
    def caller(cls, *route_args: Any, transport: StreamTransport | DatagramTransport,
               address: Address) -> Any:
        """``direction: transmit``: a :class:`rosgate.ServiceRoute` subclass made with
        ``route_args`` that calls the device at ``address`` (over a datagram transport only
        when :attr:`on_a_line` says it can): the core serves the ROS service
        with its ``on_request(request, respond)`` (answer every call within ``timeout``) and
        calls its ``close()``, if it has one, when the route is removed."""

    @classmethod
    @abstractmethod
    def server(cls, name: str, link_drop: LinkDrop, idle_timeout: float) -> CallPort:
        """``direction: receive``: the calls of one listening port (``name``), for every service
        the core adds to it; what belongs to none of them is counted through ``link_drop``. A
        connection that falls silent for ``idle_timeout`` seconds
        (``bridge.limits.idle_timeout``) before a whole request is closed."""

    @classmethod
    def line_server(cls, name: str, link_drop: LinkDrop, transport: DatagramTransport,
                    address: Address) -> LineCallPort:
        """``direction: receive`` on a serial line (:attr:`on_a_line`): the calls arriving at
        ``address`` of ``transport`` (bound here), for every service the core adds."""
        raise NotImplementedError(f"{cls.name} calls need a stream transport")
