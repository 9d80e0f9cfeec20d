"""Transports: the links that move opaque frames between two machines.

A transport plugin is a subclass of :class:`Transport` registered through the
``rosgate_transports`` hook. It only opens sockets (or socket-like objects): the core does
everything above them — envelope, cipher, stream framing (length prefix), fragmentation and
reassembly for frames larger than :attr:`Transport.max_frame`, reconnection, counting.

There are two kinds of link:

* **datagram** (``stream = False``): every ``send`` is delivered whole or not at all (UDP, CAN).
  Implement :meth:`Transport.bind`, returning a :class:`DatagramEndpoint`.
* **stream** (``stream = True``): an ordered byte stream with no boundaries (TCP, RFCOMM).
  Implement :meth:`Transport.listen` and :meth:`Transport.connect`, returning
  :class:`StreamListener` and :class:`StreamConnection`.

Addresses are ``(host, port)`` pairs; what ``host`` and ``port`` mean is the transport's own
business (an IP address and a UDP port; a Bluetooth device address and an RFCOMM channel).
"""

from __future__ import annotations

import select
import socket
from typing import Any, Callable, ClassVar, Mapping, Protocol

Address = tuple[str, int]


class DatagramEndpoint(Protocol):
    """A bound datagram socket (or a look-alike)."""

    def send(self, frame: bytes, to: Address) -> None:
        """Send one frame of at most ``max_frame`` bytes. May drop silently when the link is full."""

    def receive(self, timeout: float) -> tuple[bytes, Address] | None:
        """Wait up to ``timeout`` seconds for one frame; ``None`` when none came."""

    def close(self) -> None:
        """Release the endpoint; a ``receive`` running in another thread returns soon after."""


class StreamConnection(Protocol):
    """One connected byte stream."""

    def send(self, data: bytes) -> None:
        """Send all of ``data``; raise ``OSError`` when the connection is gone."""

    def receive(self, max_bytes: int, timeout: float) -> bytes | None:
        """Up to ``max_bytes``; ``b""`` when the far end closed; ``None`` after ``timeout`` with none."""

    def close(self) -> None:
        """Close; a ``receive`` running in another thread returns soon after."""


class StreamListener(Protocol):
    def accept(self, timeout: float) -> tuple[StreamConnection, Address] | None:
        """Wait up to ``timeout`` seconds for a connection; ``None`` when none came."""

    def close(self) -> None: ...


class Transport:
    """Base class of transport plugins. Subclass it and set the class attributes."""

    #: the name users write in bringup.yaml (``transport: udp``)
    name: ClassVar[str]
    #: True for byte streams (the core frames them), False for datagram links
    stream: ClassVar[bool]
    #: the largest frame one ``send`` carries on a datagram link; the core fragments above it
    max_frame: ClassVar[int] = 0

    def __init__(self, options: Mapping[str, Any]):
        """``options`` is this plugin's table under ``plugins:`` in bringup.yaml (may be empty).

        Raise :class:`rosgate.OptionError` for an option that is unknown or wrong.
        """
        self.options = dict(options)

    def parse_address(self, text: str) -> Address:
        """Turn the user's notation (``host:port`` for IP links) into an address, or raise
        ``ValueError`` with a sentence saying what is expected."""
        raise NotImplementedError(f"transport {self.name!r} does not take addresses in bringup.yaml")

    def check_address(self, address: Address) -> Address:
        """Validate an address built by the core from a host and a ``port:`` value."""
        return address

    # datagram links
    def bind(self, address: Address) -> DatagramEndpoint:
        """Bind a datagram endpoint (port 0: any free port). Raise ``LinkError`` when impossible."""
        raise NotImplementedError(f"transport {self.name!r} is not a datagram link")

    # stream links
    def listen(self, address: Address) -> StreamListener:
        """Listen for stream connections. Raise ``LinkError`` when impossible (port in use...)."""
        raise NotImplementedError(f"transport {self.name!r} is not a stream link")

    def connect(self, address: Address, timeout: float) -> StreamConnection:
        """Connect within ``timeout`` seconds or raise ``OSError``."""
        raise NotImplementedError(f"transport {self.name!r} is not a stream link")


class SocketConnection:
    """A :class:`StreamConnection` over a connected stream socket of any family (TCP, RFCOMM,
    Unix), for transports whose links are plain sockets.

    The socket stays blocking and a receive waits in poll(): one thread sends while another
    receives, and switching the socket's timeout under a sender (settimeout makes the socket
    non-blocking) fails its send or receive with EAGAIN at random.
    """

    def __init__(self, sock: socket.socket):
        sock.settimeout(None)
        self.sock = sock
        self._readable = select.poll()
        self._readable.register(sock, select.POLLIN)

    def send(self, data: bytes) -> None:
        self.sock.sendall(data)

    def receive(self, max_bytes: int, timeout: float) -> bytes | None:
        if not self._readable.poll(timeout * 1000):
            return None
        return self.sock.recv(max_bytes)  # data, b"" at the end, or OSError once closed

    def close(self) -> None:
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self.sock.close()


class SocketListener:
    """A :class:`StreamListener` over a listening socket: ``wrap`` makes each accepted socket a
    connection, ``address_of`` turns the socket's peer address into an :data:`Address`."""

    def __init__(self, sock: socket.socket,
                 wrap: Callable[[socket.socket], SocketConnection] = SocketConnection,
                 address_of: Callable[[Any], Address] = lambda peer: peer[:2]):
        self.sock = sock
        self.wrap = wrap
        self.address_of = address_of

    def accept(self, timeout: float) -> tuple[SocketConnection, Address] | None:
        self.sock.settimeout(timeout)
        try:
            sock, peer = self.sock.accept()
        except TimeoutError:
            return None
        return self.wrap(sock), self.address_of(peer)

    def close(self) -> None:
        self.sock.close()


def check_ip_address(address: Address) -> Address:
    """For IP transports: the host must be an IPv4 or IPv6 address or a host name — not, say, the
    Bluetooth device address of an RFCOMM main line. Raises ``ValueError`` saying so."""
    host = address[0]
    if ":" in host:  # host names have none; only IPv6 addresses do
        try:
            socket.inet_pton(socket.AF_INET6, host)
        except OSError:
            raise ValueError(f"{host!r} is not an IP address or host name") from None
    return address


def parse_host_port(text: str) -> Address:
    """``host:port`` or ``[v6addr]:port`` to ``(host, port)``, for IP transports.

    Raises ``ValueError`` with a sentence saying what is expected."""
    text = text.strip()
    host, sep, port = text.rpartition(":")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"{text!r} is not host:port (for example 192.168.1.20:12000)")
    return host, int(port)
