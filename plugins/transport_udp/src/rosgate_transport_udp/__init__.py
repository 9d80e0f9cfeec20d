"""rosgate transport ``udp``: UDP datagrams over IPv4 or IPv6.

A datagram link: each frame is one datagram, delivered whole or not at all, in any order.
Frames larger than ``max_frame`` are fragmented by the rosgate core.

``max_frame`` is the largest datagram rosgate sends. A datagram larger than the path's MTU
leaves as IP fragments, and is lost when any one of them is: at 1 % packet loss a 65,000-byte
datagram (44 fragments over Ethernet's 1,500) is lost 36 % of the time, and a 1 MB message of
sixteen of them almost always. So by default it comes from the path: the MTU of the route to
the far side (the kernel's ``IP_MTU`` on a connected socket: 1,500 on Ethernet, 65,535 on
loopback) less the IP and UDP headers (28 bytes, 48 over IPv6) — 1,472 on Ethernet, 65,000 (the
most) on loopback — said once in the log. A side that binds an address of its own (a server)
takes its interface's MTU; where the path is not known (a server on 0.0.0.0) it is 1,200 bytes,
which fit every IPv6 path (whose minimum MTU, 1,280, less 48 bytes of headers, leaves 1,232)
and the usual tunnels (WireGuard, Tailscale's 1,280), as QUIC reasons. A ``max_frame`` in the
file is an upper bound: the path's still lowers it. The kernel knows the first hop's MTU, not a
smaller one further on (a tunnel behind a router): there, set ``max_frame`` (1,200 is safe).

Where the kernel has UDP segmentation offload (``UDP_SEGMENT``, Linux 4.18) and receive offload
(``UDP_GRO``, Linux 5.0), the fragments of a frame leave in one system call and arrive in one
(the kernel cuts and joins them, on the wire they are the same datagrams); elsewhere, or with
``offload: false``, one call per datagram.

Addresses: ``host:port`` (``[v6addr]:port`` for IPv6).

Options (``plugins: {udp: {...}}`` in bringup.yaml): see :class:`UdpTransport.Options`, or
``rosgate plugins --options udp``. A burst larger than the receive buffer is lost, so large
messages need a large one. As root the system limit ``net.core.rmem_max`` is bypassed; otherwise
the kernel caps the buffer there, and the log says so once, with the ``sysctl`` that lifts it.

``send`` never waits for the far side: a frame the kernel refuses (``ENOBUFS``, no route) is an
``OSError``, which the core counts as ``send_error``.
"""

from __future__ import annotations

import errno
import logging
import select
import socket
import struct
import sys
from collections import deque
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
# SO_RXQ_OVFL (Linux): each datagram comes with how many the socket's full receive buffer has
# dropped so far (a control message, sent once there are any)
_SO_RXQ_OVFL = getattr(socket, "SO_RXQ_OVFL", 40 if _LINUX else -1)
_OVERFLOWS = struct.Struct("@I")
_TIMEVAL = struct.Struct("@ll")  # SO_RCVTIMEO's struct timeval: seconds, microseconds
#: the shortest wait left to SO_RCVTIMEO, which the kernel counts in its ticks (4 ms at 250 Hz):
#: a shorter one (a packetizer's timer is due) waits in poll, which keeps to it
_KERNEL_WAIT = 0.05
# Linux's numbers, not named by Python's socket module: the route's MTU on a connected socket,
# segmentation offload (a sendmsg control message: the size of each datagram), receive offload
# (a socket option, then a control message on receive: the size of the datagrams joined)
_IP_MTU = getattr(socket, "IP_MTU", 14 if _LINUX else -1)
_IPV6_MTU = getattr(socket, "IPV6_MTU", 24 if _LINUX else -1)
_SOL_UDP = getattr(socket, "SOL_UDP", 17)
_UDP_SEGMENT = getattr(socket, "UDP_SEGMENT", 103 if _LINUX else -1)
_UDP_GRO = getattr(socket, "UDP_GRO", 104 if _LINUX else -1)
_GRO_SIZE = struct.Struct("@i")
_SEGMENT_SIZE = struct.Struct("@H")
#: what one segmented send may carry: the kernel's limits (64 datagrams, one IP packet's bytes)
_GSO_DATAGRAMS, _GSO_BYTES = 64, 65_000
#: errors of a first segmented send that mean the path cannot do it (a device without
#: checksum offload: EIO), not that the datagrams are wrong
_NO_GSO = {errno.EIO, errno.EINVAL, errno.ENOPROTOOPT, errno.EOPNOTSUPP}

DEFAULT_FRAME = 1_200  # where the path is not known: fits every path (see the docstring)
MOST_FRAME = 65_000    # the option's maximum, below IPv4's 65,507 with room to spare
HEADERS = {socket.AF_INET: 28, socket.AF_INET6: 48}  # IP and UDP headers


class UdpEndpoint:
    """A bound UDP socket. The socket stays blocking, with no timeout of Python's
    (``settimeout`` is an ``ioctl``, and CPython polls before every send and receive on a socket
    that has one): a receive waits in the kernel's own ``recvmsg`` under the socket's
    ``SO_RCVTIMEO``, set only when the wait asked for changes — one system call per datagram.
    A short wait (below :data:`_KERNEL_WAIT`), or one where the option cannot be set, waits in
    ``poll``, then receives (two).

    With ``offload`` (and a kernel that has it), :meth:`send_datagrams` hands a run of
    same-sized datagrams to the kernel in one ``sendmsg`` (``UDP_SEGMENT``), and a receive may
    take several datagrams the kernel joined (``UDP_GRO``): the first is returned at once, the
    others are kept and returned by the next receives, without a system call."""

    def __init__(self, sock: socket.socket, offload: bool = True):
        self.sock = sock
        self._readable = select.poll()
        self._readable.register(sock, select.POLLIN)
        #: the receive timeout set on the socket (seconds; None: none yet), or False where it
        #: cannot be set (then receives wait in poll); Linux's struct timeval only
        self._timeout: float | bool | None = None if _LINUX else False
        try:  # the kernel stamps every datagram with its arrival (receive_into reports it)
            sock.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
            self._stamps = socket.CMSG_SPACE(_TIMESPEC.size)
        except OSError:
            self._stamps = 0
        #: datagrams the kernel dropped because the receive buffer was full, so far (as the
        #: last datagram received says: the link counts them ``receive_buffer_full``)
        self.overflowed = 0
        try:
            sock.setsockopt(socket.SOL_SOCKET, _SO_RXQ_OVFL, 1)
            self._stamps += socket.CMSG_SPACE(_OVERFLOWS.size)
        except OSError:
            pass
        #: segmentation offload: None until the first segmented send says whether the path
        #: takes it, False when it does not (or the kernel has none)
        self.gso: bool | None = None if offload and _kernel_has(sock, _UDP_SEGMENT) else False
        self.gro = offload and _enable(sock, _UDP_GRO)
        self._ancillary = self._stamps + (socket.CMSG_SPACE(_GRO_SIZE.size) if self.gro else 0)
        #: datagrams the kernel joined that are still to be returned: (data, source, arrived)
        self._joined: deque[tuple[memoryview, Address, int]] = deque()
        self._buffer: memoryview | None = None  # receive's own (the core uses receive_into)

    def send(self, frame: bytes, to: Address) -> None:
        self.sock.sendto(frame, to)

    def send_parts(self, parts: list[bytes | memoryview], to: Address) -> None:
        self.sock.sendmsg(parts, (), 0, to)

    def send_datagrams(self, datagrams: list[list[bytes | memoryview]], to: Address) -> None:
        """Several datagrams (each as its parts) to ``to``, in order: runs of equal size (the
        last of a run may be shorter) in one segmented ``sendmsg`` each where the kernel can,
        else one ``sendmsg`` per datagram."""
        sizes = [sum(map(len, parts)) for parts in datagrams]
        start = 0
        while start < len(datagrams):
            size, end, total = sizes[start], start + 1, sizes[start]
            if self.gso is not False:
                while (end < len(datagrams) and end - start < _GSO_DATAGRAMS
                       and sizes[end] <= size and total + sizes[end] <= _GSO_BYTES):
                    total += sizes[end]
                    end += 1
                    if sizes[end - 1] < size:
                        break  # only the last may be shorter
            if end - start == 1:
                self.sock.sendmsg(datagrams[start], (), 0, to)
            else:
                self._send_segmented(datagrams[start:end], size, to)
            start = end

    def _send_segmented(self, run: list[list[bytes | memoryview]], size: int,
                        to: Address) -> None:
        parts = [part for datagram in run for part in datagram]
        try:
            self.sock.sendmsg(parts, [(_SOL_UDP, _UDP_SEGMENT, _SEGMENT_SIZE.pack(size))], 0, to)
        except OSError as exc:
            if self.gso is not None or exc.errno not in _NO_GSO:
                raise
            self.gso = False  # the path does not take it: one call per datagram from now on
            log.info("udp: segmentation offload failed (%s): one system call per datagram",
                     exc.strerror)
            for datagram in run:
                self.sock.sendmsg(datagram, (), 0, to)
            return
        self.gso = True

    def receive(self, timeout: float) -> tuple[bytes, Address] | None:
        if self._buffer is None:
            self._buffer = memoryview(bytearray(65_536))
        buffer = self._buffer
        got = self.receive_into(buffer, timeout)
        if got is None:
            return None
        return bytes(buffer[:got[0]]), got[1]

    def receive_into(self, buffer: memoryview, timeout: float) -> tuple[int, Address, int] | None:
        if self._joined:  # the rest of what the kernel joined: no system call
            data, source, arrived = self._joined.popleft()
            buffer[:len(data)] = data
            return len(data), source, arrived
        flags, timed = 0, self._timeout
        if timed is False or timeout != timed and (timeout < _KERNEL_WAIT or
                                                   not self._wait(timeout)):
            if not self._readable.poll(timeout * 1000):
                return None
            flags = socket.MSG_DONTWAIT
        try:
            size, ancillary, _, source = self.sock.recvmsg_into((buffer,), self._ancillary, flags)
        except BlockingIOError:
            # nothing within the timeout; or poll said readable and someone was faster (or the
            # datagram had a bad checksum)
            return None
        if source is None:  # the socket was shut down (close() wakes a waiting receive)
            return None
        arrived, joined = 0, 0
        for level, kind, value in ancillary:
            if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS:
                seconds, nanoseconds = _TIMESPEC.unpack_from(value)
                arrived = seconds * 1_000_000_000 + nanoseconds
            elif level == socket.SOL_SOCKET and kind == _SO_RXQ_OVFL:
                self.overflowed = _OVERFLOWS.unpack_from(value)[0]
            elif level == _SOL_UDP and kind == _UDP_GRO:
                joined = _GRO_SIZE.unpack_from(value)[0]
        source = source if len(source) == 2 else source[:2]
        if 0 < joined < size:  # several datagrams: the first is in place, keep the others
            rest = memoryview(bytes(buffer[joined:size]))
            self._joined.extend((rest[i:i + joined], source, arrived)
                                for i in range(0, len(rest), joined))
            size = joined
        return size, source, arrived

    def _wait(self, timeout: float) -> bool:
        """Set the socket's receive timeout; whether it could be set (else receives wait in
        poll from now on)."""
        micros = round(timeout * 1e6)
        try:
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVTIMEO,
                                 _TIMEVAL.pack(micros // 1_000_000, micros % 1_000_000))
        except (OSError, AttributeError, struct.error):
            self._timeout = False
            return False
        self._timeout = timeout
        return True

    def close(self) -> None:
        try:
            self.sock.shutdown(socket.SHUT_RDWR)  # wakes a receive blocked in another thread
        except OSError:
            pass  # ENOTCONN: an unconnected UDP socket still wakes on Linux
        self.sock.close()


def _kernel_has(sock: socket.socket, option: int) -> bool:
    """Whether the kernel knows a UDP socket option (reading it fails where it does not)."""
    try:
        sock.getsockopt(_SOL_UDP, option)
    except OSError:
        return False
    return True


def _enable(sock: socket.socket, option: int) -> bool:
    try:
        sock.setsockopt(_SOL_UDP, option, 1)
    except OSError:
        return False
    return True


def path_frame(host: str) -> tuple[int, int] | None:
    """The MTU of the route to ``host`` and the largest datagram it carries whole (the MTU less
    the IP and UDP headers); None when it is not known: an unspecified address (0.0.0.0, ::),
    no route, a system without ``IP_MTU``. For an address of this machine (a server binding
    it), its interface's MTU: the route to it is loopback, the traffic it carries is not."""
    if host in ("", "0.0.0.0", "::") or _IP_MTU < 0:
        return None
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    try:
        with socket.socket(family, socket.SOCK_DGRAM) as probe:
            probe.connect((host, 9))  # sends nothing: it only picks the route
            if family == socket.AF_INET6:
                mtu = probe.getsockopt(socket.IPPROTO_IPV6, _IPV6_MTU)
            else:
                mtu = probe.getsockopt(socket.IPPROTO_IP, _IP_MTU)
            own = probe.getsockname()[0] == host and not host.startswith(("127.", "::1"))
    except OSError:
        return None
    if own:
        found = _interface_mtu(host)
        if found is None:
            return None
        mtu = found
    return mtu, mtu - HEADERS[family]


def _interface_mtu(address: str) -> int | None:
    """The MTU of the interface that holds an IPv4 ``address`` of this machine (Linux ioctls),
    or None."""
    if ":" in address or not _LINUX:
        return None
    import fcntl

    siocgifaddr, siocgifmtu = 0x8915, 0x8921
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        for _, name in socket.if_nameindex():
            request = struct.pack("256s", name.encode()[:15])
            try:
                found = socket.inet_ntoa(fcntl.ioctl(sock, siocgifaddr, request)[20:24])
                if found == address:
                    return int(struct.unpack_from("@i", fcntl.ioctl(sock, siocgifmtu,
                                                                    request), 16)[0])
            except OSError:
                continue
    return None


class UdpTransport(DatagramTransport):
    name = "udp"
    max_frame = DEFAULT_FRAME  # until a path is known (see the module's docstring)
    packet_overhead = 28  # an IPv4 header and a UDP header, for bandwidth budgets

    @dataclass(frozen=True)
    class Options:
        receive_buffer: int = option(4 * 1024 * 1024, "bytes of kernel receive buffer to ask for",
                                     minimum=1)
        send_buffer: int = option(4 * 1024 * 1024, "bytes of kernel send buffer to ask for",
                                  minimum=1)
        max_frame: int | None = option(
            None, "the largest datagram to send, in bytes; longer frames go in fragments. "
            "Default: the path's MTU less the IP and UDP headers (1472 on Ethernet, 65000 on "
            "loopback), 1200 where the path is not known; a value set here is an upper bound",
            minimum=256, maximum=MOST_FRAME)
        offload: bool = option(True, "let the kernel cut and join a frame's datagrams "
                               "(UDP_SEGMENT, UDP_GRO) where it can: one system call per frame")

    options: Options

    def __init__(self, options: object):
        super().__init__(options)
        configured = self.options.max_frame
        self.max_frame = configured if configured is not None else DEFAULT_FRAME
        self._bound = configured if configured is not None else MOST_FRAME
        #: the largest datagram of each path seen (hosts checked: the far side, or the address
        #: this side binds); max_frame is the smallest, within the bound
        self.paths: dict[str, int] = {}

    def parse_address(self, text: str) -> Address:
        return parse_host_port(text)

    def check_address(self, address: Address) -> Address:
        address = check_ip_address(address)
        self._learn_path(address[0])
        return address

    def _learn_path(self, host: str) -> None:
        """Take the path to ``host`` into ``max_frame`` (links made from now on use it); say
        the result when it changes."""
        if host in self.paths:
            return
        found = path_frame(host)
        if found is None:
            return
        mtu, frame = found
        self.paths[host] = frame
        chosen = min(self._bound, *self.paths.values())
        if chosen == self.max_frame and len(self.paths) > 1:
            return
        self.max_frame = chosen
        bound = (f", at most {self._bound} as the file says" if self.options.max_frame
                 else f", at most {MOST_FRAME}")
        log.info("udp: max_frame %d bytes, from the path to %s (MTU %d less %d bytes of IP and "
                 "UDP headers%s)", chosen, host, mtu, mtu - frame, bound)

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
        return UdpEndpoint(sock, self.options.offload)


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
