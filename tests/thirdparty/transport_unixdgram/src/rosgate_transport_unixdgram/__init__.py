"""rosgate transport ``unixdgram``: datagrams between processes of one machine over Unix-domain
sockets. A complete transport plugin in one page.

Addresses: ``host`` is a directory and ``port`` a number; the socket is ``<dir>/<port>.sock``.
In a peer-role bringup.yaml, ``peer:`` and ``listen:`` name the directory.

Options (``plugins: {unixdgram: {...}}``): ``max_frame`` — the largest datagram; the rosgate
core fragments larger frames, so this link carries messages of any size.
"""

from __future__ import annotations

import os
import socket
from dataclasses import dataclass

from rosgate import Address, DatagramTransport, LinkError, hookimpl, option


class UnixDatagramEndpoint:
    def __init__(self, sock: socket.socket, path: str):
        self.sock = sock
        self.path = path

    def send(self, frame: bytes, to: Address) -> None:
        self.sock.sendto(frame, _path(to))

    def receive(self, timeout: float) -> tuple[bytes, Address] | None:
        self.sock.settimeout(timeout)
        try:
            data, source = self.sock.recvfrom(1 << 20)
        except TimeoutError:
            return None
        return data, _address(source)

    def close(self) -> None:
        try:
            self.sock.shutdown(socket.SHUT_RDWR)  # wakes a receive blocked in another thread
        except OSError:
            pass
        self.sock.close()
        if self.path:
            try:
                os.unlink(self.path)
            except FileNotFoundError:
                pass


class UnixDatagramTransport(DatagramTransport):
    name = "unixdgram"

    @dataclass(frozen=True)
    class Options:
        max_frame: int = option(16000, "the largest datagram, in bytes", minimum=64,
                                maximum=200_000)

    options: Options

    def __init__(self, options: Options):
        super().__init__(options)
        self.max_frame = self.options.max_frame

    def bind(self, address: Address) -> UnixDatagramEndpoint:
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        path = _path(address) if address[1] else ""  # port 0: an anonymous socket
        try:
            if path and os.path.exists(path):
                os.unlink(path)  # a socket file left by a previous run
            sock.bind(path)
        except OSError as exc:
            sock.close()
            raise LinkError(f"cannot bind {path or 'an anonymous socket'}: "
                            f"{exc.strerror}") from None
        return UnixDatagramEndpoint(sock, path)


def _path(address: Address) -> str:
    return os.path.join(address[0], f"{address[1]}.sock")


def _address(path: str | bytes | None) -> Address:
    """The address a datagram came from, in the form ``send`` takes, so it can be answered
    (a server answers its clients there); ``("", 0)`` for an anonymous sender (Linux names it
    ``b""`` or ``None``)."""
    if not isinstance(path, str):
        return "", 0
    directory, name = os.path.split(path)
    number = name.removesuffix(".sock")
    return (directory, int(number)) if number.isdigit() and name.endswith(".sock") else ("", 0)


@hookimpl
def rosgate_transports(register):
    register(UnixDatagramTransport)
