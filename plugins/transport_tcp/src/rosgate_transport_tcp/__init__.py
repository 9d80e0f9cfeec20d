"""rosgate transport ``tcp``: TCP byte streams over IPv4 or IPv6.

A stream link: the rosgate core puts a length prefix on every frame, so message boundaries
never depend on searching the payload. Used for the main line of client/server bridges, and for
topics that must arrive complete and in order.

Addresses: ``host:port`` (``[v6addr]:port`` for IPv6).

Options (``plugins: {tcp: {...}}``): ``nodelay``, see :class:`TcpTransport.Options`. Frames
leave at once by default; the core already batches what is queued into one write.
"""

from __future__ import annotations

import socket
from dataclasses import dataclass

from rosgate import (
    Address,
    LinkError,
    SocketConnection,
    SocketListener,
    StreamTransport,
    check_ip_address,
    hookimpl,
    ip_source_hosts,
    option,
    parse_host_port,
)


class TcpConnection(SocketConnection):
    def __init__(self, sock: socket.socket, nodelay: bool):
        if nodelay:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        super().__init__(sock)


class TcpTransport(StreamTransport):
    name = "tcp"

    @dataclass(frozen=True)
    class Options:
        nodelay: bool = option(True, "disable Nagle's algorithm: frames leave at once")

    options: Options

    def parse_address(self, text: str) -> Address:
        return parse_host_port(text)

    def check_address(self, address: Address) -> Address:
        return check_ip_address(address)

    def source_hosts(self, host: str) -> frozenset[str]:
        return ip_source_hosts(host)

    def listen(self, address: Address) -> SocketListener:
        sock = socket.socket(_family(address), socket.SOCK_STREAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind(address)
            sock.listen(64)
        except OSError as exc:
            sock.close()
            raise LinkError(f"cannot listen on TCP {address[0]}:{address[1]}: "
                            f"{exc.strerror}") from None
        return SocketListener(sock, lambda accepted: TcpConnection(accepted, self.options.nodelay))

    def connect(self, address: Address, timeout: float) -> TcpConnection:
        sock = socket.create_connection(address, timeout=timeout)
        return TcpConnection(sock, self.options.nodelay)


def _family(address: Address) -> socket.AddressFamily:
    return socket.AF_INET6 if ":" in address[0] else socket.AF_INET


@hookimpl
def rosgate_transports(register):
    register(TcpTransport)
