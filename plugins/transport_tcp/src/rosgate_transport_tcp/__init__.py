"""rosgate transport ``tcp``: TCP byte streams over IPv4 or IPv6.

A stream link: the rosgate core puts a length prefix on every frame, so message boundaries
never depend on searching the payload. Used for the main line of client/server bridges, and for
topics that must arrive complete and in order.

Addresses: ``host:port`` (``[v6addr]:port`` for IPv6).

Options (``plugins: {tcp: {...}}``):

``nodelay``  disable Nagle's algorithm (default true: frames leave at once; the core already
             batches what is queued into one write).
"""

from __future__ import annotations

import select
import socket
from typing import Any, Mapping

from rosgate import Address, LinkError, OptionError, Transport, hookimpl, parse_host_port


class TcpConnection:
    """Sending and receiving run in two threads at once: the socket stays blocking, and a receive
    waits with select(). (A socket timeout is one per socket: a sender setting it while the
    receiver waits made recv fail with EAGAIN and dropped the connection.)"""

    def __init__(self, sock: socket.socket, nodelay: bool):
        if nodelay:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.settimeout(None)
        self.sock = sock

    def send(self, data: bytes) -> None:
        self.sock.sendall(data)

    def receive(self, max_bytes: int, timeout: float) -> bytes | None:
        readable, _, _ = select.select([self.sock], [], [], timeout)
        return self.sock.recv(max_bytes) if readable else None

    def close(self) -> None:
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self.sock.close()


class TcpListener:
    def __init__(self, sock: socket.socket, nodelay: bool):
        self.sock = sock
        self.nodelay = nodelay

    def accept(self, timeout: float) -> tuple[TcpConnection, Address] | None:
        self.sock.settimeout(timeout)
        try:
            sock, peer = self.sock.accept()
        except TimeoutError:
            return None
        return TcpConnection(sock, self.nodelay), peer[:2]

    def close(self) -> None:
        self.sock.close()


class TcpTransport(Transport):
    name = "tcp"
    stream = True

    def __init__(self, options: Mapping[str, Any]):
        super().__init__(options)
        unknown = set(options) - {"nodelay"}
        if unknown:
            raise OptionError(sorted(unknown)[0], "unknown option of tcp", "the valid option is nodelay")
        self.nodelay = options.get("nodelay", True)
        if not isinstance(self.nodelay, bool):
            raise OptionError("nodelay", f"must be true or false, not {self.nodelay!r}")

    def parse_address(self, text: str) -> Address:
        return parse_host_port(text)

    def listen(self, address: Address) -> TcpListener:
        sock = socket.socket(_family(address), socket.SOCK_STREAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind(address)
            sock.listen(64)
        except OSError as exc:
            sock.close()
            raise LinkError(f"cannot listen on TCP {address[0]}:{address[1]}: {exc.strerror}") from None
        return TcpListener(sock, self.nodelay)

    def connect(self, address: Address, timeout: float) -> TcpConnection:
        sock = socket.create_connection(address, timeout=timeout)
        return TcpConnection(sock, self.nodelay)


def _family(address: Address) -> socket.AddressFamily:
    return socket.AF_INET6 if ":" in address[0] else socket.AF_INET


@hookimpl
def rosgate_transports(register):
    register(TcpTransport)
