"""rosgate transport ``unixdgram``: datagrams between processes of one machine over Unix-domain
sockets. A complete transport plugin in one page.

Addresses: ``host`` is a directory and ``port`` a number; the socket is ``<dir>/<port>.sock``.
In a peer-role bringup.yaml, ``peer:`` and ``listen:`` name the directory.

Options (``plugins: {unixdgram: {...}}``): ``max_frame`` — the largest datagram (default 16000);
the rosgate core fragments larger frames, so this link carries messages of any size.
"""

from __future__ import annotations

import os
import socket
from typing import Any, Mapping

from rosgate import Address, LinkError, OptionError, Transport, hookimpl


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


class UnixDatagramTransport(Transport):
    name = "unixdgram"
    stream = False

    def __init__(self, options: Mapping[str, Any]):
        super().__init__(options)
        unknown = set(options) - {"max_frame"}
        if unknown:
            raise OptionError(sorted(unknown)[0], "unknown option of unixdgram",
                              "the valid option is max_frame")
        self.max_frame = options.get("max_frame", 16000)
        if not isinstance(self.max_frame, int) or not 64 <= self.max_frame <= 200_000:
            raise OptionError("max_frame", "must be a number of bytes from 64 to 200000")

    def bind(self, address: Address) -> UnixDatagramEndpoint:
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        path = _path(address) if address[1] else ""  # port 0: an anonymous socket
        try:
            if path and os.path.exists(path):
                os.unlink(path)  # a socket file left by a previous run
            sock.bind(path)
        except OSError as exc:
            sock.close()
            raise LinkError(f"cannot bind {path or 'an anonymous socket'}: {exc.strerror}") from None
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
