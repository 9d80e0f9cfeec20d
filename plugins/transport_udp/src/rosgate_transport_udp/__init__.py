"""rosgate transport ``udp``: UDP datagrams over IPv4 or IPv6.

A datagram link: each frame is one datagram, delivered whole or not at all, in any order.
Frames larger than ``max_frame`` are fragmented by the rosgate core.

``max_frame`` (default 1,200 bytes) is the largest datagram rosgate sends. A datagram larger
than the path's MTU leaves as IP fragments, and is lost when any one of them is: at 1 % packet
loss a 65,000-byte datagram (45 fragments over Ethernet's 1,500) is lost 36 % of the time, and a
1 MB message of sixteen of them almost always. 1,200 bytes fit every IPv6 path (whose minimum
MTU, 1,280, less 48 bytes of headers, leaves 1,232) and the usual tunnels (WireGuard,
Tailscale's 1,280), as QUIC reasons. On a network you know: 1,472 fills an Ethernet frame over
IPv4; on loopback or with jumbo frames, up to 65,000 saves the fragmenting's CPU (the benchmark's
loopback rows set 65,000).

Addresses: ``host:port`` (``[v6addr]:port`` for IPv6).

Options (``plugins: {udp: {...}}`` in bringup.yaml): see :class:`UdpTransport.Options`, or
``rosgate plugins --options udp``. A burst larger than the receive buffer is lost, so large
messages need a large one. As root the system limit ``net.core.rmem_max`` is bypassed; otherwise
raise it.

``send`` never waits for the far side: a frame the kernel refuses (``ENOBUFS``, no route) is an
``OSError``, which the core counts as ``send_error``.
"""

from __future__ import annotations

import logging
import socket
from dataclasses import dataclass

from rosgate import (Address, DatagramTransport, LinkError, check_ip_address, hookimpl, option,
                     parse_host_port)

log = logging.getLogger("rosgate.udp")

# SO_RCVBUFFORCE / SO_SNDBUFFORCE: Linux, lets a privileged process exceed rmem_max/wmem_max
_FORCE = {socket.SO_RCVBUF: getattr(socket, "SO_RCVBUFFORCE", None),
          socket.SO_SNDBUF: getattr(socket, "SO_SNDBUFFORCE", None)}


class UdpEndpoint:
    def __init__(self, sock: socket.socket):
        self.sock = sock

    def send(self, frame: bytes, to: Address) -> None:
        self.sock.sendto(frame, to)

    def receive(self, timeout: float) -> tuple[bytes, Address] | None:
        self.sock.settimeout(timeout)
        try:
            data, source = self.sock.recvfrom(65536)
        except TimeoutError:
            return None
        return data, source[:2]

    def close(self) -> None:
        try:
            self.sock.shutdown(socket.SHUT_RDWR)  # wakes a receive blocked in another thread
        except OSError:
            pass  # ENOTCONN: an unconnected UDP socket still wakes on Linux
        self.sock.close()


class UdpTransport(DatagramTransport):
    name = "udp"
    max_frame = 1_200  # the default of the option: fits every path (see the module's docstring)
    packet_overhead = 28  # an IPv4 header and a UDP header, for bandwidth budgets

    @dataclass(frozen=True)
    class Options:
        receive_buffer: int = option(4 * 1024 * 1024, "bytes of kernel receive buffer to ask for",
                                     minimum=1)
        send_buffer: int = option(4 * 1024 * 1024, "bytes of kernel send buffer to ask for",
                                  minimum=1)
        max_frame: int = option(
            1_200, "the largest datagram to send, in bytes; longer frames go in fragments "
            "(1472 fills Ethernet over IPv4; 65000 on loopback)", minimum=256, maximum=65_000)

    options: Options

    def __init__(self, options: object):
        super().__init__(options)
        self.max_frame = self.options.max_frame

    def parse_address(self, text: str) -> Address:
        return parse_host_port(text)

    def check_address(self, address: Address) -> Address:
        return check_ip_address(address)

    def bind(self, address: Address) -> UdpEndpoint:
        family = socket.AF_INET6 if ":" in address[0] else socket.AF_INET
        sock = socket.socket(family, socket.SOCK_DGRAM)
        _set_buffer(sock, socket.SO_RCVBUF, self.options.receive_buffer)
        _set_buffer(sock, socket.SO_SNDBUF, self.options.send_buffer)
        try:
            sock.bind(address)
        except OSError as exc:
            sock.close()
            raise LinkError(f"cannot bind UDP {address[0]}:{address[1]}: {exc.strerror}") from None
        return UdpEndpoint(sock)


_warned: dict[int, bool] = {}


def _set_buffer(sock: socket.socket, option: int, size: int) -> None:
    forced = _FORCE[option]
    try:
        sock.setsockopt(socket.SOL_SOCKET, forced if forced else option, size)
    except PermissionError:
        sock.setsockopt(socket.SOL_SOCKET, option, size)
    got = sock.getsockopt(socket.SOL_SOCKET, option) // 2  # Linux reports twice what it grants
    if got < size and not _warned.get(option):
        _warned[option] = True
        log.warning("udp: asked for a %d-byte socket buffer, got %d; large bursts may be lost "
                    "(raise net.core.rmem_max / wmem_max)", size, got)


@hookimpl
def rosgate_transports(register):
    register(UdpTransport)
