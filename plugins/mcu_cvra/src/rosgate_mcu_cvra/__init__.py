"""rosgate's CVRA microcontroller profile: service calls as CVRA's firmware makes them
(``framing: serial_datagram`` on a service entry, peer role, TCP or a serial line, the
``msgpack`` codec).

One connection per call; the request is one serial datagram (:mod:`.serial_datagram`: SLIP-style
escapes and a CRC-32) holding the service's name and its arguments, and the answer is one plain
MessagePack value. :mod:`.calls` has both sides: the bridge calling a microcontroller's service
(``direction: transmit``) and a microcontroller calling a ROS service through the bridge
(``direction: receive``); :mod:`.line_calls` the same over a serial line, where a call carries
an id. Topics (``framing: none``) need no plugin: the core writes and reads
them. docs/microcontrollers.md is the user's guide.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from rosgate import Address, DatagramTransport, LinkDrop, ServiceFraming, StreamTransport, hookimpl

from .calls import CallServer, CvraCallerRoute
from .line_calls import LineCallerRoute, LineCallServer

__all__ = ["CallServer", "CvraCallerRoute", "LineCallServer", "LineCallerRoute",
           "SerialDatagramCalls"]


class SerialDatagramCalls(ServiceFraming):
    """``framing: serial_datagram``: CVRA's call pattern."""

    name = "serial_datagram"
    on_a_line = True  # a serial line: calls carry an id (line_calls)

    @dataclass(frozen=True)
    class Options:
        """None: an entry's own keys (layout, args, floats, no_answer) say all there is."""

    @classmethod
    def caller(cls, *route_args: Any, transport: StreamTransport | DatagramTransport,
               address: Address) -> CvraCallerRoute | LineCallerRoute:
        if isinstance(transport, DatagramTransport):
            return LineCallerRoute(*route_args, transport=transport, address=address)
        return CvraCallerRoute(*route_args, transport=transport, address=address)

    @classmethod
    def server(cls, name: str, link_drop: LinkDrop, idle_timeout: float) -> CallServer:
        return CallServer(name, link_drop, idle_timeout)


    @classmethod
    def line_server(cls, name: str, link_drop: LinkDrop, transport: DatagramTransport,
                    address: Address) -> LineCallServer:
        return LineCallServer(name, link_drop, transport, address)


@hookimpl
def rosgate_service_framings(register: Any) -> None:
    register(SerialDatagramCalls)
