"""rosgate transport ``can``: topics over a CAN or CAN FD bus, through any python-can interface
(socketcan, pcan, kvaser, slcan, virtual, ...). A complete transport plugin in one page.

Options (``plugins: {can: {...}}``): :class:`CanTransport.Options`. ``base_id`` and ``extended``
are this plugin's; ``interface``, ``channel``, ``bitrate``, ``data_bitrate`` and ``fd`` go to
``can.Bus``, and so does everything in ``bus:``, the table for whatever else an interface takes
(``receive_own_messages``, ``serial_port``, vendor options), written as python-can documents it.
What bringup.yaml leaves out comes from python-can's own configuration (``~/can.conf``,
``CAN_INTERFACE``...), as for any python-can program.

Addressing: a topic's ``port`` is its arbitration id's offset, **arbitration id = base_id +
port**, and a receiving topic's bus filters on that id. The ``host`` of an address means nothing
on a bus (``peer:`` and ``listen:`` may say ``can0``, or anything). One node sends on an id: two
senders on one id would garble each other's frames (the pieces of a frame carry no sender), so
give every transmitting topic of every node its own port; topics of one node may share one.

Frames: a link of such small frames cuts every frame into pieces of 8 (or 64) bytes with a
one-byte header (the ``compact`` packetizer of ``rosgate-compact``, a dependency), reassembles
them per arbitration id, and drops and counts a frame one of whose pieces is lost. CAN FD pieces
are padded to the next valid length (12, 16, 20, 24, 32, 48, 64). Each engine opens the bus
once, however many topics use it, since pcan, kvaser and slcan channels open only once per
process.
"""

from __future__ import annotations

import logging
import queue
import threading
from dataclasses import dataclass, fields
from typing import Any

from rosgate import Address, DatagramTransport, LinkError, OptionError, hookimpl, option

log = logging.getLogger("rosgate")

POLL = 0.2          # seconds a bus read waits before checking whether the bus is closing
SEND_TIMEOUT = 1.0  # seconds a send may wait for room in the interface's transmit queue


class CanEndpoint:
    """One port of the shared bus: sends to any arbitration id, receives its own."""

    def __init__(self, transport: CanTransport, port: int,
                 inbox: queue.SimpleQueue[bytes | None]):
        self.transport = transport
        self.source = (str(transport.bus_options.get("channel", "")), port)
        self.inbox = inbox
        self.closed = False

    def send(self, frame: bytes, to: Address) -> None:
        self.transport.send(frame, to[1])

    def receive(self, timeout: float) -> tuple[bytes, Address] | None:
        if self.closed:
            raise OSError("the CAN endpoint is closed")
        try:
            data = self.inbox.get(timeout=timeout)
        except queue.Empty:
            return None
        if data is None:  # close() woke this receive up
            raise OSError("the CAN endpoint is closed")
        return data, self.source

    def close(self) -> None:
        if not self.closed:  # the bus is shared: give up this endpoint's share once only
            self.closed = True
            self.transport.release(self.source[1])
            # a receive blocked in another thread would otherwise wait out its whole timeout
            self.inbox.put(None)


class CanTransport(DatagramTransport):
    name = "can"

    @dataclass(frozen=True)
    class Options:
        interface: str | None = option(
            None, "python-can interface: socketcan, pcan, kvaser, slcan, virtual, ...")
        channel: str | int | None = option(
            None, "the interface's channel: can0, PCAN_USBBUS1, /dev/ttyACM0, ...")
        bitrate: int | None = option(
            None, "nominal bit rate, bit/s; SocketCAN ignores it: set it with ip link", minimum=1)
        data_bitrate: int | None = option(None, "CAN FD data-phase bit rate, bit/s", minimum=1)
        fd: bool = option(False, "CAN FD: 64-byte frames with bit-rate switching (else 8 bytes)")
        base_id: int = option(0x100, "arbitration id of port 0: a port's id is base_id + port")
        extended: bool = option(False, "29-bit arbitration ids (else 11-bit)")
        bus: dict[str, Any] = option(
            {}, "more can.Bus arguments, as python-can documents them (receive_own_messages, ...)")

        def __post_init__(self) -> None:
            last = 0x1FFFFFFF if self.extended else 0x7FF
            if not 0 <= self.base_id < last:
                raise OptionError("base_id", f"must be an arbitration id from 0 to {last - 1}")
            if self.interface is not None:
                import can  # behind the first use: listing plugins does not load python-can

                known = can.interfaces.BACKENDS
                if self.interface not in known:
                    raise OptionError("interface",
                                      f"python-can has no interface {self.interface!r}",
                                      f"use one of {', '.join(sorted(known))}")
            named = set(self.bus) & {f.name for f in fields(self)}
            if named:
                key = sorted(named)[0]
                raise OptionError("bus", f"{key} is an option of its own, not a bus: argument",
                                  f"write {key}: beside bus:, not in it")

    options: Options

    def __init__(self, options: Options):
        super().__init__(options)
        o = self.options
        # what bringup.yaml leaves out, python-can's own configuration decides (fd only when
        # true: classic CAN is every interface's default)
        named = {"interface": o.interface, "channel": o.channel, "bitrate": o.bitrate,
                 "data_bitrate": o.data_bitrate, "fd": o.fd or None}
        self.bus_options = {k: v for k, v in named.items() if v is not None} | o.bus
        self.max_id = 0x1FFFFFFF if o.extended else 0x7FF
        self.max_frame = 64 if o.fd else 8
        self._bus: Any = None
        # arbitration id -> endpoint; None in an inbox wakes a receive when the endpoint closes
        self._inboxes: dict[int, queue.SimpleQueue[bytes | None]] = {}
        self._users = 0
        self._lock = threading.Lock()
        self._closing = threading.Event()  # of the bus open now; each bus has its own

    def bind(self, address: Address) -> CanEndpoint:
        import can

        port = address[1]
        try:
            can_id = self.can_id(port)
        except ValueError as exc:
            raise LinkError(str(exc), "use a smaller port or base_id, or extended: true") from None
        with self._lock:
            if self._bus is None:
                try:
                    self._bus = can.ThreadSafeBus(**self.bus_options)
                except (can.CanError, ValueError, TypeError, OSError) as exc:
                    raise LinkError(f"python-can cannot open {self.bus_options.get('interface')} "
                                    f"channel {self.bus_options.get('channel')}: {exc}",
                                    "check the interface, its channel and its driver (SocketCAN: "
                                    "ip link set <channel> up type can bitrate <bits/s>)") from None
                self._closing = threading.Event()
                threading.Thread(target=self._receive_loop, args=(self._bus, self._closing),
                                 name="rx-can", daemon=True).start()
            if port and can_id in self._inboxes:
                raise LinkError(f"arbitration id {can_id:#x} (port {port}) is already bound",
                                "give each receiving port of a bus to one topic list")
            inbox: queue.SimpleQueue[bytes | None] = queue.SimpleQueue()
            if port:  # port 0: a sender only
                self._inboxes[can_id] = inbox
                self._bus.set_filters([{"can_id": i, "can_mask": self.max_id,
                                        "extended": self.options.extended} for i in self._inboxes])
            self._users += 1
        return CanEndpoint(self, port, inbox)

    def send(self, frame: bytes, port: int) -> None:
        import can
        from can.util import dlc2len, len2dlc

        bus = self._bus
        if bus is None:  # a message still on its way while the engine stops
            raise OSError("the CAN bus is closed")
        if self.options.fd:
            frame = frame.ljust(dlc2len(len2dlc(len(frame))), b"\0")
        try:
            message = can.Message(arbitration_id=self.can_id(port), data=frame,
                                  is_fd=self.options.fd, bitrate_switch=self.options.fd,
                                  is_extended_id=self.options.extended)
            bus.send(message, timeout=SEND_TIMEOUT)
        except (can.CanError, ValueError) as exc:  # the link counts an OSError as send_error
            raise OSError(f"CAN send to port {port} failed: {exc}") from None

    def can_id(self, port: int) -> int:
        """The arbitration id of a port; ``ValueError`` past the last id."""
        if self.options.base_id + port > self.max_id:
            raise ValueError(f"port {port} is arbitration id {self.options.base_id + port:#x}, "
                             "past the last "
                             f"{'extended' if self.options.extended else 'standard'} id "
                             f"{self.max_id:#x}")
        return self.options.base_id + port

    def release(self, port: int) -> None:
        with self._lock:
            if port:
                self._inboxes.pop(self.options.base_id + port, None)
            self._users -= 1
            if self._users == 0:
                self._closing.set()
                self._bus.shutdown()
                self._bus = None

    def _receive_loop(self, bus: Any, closing: threading.Event) -> None:
        import can

        while not closing.is_set():
            try:
                message = bus.recv(POLL)
            except can.CanError as exc:  # a bus error is the bus's state, not the end of the link
                if not closing.is_set():
                    log.warning("can: receive failed: %s", exc)
                    closing.wait(POLL)
                continue
            if (message is None or message.is_error_frame or message.is_remote_frame
                    or message.is_extended_id != self.options.extended):
                continue
            inbox = self._inboxes.get(message.arbitration_id)
            if inbox is not None:
                inbox.put(bytes(message.data))


@hookimpl
def rosgate_transports(register):
    register(CanTransport)
