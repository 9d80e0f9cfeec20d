"""rosgate transport ``udp``: UDP datagrams over IPv4 or IPv6.

A datagram link: each frame is one datagram, delivered whole or not at all, in any order.
Frames larger than ``max_frame`` are fragmented by the rosgate core.

``max_frame`` (default 1,200 bytes) is the largest datagram rosgate sends. A datagram larger
than the path's MTU leaves as IP fragments, and is lost when any one of them is: at 1 % packet
loss a 65,000-byte datagram (44 fragments over Ethernet's 1,500) is lost 36 % of the time, and a
1 MB message of sixteen of them almost always. 1,200 bytes fit every IPv6 path (whose minimum
MTU, 1,280, less 48 bytes of headers, leaves 1,232) and the usual tunnels (WireGuard,
Tailscale's 1,280), as QUIC reasons. On a network you know: 1,472 fills an Ethernet frame over
IPv4; on loopback or with jumbo frames, up to 65,000 saves the fragmenting's CPU (the benchmark's
loopback rows set 65,000).

Addresses: ``host:port`` (``[v6addr]:port`` for IPv6).

Options (``plugins: {udp: {...}}`` in bringup.yaml): see :class:`UdpTransport.Options`, or
``rosgate plugins --options udp``. A burst larger than the receive buffer is lost, so large
messages need a large one. As root the system limit ``net.core.rmem_max`` is bypassed; otherwise
the kernel caps the buffer there, and the log says so once, with the ``sysctl`` that lifts it.

``send`` never waits for the far side: a frame the kernel refuses (``ENOBUFS``, no route) is an
``OSError``, which the core counts as ``send_error``.
"""

from __future__ import annotations

import logging
import select
import socket
import struct
import sys
from dataclasses import dataclass

from rosgate import (
    Address,
    DatagramTransport,
    LinkError,
    check_ip_address,
    hookimpl,
    ip_source_hosts,
    option,
    parse_host_port,
)

log = logging.getLogger("rosgate.udp")

# SO_RCVBUFFORCE / SO_SNDBUFFORCE (Linux): let a privileged process exceed rmem_max / wmem_max.
# Python's socket module does not name them; their numbers are Linux's ABI.
_LINUX = sys.platform.startswith("linux")
_FORCE = {socket.SO_RCVBUF: getattr(socket, "SO_RCVBUFFORCE", 33 if _LINUX else None),
          socket.SO_SNDBUF: getattr(socket, "SO_SNDBUFFORCE", 32 if _LINUX else None)}
_LIMIT = {socket.SO_RCVBUF: ("receive", "net.core.rmem_max"),
          socket.SO_SNDBUF: ("send", "net.core.wmem_max")}
# SO_TIMESTAMPNS (also the control message's type): not named by Python either; on other
# systems the option fails and arrival times are unknown (0)
_SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35 if _LINUX else -1)
_TIMESPEC = struct.Struct("@qq")


class UdpEndpoint:
    """A bound UDP socket. The socket stays blocking, with no timeout: a receive waits in
    ``poll`` instead, so neither side pays for a timeout mode (``settimeout`` is an ``ioctl``, and
    CPython polls before every send on a socket that has one)."""

    def __init__(self, sock: socket.socket):
        self.sock = sock
        self._readable = select.poll()
        self._readable.register(sock, select.POLLIN)
        try:  # the kernel stamps every datagram with its arrival (receive_into reports it)
            sock.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
            self._stamps = _TIMESPEC.size * 2
        except OSError:
            self._stamps = 0

    def send(self, frame: bytes, to: Address) -> None:
        self.sock.sendto(frame, to)

    def send_parts(self, parts: list[bytes | memoryview], to: Address) -> None:
        self.sock.sendmsg(parts, (), 0, to)

    def receive(self, timeout: float) -> tuple[bytes, Address] | None:
        if not self._readable.poll(timeout * 1000):
            return None
        try:
            data, source = self.sock.recvfrom(65536, socket.MSG_DONTWAIT)
        except BlockingIOError:
            return None
        return data, source if len(source) == 2 else source[:2]

    def receive_into(self, buffer: memoryview, timeout: float) -> tuple[int, Address, int] | None:
        if not self._readable.poll(timeout * 1000):
            return None
        try:
            size, stamps, _, source = self.sock.recvmsg_into((buffer,), self._stamps,
                                                             socket.MSG_DONTWAIT)
        except BlockingIOError:  # poll said readable, and someone was faster (or a bad checksum)
            return None
        arrived = 0
        for level, kind, data in stamps:
            if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS:
                seconds, nanoseconds = _TIMESPEC.unpack_from(data)
                arrived = seconds * 1_000_000_000 + nanoseconds
        return size, source if len(source) == 2 else source[:2], arrived

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

    def source_hosts(self, host: str) -> frozenset[str]:
        return ip_source_hosts(host)

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


_warned: set[int] = set()


def _set_buffer(sock: socket.socket, option: int, size: int) -> None:
    """Ask for ``size`` bytes of kernel buffer: forced past the system's limit where the process
    may (root, CAP_NET_ADMIN), else up to it, with a warning (once per process) that says what
    the cap costs and how to lift it."""
    forced = _FORCE[option]
    try:
        sock.setsockopt(socket.SOL_SOCKET, forced if forced else option, size)
    except PermissionError:
        sock.setsockopt(socket.SOL_SOCKET, option, size)
    got = sock.getsockopt(socket.SOL_SOCKET, option) // 2  # Linux reports twice what it grants
    if got < size and option not in _warned:
        _warned.add(option)
        kind, limit = _LIMIT[option]
        log.warning("udp: the kernel gave a %s buffer of %d bytes, not the %d asked for (%s "
                    "caps it): a burst of more than that (a few large images at once) is lost "
                    "on the way in. Raise the cap: sysctl -w %s=%d, or run as root", kind, got,
                    size, limit, limit, 2 * size)


@hookimpl
def rosgate_transports(register):
    register(UdpTransport)
