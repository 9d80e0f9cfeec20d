"""Transports: the links that move opaque frames between two machines.

A transport plugin subclasses one kind — :class:`DatagramTransport` (every ``send`` delivered
whole or not at all: UDP, CAN), :class:`StreamTransport` (an ordered byte stream: TCP, RFCOMM) or
:class:`rosgate.bus.BusTransport` — and registers it through the ``rosgate_transports`` hook; the
core asks ``isinstance``. It only opens sockets (or socket-like objects): the core does
everything above them — envelope, cipher, stream framing, fragmentation and reassembly of frames
larger than :attr:`DatagramTransport.max_frame`, reconnection, counting.

Addresses are ``(host, port)`` pairs whose meaning is the transport's business (an IP address
and a UDP port; a Bluetooth device address and an RFCOMM channel). Which address reaches which
method, per role, is the table in docs/plugins.md. A ``ValueError`` from ``parse_address`` or
``check_address`` is shown to the user at the key the address came from (``bridge.server``,
``topics[2].port``), so say in it what is expected.
"""

from __future__ import annotations

import errno
import select
import socket
from abc import ABC, abstractmethod
from collections.abc import Callable
from contextlib import suppress
from dataclasses import replace
from typing import Any, ClassVar, Protocol

from .config import LinkConfig
from .options import as_options

Address = tuple[str, int]


class DatagramEndpoint(Protocol):
    """A bound datagram socket (or a look-alike). ``send`` may be called from several threads
    at once (ROS executor threads that transmit, link threads that answer): make it safe to call
    concurrently, as a socket's ``sendto`` is. ``receive`` is called from the link's receiving
    thread; ``close`` from another."""

    def send(self, frame: bytes, to: Address) -> None:
        """Hand one frame of at most ``max_frame`` bytes to the link, addressed to ``to``.

        Never wait for the far side (no acknowledgements, no retries): a full kernel buffer may
        block briefly, nothing longer. When the frame could not be handed over, raise
        ``OSError``: the core counts it against the topic (``send_error``) and goes on. Never drop
        a frame without raising. Any other exception is a bug in the plugin and reaches the
        caller's thread.
        """

    def receive(self, timeout: float) -> tuple[bytes, Address] | None:
        """Wait up to ``timeout`` seconds for one frame: ``(frame, source)``, or ``None`` when
        none came. ``source`` should be an address ``send`` can answer (a server answers its
        clients there); on a bus, where a frame names no sender, where it arrived. It must be
        hashable: the core reassembles fragments per source. ``OSError`` is taken as a passing
        failure (the core calls again) until the endpoint is closed; any other exception is a
        bug, logged and counted (``transport_error``)."""

    def close(self) -> None:
        """Release the endpoint; a ``receive`` blocked in another thread returns soon after
        (``None`` or ``OSError``)."""


class CheckingDatagramEndpoint(DatagramEndpoint, Protocol):
    """A :class:`DatagramEndpoint` that checks frames itself (a serial line's CRC) and drops
    the spoilt ones: the core hands it, once, where to count them."""

    def count_drops(self, drop: Callable[[Any, str], None]) -> None:
        """Count every frame dropped from now on with ``drop(reason, detail)``: ``reason`` a
        drop reason (declared with :func:`rosgate.drops.declare`), ``detail`` a sentence."""


class LineDatagramEndpoint(DatagramEndpoint, Protocol):
    """A :class:`DatagramEndpoint` that knows when its line is gone — a serial port whose
    device vanished, an adapter unplugged — and when it is back: the core hands it, once, whom
    to tell. While the line is gone the link sends nothing: its reliable topics' frames wait in
    its queue (within ``bridge.queue``, the oldest dropped first past it: ``queue_full``), a
    best-effort frame is dropped (``link_down``), and its packetizers' clocks stand still, so
    loss recovery gives nothing up for the outage; once it is back what waited goes, in order."""

    def watch_line(self, changed: Callable[[bool], None]) -> None:
        """Call ``changed(False)`` when the line is gone (nothing can be sent or received) and
        ``changed(True)`` once it is back and sends work again; ``changed(False)`` at once if it
        is gone already. Call it from any thread but never with a lock ``send`` takes."""


class FastDatagramEndpoint(DatagramEndpoint, Protocol):
    """A :class:`DatagramEndpoint` with the core's fast path: an allocation and a copy less per
    frame. Each method is optional: the core looks for it once per link, else uses ``send`` and
    ``receive`` (the kit's conformance suite tests whichever a transport has)."""

    def receive_into(self, buffer: memoryview,
                     timeout: float) -> tuple[int, Address, int] | None:
        """As :meth:`~DatagramEndpoint.receive`, but write the frame into ``buffer`` from its
        start and return ``(length, source, arrived)``: ``arrived`` is when the frame reached
        this machine, in nanoseconds of ``time.time_ns()``'s clock (UDP asks the kernel:
        ``SO_TIMESTAMPNS``), or 0 when the link cannot tell. With it, a receiving route drops a
        best-effort message that waited too long in the receive buffer (the topic's ``max_delay``).
        ``buffer`` is longer than any frame the link accepts (more than ``max_frame`` and than
        65,535 bytes): the core counts a frame that fills it as too long. Called from one thread;
        ``buffer`` is the core's and reused. An endpoint with an ``overflowed`` attribute (an
        int: the frames dropped so far because its receive buffer was full, as of the last
        receive; UDP asks the kernel: ``SO_RXQ_OVFL``) has them counted
        ``receive_buffer_full``."""

    def send_parts(self, parts: list[bytes | memoryview], to: Address) -> None:
        """As :meth:`~DatagramEndpoint.send`, for the one frame that ``parts`` make in order
        (a header and a view of a payload; several frames coalesced): scatter-gather
        (``sendmsg``) instead of joining them. Their total is at most ``max_frame``."""


class StreamConnection(Protocol):
    """One connected byte stream: ``send`` is called from one thread (the link's writer) while
    ``receive`` is from another (the link's reader); ``close`` from any thread."""

    def send(self, data: bytes) -> None:
        """Send all of ``data``, or raise ``OSError`` when the connection is gone: the core
        counts the frames in it (``link_down``), closes the connection and connects again."""

    def receive(self, max_bytes: int, timeout: float) -> bytes | None:
        """Up to ``max_bytes``; ``b""`` when the far end closed; ``None`` after ``timeout`` with
        none; ``OSError`` when the connection failed (the core connects again)."""

    def close(self) -> None:
        """Close; a ``receive`` blocked in another thread returns soon after."""

    # optional: ``address_gone() -> bool``, whether this machine no longer has the address the
    # connection was made from (a roam, a renewed lease): the core then connects again at once
    # instead of waiting for the far side to fall silent. :class:`SocketConnection` has it.


class FastStreamConnection(StreamConnection, Protocol):
    """A :class:`StreamConnection` that also offers the core's fast path; as for datagrams
    (:class:`FastDatagramEndpoint`), each method is optional and the core looks for it once per
    connection. :class:`SocketConnection` has both."""

    def receive_into(self, buffer: memoryview, timeout: float) -> int | None:
        """As :meth:`~StreamConnection.receive`, writing up to ``len(buffer)`` bytes into
        ``buffer``: how many (0 when the far end closed), or ``None`` after ``timeout``: no new
        bytes object per read, and a large frame is read straight into the buffer handed on."""

    def send_nowait(self, data: bytes) -> int:
        """Write what of ``data`` goes without waiting: how many bytes (0 when none). The core
        writes from the caller's thread when nothing else is being written, and leaves the rest
        to the link's writer. ``OSError`` as for ``send``."""


class StreamListener(Protocol):
    """Accepts connections; ``accept`` is called from one thread, ``close`` from another."""

    def accept(self, timeout: float) -> tuple[StreamConnection, Address] | None:
        """Wait up to ``timeout`` seconds for a connection: ``(connection, peer)``, or ``None``
        when none came."""

    def close(self) -> None: ...


class Transport(ABC):
    """What the three kinds share: a name, options and addresses. A class that subclasses this
    one alone is refused when it registers. The core makes one instance per bridge, from the
    plugin's declared ``Options`` (:mod:`rosgate.options`), shared by all its links."""

    #: the name users write in bringup.yaml (``transport: udp``)
    name: ClassVar[str]

    def __init__(self, options: Any):
        """``options``: the plugin's ``Options`` instance, parsed by the core from its table under
        ``plugins:`` (a plain mapping is parsed here the same way: handy in tests). Kept as
        :attr:`options`. A subclass that overrides ``__init__`` calls this first, then reads
        ``self.options``; a problem only found here is raised as :class:`rosgate.OptionError`.
        """
        self.options = as_options(type(self), options)

    def parse_address(self, text: str) -> Address:
        """Turn the user's notation of ``bridge.server`` (``host:port`` for IP links) into an
        address, or raise ``ValueError`` with a sentence saying what is expected."""
        raise NotImplementedError(f"transport {self.name!r} does not take addresses in "
                                  "bringup.yaml")

    def check_address(self, address: Address) -> Address:
        """Validate (and normalise) an address built by the core from a host and a ``port:``
        value; ``ValueError`` with a sentence saying what is expected."""
        return address

    def source_hosts(self, host: str) -> frozenset[str] | None:
        """The hosts that frames and connections from ``host`` (``bridge.peer``, or a client's
        server) show in their source address, so that a link takes them from there only; None
        when this transport cannot tell who sent a frame (a bus), and then nothing is filtered.
        Called once per host when a bridge starts. IP transports resolve a name to its
        addresses (:func:`ip_source_hosts`)."""
        return None


class DatagramTransport(Transport):
    """A link that keeps message boundaries (UDP, CAN). Set :attr:`max_frame`; the core cuts
    larger frames (every frame below 256 bytes: see :data:`rosgate.packetizer.SMALL_FRAME`)."""

    #: the largest frame one ``send`` carries; the core fragments above it. A class attribute,
    #: or an instance attribute set in ``__init__`` from an option.
    max_frame: int = 0
    #: bytes the layers below add to every frame sent (UDP over IPv4: 28), so that a bandwidth
    #: budget (``bridge.links``) counts what the link carries
    packet_overhead: ClassVar[int] = 0
    #: bits per second the link itself carries at most, when it knows (a serial line, from its
    #: baud rate): the budget of its links when ``bridge.links`` gives no ``bandwidth``
    bandwidth: float | None = None
    #: every destination shares one line (a serial port): one budget for each link, not one
    #: per destination as on IP links
    one_line: ClassVar[bool] = False

    @abstractmethod
    def bind(self, address: Address) -> DatagramEndpoint:
        """Bind a datagram endpoint at ``address`` (port 0: any free port). Raise
        :class:`rosgate.LinkError` when it cannot be done (address in use, no such interface),
        with a ``fix`` when you know better than "free the port, or pick another one"."""


def line_budget(links: dict[str, LinkConfig], transport: Transport) -> LinkConfig | None:
    """The budget of ``transport``'s links: ``bridge.links``'s, its ``bandwidth`` taken from
    the transport when the file gives none and the link knows its own (a serial line)."""
    given = links.get(transport.name)
    own = transport.bandwidth if isinstance(transport, DatagramTransport) else None
    if own is None or given is not None and given.bandwidth is not None:
        return given
    return LinkConfig(transport.name, own) if given is None else replace(given, bandwidth=own)


class StreamTransport(Transport):
    """An ordered byte stream (TCP, RFCOMM). The core puts a length prefix on every frame."""

    @abstractmethod
    def listen(self, address: Address) -> StreamListener:
        """Listen for connections at ``address``. Raise :class:`rosgate.LinkError` when it cannot
        be done (port in use...)."""

    @abstractmethod
    def connect(self, address: Address, timeout: float) -> StreamConnection:
        """Connect within ``timeout`` seconds, or raise ``OSError`` (``TimeoutError`` included):
        the core tries again later, with backoff. Called from a connecting thread, never from a
        ROS callback."""


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
        try:  # an IP connection's own address, with any port: whether it is still this host's
            local = sock.getsockname()
        except OSError:
            local = None
        self._local = (local[0], 0, *local[2:]) if sock.family in (
            socket.AF_INET, socket.AF_INET6) and isinstance(local, tuple) else None

    def address_gone(self) -> bool:
        """Whether this host no longer has the address the connection was made from (it
        roamed): no byte can go through it again. A bind to that address says it."""
        if self._local is None:
            return False
        with socket.socket(self.sock.family, socket.SOCK_DGRAM) as probe:
            try:
                probe.bind(self._local)
            except OSError as exc:
                return exc.errno == errno.EADDRNOTAVAIL
        return False

    def send(self, data: bytes) -> None:
        self.sock.sendall(data)

    def send_nowait(self, data: bytes) -> int:
        try:
            return self.sock.send(data, socket.MSG_DONTWAIT)
        except BlockingIOError:
            return 0

    def receive(self, max_bytes: int, timeout: float) -> bytes | None:
        if not self._readable.poll(timeout * 1000):
            return None
        return self.sock.recv(max_bytes)  # data, b"" at the end, or OSError once closed

    def receive_into(self, buffer: memoryview, timeout: float) -> int | None:
        if not self._readable.poll(timeout * 1000):
            return None
        return self.sock.recv_into(buffer)  # 0 at the end, or OSError once closed

    def close(self) -> None:
        with suppress(OSError):
            self.sock.shutdown(socket.SHUT_RDWR)
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


def ip_source_hosts(host: str) -> frozenset[str]:
    """For IP transports' :meth:`Transport.source_hosts`: every address ``host`` resolves to
    (itself when it does not resolve)."""
    try:
        found = {info[4][0] for info in socket.getaddrinfo(host, None)}
    except (OSError, UnicodeError):
        found = set()
    return frozenset({host} | {str(address).partition("%")[0] for address in found})


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
